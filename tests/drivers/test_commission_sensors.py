"""`rig commission` on the emulated rig (real drivers: Modbus TCP on 127.0.0.1, the DTA-4 on a real pty) with the
sensors' wiring faults of [hil] (drivers/devicemaps/hil_wiring_faults.md), several on different mounts in one run:
each named on its channel; what calibration corrects (a transducer's range slip, swap, sign, offsets) reads right
when the written commissioning.toml is applied (commissioning the same miswired rig again: those channels ok); what
it cannot (dead, noisy) stays refused. A channel dead at a constant stops commissioning at once, naming it."""
from __future__ import annotations

import json
import subprocess
import sys
import tomllib

import numpy as np
import pytest

from tests.drivers.test_commission import _commission

from rig.errors import EXIT_FAULT, EXIT_FINDINGS
from rig.commands.hil import HIL_DEFAULT_CONFIG
from rig.commissioning import stroke_unit
from rig.errors import EXIT_HARM
from sim_backend.emulators import shared as sh
from sim_backend.emulators.modbus_server import MAX_DELAY_STEPS, Module

FL, FR, RL, RR = "front_left", "front_right", "rear_left", "rear_right"


def _miswired(tmp_path, name, keys: str):
    cfg = tmp_path / f"{name}.toml"
    cfg.write_text(HIL_DEFAULT_CONFIG.read_text().replace("[hil]\n", "[hil]\n" + keys, 1))
    return cfg


def _commission_twice(tmp_path, keys: str):
    """Commission the miswired rig, then the same rig through the calibration it wrote: (first, second) results."""
    cfg = _miswired(tmp_path, "miswired", keys)
    run, out = _commission(tmp_path / "first", "--config", str(cfg))
    assert run.returncode == EXIT_FINDINGS, run.stderr[-3000:]
    first = json.loads(run.stdout)
    first["text"] = (out / "report.txt").read_text()
    first["toml"] = tomllib.loads((out / "commissioning.toml").read_text())
    fixed = tmp_path / "calibrated.toml"
    fixed.write_text(cfg.read_text() + f'\n[drivers]\ncalibration = "{out / "commissioning.toml"}"\n')
    run, _ = _commission(tmp_path / "second", "--config", str(fixed))
    assert run.returncode == EXIT_FINDINGS, run.stderr[-3000:]
    return first, json.loads(run.stdout)


def _sensors(res) -> dict:
    """The sensor channels' verdicts (the valves' are judged beside them: valve:<mount>)."""
    return {k: v for k, v in res["verdicts"].items() if not k.startswith("valve:")}


def _floor_ok(*mounts) -> dict:
    return {f"floor:{m}": "ok" for m in mounts}


def _floor_unchecked(*mounts) -> dict:
    return {f"floor:{m}": "unchecked" for m in mounts}


def _valves(res) -> dict:
    return {k: v for k, v in res["verdicts"].items() if k.startswith("valve:")}


def _faults(res) -> set:
    """What one commissioning named, {(channel, kind)} (as `rig prove --commission` grades it)."""
    return {(f["channel"], f["kind"]) for f in res["faults"]}


@pytest.mark.hil
def test_range_slip_offsets_dead_and_noisy_channels(tmp_path):
    # front_left's transducer ranged a decade off (reads 0.1 x), front_right's accelerometer dead (unwired: the
    # module's own noise only), rear_left's accelerometer noisy and its transducer 50 um off, rear_right's
    # transducer noisy and its accelerometer 0.5 m/s^2 off
    first, second = _commission_twice(tmp_path, "dt_factor = [0.1, 1.0, 1.0, 1.0]\n"
                                                "ai_factor = [1.0, 0.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0]\n"
                                                "ai_noise_mps2 = [0.0, 0.002, 0.02, 0.0, 0.0, 0.0, 0.0, 0.0]\n"
                                                "dt_offset_m = [0.0, 0.0, 50e-6, 0.0]\n"
                                                "dt_noise_m = [0.0, 0.0, 0.0, 2e-7]\n"
                                                "ai_offset_mps2 = [0.0, 0.0, 0.0, 0.5, 0.0, 0.0, 0.0, 0.0]\n")
    assert _valves(first) == {f"valve:{m}": "ok" for m in (FL, FR, RL, RR)}      # each judged through its stroke
    assert _sensors(first) == {f"accel:{FL}": "ok", f"stroke:{FL}": "corrected",
                               f"accel:{FR}": "refused", f"stroke:{FR}": "ok",
                               f"accel:{RL}": "refused", f"stroke:{RL}": "corrected",
                               f"accel:{RR}": "corrected", f"stroke:{RR}": "refused",
                               # the floor under a mount whose accelerometer or transducer is refused: nothing to
                               # hold it against
                               **_floor_ok(FL), **_floor_unchecked(FR, RL, RR)}
    assert _faults(first) == {(f"stroke:{FL}", "scale"), (f"accel:{FR}", "dead"), (f"accel:{RL}", "noisy"),
                              (f"stroke:{RL}", "offset"), (f"stroke:{RR}", "noisy"), (f"accel:{RR}", "offset")}
    text = first["text"]
    assert f"transducer of {FL} (channel mapped to {FL}): reads 0.1 x its stroke" in text
    assert f"accelerometer on {FR}: scale" in text and "(dead, unwired, or its range 1000 x too coarse" in text
    assert f"accelerometer channel mapped to {RL}: noisy" in text
    assert f"transducer channel mapped to {RR}: noisy" in text
    assert f"transducer channel mapped to {RL}: offset +" in text
    assert f"accelerometer channel mapped to {RR}: offset +" in text
    cal = first["toml"]
    assert cal["stroke"][FL]["scale"] == 10.0 and cal["stroke"][RL]["offset_m"] == pytest.approx(50e-6, abs=2e-6)
    assert cal["accel"][RR]["offset_mps2"] == pytest.approx(0.5, abs=0.02)
    assert cal["accel"][FR]["scale"] == 1.0                        # a dead channel's scale is no calibration
    # the calibration applied: the slip and the offsets read right; the dead and noisy channels stay refused
    assert _faults(second) == {(f"accel:{FR}", "dead"), (f"accel:{RL}", "noisy"), (f"stroke:{RR}", "noisy")}
    assert _sensors(second) == {**_sensors(first), f"stroke:{FL}": "ok", f"stroke:{RL}": "ok", f"accel:{RR}": "ok"}
    others = [abs(second["valve_gain_vs_model"][m]) for m in (FR, RL)]
    assert min(others) / 2 < abs(second["valve_gain_vs_model"][FL]) < 2 * max(others)
    assert abs(second["accel_scale"][FL]) == pytest.approx(1.0, abs=0.35)
    assert abs(second["channels"]["stroke"][RL]["offset_m"]) < 1e-6
    assert abs(second["channels"]["accel"][RR]["offset_mps2"]) < 0.02


@pytest.mark.hil
def test_swapped_inverted_and_dead_transducers(tmp_path):
    # front_left and front_right's transducers swapped, rear_left's inverted, rear_right's dead (the amplifier's
    # own few nm of noise only)
    first, second = _commission_twice(tmp_path, "dt_source = [1, 0, 2, 3]\ndt_factor = [1.0, 1.0, -1.0, 0.0]\n"
                                                "dt_noise_m = [0.0, 0.0, 0.0, 5e-9]\n")
    assert first["stroke_of_valve"][:2] == [FR, FL]
    assert _sensors(first) == {f"accel:{FL}": "ok", f"stroke:{FL}": "corrected",
                               f"accel:{FR}": "ok", f"stroke:{FR}": "corrected",
                               f"accel:{RL}": "ok", f"stroke:{RL}": "corrected",
                               f"accel:{RR}": "unchecked", f"stroke:{RR}": "refused",
                               **_floor_ok(FL, FR, RL), **_floor_unchecked(RR)}
    # the valves judged through their strokes as found (swapped, inverted); the dead one's valve is not judged
    assert _valves(first) == {f"valve:{FL}": "ok", f"valve:{FR}": "ok", f"valve:{RL}": "ok", f"valve:{RR}": "unchecked"}
    assert _faults(first) == {(f"stroke:{FL}", "swap"), (f"stroke:{FR}", "swap"), (f"stroke:{RL}", "sign"),
                              (f"stroke:{RR}", "dead")}
    assert _faults(second) == {(f"stroke:{RR}", "dead")}
    text = first["text"]
    assert f"transducers swapped: valve {FL} is answered by the channel mapped to {FR}" in text
    assert f"stroke of {RL}: sign inverted" in text and f"transducer of {RR}: no answer to its valve" in text
    assert f"accelerometer on {RL}" not in text                # judged against its stroke as calibrated
    cal = first["toml"]
    assert cal["stroke"][FR]["mount"] == FL and cal["stroke"][RL]["sign"] == -1.0
    assert _sensors(second) == {**{k: "ok" for k in _sensors(first)}, f"accel:{RR}": "unchecked",
                                f"stroke:{RR}": "refused", **_floor_unchecked(RR)}
    assert second["stroke_of_valve"][:3] == [FL, FR, RL] and second["valve_gain_vs_model"][RL] > 0


@pytest.mark.hil
@pytest.mark.parametrize("keys, line", [
    ("ai_factor = [1.0, 0.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0]\n", f"{FR}: accelerometer stuck"),
    ("dt_factor = [1.0, 1.0, 1.0, 0.0]\n", f"{RR}: displacement transducer stuck"),
    ("dt_factor = [1e-3, 1.0, 1.0, 1.0]\n", f"{FL}: displacement transducer stuck"),   # mm read as um: 0 at null
    ("dt_factor = [1.0, 1e3, 1.0, 1.0]\n", f"{FR}: stroke limit"),                       # um read as mm
    # an accelerometer 100 x (the emulated module's largest factor; 1000 x meets the rail sooner)
    ("ai_factor = [1.0, 1.0, 100.0, 1.0, 1.0, 1.0, 1.0, 1.0]\n", "AI ch2 (rear_left) at the +-10 V rail"),
])
def test_a_channel_dead_at_a_constant_stops_commissioning_naming_it(tmp_path, keys, line):
    """A dead channel, or a unit slip of 1000 (100 on the accelerometer), stops commissioning by the safety rules,
    naming the channel: nothing judged, no calibration written."""
    run, out = _commission(tmp_path, "--config", str(_miswired(tmp_path, "dead", keys)))
    assert run.returncode == EXIT_FAULT and run.stdout == ""
    assert line in run.stderr and "nothing judged" in run.stderr and not (out / "commissioning.toml").exists()


@pytest.mark.hil
def test_an_accelerometer_ranged_1000_x_too_coarse_is_refused_not_corrected(tmp_path):
    """rear_left's accelerometer reads 1e-3 x its signal (mm/s^2 read as m/s^2): below the module's resolution it
    answers like an unwired input; refused on its channel with the range named as a cause, its scale left 1 in the
    calibration (1000 x the module's steps would be no calibration), the other channels ok."""
    cfg = _miswired(tmp_path, "coarse", "ai_factor = [1.0, 1.0, 0.001, 1.0, 1.0, 1.0, 1.0, 1.0]\n")
    run, out = _commission(tmp_path / "c", "--config", str(cfg))
    assert run.returncode == EXIT_FINDINGS, run.stderr[-3000:]
    res = json.loads(run.stdout)
    assert _sensors(res) == {**{f"{k}:{m}": "ok" for k in ("accel", "stroke", "floor") for m in (FL, FR, RL, RR)},
                             f"accel:{RL}": "refused", **_floor_unchecked(RL)}, res["findings"]
    assert abs(res["accel_scale"][RL]) < 0.01
    assert any(f.startswith(f"accelerometer on {RL}: scale") and "range 1000 x too coarse" in f
               for f in res["findings"])
    assert tomllib.loads((out / "commissioning.toml").read_text())["accel"][RL]["scale"] == 1.0


def test_a_range_slip_is_told_from_a_g_range_and_a_valve_gain():
    assert stroke_unit(0.04, 10.0, 0.4) == 10.0           # the transducer reads 0.1 x: both moved
    assert stroke_unit(400.0, 1e-3, 0.4) == pytest.approx(1e-3)   # um read as mm
    assert stroke_unit(0.4, 0.102, 0.4) == 1.0            # an accelerometer's g range: the gain did not move
    assert stroke_unit(0.04, 1.0, 0.4) == 1.0             # a valve's own gain: the accelerometer did not move
    assert stroke_unit(0.0, 0.0, 0.4) == 1.0              # dead: nothing to correct
    # two faults on one mount: a range a decade up and an accelerometer's g range (0.102 / 10 against x'')
    assert stroke_unit(3.6, 0.0102, 0.4) == pytest.approx(0.1)
    assert stroke_unit(4.0, 1.0, 0.4) == 1.0              # a valve ten times strong: the accelerometer did not move
    assert stroke_unit(0.64, 0.102, 0.4) == 1.0           # a g range beside a valve's gain of 1.6


def test_the_module_delays_its_signal_by_fractional_conversions():
    arr = sh.new_shared()
    for k in range(1, 20):
        sh.publish(arr, k * 1e-3, [0.1 * k, 0.0, 0.0, 0.0], [0.0] * 4, floor_mps2=[0.0] * 4)
    now, late = Module(arr, 2.0), Module(arr, 2.0, delay_steps=2.5)
    lsb = 20.0 / 65535 / 2.0                              # m/s^2 per count at 2 V per m/s^2
    step = (now.read(0, 1)[0] - late.read(0, 1)[0]) * lsb / 0.1
    assert step == pytest.approx(2.5, abs=0.02) and late.read(8, 1) == now.read(8, 1)   # same conversion counter
    with pytest.raises(ValueError, match="module delay"):
        Module(arr, 2.0, delay_steps=MAX_DELAY_STEPS + 1)
    assert MAX_DELAY_STEPS < sh.FIFO_SLOTS


@pytest.mark.hil
def test_a_late_module_makes_isolation_harm_and_the_supervisor_says_so(tmp_path):
    # [hil] extra_delay_s: the analog module's signal 20 ms late (10 conversions at 500 Hz), the loop's feedback
    # with it: isolation makes the table worse, and `rig hil` says so and switches it off
    cfg = _miswired(tmp_path, "late", "extra_delay_s = 0.02\n")
    run = subprocess.run([sys.executable, "-m", "rig.cli", "hil", "--config", str(cfg), "--seconds", "10", "--json",
                          "--record", str(tmp_path / "late.h5")], capture_output=True, text=True, timeout=600)
    assert run.returncode == EXIT_HARM, run.stderr[-3000:]
    figs = json.loads(run.stdout)
    assert "do-no-harm: isolation made the table worse" in figs["harm"] and figs["isolation_reduction_db"] < 0


def test_a_stall_of_the_hosts_frames_is_no_sensors_quiet():
    """noise_floor leaves out a window in which every channel held its sample (the host held the loop off: a stall
    of the amplifier's frames), and keeps one in which a single channel repeats (its resolution). Measured in
    `rig prove --commission --seed 2` (case 16): one such 0.1 s window read a transducer at 1.2 nm against 12-16 nm in
    its other windows, and two transducers wired right were named noisy against it."""
    from rig.commissioning import noise_floor
    rng = np.random.default_rng(0)
    fs, sigma = 500.0, np.array([1.0, 1.2, 0.9, 1.1])
    x = rng.normal(0.0, 1.0, (600, 4)) * sigma
    x[:, 3] = np.round(x[:, 3] * 1.5) / 1.5         # coarse steps: this channel alone repeats now and then
    stalled = x.copy()
    stalled[150:200] = stalled[149]                 # 0.1 s of the same frame on every channel
    plain, held = noise_floor(x, fs), noise_floor(stalled, fs)
    assert np.all(held > 0.7 * plain) and np.all(held < 1.3 * plain), (plain, held)
    assert np.all(plain > 0.5 * sigma)
    assert noise_floor(np.zeros((600, 2)), fs).tolist() == [0.0, 0.0]      # all held (dead at a constant): 0


def test_two_dead_transducers_are_no_reference_for_a_sensors_noise():
    """A dead transducer reads the amplifier's own few nm: the others' noise floors are held against the median of
    the sensors that answer, so that two dead ones (each on its mount, as `rig prove --commission` may draw) do not
    make two transducers wired right noisy."""
    from rig import commissioning
    names = ["front_left", "front_right", "rear_left", "rear_right"]
    floors = {"front_left": 2.8e-9, "front_right": 12.4e-9, "rear_left": 12.2e-9, "rear_right": 3.0e-9}
    channels = {"stroke": {m: {"offset_m": 0.0, "noise_rms_m": 3e-7, "noise_floor_m": floors[m], "alive": True}
                           for m in names}}
    verdicts, findings = {}, []
    named = commissioning.sensor_findings(names, channels, [0, 1, 2, 3], [0, 1, 2, 3], {m: 1.0 for m in names},
                                          {m: 1.0 for m in names}, {"front_left", "rear_right"}, verdicts, findings)
    assert not named and not [f for f in findings if "noisy" in f], findings
    floors["rear_left"] = 60e-9                     # a noisy one among them is still named
    channels["stroke"]["rear_left"]["noise_floor_m"] = 60e-9
    named = commissioning.sensor_findings(names, channels, [0, 1, 2, 3], [0, 1, 2, 3], {m: 1.0 for m in names},
                                          {m: 1.0 for m in names}, {"front_left", "rear_right"}, {}, [])
    assert named == {("stroke:rear_left", "noisy")}
