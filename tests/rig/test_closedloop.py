"""rig.closedloop: feedback from the measured position to the command, from the file's attributes or the data."""
import numpy as np
from scipy.signal import lfilter

from rig import closedloop

FS = 2000.0


def _plant(u: np.ndarray) -> np.ndarray:
    """A lightly damped second-order discrete plant (a stand of a few tens of Hz), one sample of delay."""
    return lfilter([0.0, 0.002], [1.0, -1.95, 0.96], u)


def test_open_loop_command_is_not_flagged():
    rng = np.random.default_rng(1)
    u = rng.standard_normal(40_000)
    y = _plant(u) + 0.01 * rng.standard_normal(len(u))
    ev = closedloop.check(u, y, FS)
    assert ev.closed is False and ev.statistic is not None and ev.statistic < closedloop.THRESHOLD


def test_command_computed_from_the_measured_position_is_flagged():
    rng = np.random.default_rng(2)
    n = 40_000
    r = rng.standard_normal(n)
    noise = 0.05 * rng.standard_normal(n)   # the sensor noise the controller feeds back
    b, a = [0.0, 0.002], [1.0, -1.95, 0.96]
    x = np.zeros(n)                     # plant output without noise
    y = np.zeros(n)                     # measured position
    u = np.zeros(n)
    for k in range(2, n):
        x[k] = -a[1] * x[k - 1] - a[2] * x[k - 2] + b[1] * u[k - 1]
        y[k] = x[k] + noise[k]
        u[k] = r[k] - 5.0 * y[k]        # the controller answers the position of its own sample
    ev = closedloop.check(u, y, FS)
    assert ev.closed is True and ev.statistic > 2 * closedloop.THRESHOLD
    assert "reacts to the measured position" in ev.reason


def test_rig_run_recordings_are_closed_loop_by_their_attributes():
    ev = closedloop.check(np.zeros(10), np.zeros(10), FS, {"command": "rig run", "isolation_at_start": "on"})
    assert ev.closed and "rig run" in ev.reason and ev.as_dict()["closed_loop"] is True


def test_too_short_says_so():
    ev = closedloop.check(np.ones(100), np.arange(100.0), FS)
    assert ev.closed is False and "too short" in ev.reason
