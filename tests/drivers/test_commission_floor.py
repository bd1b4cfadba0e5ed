"""The floor accelerometers in `rig commission`: each checked against the table (table = floor + stroke at its
mount), on the emulated rig over the real drivers (Modbus TCP on 127.0.0.1, the DTA-4 on a real pty, the valves
through the canopen stack) with floor wiring faults from [hil] (drivers/devicemaps/hil_wiring_faults.md: AI ch4-7):
front_left's floor accelerometer inverted, rear_left's and rear_right's swapped. Each named on its floor channel
with its mount, nothing else named; the calibration's [floor.*] tables applied by the drivers, `rig hil` through
them gains from the floor feedforward, and commissioning the same miswired rig again finds every channel ok. A rig
wired right names nothing on its floor channels (the simulated backend, and the miswired rig through its
calibration)."""
from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
import tomllib

import numpy as np
import pytest

from tests.drivers.test_commission import _commission as _commission_sim
from tests.hosttiming import ran_to_the_end, skip_unless_on_time
from tests.drivers.test_commission_valves import _commission
from tests.drivers.test_commission_sensors import _miswired

from drivers import build_driver_port, conversion
from rig import commissioning
from rig.errors import EXIT_FINDINGS
from rig.config import MOUNTS, Config

FL, FR, RL, RR = MOUNTS
FLOOR_FAULTS = "ai_source = [0, 1, 2, 3, 4, 5, 7, 6]\nai_factor = [1.0, 1.0, 1.0, 1.0, -1.0, 1.0, 1.0, 1.0]\n"


def _floor(res) -> dict:
    return {k: v for k, v in res["verdicts"].items() if k.startswith("floor:")}


@pytest.mark.hil
def test_an_inverted_and_two_swapped_floor_accelerometers_are_named_and_corrected(tmp_path):
    cfg = _miswired(tmp_path, "floor", FLOOR_FAULTS)
    run = _commission(cfg, tmp_path / "first")
    assert run.returncode == EXIT_FINDINGS, run.stderr[-3000:]
    res = json.loads(run.stdout)
    assert {k: v for k, v in res["verdicts"].items() if v != "ok"} == {
        f"floor:{FL}": "corrected", f"floor:{RL}": "corrected", f"floor:{RR}": "corrected"}
    assert {(f["channel"], f["kind"]) for f in res["faults"]} == {
        (f"floor:{FL}", "sign"), (f"floor:{RR}", "swap"), (f"floor:{RL}", "swap")}
    assert res["floor_of_mount"] == [FL, FR, RR, RL]
    assert res["floor_scale"][FL] == pytest.approx(-1.0, abs=commissioning.SCALE_TOL)
    assert all(res["floor_scale"][m] == pytest.approx(1.0, abs=commissioning.SCALE_TOL) for m in (FR, RL, RR))
    text = (tmp_path / "first" / "report.txt").read_text()
    assert f"floor accelerometer under {FL} (channel mapped to {FL}): sign inverted" in text
    assert f"floor accelerometers swapped: the floor under {RL} is read by the channel mapped to {RR}" in text
    cal = tomllib.loads((tmp_path / "first" / "commissioning.toml").read_text())["floor"]
    assert cal[FL]["sign"] == -1.0 and cal[RR]["mount"] == RL and cal[RL]["mount"] == RR
    assert all(cal[m]["scale"] == 1.0 for m in MOUNTS)
    assert all(cal[m]["offset_mps2"] == 0.0 for m in MOUNTS)      # none named: the floor's own motion is no offset
    # the calibration applied by the drivers ([drivers] calibration): the same miswired rig reads right
    fixed = tmp_path / "calibrated.toml"
    fixed.write_text(cfg.read_text() + f'\n[drivers]\ncalibration = "{tmp_path / "first" / "commissioning.toml"}"\n')
    # `rig hil` through it: the floor feedforward, fed the floor as calibrated, adds isolation (an inverted or a
    # swapped floor channel would feed the floor's motion forward the wrong way)
    hil = subprocess.run([sys.executable, "-m", "rig.cli", "hil", "--config", str(fixed), "--seconds", "9", "--json",
                          "--record", str(tmp_path / "calibrated.h5")], capture_output=True, text=True, timeout=600)
    assert ran_to_the_end(hil), hil.stderr[-3000:]
    skip_unless_on_time(hil)
    figs = json.loads(hil.stdout)
    assert figs["harm"] is None and figs["feedforward_reduction_db"] > figs["isolation_reduction_db"] + 1.0, figs
    again = _commission(fixed, tmp_path / "again")
    assert again.returncode == 0, again.stderr[-3000:] + again.stdout[-2000:]
    res2 = json.loads(again.stdout)
    assert res2["all_ok"] and not res2["faults"] and res2["floor_of_mount"] == list(MOUNTS)
    assert all(s == pytest.approx(1.0, abs=commissioning.SCALE_TOL) for s in res2["floor_scale"].values())


def test_a_rig_wired_right_names_nothing_on_its_floor_channels(tmp_path):
    run, out = _commission_sim(tmp_path, "--backend", "sim")
    assert run.returncode == 0, run.stderr[-3000:]
    res = json.loads(run.stdout)
    assert _floor(res) == {f"floor:{m}": "ok" for m in MOUNTS} and res["floor_of_mount"] == list(MOUNTS)
    H = np.asarray(res["floor_response"])           # each channel answers its own mount's floor most
    assert np.all(np.argmax(np.abs(H), axis=1) == np.arange(4)) and np.all(np.abs(np.diag(H) - 1) < 0.15)
    assert "floor accelerometer ok" in (out / "report.txt").read_text()


def test_the_drivers_apply_the_floor_table(tmp_path):
    """[floor.<channel>] as `rig commission` writes it, in the analog module's conversion the drivers build (AI
    ch4-7, drivers/__init__.py): the swapped pair read back in mount order, the inverted one's sign put right, its
    offset taken off; the mount accelerometers (AI ch0-3) untouched."""
    (tmp_path / "commissioning.toml").write_text(
        f'[floor.{FL}]\nmount = "{FL}"\nsign = -1.0\nscale = 1.0\noffset_mps2 = 0.01\n'
        f'[floor.{RL}]\nmount = "{RR}"\nsign = 1.0\nscale = 1.0\noffset_mps2 = 0.0\n'
        f'[floor.{RR}]\nmount = "{RL}"\nsign = 1.0\nscale = 1.0\noffset_mps2 = 0.0\n')
    base = Config().replace(sensors=dataclasses.replace(Config().sensors, floor_accel=True))
    cfg = base.replace(drivers=dataclasses.replace(base.drivers, calibration=str(tmp_path / "commissioning.toml")))
    ports = [build_driver_port(c, "hardware", can_interface="virtual", can_channel="never", modbus_host="127.0.0.1",
                               modbus_port=1, serial_port="/nonexistent/tty", stale_s=0.1) for c in (base, cfg)]
    try:
        plain, fixed = ([conversion.from_dict(s["channels"]) for s in p.specs if s["kind"] == "analog"][0]
                        for p in ports)
    finally:
        for p in ports:
            p.close()
    assert fixed[:4] == plain[:4]
    assert [c.source for c in fixed[4:]] == [4, 5, 7, 6]
    raw = [0.0] * 4 + [2.0, 2.0, 3.0, 4.0]
    g = plain[4].gain
    assert conversion.apply(fixed[4:], raw) == pytest.approx([-2 * g + 0.01, 2 * g, 4 * g, 3 * g])


# floor_response's c (report.json `floor_response`, H[channel, mount]) of four commissionings of
# `rig prove --commission --seed 2`, each with a mount left out of the floor's map (nothing to hold its floor against:
# its transducer dead, or its table accelerometer dead), and in the last two a floor channel dead on another mount
# (at a constant: a row of zeros; with the module's own noise: a row of a few thousandths); the floor otherwise wired
# right. (the mount left out, the mounts' floor channels as wired)
MEASURED_H = {
    "front_left's transducer dead": (0, [0, 1, 2, 3], [
        [0.947, 0.464, 0.446, 0.469], [0.41, 0.999, 0.445, 0.519], [0.569, 0.67, 0.891, 0.631],
        [0.397, 0.539, 0.449, 0.971]]),
    "front_right's transducer dead": (1, [0, 1, 2, 3], [
        [1.064, 0.425, 0.567, 0.485], [0.524, 0.907, 0.547, 0.54], [0.545, 0.417, 1.071, 0.532],
        [0.497, 0.473, 0.527, 1.077]]),
    "rear_left's accelerometer dead, front_left's floor dead at a constant": (2, [0, 1, 2, 3], [
        [0.0, -0.0, 0.0, 0.0], [0.473, 1.046, 1.134, 0.511], [0.455, 0.486, 1.111, 0.462],
        [0.466, 0.668, 0.936, 1.073]]),
    "rear_right's transducer dead, front_right's floor dead with the module's noise": (3, [0, 1, 2, 3], [
        [1.064, 0.548, 0.497, 0.409], [-0.003, 0.003, -0.003, 0.003], [0.521, 0.513, 1.084, 0.503],
        [0.507, 0.561, 0.56, 0.914]]),
}


@pytest.mark.parametrize("case", sorted(MEASURED_H))
def test_a_mount_left_out_of_the_floor_map_takes_no_other_mounts_floor_channel(case):
    """The floor's channel map over the mounts that can hold it: the floor channel of the mount left out answers
    none of them (the floor's part common to the mounts, about 0.5) and a dead floor channel answers nothing; neither
    may take another mount's channel, and each mount held keeps its own (floor_response gives the one left out the
    channel left: its own). Before: each channel's answers over its own largest made the flat row read 1, and a dead
    channel's zeros cost without end on every mount; each named two floor channels swapped, with a scale."""
    left_out, wired, H = MEASURED_H[case]
    table = [p for p in range(4) if p != left_out]
    assert commissioning.channel_map(np.abs(np.asarray(H))[:, table], own=table) == [wired[p] for p in table]
    assert commissioning.channel_map(np.abs(np.asarray(H))) == wired


@pytest.mark.parametrize("seed", range(20))
def test_the_channel_map_cancels_each_channels_scale(seed):
    """A channel's scale (a unit's slip within SCALE_FIX) does not move the map: square, any such factor per
    channel gives the same assignment; over the mounts but one (its channel wired right, its row flat over the
    others: the floor's common part 0.4-0.6, measured), a channel read 0.1 x still takes its own."""
    rng = np.random.default_rng(seed)
    R = 0.4 + 0.2 * rng.random((4, 4))
    perm = rng.permutation(4)
    R[perm, np.arange(4)] = 1.0 + 0.2 * rng.random(4)             # channel perm[j] answers valve j
    scaled = R * np.array([0.10197, 1.0, 9.80665, 0.1])[:, None]
    assert commissioning.channel_map(R) == commissioning.channel_map(scaled) == list(perm)
    fixed = [v for v in range(4) if perm[v] == v]
    if fixed:
        v = fixed[seed % len(fixed)]
        sub = [j for j in range(4) if j != v]
        assert commissioning.channel_map(scaled[:, sub], own=sub) == [int(perm[j]) for j in sub]


def test_a_real_floor_swap_outweighs_the_wiring_as_documented():
    """The documented wiring's weight decides only between answers that do not tell: two floor channels swapped
    (each 1.0 under the other's mount, 0.5 elsewhere) are found swapped, over all mounts and over three of them;
    two channels answering the other's mount a few % above their own (no peak: the floor's common part) stay."""
    H = np.full((4, 4), 0.5)
    for k, p in ((0, 0), (1, 1), (2, 3), (3, 2)):
        H[k, p] = 1.0
    assert commissioning.channel_map(H) == [0, 1, 3, 2]
    assert commissioning.channel_map(H[:, [1, 2, 3]], own=[1, 2, 3]) == [1, 3, 2]
    H[2:, 2:] = [[0.5, 0.52], [0.52, 0.5]]
    assert commissioning.channel_map(H) == [0, 1, 2, 3]
    assert commissioning.channel_map(H[:, [1, 2, 3]], own=[1, 2, 3]) == [1, 2, 3]
