"""One contract, every backend (python-can's back2back style): the same tests run against the simulated
backend and against the real drivers on the emulated rig. Real time, no floor vibration (clean responses);
nothing here asserts on timing."""
from __future__ import annotations

import math
import time

import pytest

from rig.backends import make_port
from rig.config import Config, HilConfig, VibrationConfig, hil_run_config
from rig.port import Commands, Measurements, Port

pytestmark = pytest.mark.hil           # the real drivers against the emulated devices, on loopback

RATE_HZ = 1000.0


def contract_config() -> Config:
    return hil_run_config(Config().replace(hil=HilConfig(rate_hz=RATE_HZ), vibration=VibrationConfig(rms_m=0.0)))


@pytest.fixture(scope="module", params=["sim", "hil"])
def backend(request):
    from rig.runtime.kernel import io_entry
    io_entry()                  # compiled before the port runs (cold numba cache: ~20 s the port would queue)
    port = make_port(contract_config(), request.param)
    port.open()
    try:
        yield request.param, port
    finally:
        port.close()
        port.close()                                   # idempotent


def periods(port, seconds, cmd=None):
    """Read (and write cmd, if given) at RATE_HZ in real time; returns the readings."""
    dt_ns = int(1e9 / RATE_HZ)
    out = []
    t = time.monotonic_ns()
    end = t + int(seconds * 1e9)
    while t < end:
        t += dt_ns
        d = t - time.monotonic_ns()
        if d > 0:
            time.sleep(d * 1e-9)
        m = port.read(t)
        out.append(m)
        if cmd is not None:
            port.write(t, Commands(list(cmd)))
    return out


def test_is_a_port_with_four_mounts(backend):
    name, port = backend
    assert isinstance(port, Port)
    assert port.n_mounts == 4 and port.name == name


def test_read_gives_finite_fresh_measurements(backend):
    _, port = backend
    ms = periods(port, 0.2, (0.0,) * 4)
    m = ms[-1]
    assert isinstance(m, Measurements)
    assert len(m.accel_mps2) == len(m.stroke_m) == len(m.sample_t_ns) == 4
    assert all(math.isfinite(x) for x in m.accel_mps2 + m.stroke_m)
    assert all(isinstance(t, int) for t in m.sample_t_ns)
    assert all(x.device_fault is None for x in ms)
    # no floor motion, valves at null: the actuators sit still (|stroke| well under a micrometre)
    assert max(abs(x) for x in m.stroke_m) < 1e-6


def test_valve_commands_move_each_actuator_its_own_way(backend):
    _, port = backend
    before = periods(port, 0.05, (0.0,) * 4)[-1].stroke_m
    ms = periods(port, 0.25, (2.0, -2.0, 1.0, 0.0))
    after = ms[-1].stroke_m
    d = [a - b for a, b in zip(after, before)]
    # DC gain about 2.68 um/V through the K_C K_L lag (7.4 Hz): most of it after 0.25 s
    assert d[0] > 2.5e-6 and d[1] < -2.5e-6
    assert 1.0e-6 < d[2] < d[0]
    assert abs(d[3]) < 0.5 * abs(d[2])
    assert all(m.device_fault is None for m in ms)


def test_safe_state_nulls_the_valves(backend):
    _, port = backend
    peak = periods(port, 0.2, (3.0, 3.0, 3.0, 3.0))[-1].stroke_m
    port.safe_state()
    ms = periods(port, 0.4)                            # reads only: nothing overrides the null
    end = ms[-1].stroke_m
    # the valve at null: the membrane spring K_L pulls each piston back (no drift, no hold of the command)
    assert all(abs(e) < 0.35 * abs(p) for e, p in zip(end, peak)), (peak, end)
    assert all(m.device_fault is None for m in ms)


def test_runtime_loop_runs_through_the_port(backend):
    """The runtime's loop (rig/runtime/loop.py) on this backend: INACTIVE then ACTIVE with a centring law."""
    from rig.runtime.lifecycle import State
    from rig.runtime.loop import Loop
    from tests.rig.support import CentringP

    _, port = backend
    cfg = contract_config()
    centring = [CentringP(2e5, dt=1.0 / RATE_HZ) for _ in range(4)]      # stroke centring: valve = -k * stroke
    loop = Loop(cfg, port, centring, rate_hz=RATE_HZ, watchdog_thread=False)
    loop.configure()                                   # the port is open already: open() is idempotent
    reason = loop.run(seconds=0.5, activate_after_s=0.05)
    assert reason == "time", loop.lc.fault_reason
    assert loop.lc.state is not State.FAULT
    assert loop.iterations >= 100
