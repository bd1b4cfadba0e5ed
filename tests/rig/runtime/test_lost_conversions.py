"""Conversions the accelerometer module lost (a hold-up longer than its FIFO; drivers/modbus_io.py publishes a
line across them, marked as lost in the exchange block): the isolation's and the floor feedforward's double
integrations would read the line's error as a velocity, and the inverse actuator's leakage term and the isolation
gain turn the stroke that velocity integrates into a ramp of valve volts (a 2 kHz HIL run faulted so, 'not in
control'). Marked, the period that takes them suspends isolation the saturation recovery's bumpless way and
restarts the feedforward, which comes back, bumpless and as the undisturbed run's, after its restart time."""
from __future__ import annotations

import numpy as np

from controllers.feedforward import make_feedforward_filters
from controllers.isolation import make_isolation_controllers
from rig.config import MOUNTS, config_from_dict
from rig.port import Measurements
from rig.runtime import exchange as ex
from rig.runtime.kernel import MODE_ACTIVE, PeriodKernel
from sim_backend.rig_plant import FloorMotion

DT = 1 / 2000
AT, HOLD, LOST = int(4 / DT), 90, 30         # a 45 ms hold at 2 kHz, 30 conversions past a FIFO of 60


def _floor(seconds: float) -> np.ndarray:
    """(periods, 4) floor accelerations [m/s^2]: the simulated floor (3 um rms, 1-50 Hz)."""
    fm = FloorMotion(DT, rms_m=3e-6, seed=4)
    x = np.concatenate([fm.next_block(4096) for _ in range(int(seconds / DT) // 4096 + 2)])[:, :4]
    return np.diff(x, 2, axis=0)[:int(seconds / DT)] / DT ** 2


def _through_a_hold(marked: bool | None, floor: np.ndarray, isolate: bool = False):
    """The kernel over `floor`, the feedforward switched on from the start (isolation too if asked); at period AT
    it takes HOLD periods' conversions at once, the oldest LOST of them the module's line across them: marked as
    lost (marked), not marked (the module before the mark), or all real (None). Per period: the first mount's
    feedforward part, the raw commands, each mount's isolation suspended."""
    cfg = config_from_dict({"sensors": {"floor_accel": True}})
    ctrls = make_isolation_controllers(cfg, DT)
    k = PeriodKernel(cfg, ctrls, MOUNTS, DT, 50, make_feedforward_filters(cfg, DT))
    k.set_feedforward(True)
    if isolate:
        k.set_enabled(True)
    rf, rr = k.layout["ff_cmd_V"], k.layout["valve_cmd_raw_V"]
    rng = np.random.default_rng(2)
    ff, raw, sus, p, t = [], [], [], 0, 0
    while p < len(floor):
        take = HOLD if p == AT else 1
        rows = floor[p:p + take].copy()
        if p == AT and marked is not None:
            rows[:LOST] = np.linspace(floor[p - 1], floor[p + LOST], LOST + 2)[1:-1]
        if p == AT and marked:
            ex.mark_lost(k._local.io, float(k._local.counter + 1))
        convs = [np.concatenate([r, r]) for r in rows]          # the mounts ride the floor (valves open loop)
        t += take * round(DT * 1e9)
        m = Measurements(t, convs[-1][:4].tolist(), (1e-8 * rng.standard_normal(4)).tolist(), [t] * 4,
                         floor_accel_mps2=rows[-1].tolist(), accel_older=tuple(tuple(c) for c in convs[:-1]),
                         new_samples=take)
        code = k.period(m, t, t * 1e-9, 0.0, 0.0, MODE_ACTIVE, 0)
        assert code in (0, 500) or marked is False, code         # (the unmarked ramp reaches the limits' rules)
        ff += [k.row[rf]] * take                                 # the period's, held over the hold
        raw += [k.row[rr:rr + 4].copy()] * take
        sus += [k.suspended()] * take
        p += take
    return np.array(ff), np.array(raw), np.array(sus), k


def test_the_feedforward_restarts_instead_of_ramping_the_valves():
    floor = _floor(24.0)
    clean, *_ = _through_a_hold(None, floor)
    unmarked, *_ = _through_a_hold(False, floor)
    marked, _, _, k = _through_a_hold(True, floor)
    size = np.std(clean[AT - int(2 / DT):AT])                            # the feedforward's own command, rms
    after = slice(AT + HOLD, AT + HOLD + int(2 / DT))
    assert np.sqrt(np.mean((unmarked - clean)[after] ** 2)) > 5 * size   # the ramp the mark prevents
    restart_s = k.ffs[0].restart_s
    assert 10 < restart_s < 20                                           # five time constants at 0.05 Hz
    held = marked[AT + HOLD + int(0.6 / DT):AT + HOLD + int((restart_s - 0.1) / DT)]
    assert np.max(np.abs(held)) < 0.01 * size                            # faded out, then off
    steps = np.abs(np.diff(marked[AT - int(1 / DT):]))
    assert steps.max() < 1.5 * np.abs(np.diff(clean[AT - int(1 / DT):])).max()   # no jump: out, nor back in
    back = slice(AT + HOLD + int((restart_s + 1) / DT), len(floor))
    assert np.sqrt(np.mean((marked - clean)[back] ** 2)) < 0.2 * size    # back, as the undisturbed run's


def test_isolation_is_suspended_at_once_and_bumplessly():
    """The isolation's estimate is as wrong as the feedforward's: suspended in the period that takes the lost
    conversions, its output held then faded, not driven to the clamp first, and not resumed before five time
    constants of the blend (then the saturation recovery resumes it once the estimate has settled); without the
    mark it is not suspended."""
    floor = _floor(5.0)
    _, raw, sus, _ = _through_a_hold(True, floor, isolate=True)
    _, raw0, sus0, _ = _through_a_hold(None, floor, isolate=True)
    assert not sus[:AT].any() and sus[AT + HOLD - 1:].all()            # all four, in that period, and held
    #                                   (the estimate's error still grows: no resume before the blend forgets it)
    assert not sus0.any()
    fb, fb0 = raw - raw0, raw0                                           # (same feedforward part until AT)
    assert np.max(np.abs(fb[:AT])) == 0.0
    jump = np.max(np.abs(raw[AT + HOLD] - raw[AT - 1]))
    assert jump < 4 * np.max(np.abs(np.diff(raw0[AT - int(1 / DT):AT], axis=0)))   # held, not a step
    assert np.max(np.abs(raw[AT + HOLD:])) < 10.0                        # never at the clamp


def test_the_running_loop_says_it_and_isolates_again_after_the_hold(caplog):
    """The loop over the simulated rig (sample-driven, every conversion counted), one conversion marked lost at
    0.8 s as the module would: one warning line at once, each mount suspended for that reason, no fault, and
    isolation back by itself once the hold (five time constants of the 0.1 Hz blend, 8 s) is over."""
    import logging

    from rig.runtime.clock import SimClock
    from rig.runtime.loop import Loop
    from sim_backend.backend import make_sim_port
    rate = 5000.0
    cfg = config_from_dict({})
    clk = SimClock()
    port = make_sim_port(cfg, 1 / rate, clock=clk, sample_driven=True)
    ctrls = make_isolation_controllers(cfg, 1 / rate)
    loop = Loop(cfg, port, ctrls, clock=clk, rate_hz=rate, stop_on_fault=False)
    loop.configure()
    loop.activate()
    io = port.exchange.io
    a = port.exchange.part("accel")
    periods = [0]
    suspended = []

    def mark():                                  # before the port's update, which publishes the next conversion
        periods[0] += 1
        if periods[0] == int(0.8 * rate):
            ex.mark_lost(io, io[a + ex.A_NEWEST] + 1)
        if periods[0] % 500 == 0:
            suspended.append((periods[0] / rate, all(c.suspended(s) for c, s in zip(ctrls, loop.states))))
    loop.slow_down(mark)
    with caplog.at_level(logging.INFO, logger="rig.loop"):
        loop.run(seconds=11.0)
    assert loop.lc.fault_reason is None
    said = [r.message for r in caplog.records]
    lost = [m for m in said if "conversions lost past the module's FIFO" in m]
    assert len(lost) == 1 and "isolating mounts suspended until their estimate settles" in lost[0]
    assert sum("isolation suspended (conversions lost, centring alone)" in m for m in said) == 4
    assert sum("isolation resumed" in m for m in said) == 4
    held = [s for t, s in suspended if 0.9 <= t <= 8.7]
    assert held and all(held)                                  # held off throughout the hold
    assert not suspended[-1][1]                                # and isolating again
