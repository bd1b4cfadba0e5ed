"""The period kernel: sensor check -> controllers -> command limit -> recording row, one compiled call per
period for any number of mounts (1..8), over one float64 memory block it owns.

The rules are the compiled functions of their own modules (rig/runtime/safety.py: check_sensors, limit_commands;
controllers/*.py: one law per controller kind); this module only arranges them and the memory. Per mount the
kernel dispatches on the controller's kind (off, isolation, playback, PID, operating modes) with that mount's
own named state and coefficients, so mounts can run different kinds. A controller may publish some of its
state as recording channels of their own (`published`: the operating modes' mode, reference and tracking
error); the row gets one channel per published name, one column per mount (NaN where a mount has none). Skipped periods are replayed here (the measurement
interpolated from the last period's to this one's: holding it would leave the double integration of
acceleration a velocity error), and a sample-driven port's older conversions are stepped here, in order.

With floor accelerometers ([sensors] floor_accel) the kernel takes a fourth per-mount input, floor_accel, checks
it (check_floor) and runs each mount's floor feedforward (controllers/feedforward.py feedforward_step) beside
its controller, whatever the controller's kind: the feedforward's command is added to the controller's before
the limits. Its filters always run; switching it (set_feedforward) fades its output in or out. A period whose
conversions include one the module lost (the exchange block's accel LOST mark) first suspends each mount's
isolation and restarts its feedforward (_after_loss).

The block (`mem`), its parts named by the header below: the inputs of the period, the older conversions, the
previous measurement, the safety limits and states, the mount table (kind, coefficients, state per mount), the
coefficients, the controller states and the recording row (rig/runtime/layout.py RowLayout offsets); its header
also holds the addresses of the exchange block and of the recorder's ring the period reads and writes
(bind_io, bind_ring). The period's call takes the block's address and the period's numbers only: numba
unboxes an array argument through a reference-counted wrapper, allocated and freed per call, and the call's
unboxing is most of the cost of a period this size.
"""
from __future__ import annotations

import functools
import struct
from pathlib import Path

import numba
import numpy as np
from numba.core import types
from numba.extending import intrinsic

from controllers import isolation, modes, playback, tracking
from controllers.compiled_cache import drop_stale
from controllers.feedforward import STATE_EXTRA as FF_STATE_EXTRA, feedforward_restart, feedforward_step
from controllers.isolation import isolation_step, isolation_suspend
from controllers.modes import modes_step, modes_suspend
from controllers.playback import playback_step
from controllers.timebase import same_period
from controllers.tracking import track_step
from rig.config import MAX_MOUNTS, Config
from rig.errors import ConfigError
from rig.port import Measurements
from rig.runtime import exchange as ex
from rig.runtime import ring as ring_rule
from rig.runtime.layout import RowLayout, loop_channels
from rig.runtime.measured import MeasuredBlock
from rig.runtime.recorder import Channel
from rig.runtime.safety import (CHECK_STATE, LIMITER_FLAGS, LIMITS, CommandLimiter, OscillationRule, SensorCheck,
                        _F_LIMITED, _F_SATRUN, _L_OSC_N, OSC_STATE, check_floor, check_oscillation, check_sensors,
                        limit_commands)

def _drop_stale_cache() -> None:
    """The period compiles in the exchange block's and the safety rules' constants (rig/runtime/exchange.py,
    safety.py) and the control laws with their state and coefficient layouts (controllers/): when any of those
    files changes, this module's cached code is dropped (controllers/compiled_cache.py)."""
    here = Path(__file__).resolve()
    laws = sorted((here.parents[2] / "controllers").glob("*.py"))
    drop_stale(here, [here, here.with_name("exchange.py"), here.with_name("safety.py"), *laws])


_drop_stale_cache()

KIND_OFF = 0
KINDS = {KIND_OFF: "off", isolation.KIND: "isolation", playback.KIND: "playback", tracking.KIND: "pid",
         modes.KIND: "modes"}
_ISO, _PLAY, _PID, _MODES = isolation.KIND, playback.KIND, tracking.KIND, modes.KIND
OLDER_CAP = 128             # conversions taken in one period besides the newest (a hold-up of 64 ms at 2 kHz)

MODE_FAULT, MODE_INACTIVE, MODE_ACTIVE = 0, 1, 2    # FAULT records only; INACTIVE steps, writes null
# the inputs, then MOUNT_INPUTS; state .. skipped: the row's flag columns (the lifecycle state, isolation on, the
# scheduler's overrun and skipped counts at the period's start)
INPUTS = ("t_ns", "t_s", "wake_us", "comp_us", "mode", "miss", "n_older", "step", "state", "isolation",
          "overruns", "skipped", "lost")
MOUNT_INPUTS = ("accel", "stroke", "sample_t", "floor_accel", "stroke_t")   # n each; floor_accel: floor sensors
(_IN_T_NS, _IN_T_S, _IN_WAKE, _IN_COMP, _IN_MODE, _IN_MISS, _IN_OLDER, _IN_STEP, _IN_STATE, _IN_ISO, _IN_OVER,
 _IN_SKIP, _IN_LOST) = range(len(INPUTS))
_FAULT_STATE = 3.0          # rig.runtime.lifecycle.State.FAULT (the row's fault column)
MOUNT_TABLE = ("kind", "coef", "n_coef", "state", "n_state")
HEADER = ("n", "inputs", "older", "prev", "limits", "check", "last_cmd", "flags", "mounts", "states",
          "n_states", "row", "n_row", "max_held", "r_time", "r_accel", "r_stroke", "r_cmd", "r_raw", "r_state",
          "r_limited", "r_wake", "r_comp", "n_pub", "pub", "r_pub", "osc", "n_floor", "ff", "r_floor", "r_ff",
          "r_ff_on", "r_flags", "dt_ns", "a_last", "t_prev", "held_up", "x_age", "lost_t", "size", "io_at",
          "ring_at", "ring_rows", "hdr_at")
(_H_N, _H_IN, _H_OLDER, _H_PREV, _H_LIM, _H_CHK, _H_LAST, _H_FLAGS, _H_MOUNTS, _H_ST, _H_NST, _H_ROW, _H_NROW,
 _H_MAXHELD, _H_RT, _H_RA, _H_RX, _H_RC, _H_RR, _H_RS, _H_RL, _H_RW, _H_RP, _H_NPUB, _H_PUB, _H_RPUB, _H_OSC,
 _H_NFL, _H_FF, _H_RG, _H_RF, _H_RO, _H_RFLAGS, _H_DTNS, _H_ALAST, _H_TPREV, _H_HELD, _H_XAGE, _H_LOSTT, _H_SIZE,
 _H_IOAT, _H_RINGAT, _H_RINGROWS, _H_HDRAT) = range(len(HEADER))
# The period's input rules over the exchange block (codes beside the safety rules' of rig/runtime/safety.py)
CHECK_STROKE_STALE = 1000   # the transducer's newest sample older than its own limit (it is held between frames)
DEVICE_FAULT = 1100         # + device: a device reported a fault (its line: the block's text part)
DEVICE_SILENT = 1200        # + device: a device's I/O has not reported for longer than its limit
BEHIND = 1300               # the loop fell further behind the accelerometer module than it replays
NO_SAMPLE = 1400            # no conversion (or no transducer sample) published yet
WAKE_COMMANDS = -1          # not a rule: the valves' I/O waits for the period's commands (the caller wakes it)
_OSC_KINDS = (isolation.KIND, tracking.KIND, modes.KIND)      # feedback kinds the oscillation rule checks
# The feedforward part of the block: the floor range, then per mount FF_TABLE
FF_TABLE = ("coef", "n_sections", "state", "fade")


# the recorder ring's producer rule (rig/runtime/ring.py), compiled into the period
_publish = numba.njit(cache=True, inline="always")(ring_rule.publish)
_claim = numba.njit(cache=True, inline="always")(ring_rule.claim)


@numba.njit("void(float64[::1], float64, float64, float64, float64)", cache=True)
def row_flags(mem, state, isolation, overruns, skipped):
    """The row's flag columns (layout.FLAG_CHANNELS: lifecycle_state, isolation_on, fault, overruns,
    skipped_periods, in this order): every period in run_period, and by the loop after a period faulted."""
    r = int(mem[_H_ROW]) + int(mem[_H_RFLAGS])
    mem[r] = state
    mem[r + 1] = isolation
    mem[r + 2] = 1.0 if state == _FAULT_STATE else 0.0
    mem[r + 3] = overruns
    mem[r + 4] = skipped


@numba.njit(cache=True, inline="always")
def _step_mount(mem, m, a, x):
    """Mount m's controller, one period, by its kind; the command [V]."""
    b = int(mem[_H_MOUNTS]) + m * 5
    kind = int(mem[b])
    co = int(mem[b + 1])
    so = int(mem[b + 3])
    cf = mem[co:co + int(mem[b + 2])]
    st = mem[so:so + int(mem[b + 4])]
    if kind == _ISO:
        return isolation_step(st, cf, a, x)
    if kind == _PID:
        return track_step(st, cf, x)
    if kind == _MODES:
        return modes_step(st, cf, a, x)
    if kind == _PLAY:
        return playback_step(st, cf)
    return 0.0


@numba.njit(cache=True, inline="always")
def _ff_mount(mem, m, g):
    """Mount m's floor feedforward, one period, on the floor acceleration g [m/s^2]; its command [V]."""
    b = int(mem[_H_FF]) + 1 + m * 4
    co = int(mem[b])
    ns = int(mem[b + 1])
    so = int(mem[b + 2])
    return feedforward_step(mem[co:co + 5 * ns], mem[b + 3], mem[so:so + 2 * ns + FF_STATE_EXTRA], g)


@numba.njit(cache=True)
def _after_loss(mem, n, nf):
    """Conversions were lost (the module's estimate stands in for them): each mount's isolation suspended (its
    saturation recovery resumes it) and its floor feedforward from rest (controllers/feedforward.py): both
    integrate the acceleration, and the estimate's error would be a velocity to them."""
    for m in range(n):
        b = int(mem[_H_MOUNTS]) + m * 5
        kind = int(mem[b])
        co, so = int(mem[b + 1]), int(mem[b + 3])
        cf = mem[co:co + int(mem[b + 2])]
        st = mem[so:so + int(mem[b + 4])]
        if kind == _ISO:
            isolation_suspend(st, cf)
        elif kind == _MODES:
            modes_suspend(st, cf)
        if nf:
            f = int(mem[_H_FF]) + 1 + m * 4
            co, ns, so = int(mem[f]), int(mem[f + 1]), int(mem[f + 2])
            feedforward_restart(mem[co:co + 5 * ns], mem[so:so + 2 * ns + FF_STATE_EXTRA])


@numba.njit(cache=True)
def _catch_up(mem, n, acc, xs, fl, nf, miss, n_older):
    """The periods the controllers did not see: `miss` skipped ones replayed (at most max_held, the latest),
    inputs interpolated from the previous period's measurement to this one's; or a sample-driven port's
    n_older conversions before the newest (mount accelerations, then floor ones), with the stroke interpolated
    from the previous period's to this one's: the transducer hands over no older samples, and stepping them all
    with the newest stroke puts a step into the blend's slow stroke path after a late period (the stroke
    moved meanwhile: the valve held its command), a table offset that decays only at the blend's pace.
    The feedforward (nf > 0) steps with them. Outputs are not written."""
    prev = int(mem[_H_PREV])
    for j in range(max(0, miss - int(mem[_H_MAXHELD])), miss):
        f = (j + 1) / (miss + 1)
        for m in range(n):
            pa = mem[prev + m]
            px = mem[prev + n + m]
            _step_mount(mem, m, pa + f * (acc[m] - pa), px + f * (xs[m] - px))
            if nf:
                pg = mem[prev + 2 * n + m]
                _ff_mount(mem, m, pg + f * (fl[m] - pg))
    older = int(mem[_H_OLDER])
    w = n + nf
    for k in range(n_older):
        f = (k + 1) / (n_older + 1)
        for m in range(n):
            px = mem[prev + n + m]
            _step_mount(mem, m, mem[older + k * w + m], px + f * (xs[m] - px))
            if nf:
                _ff_mount(mem, m, mem[older + k * w + n + m])


@numba.njit(cache=True, inline="always")      # one compiled period, as before the split
def _control(mem, i, n, mode, acc, xs, fl, nf, row, flags):
    """Outside FAULT: the sensor checks; the controllers' step (or their hold without a new conversion); the
    limit if ACTIVE, the null if not. 0, or the code of the rule that fired."""
    m0 = i + len(INPUTS)
    rc, rr = int(mem[_H_RC]), int(mem[_H_RR])
    lim = mem[int(mem[_H_LIM]):int(mem[_H_LIM]) + len(LIMITS)]
    chk = mem[int(mem[_H_CHK]):int(mem[_H_CHK]) + len(CHECK_STATE) * n].reshape((len(CHECK_STATE), n))
    code = check_sensors(chk, lim, acc, xs, mem[m0 + 2 * n:m0 + 3 * n], mem[m0 + 3 * n + nf:m0 + 4 * n + nf],
                         mem[i + _IN_T_NS])
    if code == 0 and nf:
        code = check_floor(fl, mem[int(mem[_H_FF])])
    if code != 0:
        return code
    if mem[i + _IN_STEP] > 0.5:
        if mem[i + _IN_LOST] > 0.5:              # lost conversions among these
            _after_loss(mem, n, nf)
            mem[_H_LOSTT] = mem[i + _IN_T_NS]
        _catch_up(mem, n, acc, xs, fl, nf, int(mem[i + _IN_MISS]), int(mem[i + _IN_OLDER]))
        if nf:
            rf = int(mem[_H_RF])
            for m in range(n):
                uf = _ff_mount(mem, m, fl[m])
                row[rf + m] = uf
                row[rr + m] = _step_mount(mem, m, acc[m], xs[m]) + uf
        else:
            for m in range(n):
                row[rr + m] = _step_mount(mem, m, acc[m], xs[m])
    prev = int(mem[_H_PREV])
    mem[prev:prev + n] = acc
    mem[prev + n:prev + 2 * n] = xs
    mem[prev + 2 * n:prev + 2 * n + nf] = fl
    if mode != MODE_ACTIVE:
        row[rc:rc + n] = 0.0
        return 0
    last = mem[int(mem[_H_LAST]):int(mem[_H_LAST]) + n]
    code = limit_commands(last, flags, lim, row[rr:rr + n], row[rc:rc + n])
    if code == 0:
        w = len(OSC_STATE) + int(lim[_L_OSC_N])
        o = int(mem[_H_OSC])
        code = check_oscillation(mem[o:o + n * w].reshape((n, w)), lim, row[rc:rc + n], mem[i + _IN_T_NS])
    return code


@numba.njit(cache=True, inline="always")      # one compiled period, as before the split
def _row_rest(mem, i, n, nf, row, flags):
    """The row after the commands: controller states, published channels, flags, times, feedforward switch."""
    o_st = int(mem[_H_ST])
    nst = int(mem[_H_NST])
    rs = int(mem[_H_RS])
    row[rs:rs + nst] = mem[o_st:o_st + nst]
    npub = int(mem[_H_NPUB])
    if npub:                                   # published state: its block index per (channel, mount), or -1
        pub = int(mem[_H_PUB])
        rp = int(mem[_H_RPUB])
        for j in range(npub * n):
            k = int(mem[pub + j])
            row[rp + j] = mem[k] if k >= 0 else np.nan
    row_flags(mem, mem[i + _IN_STATE], mem[i + _IN_ISO], mem[i + _IN_OVER], mem[i + _IN_SKIP])
    row[int(mem[_H_RL])] = flags[_F_LIMITED]
    row[int(mem[_H_RT])] = mem[i + _IN_T_S]
    row[int(mem[_H_RW])] = mem[i + _IN_WAKE]
    row[int(mem[_H_RP])] = mem[i + _IN_COMP]
    if nf:          # the switch request of the first mount's feedforward (they switch together)
        b = int(mem[_H_FF]) + 1
        row[int(mem[_H_RO])] = mem[int(mem[b + 2]) + 2 * int(mem[b + 1]) + 1]


@numba.njit(cache=True)
def run_period(mem, ring, hdr):
    """One period on the block: check the measurement; step the controllers (unless the port has no new
    conversion: they hold); limit the commands if ACTIVE, null if INACTIVE; fill the recording row; given a
    recorder's ring (rows > 0) and its header (rig/runtime/ring.py), publish the row of the period before and write
    this one into the next row, claimed (a full ring: dropped and counted). FAULT: the row only.
    0, or a rule's code (rig/runtime/safety.py): the caller then corrects the claimed row (its fault, null commands)
    before the next period publishes it."""
    n = int(mem[_H_N])
    i = int(mem[_H_IN])
    mode = int(mem[i + _IN_MODE])
    m0 = i + len(INPUTS)
    acc = mem[m0:m0 + n]
    xs = mem[m0 + n:m0 + 2 * n]
    nf = int(mem[_H_NFL])
    fl = mem[m0 + 3 * n:m0 + 3 * n + nf]
    row = mem[int(mem[_H_ROW]):int(mem[_H_ROW]) + int(mem[_H_NROW])]
    ra, rx, rc = int(mem[_H_RA]), int(mem[_H_RX]), int(mem[_H_RC])
    row[ra:ra + n] = acc
    row[rx:rx + n] = xs
    if nf:
        rg = int(mem[_H_RG])
        row[rg:rg + nf] = fl
    flags = mem[int(mem[_H_FLAGS]):int(mem[_H_FLAGS]) + 3]
    code = 0
    if mode == MODE_FAULT:
        row[rc:rc + n] = 0.0
    else:
        code = _control(mem, i, n, mode, acc, xs, fl, nf, row, flags)
    _row_rest(mem, i, n, nf, row, flags)
    cap = ring.shape[0]
    if cap > 0:
        _publish(hdr)
        slot = _claim(hdr, cap)
        if slot >= 0:
            ring[slot, :] = row
    return code


@numba.njit(cache=True)
def _take_conversions(mem, io, t_ns, i, n, nf):
    """The accelerometer module's newest conversion into the inputs (mount accelerations, their time stamps,
    floor accelerations) and, counted, the older ones since the last period into the block's older part; latest
    value only: the periods skipped since the last one (replayed). 0, or BEHIND / NO_SAMPLE."""
    a = int(io[ex.H_ACCEL])
    cap, w = int(io[ex.H_ACAP]), int(io[ex.H_AWIDTH])
    newest = io[a + ex.A_NEWEST]
    ex.fence()
    if newest < 0:
        return NO_SAMPLE
    m0 = i + len(INPUTS)
    mem[i + _IN_LOST] = 0.0
    s = a + ex.A_SLOTS + (int(newest) % cap) * w
    mem[m0 + 2 * n:m0 + 3 * n] = io[s + 1:s + 1 + n]
    mem[m0:m0 + n] = io[s + 1 + n:s + 1 + 2 * n]
    mem[m0 + 3 * n:m0 + 3 * n + nf] = io[s + 1 + 2 * n:s + 1 + 2 * n + nf]
    ex.fence()
    if io[s + ex.SLOT_COUNTER] != newest:         # rewritten meanwhile: the module lapped the loop
        mem[_H_HELD] = cap
        return BEHIND
    last = mem[_H_ALAST]
    mem[_H_ALAST] = newest
    if io[a + ex.A_COUNTED] < 0.5:                # the latest value: skipped periods are replayed
        tp = mem[_H_TPREV]
        miss = int((t_ns - tp) // mem[_H_DTNS]) - 1 if tp >= 0 else 0
        mem[i + _IN_MISS] = miss if miss > 0 else 0
        mem[i + _IN_OLDER] = 0.0
        mem[i + _IN_STEP] = 1.0
        return 0
    k = 1 if last < 0 else int(newest - last)
    older = k - 1 if k > 0 else 0
    lost = io[a + ex.A_LOST]
    if last >= 0 and last < lost <= newest:     # one of these is an estimate of a conversion the module lost
        mem[i + _IN_LOST] = 1.0
    mem[i + _IN_MISS] = 0.0
    mem[i + _IN_STEP] = 1.0 if k > 0 else 0.0
    mem[i + _IN_OLDER] = older
    if older > OLDER_CAP:
        mem[_H_HELD] = older
        return BEHIND
    o, wc = int(mem[_H_OLDER]), n + nf
    for j in range(older):
        c = last + 1 + j
        sj = a + ex.A_SLOTS + (int(c) % cap) * w
        mem[o + j * wc:o + j * wc + n] = io[sj + 1 + n:sj + 1 + 2 * n]
        mem[o + j * wc + n:o + (j + 1) * wc] = io[sj + 1 + 2 * n:sj + 1 + 2 * n + nf]
        ex.fence()
        if io[sj + ex.SLOT_COUNTER] != c:
            mem[_H_HELD] = older
            return BEHIND
    return 0


@numba.njit(cache=True)
def _take(mem, io, t_ns):
    """The period's inputs from the exchange block (rig/runtime/exchange.py): the conversions, the transducer's
    newest sample (held between its frames, checked against its own staleness limit) and the devices' reports.
    0, or the code of the input rule that fired. The age of the samples used goes to the block's ages ring."""
    n, nf, i = int(mem[_H_N]), int(mem[_H_NFL]), int(mem[_H_IN])
    code = _take_conversions(mem, io, t_ns, i, n, nf)
    mem[_H_TPREV] = t_ns
    if code != 0:
        return code
    so, scap, sw = int(io[ex.H_STROKE]), int(io[ex.H_SCAP]), int(io[ex.H_SWIDTH])
    t_x = 0.0
    for _ in range(2):                            # (a sample rewritten while read: the newer one, once more)
        sn = io[so + ex.S_NEWEST]
        ex.fence()
        if sn < 0:
            return NO_SAMPLE
        ss = so + ex.S_SLOTS + (int(sn) % scap) * sw
        m0 = i + len(INPUTS)
        mem[m0 + n:m0 + 2 * n] = io[ss + 2:ss + 2 + n]
        t_x = io[ss + 1]
        mem[m0 + 3 * n + nf:m0 + 4 * n + nf] = t_x
        ex.fence()
        if io[ss + ex.SLOT_COUNTER] == sn:
            break
    lim = io[so + ex.S_STALE]
    if lim > 0 and t_ns - t_x > lim:
        mem[_H_XAGE] = t_ns - t_x
        return CHECK_STROKE_STALE
    dv, nd = int(io[ex.H_DEV]), int(io[ex.H_NDEV])
    for d in range(nd):
        r = dv + d * int(io[ex.H_DWIDTH])
        if io[r + ex.D_FAULT] != 0:
            return DEVICE_FAULT + d
        sil = io[r + ex.D_SILENT]
        if sil > 0 and t_ns - io[r + ex.D_BEAT] > sil:
            mem[_H_XAGE] = t_ns - io[r + ex.D_BEAT]
            return DEVICE_SILENT + d
    g, gcap = int(io[ex.H_AGES]), int(io[ex.H_AGESCAP])
    k = int(io[g])
    j = g + 1 + 2 * (k % gcap)
    io[j] = t_ns - mem[i + len(INPUTS) + 2 * n]
    io[j + 1] = t_ns - t_x
    io[g] = k + 1
    return 0


@numba.njit(cache=True)
def period_io(mem, ring, hdr, io, t_ns, t_s, wake_us, comp_us, mode, state, isolation, overruns, skipped):
    """One period over the exchange block: take the inputs (_take), run_period, and outside FAULT, when no rule
    fired, write the period's commands (the limited ones ACTIVE, the null INACTIVE) into the block for the port
    (rig/runtime/exchange.py put_commands). 0, WAKE_COMMANDS (no rule fired and the valves' I/O sleeps waiting
    for the commands: the caller wakes it, exchange.take_waiter) or the code of the rule that fired (an input
    rule's: the period recorded as FAULT, nothing written)."""
    i = int(mem[_H_IN])
    mem[i + _IN_T_NS] = t_ns
    mem[i + _IN_T_S] = t_s
    mem[i + _IN_WAKE] = wake_us
    mem[i + _IN_COMP] = comp_us
    mem[i + _IN_MODE] = mode
    mem[i + _IN_STATE] = state
    mem[i + _IN_ISO] = isolation
    mem[i + _IN_OVER] = overruns
    mem[i + _IN_SKIP] = skipped
    code = _take(mem, io, t_ns)
    if code != 0:
        mem[i + _IN_MODE] = MODE_FAULT
        run_period(mem, ring, hdr)
        return code
    code = run_period(mem, ring, hdr)
    if code == 0 and mode != MODE_FAULT:
        rc = int(mem[_H_ROW]) + int(mem[_H_RC])
        ex.put_commands(io, t_ns, mem[rc:rc + int(mem[_H_N])])
    if code == 0 and ex.take_waiter(io):
        return WAKE_COMMANDS
    return code


@intrinsic
def _f64_at(typingctx, addr):
    """The float64 buffer at an address (an int64 word: the views the kernel binds, kept alive by it)."""
    def codegen(context, builder, signature, args):
        return builder.inttoptr(args[0], context.get_value_type(types.CPointer(types.float64)))
    return types.CPointer(types.float64)(types.int64), codegen


@intrinsic
def _i64_at(typingctx, addr):
    """The int64 buffer at an address (the recorder ring's header)."""
    def codegen(context, builder, signature, args):
        return builder.inttoptr(args[0], context.get_value_type(types.CPointer(types.int64)))
    return types.CPointer(types.int64)(types.int64), codegen


_AT_SIG = "int64(int64, float64, float64, float64, float64, float64, float64, float64, float64, float64)"


@numba.njit(cache=True)
def period_at(at, t_ns, t_s, wake_us, comp_us, mode, state, isolation, overruns, skipped):
    """period_io over the block at address `at` (PeriodKernel.at) and the exchange block, the recorder's ring
    and its header at the addresses in its header (PeriodKernel.bind_io, bind_ring): the call's arguments are
    plain numbers, so calling it unboxes no array (numba makes a reference-counted wrapper per array argument,
    an allocation each, every period)."""
    mem = numba.carray(_f64_at(at), len(HEADER))
    mem = numba.carray(_f64_at(at), int(mem[_H_SIZE]))
    io = numba.carray(_f64_at(int(mem[_H_IOAT])), len(ex.HEADER))
    io = numba.carray(_f64_at(int(mem[_H_IOAT])), int(io[ex.H_FUTEX]) // 8)
    ring = numba.carray(_f64_at(int(mem[_H_RINGAT])), (int(mem[_H_RINGROWS]), int(mem[_H_NROW])))
    hdr = numba.carray(_i64_at(int(mem[_H_HDRAT])), len(ring_rule.HEADER))
    return period_io(mem, ring, hdr, io, t_ns, t_s, wake_us, comp_us, mode, state, isolation, overruns, skipped)


_ENTRY: list = []


def io_entry():
    """The compiled period over the blocks (period_at), its native entry: compiled (or loaded from numba's
    cache) on the first call, which a Session makes before its port starts any device."""
    if not _ENTRY:
        period_at.compile(_AT_SIG)
        _ENTRY.append(native_entry(period_at))
    return _ENTRY[0]


def native_entry(dispatcher):
    """The compiled function's own entry point (argument unboxing only) for its one compiled signature,
    skipping the dispatcher's type resolution. The caller must pass exactly those types (period_at: an int and
    floats). Falls back to the dispatcher where numba does not offer this."""
    try:
        (sig,) = dispatcher.signatures
        return dispatcher.overloads[sig].entry_point
    except (AttributeError, KeyError, TypeError, ValueError):
        return dispatcher


def ring_ok(ring, hdr) -> bool:
    """A recorder ring the kernel may write: 2-D C-contiguous float64 rows, and its header: C-contiguous
    int64 of rig/runtime/ring.py HEADER's words (the kernel takes their addresses: it checks nothing)."""
    return (isinstance(ring, np.ndarray) and ring.ndim == 2 and ring.dtype == np.float64
            and ring.flags.c_contiguous and ring.flags.writeable
            and isinstance(hdr, np.ndarray) and hdr.ndim == 1 and hdr.dtype == np.int64
            and hdr.flags.c_contiguous and hdr.flags.writeable and hdr.size >= len(ring_rule.HEADER))


class PeriodKernel:
    """Owns the block: builds it from the controllers (one per mount; their builders give kind, coefficients,
    named state and dt), the floor feedforward filters if any (one per mount: controllers/feedforward.py
    FeedforwardFilter; the loop then takes the floor accelerometers) and the safety builders, and runs one
    period per `period` call."""

    def __init__(self, cfg: Config, controllers: list, names: tuple[str, ...], dt: float,
                 max_held_steps: int, feedforward: list | None = None) -> None:
        n = len(controllers)
        if not 1 <= n <= MAX_MOUNTS:
            raise ConfigError(f"loop: {n} mounts; the period kernel takes 1 to {MAX_MOUNTS}")
        for name, c in zip(names, controllers):
            _check_controller(name, c, dt)
        ffs = list(feedforward) if feedforward else []
        _check_feedforward(names, ffs, dt)
        nf = n if ffs else 0
        self.n, self.ctrls, self.names, self.dt = n, list(controllers), tuple(names), dt
        self.ffs, self.nf = ffs, nf
        self.floor_range = cfg.sensors.floor_range_mps2
        self.state_labels = tuple(f"{m}.{s}" for m, c in zip(names, controllers) for s in c.state_names)
        self.published = _published(controllers)      # name -> (unit, description)
        self.layout = RowLayout(loop_channels(self.names, self.state_labels,
                                              [Channel(k, u, n, self.names, d) for k, (u, d) in self.published.items()],
                                              floor=bool(nf)))
        self.check = SensorCheck(cfg, n, self.names)
        self.limiter = CommandLimiter(cfg, n, dt)
        self.osc = OscillationRule(cfg, n, self.names)
        coefs = [np.ascontiguousarray(c.coefficients(), dtype=np.float64) for c in controllers]
        nst = [len(c.state_names) for c in controllers]
        ff_coefs = [np.asarray(f.coef, dtype=np.float64) for f in ffs]
        ff_nst = [len(f.initial_state()) for f in ffs]
        # the controllers' coefficients last: a tracking controller's profile table (track_profile_s of
        # samples) would otherwise sit between the parts every period touches
        parts = {"header": len(HEADER), "inputs": len(INPUTS) + 4 * n + nf, "older": OLDER_CAP * (n + nf),
                 "prev": 2 * n + nf, "limits": len(LIMITS), "check": len(CHECK_STATE) * n, "last_cmd": n,
                 "flags": len(LIMITER_FLAGS), "mounts": len(MOUNT_TABLE) * n, "states": sum(nst),
                 "pub": len(self.published) * n, "osc": n * self.osc.width,
                 "ff": 1 + len(FF_TABLE) * nf if nf else 0, "ff_coefs": sum(len(c) for c in ff_coefs),
                 "ff_states": sum(ff_nst), "row": self.layout.ncols, "coefs": sum(len(c) for c in coefs)}
        at, off = 0, {}
        for part, size in parts.items():
            off[part] = at
            at += size
        off["size"] = at
        self.mem = mem = np.zeros(at)
        lay = self.layout
        mem[:len(HEADER)] = self._header(off, max_held_steps, sum(nst))
        mem[off["limits"]:off["limits"] + len(LIMITS)] = (self.check.limits() + self.limiter.limits()
                                                          + self.osc.limits())
        self.osc_state = mem[off["osc"]:off["osc"] + n * self.osc.width].reshape(n, self.osc.width)
        self._osc_initial = self.osc.initial_state([c.kind in _OSC_KINDS for c in controllers])
        self.osc_state[:] = self._osc_initial
        self._place_controllers(off, coefs, nst)
        self._place_feedforward(off, ff_coefs, ff_nst)
        self.check_state = mem[off["check"]:off["check"] + len(CHECK_STATE) * n].reshape(len(CHECK_STATE), n)
        self.last_cmd = mem[off["last_cmd"]:off["last_cmd"] + n]
        self.flags = mem[off["flags"]:off["flags"] + len(LIMITER_FLAGS)]
        self.limiter.view(self.last_cmd, self.flags)
        self.row = mem[off["row"]:off["row"] + lay.ncols]
        self.no_ring = np.zeros((0, lay.ncols))       # stands in for the ring without a recorder (no rows) ...
        self.no_hdr = np.zeros(len(ring_rule.HEADER), dtype=np.int64)     # ... and for its header
        self.at = mem.ctypes.data                       # the block's address: the compiled period's argument
        self.io = None                                  # the exchange block the period takes and writes (bind_io)
        self.bind_ring(self.no_ring, self.no_hdr)
        self._in = off["inputs"] + len(INPUTS)          # the measurement inputs: accel, stroke, sample_t, floor
        self._in_t = off["inputs"] + _IN_T_NS
        self._prev_x = off["prev"] + n                  # the last checked stroke per mount
        self._local = None                              # period(): a block of its own for a Measurements
        unpack = struct.Struct(f"<{n}d").unpack_from
        # commands(): the limited commands of the last period (the row's valve_cmd_V), a tuple; a partial of
        # the C unpack, no Python frame (the loop's hot path)
        self.commands = functools.partial(unpack, mem, 8 * (off["row"] + lay["valve_cmd_V"]))
        self._raw = functools.partial(unpack, mem, 8 * (off["row"] + lay["valve_cmd_raw_V"]))
        self.reset_check()
        self.fresh_states()
        self.call = io_entry()                          # compiled (or loaded) now, not in the first period

    def _header(self, off: dict, max_held_steps: int, n_states: int) -> tuple:
        """The block's header (HEADER's order): where each part and each row column is."""
        n, nf, lay = self.n, self.nf, self.layout
        return (n, off["inputs"], off["older"], off["prev"], off["limits"], off["check"],
                off["last_cmd"], off["flags"], off["mounts"], off["states"], n_states, off["row"],
                lay.ncols, max_held_steps, lay["time_s"], lay["accel_mps2"], lay["stroke_m"],
                lay["valve_cmd_V"], lay["valve_cmd_raw_V"],
                lay["controller_state"] if "controller_state" in lay else lay.ncols,
                lay["cmd_limited"], lay["wake_latency_us"], lay["compute_prev_us"], len(self.published),
                off["pub"], lay[next(iter(self.published))] if self.published else lay.ncols, off["osc"],
                nf, off["ff"],
                *((lay["floor_accel_mps2"], lay["ff_cmd_V"], lay["feedforward_on"]) if nf
                  else (lay.ncols,) * 3), lay["lifecycle_state"], round(self.dt * 1e9), -1.0, -1.0, 0.0, 0.0, -1.0,
                off["size"], 0.0, 0.0, 0.0, 0.0)

    def _place_controllers(self, off: dict, coefs: list, nst: list) -> None:
        """Each mount's controller: its table entry, its coefficients and state in the block, and where its
        published channels are."""
        mem, n = self.mem, self.n
        self.states, self.coefs = [], []
        so, co = off["states"], off["coefs"]
        mem[off["pub"]:off["pub"] + len(self.published) * n] = -1.0
        for m, (c, cf) in enumerate(zip(self.ctrls, coefs)):
            mem[off["mounts"] + 5 * m:off["mounts"] + 5 * m + 5] = (c.kind, co, len(cf), so, nst[m])
            mem[co:co + len(cf)] = cf
            self.states.append(mem[so:so + nst[m]])
            self.coefs.append(mem[co:co + len(cf)])
            for name, _, _, idx in getattr(c, "published", ()):
                mem[off["pub"] + list(self.published).index(name) * n + m] = so + idx
            co += len(cf)
            so += nst[m]

    def _place_feedforward(self, off: dict, ff_coefs: list, ff_nst: list) -> None:
        """Each mount's floor feedforward, when there is one: table entry, coefficients, state."""
        mem = self.mem
        self.ff_states = []
        if not self.nf:
            return
        mem[off["ff"]] = self.floor_range
        co, so = off["ff_coefs"], off["ff_states"]
        for m, (f, cf) in enumerate(zip(self.ffs, ff_coefs)):
            mem[off["ff"] + 1 + 4 * m:off["ff"] + 5 + 4 * m] = (co, len(f.sections), so, f.fade)
            mem[co:co + len(cf)] = cf
            self.ff_states.append(mem[so:so + ff_nst[m]])
            co += len(cf)
            so += ff_nst[m]

    # ---- the period -----------------------------------------------------------------------------------
    def bind_io(self, io) -> None:
        """The exchange block (rig/runtime/exchange.py Block.io) the period takes its inputs from and writes its
        commands into, from the next call on; held here while its address is in the block."""
        if not (isinstance(io, np.ndarray) and io.ndim == 1 and io.dtype == np.float64 and io.flags.c_contiguous
                and io.flags.writeable and io.size >= len(ex.HEADER) and io.size >= int(io[ex.H_FUTEX]) // 8):
            raise ConfigError("loop: the port's exchange block is not a writable C-contiguous float64 block of "
                              "its own header's size (rig/runtime/exchange.py)")
        self.io = io
        self.mem[_H_IOAT] = io.ctypes.data

    def bind_ring(self, ring, hdr) -> None:
        """The recorder's ring and its header (ring_ok) the period writes its row into, from the next call on;
        held here while their addresses are in the block."""
        if not ring_ok(ring, hdr) or ring.shape[1] != self.layout.ncols:
            raise ConfigError("loop: a recorder ring the period cannot write (rig/runtime/kernel.py ring_ok, "
                              f"{self.layout.ncols} columns)")
        self.ring, self.hdr = ring, hdr
        mem = self.mem
        mem[_H_RINGAT], mem[_H_RINGROWS], mem[_H_HDRAT] = ring.ctypes.data, ring.shape[0], hdr.ctypes.data

    def measurements(self):
        """The period's measurement as the kernel took it (rig.port.Measurements): accelerations, strokes, the
        accelerometers' time stamps, the floor accelerations."""
        n, nf, m0 = self.n, self.nf, self._in
        mem = self.mem
        return Measurements(int(mem[self._in_t]), mem[m0:m0 + n].tolist(), mem[m0 + n:m0 + 2 * n].tolist(),
                            [int(x) for x in mem[m0 + 2 * n:m0 + 3 * n]],
                            floor_accel_mps2=mem[m0 + 3 * n:m0 + 3 * n + nf].tolist())

    def period(self, m, t_ns: int, t_s: float, wake_us: float, comp_us: float, mode: int, miss: int,
               ring=None, hdr=None, flags=(0, False, 0, 0)) -> int:
        """One period for the measurement `m` (rig.port.Measurements) through a block of its own (the loop's
        path, for tests and tools): 0 or a rule's code; given a recorder's ring and header, its row written
        there; miss: periods skipped before this one (a latest-value measurement); flags: the row's (lifecycle
        state, isolation, overruns, skipped)."""
        if self._local is None:
            self._local = MeasuredBlock(self.n, self.nf)
        if m.new_samples is None:
            self.mem[_H_TPREV] = t_ns - (miss + 1) * self.mem[_H_DTNS]
        self._local.put(m)
        bound = self.io, self.ring, self.hdr
        self.bind_io(self._local.io)
        self.bind_ring(*((ring, hdr) if ring is not None else (self.no_ring, self.no_hdr)))
        try:
            return self.call(self.at, float(t_ns), t_s, wake_us, comp_us, float(mode), *(float(f) for f in flags))
        finally:                                        # a loop's blocks, as they were
            if bound[0] is not None:
                self.bind_io(bound[0])
            self.bind_ring(*bound[1:])

    @staticmethod
    def mem_index(name: str) -> int:
        """The header word `name` (HEADER)."""
        return HEADER.index(name)

    def record_flags(self, state, isolation: bool, overruns: int, skipped: int) -> None:
        """The row's flag columns, after a period that faulted past the compiled call (row_flags)."""
        row_flags(self.mem, float(state), float(isolation), float(overruns), float(skipped))

    def raw_commands(self) -> list:
        """The controllers' commands of the last period, before the limits (the row's valve_cmd_raw_V)."""
        return list(self._raw())

    def null_commands(self) -> None:
        """The row's commands to null (a fault in this period: nothing was written)."""
        c = self.layout["valve_cmd_V"]
        self.row[c:c + self.n] = 0.0

    # ---- state changes, between periods ---------------------------------------------------------------
    def fresh_states(self) -> None:
        """Every controller from its initial state, isolation disabled (the loop enables it on activation);
        the feedforward's filters from rest, switched off."""
        for c, st in zip(self.ctrls, self.states):
            st[:] = c.set_enabled(c.initial_state(), False)
        for f, st in zip(self.ffs, self.ff_states):
            st[:] = f.initial_state(on=False)

    def set_feedforward(self, on: bool) -> None:
        """The floor feedforward on/off (its output fades in or out; the filters keep running)."""
        for f, st in zip(self.ffs, self.ff_states):
            f.set_enabled(st, on)

    def feedforward_enabled(self) -> bool:
        return bool(self.ffs) and self.ffs[0].enabled(self.ff_states[0])

    def last_loss_ns(self) -> int:
        """The period that last took conversions the module had lost (-1: none)."""
        return int(self.mem[_H_LOSTT])

    def feedforward_restarting_s(self) -> float:
        """The time the feedforward's restart still holds its output off (0: none; the mounts restart together)."""
        return self.ffs[0].restarting_s(self.ff_states[0]) if self.ffs else 0.0

    def set_enabled(self, on: bool) -> None:
        """Isolation on/off, each controller's own bumpless way."""
        for c, st in zip(self.ctrls, self.states):
            st[:] = c.set_enabled(st.tolist(), on)

    def suspended(self) -> list[bool]:
        """Per mount: isolation held off by the controller's saturation recovery."""
        return [bool(getattr(c, "suspended", lambda s: False)(st)) for c, st in zip(self.ctrls, self.states)]

    def switch(self, m: int, request, active: bool) -> None:
        """Mount m's controller takes a request (an operating mode and its reference, controllers/modes.py),
        from the command last written (null unless ACTIVE) and the last checked position: bumpless."""
        c, st = self.ctrls[m], self.states[m]
        u = float(self.last_cmd[m]) if active else 0.0
        st[:] = c.switch(st.tolist(), request, u, float(self.mem[self._prev_x + m]), self.coefs[m])

    def activated(self) -> None:
        """INACTIVE -> ACTIVE: controllers that take the valve over (operating modes) start from the null."""
        for m, c in enumerate(self.ctrls):
            if hasattr(c, "switch"):
                self.switch(m, None, False)

    def reset_check(self) -> None:
        self.check_state[:] = self.check.initial_state()

    def reset_limiter(self) -> None:
        """The valve is at null (written while inactive, or safe state): the slew limit ramps from there, and
        the oscillation rule starts with no swing seen."""
        self.last_cmd[:] = 0.0
        self.flags[_F_SATRUN] = 0.0
        self.osc_state[:] = self._osc_initial


def _published(controllers) -> dict:
    """The published state channels of the controllers, in order of first appearance: name -> (unit, text)."""
    out: dict = {}
    for c in controllers:
        for name, unit, text, _ in getattr(c, "published", ()):
            out.setdefault(name, (unit, text))
    return out


def _check_feedforward(names, ffs: list, dt: float) -> None:
    """Feedforward filters the kernel can run: none, or one per mount at the loop's period."""
    if not ffs:
        return
    if len(ffs) != len(names):
        raise ConfigError(f"loop: {len(ffs)} feedforward filters for {len(names)} mounts")
    for name, f in zip(names, ffs):
        if not all(hasattr(f, a) for a in ("coef", "fade", "initial_state", "set_enabled", "enabled")):
            raise ConfigError(f"loop: {name}: {type(f).__name__} is not a feedforward filter "
                              f"(controllers/feedforward.py FeedforwardFilter)")
        if not same_period(f.dt, dt):
            raise ConfigError(f"loop: {name}: feedforward built for dt = {f.dt:g} s, loop period {dt:g} s")


def _check_controller(name: str, c, dt: float) -> None:
    """A controller the kernel can run, or ConfigError naming the mount and what is missing."""
    kind = getattr(c, "kind", None)
    if kind not in KINDS:
        raise ConfigError(f"loop: {name}: {type(c).__name__} is not a controller kind the period kernel runs "
                          f"(kinds: {', '.join(f'{k} {v}' for k, v in KINDS.items())})")
    for attr in ("coefficients", "initial_state", "set_enabled", "state_names"):
        if not hasattr(c, attr):
            raise ConfigError(f"loop: {name}: {type(c).__name__} has no {attr}")
    cdt = getattr(c, "dt", dt)
    if not same_period(cdt, dt):
        raise ConfigError(f"loop: {name}: controller built for dt = {cdt:g} s, loop period {dt:g} s "
                          f"(build the controllers at the loop rate)")
