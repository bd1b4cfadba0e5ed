"""The valves' side of `rig commission`: each valve's null offset, DC gain and CAN node.

On the emulated rig over the real drivers (`--backend hil`, the real canopen stack through the emulator's
gateway) with one valve fault per mount from [hil] (front_left's null at 0.3 V, front_right's flow gain
halved, rear_left's and rear_right's CAN nodes swapped): each named on its valve, nothing else named, the
calibration file holding the valve map, null and gain; that file applied (`[drivers] calibration`, the valves'
conversion), commissioning the same miswired rig again finds every valve ok, its null gone from the stroke.
Without the rig: the analysis on a synthetic recording (a lag per valve, Eq. 9), the valve map's parsimony, and
the calibration as the valves' conversion applies it."""
from __future__ import annotations

import json
import subprocess
import sys
import tomllib

import numpy as np
import pytest

from tests.hosttiming import skip_unless_commissioned_on_time
from tests.drivers.test_commission_sensors import _miswired

from drivers import conversion
from rig import commissioning
from rig.errors import EXIT_FINDINGS
from rig.config import MOUNTS
from rig.errors import ConfigError

FAULTS = ("valve_null_V = [0.3, 0.0, 0.0, 0.0]\nvalve_gain = [1.0, 0.5, 1.0, 1.0]\n"
          "valve_node_id = [1, 2, 4, 3]\n")


def _commission(cfg, out):
    """`rig commission` on the emulated rig, judged only when the host kept its time: a run the host held off the
    CPU faults on a device its I/O found stale (the emulated devices are this host's processes)."""
    argv = [sys.executable, "-m", "rig.cli", "commission", "--config", str(cfg), "--out", str(out), "--json"]
    run = subprocess.run(argv, capture_output=True, text=True, timeout=600)
    skip_unless_commissioned_on_time(run)
    return run


@pytest.mark.hil
def test_valve_faults_are_named_on_their_valves_and_the_calibration_puts_them_right(tmp_path):
    cfg = _miswired(tmp_path, "valves", FAULTS)
    run = _commission(cfg, tmp_path / "first")
    assert run.returncode == EXIT_FINDINGS, run.stderr[-3000:]
    res = json.loads(run.stdout)
    assert {k for k, v in res["verdicts"].items() if v != "ok"} == {f"valve:{m}" for m in MOUNTS}
    # the weak valve moves its own mount half as much, so the floor's motion weighed twice in its accelerometer's
    # scale against x'' (0.73-1.09 over six runs); with the floor taken out, 1.005-1.032 (docs/COMMISSIONING.md,
    # "A weak valve's accelerometer")
    assert res["accel_scale"]["front_right"] == pytest.approx(1.0, abs=0.15)
    v = res["valves"]
    assert v["front_left"]["null_V"] == pytest.approx(0.3, abs=0.05)
    assert v["front_right"]["dc_gain_vs_model"] / v["front_left"]["dc_gain_vs_model"] == pytest.approx(0.5, abs=0.1)
    assert [v[m]["moves"] for m in MOUNTS] == ["front_left", "front_right", "rear_right", "rear_left"]
    assert all(abs(v[m]["null_V"]) < commissioning.NULL_TOL_V for m in MOUNTS[1:])
    # the sensors are right: the swapped nodes are not taken for a transducer pair and an accelerometer pair
    assert res["stroke_of_valve"] == res["accel_of_valve"] == ["front_left", "front_right", "rear_right", "rear_left"]
    text = "\n".join(res["findings"])
    assert "valve front_left: null offset +0.3" in text or "valve front_left: null offset +0.2" in text
    assert "valve front_right: DC gain" in text
    assert text.count("valve nodes swapped") == 1 and "the command for rear_left moves rear_right" in text
    cal = tomllib.loads((tmp_path / "first" / "commissioning.toml").read_text())
    assert cal["valve"]["rear_left"]["mount"] == "rear_right" and cal["valve"]["rear_right"]["mount"] == "rear_left"
    assert cal["valve"]["front_left"]["null_V"] == pytest.approx(0.3, abs=0.05)
    assert cal["valve"]["front_right"]["gain"] == pytest.approx(0.5, abs=0.1)
    assert cal["stroke"]["rear_left"]["mount"] == "rear_left"          # the transducers keep their channels
    assert res["peak_stroke_m"] < 0.5 * res["stroke_limit_m"]
    # the calibration applied to the same miswired rig: every valve commands its own mount as the model has it
    fixed = tmp_path / "calibrated.toml"
    fixed.write_text(cfg.read_text() + f'\n[drivers]\ncalibration = "{tmp_path / "first" / "commissioning.toml"}"\n')
    again = _commission(fixed, tmp_path / "again")
    assert again.returncode == 0, again.stderr[-3000:] + again.stdout[-2000:]
    res2 = json.loads(again.stdout)
    assert res2["through_calibration"] == str(tmp_path / "first" / "commissioning.toml")
    assert "a check of it; what this run writes is relative to it" in again.stderr
    assert res2["all_ok"] and not res2["findings"]
    v2 = res2["valves"]
    assert all(abs(v2[m]["null_V"]) < commissioning.NULL_TOL_V for m in MOUNTS)      # the null gone: the stroke
    assert all(v2[m]["moves"] == m for m in MOUNTS)                                  # centred at zero command
    others = np.median([v2[m]["dc_gain_vs_model"] for m in MOUNTS if m != "front_right"])
    assert v2["front_right"]["dc_gain_vs_model"] / others == pytest.approx(1.0, abs=0.2)   # its gain made good


def _lag_recording(D, null, steps, fs=500.0, tau_s=0.021, seconds=15.3, noise_m=2e-8, offsets_m=(0.0,) * 4):
    """A recording of four valves each held +2 / -2 V in turn (the steps schedule), every stroke channel the
    first-order lag of Eq. 9 on D (commands - null), plus white noise and its transducer's own offset."""
    t = np.arange(int(seconds * fs)) / fs
    u = np.zeros((len(t), 4))
    t_s, hold_s, gap_s = steps
    for j in range(4):
        t0 = t_s + j * (2 * hold_s + gap_s)
        u[(t >= t0) & (t < t0 + hold_s), j] = 2.0
        u[(t >= t0 + hold_s) & (t < t0 + 2 * hold_s), j] = -2.0
    target = (u - np.asarray(null)) @ np.asarray(D).T
    x = np.zeros_like(target)
    a = 1 - np.exp(-1 / (fs * tau_s))
    x[0] = target[0]
    for k in range(1, len(t)):
        x[k] = x[k - 1] + a * (target[k] - x[k - 1])
    x += np.random.default_rng(1).normal(0, noise_m, x.shape) + np.asarray(offsets_m)
    return t, x, u


DC = 2.68e-6
D_RIG = DC * np.array([[0.93, 0.07, 0.07, -0.07], [0.07, 0.93, -0.07, 0.07],
                       [0.07, -0.07, 0.93, 0.07], [-0.07, 0.07, 0.07, 0.93]])
STEPS = (11.3, 0.4, 0.2)


def _checks(D, null, perm=(0, 1, 2, 3), offsets_m=(0.0,) * 4):
    t, x, u = _lag_recording(D, null, STEPS, offsets_m=offsets_m)
    cal = {"stroke": {m: {"mount": m, "sign": 1.0, "offset_m": float(x[(t > 0.3) & (t < 1.5), i].mean())}
                      for i, m in enumerate(MOUNTS)}}
    res = commissioning.valve_checks(MOUNTS, t, x, u, (t > 0.3) & (t < 1.5), STEPS, list(range(4)), list(perm),
                                     cal, DC)
    return res, cal


def test_a_null_is_found_through_the_tables_coupling_and_taken_out_of_the_strokes_offset():
    res, cal = _checks(D_RIG, [0.0, 0.0, -0.4, 0.0])
    assert res["valves"]["rear_left"]["null_V"] == pytest.approx(-0.4, abs=0.01)
    assert [m for m, v in res["verdicts"].items() if v != "ok"] == ["valve:rear_left"]
    assert res["calibration"]["rear_left"]["null_V"] == pytest.approx(-0.4, abs=0.01)
    # the strokes' offsets were the null's doing: none left for the transducers (their coupling included)
    assert all(abs(cal["stroke"][m]["offset_m"]) < 5e-9 for m in MOUNTS)


def test_gains_are_ok_corrected_or_refused_and_a_transducers_own_offset_is_no_null():
    D = D_RIG.copy()
    D[:, 1] *= 0.5                                     # front_right's valve at half its flow gain
    D[:, 3] *= 0.1                                     # rear_right's at a tenth: broken, not miswired
    res, cal = _checks(D, [0.0] * 4, offsets_m=(50e-6, 0.0, 0.0, 0.0))     # front_left's transducer 50 um off
    assert res["verdicts"] == {"valve:front_left": "ok", "valve:front_right": "corrected",
                               "valve:rear_left": "ok", "valve:rear_right": "refused"}
    assert res["calibration"]["front_right"]["gain"] == pytest.approx(0.5, rel=0.05)
    assert res["valves"]["front_left"]["null_V"] is None                  # not judged: the transducer's
    assert cal["stroke"]["front_left"]["offset_m"] == pytest.approx(50e-6, rel=0.01)
    assert all(abs(res["valves"][m]["null_V"]) < commissioning.NULL_TOL_V for m in MOUNTS[1:])


def test_a_dead_transducer_leaves_its_valve_unchecked_and_the_others_judged():
    D = D_RIG.copy()
    D[2, :] = 0.0                                      # rear_left's transducer reads nothing of any valve
    res, _ = _checks(D, [0.3, 0.0, 0.0, 0.0])
    assert res["verdicts"]["valve:rear_left"] == "unchecked" and res["valves"]["rear_left"]["null_V"] is None
    assert res["verdicts"]["valve:front_left"] == "corrected"
    assert res["valves"]["front_left"]["null_V"] == pytest.approx(0.3, abs=0.02)
    assert [res["verdicts"][f"valve:{m}"] for m in ("front_right", "rear_right")] == ["ok", "ok"]


def test_swapped_nodes_are_one_slip_not_two_sensor_swaps():
    assert commissioning.valve_map([1, 0, 2, 3], [1, 0, 2, 3]) == [1, 0, 2, 3]      # a node swap
    assert commissioning.valve_map([1, 0, 2, 3], [0, 1, 2, 3]) == [0, 1, 2, 3]      # transducers swapped only
    assert commissioning.valve_map([0, 1, 2, 3], [0, 1, 3, 2]) == [0, 1, 2, 3]      # accelerometers only
    assert commissioning.valve_map([1, 0, 2, 3], [1, 0, 3, 2]) == [1, 0, 2, 3]      # nodes + accelerometers
    res, _ = _checks(D_RIG, [0.0] * 4, perm=(0, 1, 3, 2))
    assert [m for m, v in res["verdicts"].items() if v != "ok"] == ["valve:rear_left", "valve:rear_right"]
    assert len(res["findings"]) == 1 and "valve nodes swapped" in res["findings"][0]


def test_the_valves_conversion_sends_each_mounts_command_to_the_node_that_moves_it():
    cal = {"valve": {"rear_left": {"mount": "rear_right", "null_V": 0.0, "gain": 1.0},
                     "rear_right": {"mount": "rear_left", "null_V": -0.2, "gain": 0.5},
                     "front_left": {"mount": "front_left", "null_V": 0.3, "gain": 1.0}}}
    chs = conversion.calibrated_valves(conversion.channels(range(4), [1.0] * 4), cal, MOUNTS)
    cmd = [1.0, 2.0, 3.0, 4.0]                          # the loop's commands, mount order
    # node i's setpoint: the command of the mount it moves, over its gain, plus its null
    assert conversion.apply(chs, cmd) == pytest.approx([1.3, 2.0, 4.0, 3.0 / 0.5 - 0.2])
    assert [c.offset for c in chs] == pytest.approx([0.3, 0.0, 0.0, -0.2])     # the safe state's null
    with pytest.raises(ConfigError, match=r"calibration \[valve\]: expected each mount moved by one valve"):
        conversion.calibrated_valves(conversion.channels(range(4), [1.0] * 4),
                                     {"valve": {"rear_left": {"mount": "rear_right"}}}, MOUNTS)
    with pytest.raises(ConfigError, match=r"calibration \[valve.stand\]: expected a mount"):
        conversion.calibrated_valves(conversion.channels(range(4), [1.0] * 4), {"valve": {"stand": {}}}, MOUNTS)


def test_two_valves_on_one_node_is_one_line(tmp_path):
    from rig.backends import _valve_node_ids
    from rig.config import load_config
    cfg = tmp_path / "twice.toml"
    cfg.write_text("[hil]\nvalve_node_id = [1, 1, 3, 4]\n")
    with pytest.raises(ConfigError, match=r"twice.toml: hil.valve_node_id: expected 4 different node numbers"):
        _valve_node_ids(load_config(cfg))
    cfg.write_text("[hil]\nvalve_node_id = [2, 1, 3, 4]\n[drivers]\nvalve_node_id_base = 5\n")
    assert _valve_node_ids(load_config(cfg)) == [6, 5, 7, 8]          # the numbers shift with the base


def test_with_swapped_nodes_a_sensors_finding_names_the_mount_it_sits_on():
    """rear_left's accelerometer inverted beside swapped rear nodes: the command for rear_right moves rear_left, and
    the inverted accelerometer answering it is named on rear_left, where it sits (the verdicts stay keyed by the
    valve's mount as configured, as the rest of the report)."""
    perm = [0, 1, 3, 2]
    R = np.eye(4)[perm].T + 0.01                       # R[channel, valve]: channel perm[j] answers valve j
    scale = dict(zip(MOUNTS, [1.0, 1.0, 1.0, -1.0]))   # valve rear_right's slot: the rear_left channel, inverted
    gain = dict(zip(MOUNTS, [0.93] * 4))
    channels = {"accel": {m: {"alive": True} for m in MOUNTS}}
    verdicts, findings = commissioning._verdicts(MOUNTS, R, R, perm, perm, scale, gain, channels, perm)
    assert findings == ["accelerometer on rear_left: sign inverted (scale -1.000 against its stroke's x'')"]
    assert verdicts["accel:rear_right"] == "corrected"
