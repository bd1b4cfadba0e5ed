"""Port.idle(): the simulated plant draws its next block of floor motion and sensor noise in the loop's slack
instead of inside a period. The sequence it produces must be the same whether or not (and whenever) the
prefetch ran, and the loop must call idle() only on the real clock, between periods."""
from __future__ import annotations

import numpy as np

from controllers.isolation import make_isolation_controllers
from rig.clock import SimClock
from rig.config import Config
from rig.loop import Loop
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
        calls[clock.is_real] = (n[0], loop.iterations, port.plant.table_m)
    assert calls[False][0] == 0
    assert calls[True][0] == calls[True][1] == 600
    assert calls[True][2] == calls[False][2]            # the same run, bit for bit
