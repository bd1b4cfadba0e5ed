"""`rig hil`'s isolation figures and its lockstep twin's are metered alike (issue 24, the floor feedforward's gap):
the emulated plant's trace band-limited up to the run's end, and no mode's window at either end of the trace."""
import json
import math
import subprocess
import sys

import numpy as np
import pytest
import scipy.signal

from rig.commands.hil_lockstep import phase_rms, seconds_to_meter, unmetered, windows
from rig.errors import EXIT_SUSPECT

RATE = 500.0
MODES = ("off", "feedback", "feedback_feedforward")


def _run_trace(seconds=15.0, settle=1.0, seed=3):
    """A table trace of a run (broadband motion, smaller in each mode) and its phase codes as schedule_modes
    meters them."""
    n = int(seconds * RATE)
    sos = scipy.signal.butter(2, (2.0, 60.0), btype="bandpass", fs=RATE, output="sos")
    x = scipy.signal.sosfilt(sos, np.random.default_rng(seed).standard_normal(n)) * 1e-6
    t = np.arange(n) / RATE
    codes = np.zeros(n, dtype=int)
    share = seconds / len(MODES)
    for j, (t0, t1) in enumerate(windows(seconds, MODES, settle)):
        codes[(t >= t0) & (t < t1)] = j + 1
    for j in range(len(MODES)):
        x[(t >= j * share) & (t < (j + 1) * share)] *= (1.0, 0.4, 0.15)[j]
    return x, codes


def test_the_last_mode_ends_settle_s_before_the_run_does():
    assert windows(15.0, MODES, 1.0) == [(1.0, 5.0), (6.0, 10.0), (11.0, 14.0)]
    assert windows(6.0, MODES[:2], 1.0) == [(1.0, 3.0), (4.0, 5.0)]


def test_what_the_plant_did_after_the_run_does_not_reach_the_figures():
    """After the loop stops the valves go to null: the table moves as with isolation off, and a step besides. Cut
    at the run's end (end=), the figures are those of the run alone; band-limited with that tail, the last mode's
    is not (the filter's backward pass carries the tail into it: the drivers' feedforward figure fell 0.2-1.6 dB
    short of the lockstep's so)."""
    x, codes = _run_trace()
    phases = {m: j + 1 for j, m in enumerate(MODES)}
    alone = phase_rms(x, codes, RATE, phases)
    tail = np.random.default_rng(9).standard_normal(int(0.4 * RATE)) * 2e-6 + 5e-6
    xt, ct = np.r_[x, tail], np.r_[codes, np.zeros(tail.size, dtype=int)]
    assert phase_rms(xt, ct, RATE, phases, end=x.size) == alone
    leaked = phase_rms(xt, ct, RATE, phases)
    assert math.isclose(leaked["off"], alone["off"], rel_tol=1e-6)          # far from the tail: untouched
    # with the tail, a window ending at the run's end would read it; the one settle_s before barely does
    assert abs(20 * math.log10(leaked["feedback_feedforward"] / alone["feedback_feedforward"])) < 1.0
    codes_at_end = codes.copy()
    codes_at_end[(np.arange(x.size) / RATE) >= 11.0] = 3
    at_end = phase_rms(xt, np.r_[codes_at_end, ct[x.size:]], RATE, phases)
    ref = phase_rms(x, codes_at_end, RATE, phases)
    assert 20 * math.log10(at_end["feedback_feedforward"] / ref["feedback_feedforward"]) > 0.5


def test_no_window_is_empty_and_a_short_one_is_named():
    """`rig hil --config hil_2khz.toml --seconds 6` metered its last mode from 5 s to 5 s (settle_s at each end of a
    2 s share): numpy's 'Mean of empty slice' on the terminal. settle_s is now a third of the share at most, and a
    window under MIN_WINDOW_S gives no figure (unmetered) instead of one from a few periods."""
    for seconds in (0.05, 1.0, 3.0, 6.0, 6.5, 9.0, 15.0):
        assert all(t1 > t0 for t0, t1 in windows(seconds, MODES, 1.0)), seconds
    assert unmetered(6.0, MODES, 1.0) == ["feedback_feedforward"]
    assert unmetered(3.0, MODES, 1.0) == list(MODES)
    need = seconds_to_meter(MODES, 1.0)
    assert need == 9.0 and unmetered(need, MODES, 1.0) == [] and unmetered(need - 0.1, MODES, 1.0) != []
    assert unmetered(seconds_to_meter(MODES, 0.2), MODES, 0.2) == []
    assert unmetered(seconds_to_meter(MODES[:2], 0.2) - 0.01, MODES[:2], 0.2) == ["feedback"]


@pytest.mark.hil
def test_a_run_too_short_to_meter_says_so_without_numpy_warnings(tmp_path):
    """Was: `rig hil --seconds 0.1` printed numpy's RuntimeWarning and judged 'feedback made the table 3.9 dB worse'
    from 17 periods (exit 3); --seconds 0.01 ended in a scipy traceback."""
    out = subprocess.run([sys.executable, "-m", "rig.cli", "hil", "--seconds", "0.3", "--json", "--no-realtime",
                          "--record", str(tmp_path / "short.h5")], capture_output=True, text=True, timeout=180)
    assert "Warning" not in out.stderr and "Traceback" not in out.stderr, out.stderr
    assert out.returncode == EXIT_SUSPECT, out.stderr
    res = json.loads(out.stdout)
    assert res["isolation_reduction_db"] is None and res["feedforward_reduction_db"] is None
    said = [ln for ln in out.stderr.splitlines() if "no isolation figure" in ln]
    assert len(said) == 1 and said[0].startswith("rig hil: warning: off, feedback, feedback + feedforward: metered")
    assert "give --seconds 9 or more" in said[0]


@pytest.mark.hil
def test_a_prototype_run_too_short_to_meter_gives_no_isolation_figure(tmp_path):
    """Was: `rig hil --layout prototype --seconds 0.3` judged isolation from 0.07 s of holding and of isolating
    ('5.3 dB', or 'made the load worse', exit 3, by chance), exit 0."""
    out = subprocess.run([sys.executable, "-m", "rig.cli", "hil", "--layout", "prototype", "--seconds", "0.3",
                          "--json", "--no-realtime", "--record", str(tmp_path / "short.h5")], capture_output=True,
                         text=True, timeout=180)
    assert "Traceback" not in out.stderr and out.returncode == EXIT_SUSPECT, out.stderr
    assert json.loads(out.stdout)["isolation_reduction_db"] is None
    said = [ln for ln in out.stderr.splitlines() if "no isolation figure" in ln]
    assert len(said) == 1 and said[0].startswith("rig hil: warning: hold, isolate: metered for less than 1 s")


@pytest.mark.hil
def test_the_trace_metered_and_the_twin_start_are_the_loops_own(tmp_path, monkeypatch):
    """The emulated plant steps from the moment it starts, before the loop's first period (the set-up: 40-160 ms),
    and after its last one (loop.run ends with the valves at null: the table then rides the floor). `pre_steps`
    was read before the set-up and the trace cut after loop.run returned, so the lockstep twin met a floor 40-160
    steps earlier than the run, and the band filter's backward pass carried the null tail into the feedforward's
    window: its figure fell 1.3-2.2 dB short of the twin's in one 2 kHz run of three, by how long the tail was.
    Now both ends are the plant's steps when the loop reached its first and its last period."""
    from rig.commands.hil import HIL_DEFAULT_CONFIG, hil_config, run_hil
    from rig.config import load_config
    from sim_backend.emulators.rig import EmulatedRig

    traces = []
    trace = EmulatedRig.trace
    monkeypatch.setattr(EmulatedRig, "trace", lambda self: traces.append(trace(self)) or traces[-1])
    cfg = hil_config(load_config(HIL_DEFAULT_CONFIG), None)
    rate, settle = cfg.loop.rate_hz, cfg.hil.settle_s
    seconds = seconds_to_meter(MODES, settle)
    res = run_hil(cfg, seconds, record=str(tmp_path / "run.h5"), realtime=False, quiet=True, compare=False)
    assert res["faults"] == 0 and res["stop_reason"] == "time", res["fault_reason"]
    table, _, codes = traces[-1]
    (t0, _), _, (_, t1) = windows(seconds, MODES, settle)
    first_metered = int(np.flatnonzero(codes == 1)[0])        # the plant's step after the loop's period at t0
    last_metered = int(np.flatnonzero(codes == 3)[-1])        # ... before the one at t1
    # one plant step per period, give or take the plant's catch-up with the wall clock
    assert abs(first_metered - (res["pre_steps"] + round(t0 * rate))) <= 3, (first_metered, res["pre_steps"])
    assert abs(res["end_steps"] - (last_metered + round((seconds - t1) * rate))) <= 3, (last_metered, res["end_steps"])
    assert res["end_steps"] < table.size          # the valves' null tail is in the trace, and left out
