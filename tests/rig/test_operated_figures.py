"""The operated run's motion figures (rig/operated.py): the load's motion in 1-100 Hz that `rig run --layout
prototype` prints per segment is the rms of the curve its plot draws, and it reads a known motion right, in a
long segment and in a short one near the recording's end (issue 29: the summary said 7.618 um where the plot's
legend said 7.46 um for the same run)."""
from __future__ import annotations

import numpy as np
import pytest

from rig import operated

FS_HZ = 5000.0


def _run(freq_hz: float, amp_m: float, seconds: float = 4.0, switch_s: float | None = None) -> operated.OperatedRun:
    """A stand tracking in place while its load moves amp_m sin(2 pi f t) (its accelerometer reads the second
    derivative); the transducer reads the same motion (the floor stands still). A mode request at switch_s."""
    t = np.arange(0.0, seconds, 1.0 / FS_HZ)
    x = amp_m * np.sin(2 * np.pi * freq_hz * t + 0.3)
    n = len(t)
    events = [(switch_s, "stand: mode hold")] if switch_s is not None else []
    return operated.OperatedRun("synthetic.h5", "stand", t, np.full(n, 2.0), np.zeros(n), np.zeros(n), x,
                                -(2 * np.pi * freq_hz) ** 2 * x, np.zeros(n), np.zeros(n), np.ones(n, bool), events)


@pytest.mark.parametrize("freq_hz", [5.0, 37.0, 90.0])
def test_a_known_motion_reads_its_rms_in_a_long_segment_and_a_short_last_one(freq_hz):
    """Within 3 % over a long segment, within 5 % over the last 0.15 s of a recording (above 30 Hz: a stretch
    that short holds a few periods of those only)."""
    run = _run(freq_hz, 10e-6, switch_s=3.3)           # track 0-3.3 s, then hold for 0.7 s to the end
    figs = operated.figures(run)
    assert [d["request"] for d in figs] == ["track", "hold"]
    for d, rel in zip(figs, (0.03, 0.05 if freq_hz > 30 else None)):
        lo, hi = d["motion_s"]
        win = (run.t_s >= lo) & (run.t_s <= hi)
        true_um = np.sqrt(np.mean(run.position_m[win] ** 2)) * 1e6      # the motion's own rms over that stretch
        if rel is not None:
            assert d["load_motion_um"] == pytest.approx(true_um, rel=rel), (freq_hz, d, true_um)
    assert figs[0]["floor_motion_um"] < 0.1 * figs[0]["load_motion_um"]  # load - transducer: the floor stood still


def test_the_printed_figure_is_the_drawn_curves_rms_over_its_unshaded_stretch():
    import matplotlib.pyplot as plt
    run = _run(5.0, 10e-6)
    figs = operated.figures(run)
    fig = operated.figure(run, figs)
    try:
        ax = next(a for a in fig.axes if a.get_ylabel().startswith("motion"))
        load = next(np.asarray(ln.get_ydata()) for ln in ax.get_lines() if ln.get_label().startswith("load"))
        shaded = [p.get_x() for p in ax.patches]
        texts = [t.get_text() for t in ax.texts]
    finally:
        plt.close(fig)
    (d,) = figs
    lo, hi = d["motion_s"]
    assert d["from_s"] < lo and hi < d["to_s"] and len(shaded) == 2     # settling and the faded end: shaded
    win = (run.t_s >= lo) & (run.t_s <= hi)
    assert np.sqrt(np.mean(load[win] ** 2)) == pytest.approx(d["load_motion_um"], rel=1e-9)
    assert texts == [f"load {d['load_motion_um']:.3f}\nfloor {d['floor_motion_um']:.3f} um"]
    assert f"load {d['load_motion_um']:.3f} um rms in 1-100 Hz" in operated.figures_text(figs)


def test_a_segment_inside_the_faded_end_says_so_rather_than_a_figure():
    run = _run(5.0, 10e-6, switch_s=3.9)               # hold for the last 0.1 s: within the band's faded end
    figs = operated.figures(run)
    assert "load_motion_um" not in figs[-1] and "load_motion_um" in figs[0]
    assert "load not judged (in the recording's last 0.2 s" in operated.figures_text(figs).splitlines()[-1]
