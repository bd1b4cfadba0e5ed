"""SensorCheck's fast path (a few C-level calls for the common period) must decide exactly as the mount-by-mount
check does: the same fault text on the same period, the same stuck counting, for any sequence of values."""
from __future__ import annotations

import math

from hypothesis import given, settings
from hypothesis import strategies as st

from rig.config import Config
from rig.port import Measurements
from rig.safety import SensorCheck

CFG = Config()
P = 200_000
STALE_PERIODS = round(CFG.safety.stale_s * 1e9) // P
# mostly plausible values from a small set (so repeats, i.e. stuck counting, are common), now and then an
# implausible one: out of range, NaN, inf, or a sample time stamp at and beyond the staleness limit
VALUE = st.sampled_from([0.0, 1e-3, -2e-3, 5e-6] * 6 + [1e3, math.nan, math.inf])
STROKE = st.sampled_from([0.0, 1e-6, -1e-6, 3e-6] * 6 + [1.0, math.nan, -math.inf])
AGE = st.sampled_from([0] * 12 + [1, STALE_PERIODS, STALE_PERIODS + 1, 2 * STALE_PERIODS + 1])
MOUNT = st.tuples(VALUE, STROKE, AGE)
PERIOD = st.lists(MOUNT, min_size=4, max_size=4)


class _MountByMount(SensorCheck):
    def check(self, m, t_ns):
        if m.device_fault:
            return f"device fault: {m.device_fault}"
        return self._check_each(m.accel_mps2, m.stroke_m, m.sample_t_ns, t_ns)


def _meas(k, period):
    t = (k + 20_000) * P
    return t, Measurements(t, [p[0] for p in period], [p[1] for p in period], [t - p[2] * P for p in period])


@settings(max_examples=400, deadline=None)
@given(st.lists(PERIOD, min_size=1, max_size=40))
def test_fast_path_decides_like_the_mount_by_mount_check(periods):
    cfg = Config(safety=CFG.safety.__class__(stuck_samples=3))
    fast, ref = SensorCheck(cfg, 4), _MountByMount(cfg, 4)
    for k, period in enumerate(periods):
        t, m = _meas(k, period)
        got, want = fast.check(m, t), ref.check(m, t)
        assert got == want, (k, period)
        if want is not None:
            break
        assert fast._same_a == ref._same_a and fast._same_x == ref._same_x


def test_a_repeated_value_among_fresh_ones_is_counted_to_stuck():
    check = SensorCheck(Config(safety=CFG.safety.__class__(stuck_samples=3)), 4)
    reasons = []
    for k in range(5):
        t = (k + 1) * P
        m = Measurements(t, [1e-3 * (k + 1), 2e-3 * (k + 1), 0.25, 3e-3 * (k + 1)], [1e-6 * k] * 4, [t] * 4)
        reasons.append(check.check(m, t))
    assert reasons[:3] == [None, None, None]
    assert reasons[3] is not None and "rear_left: accelerometer stuck at 0.25" in reasons[3]
