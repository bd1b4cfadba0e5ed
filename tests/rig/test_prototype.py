"""The prototype on its stand, operated through a Session in simulated time as `rig run --layout prototype`
does: the targets of tracking (a 10 um 5 Hz sine, a 2 um step), the analysed closed loop against the run,
bumpless mode switches while live, refusals, several stands on the compiled path, and the recording."""
from __future__ import annotations

import h5py
import numpy as np
import pytest

from controllers.modes import MODES, OperatingModes
from rig import operated
from rig.commands import prototype_bench
from rig.runtime.clock import SimClock
from rig.commands.run import LAYOUTS
from rig.config import config_from_dict, load_config
from rig.errors import RigError
from rig.runtime.kernel import io_entry
from rig.recordings.rigformat import load_recording
from rig.runtime.session import Session

PROTO = load_config(LAYOUTS["prototype"][None])


def _run(tmp_path, cfg=PROTO, *, seconds, mode=None, script=None, name="run.h5"):
    path = tmp_path / name
    with Session(cfg, "sim", clock=SimClock(), record=path, mode=mode, script=script) as s:
        s.run(seconds=seconds, activate_after_s=0.05)
        assert s.loop.lc.fault_reason is None
    return path


def test_tracks_a_10um_5hz_sine_within_2_percent(tmp_path):
    r = prototype_bench.sine(PROTO, tmp_path)
    assert r["rms_error_pct"] <= 2.0
    assert r["limited_pct"] == 0.0 and r["peak_command_V"] < PROTO.safety.valve_limit_V


def test_a_2um_step_settles_in_20ms_without_overshoot_or_clamp(tmp_path):
    st = prototype_bench.step(PROTO, tmp_path)
    assert st["settling_2pct_ms"] <= 20.0 and st["overshoot_pct"] <= 10.0 and not st["at_clamp"]


@pytest.mark.slow
@pytest.mark.parametrize("ff", [1.0, 0.0])
def test_the_analysed_closed_loop_matches_the_run_within_half_a_db(tmp_path, ff):
    """|x_p / r| from the loop run in simulated time (lock-in over whole cycles of a sine reference) against
    the analysis of the same controller on the sampled actuator: with the feedforward and for the PID alone
    (Fig. 4), 5 to 95 Hz."""
    res = prototype_bench.frf(PROTO, tmp_path, ff)
    assert [d["frequency_hz"] for d in res] == list(prototype_bench.FREQS_HZ)
    assert max(abs(d["difference_db"]) for d in res) < 0.5, res
    assert res[-1]["run_db"] < -1.0                       # 95 Hz is where the response falls: a real check


def test_100_random_mode_switches_while_live_keep_the_command_within_the_slew_limit(tmp_path):
    """Random modes and references at random times: the command written never moves more than the slew
    limit in a period; the controllers' own output takes the valve over without a jump (switching to off
    is the exception: the valve goes to null, at the slew limit); nothing faults."""
    r = prototype_bench.switches(PROTO, tmp_path, 100, seed=18)
    assert r["switches"] + r["refused"] == 100 and r["switches"] >= 90
    assert r["max_command_step_V"] <= r["slew_limit_V_per_period"] + 1e-9
    assert r["max_takeover_step_V"] <= r["slew_limit_V_per_period"]
    assert r["limited_pct"] < 1.0


def test_a_request_the_actuator_cannot_follow_is_refused_and_changes_nothing(tmp_path):
    with Session(PROTO, "sim", clock=SimClock(), record=tmp_path / "r.h5") as s:
        with pytest.raises(RigError, match=r"outside what the actuator can hold: \+-24\.1 um") as e:
            s.request_mode("hold 30um")
        assert "\n" not in str(e.value)
        assert not s.control("track sine:amp=10um,freq=20", "test")          # refused, logged, recorded
        assert s.modes() == ["hold"]
        assert s.control("isolate", "test")
        s.run(seconds=0.15, activate_after_s=0.02)
        assert s.snapshot()["mode"] == ["isolate"]
    with h5py.File(tmp_path / "r.h5") as f:
        texts = [b.decode() for b in f["events/text"][()]]
    assert any("test: refused: reference sine:amp=10um,freq=20: moves at up to" in x for x in texts)


def test_a_refused_start_mode_fails_the_session_in_one_line():
    with pytest.raises(RigError, match="outside what the actuator can hold"):
        with Session(PROTO, "sim", clock=SimClock(), mode="hold 40um"):
            pass


@pytest.mark.parametrize("n", [1, 2, 4, 8])
def test_any_mount_count_runs_on_the_compiled_path_with_modes_per_mount(tmp_path, n):
    names = [f"s{i}" for i in range(n)]
    cfg = config_from_dict({"layout": {"plant": "stand", "mounts": names}, "stand": {"base_motion_rms_m": 1e-6}})
    path = tmp_path / "n.h5"
    with Session(cfg, "sim", clock=SimClock(), record=path) as s:
        # the one compiled entry, any mount count, compiled before the run (stands have no floor accelerometers)
        assert s.loop.kernel.call is io_entry() and s.loop.kernel.nf == 0
        assert all(isinstance(c, OperatingModes) for c in s.loop.ctrls)
        s.request_mode("track sine:amp=2um,freq=10", mount=names[-1])
        if n > 1:
            s.request_mode("isolate", mount=names[0])
        s.run(seconds=0.3, activate_after_s=0.01)
        assert s.loop.lc.fault_reason is None
    with h5py.File(path) as f:
        mode = np.asarray(f["mode"][()]).reshape(-1, n)
        assert [str(x) for x in f["mode"].attrs["labels"]] == names
        ref = np.asarray(f["reference_m"][()]).reshape(-1, n)
    last = mode[-1]
    assert MODES[int(last[-1])] == "track" and (n == 1 or MODES[int(last[0])] == "isolate")
    assert np.isfinite(ref[-1, -1]) and (n == 1 or np.isnan(ref[-1, 0]))


def test_the_recording_carries_mode_reference_and_error_and_reads_as_closed_loop_data(tmp_path):
    path = _run(tmp_path, seconds=1.2, script=[(0.1, "hold 3um"), (0.4, "track chirp:amp=0.5um,f0=2,f1=60,"
                                                                       "duration=0.6"), (1.05, "isolate")])
    run = operated.load_operated(path)
    modes = [MODES[int(m)] for m in np.unique(run.mode[run.active])]
    assert set(modes) == {"hold", "track", "isolate"}
    tr = run.mode == 2
    assert np.allclose(run.reference_m[tr] - run.position_m[tr], run.error_m[tr], atol=1e-15)
    rec = load_recording(path)
    assert rec.closed_loop and rec.reference_m is not None
    assert rec.n == int(tr.sum()) and rec.duration_s == pytest.approx(0.65, abs=0.01)
    png = operated.plot(run, tmp_path / "run.png")
    assert png.stat().st_size > 10000


def test_operating_modes_are_for_the_stand_layout():
    from rig.errors import ConfigError
    with pytest.raises(ConfigError, match="operating modes run on the stand layout"):
        with Session(config_from_dict({}), "sim", clock=SimClock(), mode="hold"):
            pass
