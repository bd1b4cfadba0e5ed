"""Sample-driven stepping (drivers/port.py, rig/runtime/loop.py): with an accelerometer module that converts on SYNC
into a FIFO, late Modbus replies must not reach the controllers' double integration as timing slips. A port
that delivers the same conversion stream late (some periods nothing new, the next period two or three) must
leave the controllers exactly where on-time delivery leaves them; delivering it the naive way (repeat the last
value, then skip to the newest) must not - that is the error the mechanism exists for."""
from __future__ import annotations

import random

import pytest

from controllers.isolation import make_isolation_controllers
from rig.runtime.clock import SimClock
from rig.config import Config
from rig.runtime.loop import Loop
from sim_backend.backend import make_sim_port

RATE = 500.0
PERIODS = 1500


class LateAccelPort:
    """The simulated rig behind a port that delivers accelerometer conversions late, as the Modbus FIFO port
    does: per period, with probability p_late nothing new (up to two periods in a row), else every pending
    conversion. sample_driven=False delivers the naive way instead: the last value again, then the newest
    (the conversions in between are lost)."""

    def __init__(self, inner, p_late: float, seed: int, sample_driven: bool = True):
        self.inner = inner
        self.n_mounts = inner.n_mounts
        self.name = "late-accel"
        self.p_late = p_late
        self.rng = random.Random(seed)
        self.sample_driven = sample_driven
        self.pending: list[list[float]] = []
        self.last = [0.0] * self.n_mounts
        self.late_periods = 0

    def open(self):
        self.inner.open()

    def close(self):
        self.inner.close()

    def safe_state(self):
        self.inner.safe_state()

    def write(self, t_ns, commands):
        self.inner.write(t_ns, commands)

    def read(self, t_ns):
        m = self.inner.read(t_ns)
        self.pending.append(list(m.accel_mps2))
        late = len(self.pending) < 3 and self.rng.random() < self.p_late
        if late:
            self.late_periods += 1
            m.accel_mps2 = list(self.last)
            if self.sample_driven:
                m.new_samples, m.accel_older = 0, ()
            return m
        self.last = self.pending[-1]
        m.accel_mps2 = list(self.last)
        if self.sample_driven:
            m.new_samples, m.accel_older = len(self.pending), tuple(self.pending[:-1])
        self.pending = []
        return m


def run_inactive(p_late: float, sample_driven: bool = True, seed: int = 3):
    """INACTIVE run (valves at null, so the plant does not depend on the controllers): the states of the
    controllers' accelerometer path (the band-limited double integration H/s^2, which sees acceleration only;
    the stroke of a late period is the current one) and the number of late periods."""
    cfg = Config()
    dt = 1.0 / RATE
    clock = SimClock()
    inner = make_sim_port(cfg, dt, clock=clock)
    port = LateAccelPort(inner, p_late, seed, sample_driven)
    loop = Loop(cfg, port, make_isolation_controllers(cfg, dt), clock=clock, rate_hz=RATE, isolation=False)
    loop.configure()
    t = 0
    for _ in range(PERIODS):
        t += loop.period_ns
        clock.t_ns = t
        loop.cycle(t)
    assert loop.lc.fault_reason is None
    if not port.pending:                                     # the stream is complete at the end
        acc_path = slice(0, 2 * len(loop.ctrls[0].h_acc))
        return [list(s)[acc_path] for s in loop.states], port.late_periods
    raise AssertionError("the run ended on a late period; pick another seed")


def test_late_conversions_reach_the_controllers_exactly():
    ref, n0 = run_inactive(0.0)
    late, n = run_inactive(0.08)
    assert n0 == 0 and n > 60                                # about 8 % of the periods were late
    for r, s in zip(ref, late):
        assert s == pytest.approx(r, rel=1e-9, abs=1e-15)
        assert max(abs(x) for x in r) > 1e-9                 # a live state, not zeros


def test_naive_repeat_and_skip_corrupts_the_double_integration():
    ref, _ = run_inactive(0.0, sample_driven=False)
    naive, n = run_inactive(0.08, sample_driven=False)
    assert n > 60
    for r, s in zip(ref, naive):
        size = max(abs(x) for x in r)
        assert max(abs(a - b) for a, b in zip(r, s)) > 0.1 * size
