"""Port.idle(): the simulated plant takes the coming period's step and draws its next block of floor motion
and sensor noise in the loop's slack instead of inside a period. The sequence it produces must be the same
whether or not (and whenever) the prefetch ran, and the loop must call idle() only on the real clock,
between periods."""
from __future__ import annotations

import ctypes
import dataclasses
import socket
import time

import numpy as np

from controllers.isolation import make_isolation_controllers
from rig.runtime.clock import SimClock
from rig.config import Config
from rig.runtime.loop import Loop
from drivers import can_stream
from sim_backend.backend import make_sim_port, stand_bank
from sim_backend.emulators import shared as sh
from sim_backend.emulators.canopen_valve import PlantServer, StreamGateway
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


def _bank_trace(prefetch_every: int | None, n: int = 2 * 256 + 9) -> np.ndarray:
    cfg = Config()
    cfg = cfg.replace(stand=dataclasses.replace(cfg.stand, base_motion_rms_m=5e-6))
    bank = stand_bank(cfg, DT, n=2)
    out = np.empty((n, 6))
    for k in range(n):
        if prefetch_every and k % prefetch_every == 0:
            bank.prefetch()
        bank.step([0.3, -0.2])
        out[k] = bank.accel_mps2 + bank.stroke_m + bank.table_m
    return out


def test_stand_bank_prefetch_leaves_its_sequence_unchanged():
    """The stand layout's plant (the prototype's) draws ahead too, and draws the same floor and noise."""
    ref = _bank_trace(None)
    assert np.std(ref[:, 0]) > 0                    # the floor and the noise do move it
    for every in (1, 5, 300):
        assert np.array_equal(_bank_trace(every), ref), every


def test_the_hil_plant_draws_its_next_block_between_syncs():
    """The emulated rig's plant process steps the plant on each SYNC; a refill inside that step held the SYNC's
    conversion up (every 256 steps, a held period at 2 kHz). After each SYNC it serves, the block the coming
    steps need is drawn already."""
    cfg = Config()
    plant = RigPlant(cfg, DT, floor=FloorMotion.from_config(cfg, DT), seed=5)
    arr = (ctypes.c_double * sh.SIZE)()
    server = PlantServer(arr, plant, DT, (1, 2, 3, 4), 2 * np.pi * 100, 10.0, True, 0)
    a, b = socket.socketpair()
    try:
        server.gw = StreamGateway(a)
        t0 = time.monotonic()
        for k in range(2 * RigPlant.BLOCK + 3):
            while time.monotonic() < t0 + k * DT:       # a SYNC a period (the plant keeps the wall clock's pace)
                pass
            server.handle(can_stream.pack(0x80, b""))
            assert plant._gi < RigPlant.BLOCK // 2 or plant._next is not None, k
        assert server.steps > 2 * RigPlant.BLOCK       # the SYNCs stepped it through two refills
    finally:
        a.close()
        b.close()
