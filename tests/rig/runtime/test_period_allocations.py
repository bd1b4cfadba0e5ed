"""The loop's period over an exchange block (the drivers' path: the kernel takes the I/O processes' conversions and
samples and writes the commands itself) allocates nothing per period: no numba wrapper per array argument, no
Python object that outlives the period; and it wakes the valves' I/O when that waits for the period's commands."""
from __future__ import annotations

import tracemalloc

import numpy as np
import pytest
from numba.core.runtime import _nrt_python as nrt

from controllers.isolation import make_isolation_controllers
from rig.config import Config
from rig.runtime import exchange as ex
from rig.runtime.clock import MonotonicClock
from rig.runtime.loop import Loop

N, RATE = 4, 2000.0
P = int(1e9 / RATE)


class BlockPort:
    """A port whose devices' side is this test: conversions, transducer samples and heartbeats put into its
    exchange block between periods, as the I/O processes do (drivers/process.py)."""
    name, n_mounts, floor_sensors = "block", N, False

    def __init__(self) -> None:
        self.exchange = ex.Block.local(ex.Layout(N, 0, devices=("valves", "module", "amplifier")))
        self.io = self.exchange.io
        self.io[self.exchange.part("accel") + ex.A_COUNTED] = 1.0
        self._dev = self.exchange.part("devices")
        self.k = 0
        self._ts, self._acc, self._xs = np.zeros(N), np.zeros(N), np.zeros(N)

    def open(self) -> None:
        pass

    def close(self) -> None:
        pass

    def safe_state(self) -> None:
        ex.safe(self.exchange)

    def feed(self, t_ns: int) -> None:
        """One conversion and one transducer sample taken one period before t_ns."""
        k = self.k
        self._ts[:] = t_ns - P
        self._acc[:] = 1e-4 * np.sin(0.3 * k)
        self._xs[:] = 1e-7 * np.sin(0.3 * k + 0.1)          # moving: never "stuck"
        ex.put_conversion(self.io, float(k), self._ts, self._acc)
        ex.put_sample(self.io, float(k), float(t_ns - P), self._xs)
        for d in range(3):
            self.io[self._dev + d * len(ex.DEVICE_ROW) + ex.D_BEAT] = t_ns
        self.k = k + 1


def active_loop():
    """The loop on the real clock (its 10 Hz watch then runs in the slack after a period, not in the period),
    its periods called here without the scheduler's waits."""
    cfg = Config()
    port = BlockPort()
    loop = Loop(cfg, port, make_isolation_controllers(cfg, 1 / RATE), clock=MonotonicClock(spin_ns=0),
                rate_hz=RATE, watchdog_thread=False, rate_check=False)
    loop.configure()
    loop.activate()
    return loop, port


def run(loop, port, periods: int, t0: int) -> int:
    t = t0
    for _ in range(periods):
        t += P
        port.feed(t)
        loop.cycle(t)
        loop._slack()                                    # the scheduler's call in the slack after a period
    assert loop.lc.fault_reason is None, loop.lc.fault_reason
    return t


def test_the_compiled_period_allocates_nothing():
    loop, port = active_loop()
    t = run(loop, port, 20, 0)
    was = nrt.memsys_stats_enabled()
    nrt.memsys_enable_stats()
    made = [0, 0]
    try:
        for _ in range(500):
            t += P
            port.feed(t)                                 # (the test's side: not the period)
            before = (nrt.memsys_get_stats_alloc(), nrt.memsys_get_stats_mi_alloc())
            loop.cycle(t)
            made[0] += nrt.memsys_get_stats_alloc() - before[0]
            made[1] += nrt.memsys_get_stats_mi_alloc() - before[1]
            loop._slack()
    finally:
        if not was:
            nrt.memsys_disable_stats()
    assert loop.lc.fault_reason is None, loop.lc.fault_reason
    assert made == [0, 0], f"numba allocated {made[0]} buffers and {made[1]} reference-counted wrappers in 500 periods"
    assert loop.kernel.commands() != (0.0,) * N          # the controllers ran and wrote


def test_the_period_keeps_no_python_object():
    loop, port = active_loop()
    t = run(loop, port, 50, 0)
    tracemalloc.start()
    try:
        t = run(loop, port, 50, t)                       # the tracer's own first allocations
        t0 = t
        for _ in range(2000):
            t += P
            port.feed(t)                                 # (the test's side: not the period)
            snap = tracemalloc.get_traced_memory()[0]
            loop.cycle(t)
            assert tracemalloc.get_traced_memory()[0] <= snap, f"period {(t - t0) // P} kept an object"
            loop._slack()
    finally:
        tracemalloc.stop()
    assert loop.lc.fault_reason is None, loop.lc.fault_reason


@pytest.mark.parametrize("waiting", [False, True])
def test_a_waiting_valves_io_is_woken_after_the_commands(waiting):
    loop, port = active_loop()
    t = run(loop, port, 20, 0)
    io, c = port.io, port.exchange.part("cmd")
    seq, woken = io[c + ex.C_SEQ], int(port.exchange.futex[ex.FUTEX_CMD])
    if waiting:
        assert ex.ask_wake(io) == seq                    # the valves' I/O: about to sleep on the command futex
    run(loop, port, 1, t)
    assert io[c + ex.C_SEQ] == seq + 2                   # the period's commands written (the sequence lock)
    assert io[c + ex.C_WAITER] == 0.0
    assert int(port.exchange.futex[ex.FUTEX_CMD]) == woken + (1 if waiting else 0)
