"""Lifecycle transitions and write gating of the loop, in simulated time (SimClock, lockstep SimBackend)."""
from __future__ import annotations

import pytest

from rig.runtime.clock import SimClock
from rig.config import Config, config_from_dict
from rig.errors import RigError
from rig.runtime.lifecycle import Lifecycle, State
from rig.runtime.loop import Loop
from sim_backend.backend import SimBackend
from tests.rig.support import CentringP, TinyPlant

RATE = 5000.0
DT = 1.0 / RATE


class CountingPort(SimBackend):
    """The real SimBackend, plus a log of every set of commands written (what the valve got, per period): by
    the period's kernel into the exchange block (seen at the port's commit), or by write()."""

    def __init__(self, *a, **kw):
        super().__init__(*a, **kw)
        self.log: list[tuple[int, list[float]]] = []
        self._logged = 0

    def write(self, t_ns, commands):
        super().write(t_ns, commands)
        self.commit(t_ns)

    def commit(self, t_ns):
        if self.writes != self._logged:
            self._logged = self.writes
            self.log.append((t_ns, self.last_written))


def make(cfg=None, n=4, kp=2e5, **loop_kw):
    cfg = cfg or Config()
    clk = SimClock()
    port = CountingPort(TinyPlant(n, DT), DT, clock=clk)
    loop = Loop(cfg, port, [CentringP(kp) for _ in range(n)], clock=clk, rate_hz=RATE, **loop_kw)
    return loop, port, clk


def test_lifecycle_allowed_and_refused_transitions():
    lc = Lifecycle()
    assert lc.state is State.UNCONFIGURED and not lc.writes_allowed
    with pytest.raises(RigError, match="cannot activate from UNCONFIGURED"):
        lc.activate()
    lc.configure()
    assert lc.state is State.INACTIVE and not lc.writes_allowed
    lc.activate()
    assert lc.writes_allowed
    lc.deactivate()
    assert lc.state is State.INACTIVE
    lc.activate()
    assert lc.fault("x") is True and lc.state is State.FAULT and not lc.writes_allowed
    assert lc.fault("y") is False and lc.fault_reason == "x"       # first reason kept
    with pytest.raises(RigError):
        lc.activate()                                                # no way out of FAULT but reset
    lc.reset()
    assert lc.state is State.INACTIVE and lc.fault_reason is None


def test_inactive_writes_null_active_writes_commands():
    loop, port, clk = make()
    loop.configure()
    loop.run(iterations=50)
    assert loop.state is State.INACTIVE
    assert len(port.log) == 50 and all(u == [0.0] * 4 for _, u in port.log)   # valve held at null
    # the centring law wants a non-zero command (the plant starts off-centre): only ACTIVE may send it
    assert any(abs(r) > 0.01 for r in loop.raw)


def test_activation_ramps_and_centres_without_jump():
    cfg = Config()
    loop, port, clk = make(cfg)
    loop.configure()
    loop.stop_reason = None
    loop.run(iterations=20, activate_after_s=10 * DT)
    # activation after 10 periods; from then on each write moves at most one slew step from the last
    step = cfg.safety.slew_V_per_s * DT
    cmds = [u for _, u in port.log]
    # 20 periods, the last the stop's: null written by the deactivation at its start and by the INACTIVE period
    assert len(cmds) == 21 and cmds[-1] == cmds[-2] == [0.0] * 4
    cmds = cmds[:19]
    assert cmds[9] == [0.0] * 4 and any(abs(v) > 0 for v in cmds[12])
    for a, b in zip(cmds[9:], cmds[10:]):
        assert max(abs(x - y) for x, y in zip(a, b)) <= step + 1e-12


def test_reactivation_does_not_jump():
    cfg = Config()
    loop, port, clk = make(cfg, kp=2e6)
    loop.configure()
    loop.activate()
    for k in range(2000):
        loop.cycle(k * loop.period_ns)
    before = list(loop.cmd)
    assert max(abs(v) for v in before) > 0.05          # a real, non-trivial command was being sent
    loop.deactivate()
    for k in range(2000, 2100):
        loop.cycle(k * loop.period_ns)
    assert port.log[-1][1] == [0.0] * 4                 # inactive: null
    n0 = len(port.log)
    loop.activate()
    for k in range(2100, 2110):
        loop.cycle(k * loop.period_ns)
    step = cfg.safety.slew_V_per_s * DT
    first = port.log[n0][1]
    assert max(abs(v) for v in first) <= step + 1e-12   # starts from null, not from the old command
    for a, b in zip(port.log[n0:], port.log[n0 + 1:]):
        assert max(abs(x - y) for x, y in zip(a[1], b[1])) <= step + 1e-12


def test_fault_nulls_valve_stops_writes_and_reset_needs_acknowledgement(caplog):
    loop, port, clk = make(stop_on_fault=False)
    loop.configure()
    loop.activate()
    for k in range(100):
        loop.cycle(k * loop.period_ns)
    n_writes = len(port.log)
    loop.fault("operator test")
    assert port.safe_calls == 1 and port.last_written == [0.0] * 4
    for k in range(100, 150):
        loop.cycle(k * loop.period_ns)
    assert len(port.log) == n_writes                    # no writes at all in FAULT
    with pytest.raises(RigError):
        loop.activate()
    loop.reset_fault()
    assert loop.state is State.INACTIVE
    loop.activate()
    loop.cycle(150 * loop.period_ns)
    assert loop.state is State.ACTIVE and len(port.log) == n_writes + 1


def test_isolation_switch_is_bumpless_with_the_real_controllers():
    """Toggle isolation on the four-mount simulated rig under floor motion: no command jump at the switch."""
    pytest.importorskip("controllers.isolation")
    from controllers.isolation import make_isolation_controllers
    from sim_backend.backend import make_sim_port
    cfg = config_from_dict({"vibration": {"rms_m": 1e-6}})
    clk = SimClock()
    port = make_sim_port(cfg, DT, clock=clk)
    loop = Loop(cfg, port, make_isolation_controllers(cfg, DT), clock=clk, rate_hz=RATE, isolation=True)
    loop.configure()
    loop.activate()
    P = loop.period_ns
    hist = []
    for k in range(6000):
        if k == 3000:
            loop.request_isolation(False)
        if k == 4500:
            loop.request_isolation(True)
        loop.cycle(k * P)
        hist.append(list(loop.cmd))
    assert loop.state is State.ACTIVE
    typical = max(max(abs(a - b) for a, b in zip(hist[k], hist[k + 1])) for k in range(2000, 2990))
    for k0 in (3000, 4500):
        jump = max(max(abs(a - b) for a, b in zip(hist[k], hist[k + 1])) for k in range(k0 - 2, k0 + 3))
        assert jump <= 2 * typical + 1e-3, (k0, jump, typical)
