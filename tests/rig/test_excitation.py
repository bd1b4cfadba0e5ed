"""Excitation signals (rig.excitation), what the diagnosis reads from a recorded command (rig.recordings.command)
and `rig chirp --levels / --multisine`."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from rig import excitation as ex
from rig.recordings.command import analyse
from rig.errors import RigError
from rig.recordings.rigformat import load_recording

FS = 2000.0
RIG = [sys.executable, "-m", "rig.cli"]


def test_odd_multisine_lines():
    e = ex.odd_multisine(FS, 20.0, 0.2, 100.0, 2.0, period_s=5.0, seed=1)
    P = int(5.0 * FS)
    assert len(e.cmd_V) == 4 * P and np.max(np.abs(e.cmd_V)) == pytest.approx(2.0)
    np.testing.assert_allclose(e.cmd_V[:P], e.cmd_V[P:2 * P])                    # periodic
    X = np.abs(np.fft.rfft(e.cmd_V[:P]))
    on = set(np.flatnonzero(X > 1e-6 * X.max()))
    assert on == set(e.info["excited_lines"])
    assert all(k % 2 == 1 for k in on)                                             # odd lines only
    odd = [k for k in range(1, 501) if k % 2 == 1]
    groups = [odd[i:i + 3] for i in range(0, len(odd) - 2, 3)]
    assert all(sum(k in on for k in g) == 2 for g in groups)                       # one in three left out
    assert min(on) * FS / P >= 0.2 and max(on) * FS / P <= 100.0


def test_multilevel_chirp_and_sweeps():
    e = ex.multilevel_chirp(FS, 10.0, 0.1, 100.0, (0.5, 1.5, 3.0), pause_s=0.5)
    n = int(10 * FS)
    assert len(e.cmd_V) == 3 * n + 2 * int(0.5 * FS)
    segs = [e.cmd_V[int(s * FS): int(s * FS) + n] for s in e.info["segment_starts_s"]]
    np.testing.assert_allclose(segs[2], 6 * segs[0], atol=1e-12)
    assert [np.max(np.abs(s)) for s in segs] == pytest.approx([0.5, 1.5, 3.0], rel=1e-3)
    lg = ex.log_sweep(FS, 20.0, 0.5, 50.0, 1.0)
    ph = np.unwrap(np.angle(__import__("scipy.signal").signal.hilbert(lg.cmd_V)))
    f_inst = np.gradient(ph) * FS / (2 * np.pi)
    assert f_inst[int(10 * FS)] == pytest.approx(5.0, rel=0.05)                   # geometric mean at mid-time
    st = ex.steps(FS, 10.0, 2.0, seed=3)
    assert np.mean(np.diff(st.cmd_V) == 0) > 0.99 and np.max(np.abs(st.cmd_V)) <= 2.0
    bn = ex.band_noise(FS, 10.0, 1.0, 50.0, 2.0, seed=3)
    F = np.abs(np.fft.rfft(bn.cmd_V)) ** 2
    f = np.fft.rfftfreq(len(bn.cmd_V), 1 / FS)
    assert F[f > 60].sum() < 0.01 * F.sum() and np.max(np.abs(bn.cmd_V)) <= 2.0


@pytest.mark.parametrize("sig, kind", [
    (lambda: ex.linear_chirp(FS, 30.0), "sweep"),
    (lambda: ex.log_sweep(FS, 30.0), "sweep"),
    (lambda: ex.multilevel_chirp(FS, 10.0), "sweep"),
    (lambda: ex.odd_multisine(FS, 30.0, period_s=5.0), "multisine"),
    (lambda: ex.band_noise(FS, 30.0), "noise"),
    (lambda: ex.steps(FS, 30.0), "steps"),
])
def test_command_kind_from_the_signal_itself(sig, kind):
    e = sig()
    c = analyse(e.cmd_V, FS)
    assert c.kind == kind, c.describe()
    if e.kind == "multilevel_chirp":
        assert c.multilevel and [s.peak_V for s in c.segments] == pytest.approx([0.5, 1.5, 3.0], rel=0.01)
    if kind == "multisine":
        assert c.period == int(5.0 * FS) and len(c.excited_lines) == len(e.info["excited_lines"])
    if e.kind in ("linear_chirp", "log_sweep"):
        assert c.sweep_law == ("linear" if e.kind == "linear_chirp" else "logarithmic")


def test_command_mid_run_starts():
    e = ex.multilevel_chirp(FS, 10.0, 0.1, 100.0, (0.5, 1.5, 3.0))
    cut = e.cmd_V[int(4.3 * FS):]                      # starts inside the first level
    c = analyse(cut, FS)
    assert c.kind == "sweep" and c.multilevel
    assert [round(s.peak_V, 2) for s in c.segments] == [0.5, 1.5, 3.0]
    assert abs(c.segments[1].i0 / FS - (10.5 - 4.3)) < 0.6
    ch = ex.linear_chirp(FS, 60.0).cmd_V[int(20.37 * FS):]
    c2 = analyse(ch, FS)
    assert c2.starts_mid_run and 30.0 < c2.band_hz[0] < 36.0


def test_for_chirp_run_checks_options():
    assert ex.for_chirp_run(FS, 10, 0.1, 100, 2.0) is None
    with pytest.raises(RigError, match="--period"):
        ex.for_chirp_run(FS, 10, 0.1, 100, 2.0, multisine=True, period_s=20.0)
    with pytest.raises(RigError, match="choose one"):
        ex.for_chirp_run(FS, 10, 0.1, 100, 2.0, multisine=True, levels_V=[1, 2])
    with pytest.raises(RigError, match="--f0/--f1"):
        ex.for_chirp_run(FS, 10, 0.1, 1500, 2.0, levels_V=[1, 2])


def _rig(*args):
    return subprocess.run(RIG + [str(a) for a in args], capture_output=True, text=True, timeout=600)


def test_rig_chirp_levels_and_multisine(tmp_path):
    out = tmp_path / "lv.h5"
    res = _rig("chirp", "--levels", "0.5,1.5,3.0", "--duration", "2", "--f0", "1", "--f1", "50", "--rate", "1000",
               "--record", out)
    assert res.returncode == 0, res.stderr
    rec = load_recording(out)
    want = ex.multilevel_chirp(1000.0, 2.0, 1.0, 50.0, (0.5, 1.5, 3.0)).cmd_V
    k0 = int(np.argmax(np.abs(rec.valve_cmd_V) > 0)) - 1           # the signal starts at sin(0) = 0
    np.testing.assert_allclose(rec.valve_cmd_V[k0:k0 + len(want)], want, atol=1e-9)
    assert rec.meta["chirp"] == "multilevel_chirp" and list(rec.meta["levels_V"]) == [0.5, 1.5, 3.0]
    out2 = tmp_path / "ms.csv"
    res = _rig("chirp", "--multisine", "--period", "1", "--duration", "3", "--f0", "1", "--f1", "50", "--rate", "1000",
               "--seed", "4", "--csv", "--record", out2)
    assert res.returncode == 0, res.stderr
    rec2 = load_recording(out2)
    c = analyse(rec2.valve_cmd_V, rec2.fs_hz)
    assert c.kind == "multisine" and c.period == 1000
    bad = _rig("chirp", "--levels", "0.5", "--record", tmp_path / "x.h5")
    assert bad.returncode == 2 and "at least two levels" in bad.stderr and "Traceback" not in bad.stderr
    bad = _rig("chirp", "--levels", "0.5,nan", "--record", tmp_path / "x.h5")
    assert bad.returncode == 2 and "expected > 0 V and <= 50 V, got 'nan'" in bad.stderr


def test_slow_narrow_band_command_at_a_low_rate_is_not_a_sine():
    """A closed loop's command logged at 10 Hz (the DaISy ball-and-beam's beam angle: a lightly damped
    oscillation near 0.27 Hz over 44 s) falls in three 0.25 Hz bins of a 4 s Welch segment; it is no single
    sine (which would refuse any claim). A real sine at that rate stays one; the unit is the command's."""
    fs, n = 10.0, 440
    rng = np.random.default_rng(0)
    w = 2 * np.pi * 0.27 / fs
    r = np.exp(-0.3 * w)
    from scipy.signal import lfilter
    u = lfilter([1.0], [1.0, -2 * r * np.cos(w), r * r], rng.standard_normal(n))
    cmd = analyse(u, fs, unit="A")
    assert cmd.kind == "noise" and cmd.describe().endswith(" A") and " V" not in cmd.describe()
    assert analyse(np.sin(2 * np.pi * 0.3 * np.arange(n) / fs), fs).kind == "sine"


def test_evidence_lengths_read_in_a_fitting_unit():
    from rig.diagnose.evidence import _length
    assert _length(-1.14e-3, "+") == "-1.14 mm" and _length(2.5e-7) == "250 nm" and _length(4.2e-5, "+") == "+42 um"
