"""The structured tuner (controllers/tune.py), the margin and robustness checks (controllers/analysis.py) and
`rig design --identified DIR` / `--tune`."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from controllers.analysis import (DiscreteRig, disk_gm_pm, disk_margin, is_stable, margins, perturbed_modal,
                                  robust_check, siso)
from controllers.isolation import IsolationController, make_isolation_controllers, params_from_config
from controllers.tune import Goals, Problem, tune
from rig.config import Config
from sim_backend.machine import modal_model_from_config
from sim_backend.rig_plant import rig_state_space

CFG = Config()
DT = 1.0 / CFG.loop.rate_hz


def test_disk_margin_guarantees_the_classic_margins():
    assert disk_gm_pm(2 / 3) == pytest.approx((6.0206, 36.87), abs=1e-3)
    rig = DiscreteRig(CFG, DT)
    for i, c in enumerate(make_isolation_controllers(CFG, DT)):
        r = siso(rig, c, i)
        a = disk_margin(r["L"])
        gm, pm = disk_gm_pm(a)
        assert r["margins"].gain_margin_db >= gm - 0.01 and r["margins"].phase_margin_deg >= pm - 0.05
        # and the guarantee is real: the loop times the disk's gain factor is still stable, just
        g = (1 + a / 2) / (1 - a / 2)
        p = params_from_config(CFG, i)
        assert is_stable(rig, [IsolationController(p.with_(kp_V_per_m=p.kp_V_per_m * g * 0.999), DT)] * 4,
                         loops=(i,))[0]


def test_perturbed_modes_move_by_their_factor():
    """perturbed_modal: flexible modes by their factor, the machine-on-actuator modes (~250-320 Hz, from the
    rigid-body modes) by theirs."""
    modal = modal_model_from_config(CFG)

    def coupled_hz(m):
        ev = np.linalg.eigvals(rig_state_space(CFG, m).A)
        f = np.abs(ev.imag[ev.imag > 0]) / (2 * np.pi)
        return np.sort(f[(f > 150) & (f < 400)])
    k = np.ones(len(modal.w_n))
    k[modal.w_n == 0] = 1.1
    base, up = coupled_hz(modal)[-3:], coupled_hz(perturbed_modal(modal, k))[-3:]
    assert np.all(up / base > 1.05) and np.all(up / base < 1.105)     # they mix through the mounts
    k = np.ones(len(modal.w_n))
    k[modal.w_n > 0] = 0.9
    assert np.allclose(perturbed_modal(modal, k).w_n[modal.w_n > 0], 0.9 * modal.w_n[modal.w_n > 0])
    with pytest.raises(ValueError):
        perturbed_modal(modal, [1.0])


def test_robust_check_finds_an_unstable_plant():
    """A design stable on the model but with too little gain margin fails the +-30 % gain check."""
    p = params_from_config(CFG)
    hot = [IsolationController(p.with_(kp_V_per_m=p.kp_V_per_m * 1.7), DT) for _ in range(4)]
    rig = DiscreteRig(CFG, DT, ground=None)
    assert is_stable(rig, hot)[0]
    r = robust_check(CFG, DT, hot, n_random=0)
    assert r["corners"] == 48 and not r["all_stable"] and r["unstable"] > 0


def test_tuner_improves_a_detuned_design():
    """From the shipped design with half its gain and a shifted peak, a short run of the tuner meets every hard
    constraint again and gains on the worst band."""
    start = params_from_config(CFG).with_(kp_V_per_m=params_from_config(CFG).kp_V_per_m * 0.5, notch2_hz=80.0)
    prob = Problem(CFG, DT, start)
    before = prob.worst_excess_db(start)
    res = tune(CFG, DT, start, starts=1, maxiter=25)
    after = res.params
    assert res.worst_excess_db > before + 1.0
    sl = prob.slack(after)
    g = Goals()
    assert min(sl["disk_margin"].values()) >= g.disk_alpha - 1e-3
    assert sl["hf_gain_V_per_mps2"] <= g.hf_gain_V_per_mps2 * 1.001
    assert sl["loop_gain_above_db"] <= g.rolloff_loop_db + 0.01
    assert prob.stable_all(after)


def _identify_json(folder, **over):
    par = {"K_L": 8.1e8, "C": 1947.0, "w_nv": 569.0, "zeta": 0.668, "K_Q": 1.83e-6, "K_C": 7.07e-11}
    par.update(over)
    folder.mkdir(exist_ok=True)
    (folder / "identify.json").write_text(json.dumps({"parameters": par}))
    return folder


def test_design_on_identified_actuator(tmp_path, capsys):
    """--identified DIR: the plant and the feedforward's model are the identified actuator."""
    from rig.cli import main
    d = _identify_json(tmp_path / "ident")
    rc = main(["design", "--json", "--robust", "0", "--identified", str(d)])
    out = json.loads(capsys.readouterr().out)
    assert rc == 0
    assert out["design_model"]["actuator"].startswith("identified")
    assert out["design_model"]["parameters"]["w_nv"] == 569.0
    assert out["feedforward"]["params"]["w_nv"] == 569.0 and out["feedforward"]["params"]["K_L"] == 8.1e8
    assert out["mimo"]["feedback_feedforward"]["uniform"]["ground_to_table"]["min_1_100hz"] > 20.0


@pytest.mark.parametrize("setup, words", [
    (lambda p: None, "not a folder"),
    (lambda p: p.mkdir(), "no identify.json"),
    (lambda p: (p.mkdir(), (p / "identify.json").write_text("{not json")), "cannot read it as JSON"),
    (lambda p: _identify_json(p, w_nv=-3.0), "parameters.w_nv: expected a positive number"),
    # found by the abuse trial: K_L = 1e300 ended in a LinAlgError traceback; held to [actuator] K_L's range
    (lambda p: _identify_json(p, K_L=1e300), "parameters.K_L: expected <= 1e+11 N/m, got 1e+300"),
    (lambda p: (p.mkdir(), (p / "identify.json").write_text('{"parameters": 3}')), "'parameters'"),
])
def test_identified_errors_are_one_line(tmp_path, capsys, setup, words):
    from rig.cli import main
    d = tmp_path / "ident"
    setup(d)
    assert main(["design", "--identified", str(d)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and words in err[0], err


def test_rig_design_tune_writes_the_controller_section(tmp_path, capsys):
    """--tune: the tuned [controller] section is analysed, reported and written (it loads as a config)."""
    from rig.cli import main
    from rig.config import load_config
    rc = main(["design", "--tune", "--starts", "1", "--robust", "0", "--json", "--out", str(tmp_path)])
    out = json.loads(capsys.readouterr().out)
    assert rc == 0 and out["tuned"]["worst_excess_db"] >= 0.0 and out["meets_paper"]["bands"] is True
    toml = (tmp_path / "controller.toml").read_text()
    assert toml.startswith("[controller]") and "notch2_hz" in toml
    cfg = load_config(tmp_path / "controller.toml")
    assert cfg.controller.kp_V_per_m == pytest.approx(float(toml.split("kp_V_per_m = ")[1].split()[0]))
    md = (tmp_path / "design.md").read_text()
    assert "Robust stability" in md and "sensitivity integral" in md
    assert all((tmp_path / n).stat().st_size > 10000 for n in ("feedforward.png", "mimo_transmissibility.png",
                                                               "sensitivity.png", "fig11_nyquist.png"))
