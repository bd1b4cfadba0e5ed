"""Port.idle(): the simulated plant takes the coming period's step and draws its next block of floor motion
and sensor noise in the loop's slack instead of inside a period. The sequence it produces must be the same
whether or not (and whenever) the prefetch ran, and the loop must call idle() only on the real clock,
between periods."""
from __future__ import annotations

import numpy as np

from controllers.isolation import make_isolation_controllers
from rig.runtime.clock import SimClock
from rig.config import Config
from rig.runtime.loop import Loop
from sim_backend.backend import make_sim_port
from sim_backend.rig_plant import FloorMotion, RigPlant

DT = 2e-4


def _trace(prefetch_every: int | None, n: int = 3 * RigPlant.BLOCK + 17) -> np.ndarray:
    cfg = Config()
    plant = RigPlant(cfg, DT, floor=FloorMotion.from_config(cfg, DT), seed=5)
    out = np.empty((n, 9))
    for k in range(n):
        if prefetch_every and k % prefetch_every == 0:
            plant.prefetch()
        plant.step([0.3, -0.2, 0.1, 0.0])
        out[k] = plant.accel_mps2 + plant.stroke_m + [plant.table_m]
    return out


def test_prefetch_leaves_the_plant_sequence_unchanged():
    ref = _trace(None)
    for every in (1, 7, 200):
        assert np.array_equal(_trace(every), ref), every


class _RealLikeClock(SimClock):
    """Simulated time that the loop treats as real (so it uses idle()); every period has its full slack."""
    is_real = True


def test_loop_calls_idle_between_periods_on_the_real_clock_only():
    cfg = Config()
    calls = {}
    for clock in (SimClock(), _RealLikeClock()):
        port = make_sim_port(cfg, DT, clock=clock)
        n = [0]
        real_idle = port.idle

        def idle(real_idle=real_idle, n=n):
            n[0] += 1
            real_idle()
        port.idle = idle
        loop = Loop(cfg, port, make_isolation_controllers(cfg, DT), clock=clock, rate_hz=1 / DT,
                    watchdog_thread=False)
        loop.run(iterations=600, activate_after_s=0.01)
        m = loop.last_meas
        calls[clock.is_real] = (n[0], loop.iterations, m.accel_mps2 + m.stroke_m + list(loop.cmd),
                                np.array(loop.states, copy=True), port._k)
    assert calls[False][0] == 0
    assert calls[True][0] == calls[True][1] == 600
    # the same run, bit for bit: measurements, commands and controller states (the plant stepped in idle)
    assert calls[True][2] == calls[False][2]
    assert np.array_equal(calls[True][3], calls[False][3])
    assert calls[True][4] == calls[False][4] + 1        # idle took the coming period's step ahead of read


def test_idle_step_then_late_read_hands_over_every_conversion():
    """A step taken in idle, then a read three periods later: the port still reports three new conversions,
    the two unread ones as accel_older, the same values as a port that stepped everything in read."""
    from rig.port import Commands
    cfg = Config()
    P = int(round(DT * 1e9))
    out = []
    for use_idle in (False, True):
        port = make_sim_port(cfg, DT)
        port.read(0)
        port.write(0, Commands([0.5, -0.5, 0.2, 0.1]))
        if use_idle:
            port.idle()
            assert port._k == 1
        m = port.read(3 * P)
        out.append((m.new_samples, [list(a) for a in m.accel_older], m.accel_mps2, m.stroke_m))
    assert out[0] == out[1]
    assert out[1][0] == 3 and len(out[1][1]) == 2
