"""Closed-loop isolation in simulated time: the loop (Loop + SimBackend + RigPlant + the real isolation
controllers) reduces the floor-to-table transmissibility by what the controller analysis predicts.

Uniform floor motion (all mounts in phase, rho = 1), band 1-50 Hz, 1 um rms (linear range: no clamp or slew).
Passive = the same loop INACTIVE (valves at null). Measured TR = H1 = S_gt / S_gg (Welch), which averages
out the sensor noise; predicted = controllers.analysis.mimo with continuous floor motion (RigPlant interpolates
the floor between samples) and one
period of computation delay (SimBackend rig mode applies each command one period later).
"""
from __future__ import annotations

import functools

import numpy as np
import pytest
import scipy.signal

pytest.importorskip("controllers.analysis")

from controllers.analysis import DiscreteRig, mimo                     # noqa: E402
from controllers.isolation import make_isolation_controllers          # noqa: E402
from rig.runtime.clock import SimClock                                         # noqa: E402
from rig.config import config_from_dict                                # noqa: E402
from rig.runtime.lifecycle import State                                        # noqa: E402
from rig.runtime.loop import Loop                                              # noqa: E402
from sim_backend.backend import make_sim_port                         # noqa: E402
from sim_backend.rig_plant import I_TABLE, FloorMotion                # noqa: E402

RATE = 5000.0
DT = 1.0 / RATE
SECONDS = 10.0
SETTLE = 1.0
F_CHECK = np.array([3.0, 8.0, 15.0, 30.0, 45.0])


def _variant(accel_hp_hz: float):
    """The real controller class with one design parameter changed (for the runtime-fidelity test)."""
    from controllers.isolation import IsolationController, params_from_config
    return lambda cfg, dt: [IsolationController(params_from_config(cfg, i).with_(accel_hp_hz=accel_hp_hz), dt)
                            for i in range(4)]


@functools.lru_cache(maxsize=None)
def table_tr(active: bool, make=make_isolation_controllers):
    cfg = config_from_dict({"vibration": {"rms_m": 1e-6}})
    clk = SimClock()
    floor = FloorMotion(DT, band_hz=(1.0, 50.0), rms_m=1e-6, seed=7, rho=1.0)
    port = make_sim_port(cfg, DT, clock=clk, floor=floor)
    loop = Loop(cfg, port, make(cfg, DT), clock=clk, rate_hz=RATE, stop_on_fault=False)
    loop.configure()
    if active:
        loop.activate()
    n = int(SECONDS * RATE)
    g = np.empty(n)
    t = np.empty(n)
    plant = port.plant
    P = loop.period_ns
    for k in range(n):
        loop.cycle(k * P)
        g[k] = plant.floor_m[0]
        t[k] = plant.table_m
    assert loop.state is (State.ACTIVE if active else State.INACTIVE), loop.lc.fault_reason
    assert loop.limiter.clamped == 0                     # linear range: the comparison is meaningful
    s = int(SETTLE * RATE)
    f, S_gt = scipy.signal.csd(g[s:], t[s:], fs=RATE, nperseg=1 << 13)
    _, S_gg = scipy.signal.welch(g[s:], fs=RATE, nperseg=1 << 13)
    H = S_gt / S_gg
    return np.interp(F_CHECK, f, np.abs(H)), cfg


def _compare(make):
    cfg = config_from_dict({"vibration": {"rms_m": 1e-6}})
    rig = DiscreteRig(cfg, DT, f_hz=F_CHECK, ground="continuous")
    m = mimo(rig, make(cfg, DT), delay=1)
    pred_db = 20 * np.log10(np.abs(m["tr_uniform_passive"][:, I_TABLE + 1])
                            / np.abs(m["tr_uniform_controlled"][:, I_TABLE + 1]))
    if not m["stable"]:
        return m, pred_db, None
    tr_p, _ = table_tr(False)                            # passive: INACTIVE, valves null (any controller)
    tr_c, _ = table_tr(True, make)
    return m, pred_db, 20 * np.log10(tr_p / tr_c)


def test_running_loop_delivers_the_analysed_reduction():
    """Runtime fidelity on a design variant that is stable with all four loops closed (accel_hp_hz 0.3 Hz):
    the loop as it runs must give what the discrete analysis of the same controller objects predicts."""
    make = _variant(0.3)
    m, pred_db, measured_db = _compare(make)
    assert m["stable"]
    assert pred_db.max() > 2.0                           # a non-trivial reduction to reproduce
    np.testing.assert_allclose(measured_db, pred_db, atol=0.5)


def test_closed_loop_reduction_of_the_delivered_design():
    m, pred_db, measured_db = _compare(make_isolation_controllers)
    assert m["stable"], f"four-loop rig unstable with the delivered design (max |z| = {np.max(np.abs(m['poles']))})"
    assert pred_db.min() > 3.0                           # the delivered design attenuates at every check point
    np.testing.assert_allclose(measured_db, pred_db, atol=0.5)
