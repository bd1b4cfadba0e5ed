"""The margins line is rig design's SISO view (paper Fig. 11) re-run on the diagnosed rig: on the model it gives
rig design's own margins, an accelerometer reading 30 % high takes 2.3 dB of gain margin and the retuning trims
that mount's gain by 1/1.3, and a valve delay that eats the phase margin is said plainly."""
from __future__ import annotations

import math

import pytest

from controllers.analysis import design_report
from controllers.isolation import make_isolation_controllers
from rig.config import MOUNTS, Config
from rig.diagnose.machine.engine import nominal_theta
from rig.diagnose.machine.margins import mount_lines
from rig.diagnose.machine.rigmodel import Base, copy_theta

DT = 1 / 5000


@pytest.fixture(scope="module")
def lines():
    base = Base.of(Config(), DT)
    th0 = nominal_theta(base)
    th = copy_theta(th0)
    th["gain_a"][1] = 1.3
    th["delay_s"][0] = 4e-4
    return mount_lines(base, th0, th)


def test_on_the_model_the_margins_are_rig_designs(lines):
    rep = design_report(Config(), make_isolation_controllers(Config(), DT), DT)
    for line, m in zip(lines, MOUNTS):
        d = rep["mounts"][m]
        assert line.nominal.gain_margin_db == pytest.approx(d["gain_margin_db"], abs=0.15)
        assert line.nominal.phase_margin_deg == pytest.approx(d["phase_margin_deg"], abs=0.5)
        assert line.nominal.table_db["1hz"] == pytest.approx(rep["attenuation_db"]["ground_to_table"][m]["1hz"], abs=0.2)


def test_a_sensitive_accelerometer_costs_gain_margin_and_the_trim_gives_it_back(lines):
    fr = lines[1]
    assert fr.nominal.gain_margin_db - fr.diagnosed.gain_margin_db == pytest.approx(20 * math.log10(1.3), abs=0.3)
    assert not fr.diagnosed.holds and fr.meets
    assert fr.trim == pytest.approx(1 / 1.3, rel=0.03)
    assert fr.retuned.gain_margin_db >= 6.0 and "restores the margins" in fr.text()


def test_a_valve_delay_eats_the_phase_margin_and_the_line_says_so(lines):
    fl = lines[0]
    assert fl.diagnosed.phase_margin_deg < fl.nominal.phase_margin_deg - 10
    assert "do NOT hold" in fl.text() and fl.retuned is not None and fl.retuned.holds
    assert lines[2].diagnosed.holds and "margins hold" in lines[2].text()
