"""The fixed-rate control loop: read -> check -> update -> limit -> write -> record, once per period.

- Absolute deadlines in integer ns on an injected clock (`t += period`), so tests run in simulated time.
- Overrun policy: "skip" jumps to the first deadline still ahead and counts the skipped periods; "catch_up"
  runs the late periods back to back. Counters: overruns (cycles that ended after their period), skipped.
  missed_deadline_fraction = (overruns + skipped) / (iterations + skipped).
- The update is a controller manager: one controller object per mount with
      initial_state() -> list[float]; step(state, (accel_mps2, stroke_m), dt) -> (valve_cmd_V, state);
      set_enabled(state, on) -> state    (isolation on/off, bumpless; centring stays active)
  Controllers also run while INACTIVE, isolation disabled and output discarded, so their filters are warm:
  activating with cold filters under floor motion kicked the loop into a latched saturation (measured).
  On activation set_enabled(state, isolation) switches isolation on the controllers' bumpless way and the
  limiter ramps from the null the valve held, so (re-)activation never jumps.
- Lifecycle gating: INACTIVE writes null, ACTIVE writes the limited commands, FAULT writes nothing after
  port.safe_state(). Any exception of port or controller is a fault, never a silent death. Safety checks
  (rig/safety.py): sensor plausibility before the update, clamp/slew/saturation after it, a gap check on the
  wake-ups (watchdog_s) and, on the real clock, a watchdog thread that nulls the valve if the loop hangs.
- Sample-driven ports (Measurements.new_samples set: an accelerometer module converting on SYNC into a FIFO,
  drivers/port.py) step the controllers once per conversion, in order, older ones first; a period without a
  new conversion holds the command. Late Modbus replies then never reach the double integration as timing
  slips (one slip per second put the HIL valves at the clamp).
- Isolation controllers (controllers/isolation.py) run as one compiled bank (controllers/bank.py, numba):
  built automatically from a list of IsolationControllers of one structure, or passed in; any other
  controllers are stepped one by one in Python. Skipped periods are replayed with the measurement
  interpolated from the last period's to this one's (holding it gave the double integration a velocity
  error: 5 ms of gap drove the valves to the clamp for seconds, measured).
- The controllers' saturation recovery (controllers/isolation.py) suspending or resuming a mount's isolation
  is logged and recorded as an event once per change (checked at 10 Hz, off the per-period path).
- Hot path in plain floats and lists or compiled code. With the four-mount bank, check -> update -> limit ->
  record is one compiled call (rig/period.py: the same decisions as rig/safety.py's stages, tested equal),
  which also copies the recording row into the recorder's ring; the loop keeps the port calls, the faults'
  texts and the rare flags. Other controllers go stage by stage, the row packed here (Recorder.push/push_row).
  The per-period allocations are the port's Measurements and small lists (no reference cycles, so gc can
  stay off during the run).
"""
from __future__ import annotations

import array
import logging
import math
import struct

import numpy as np

from rig.clock import MonotonicClock
from rig.config import MOUNTS, Config
from rig.lifecycle import Lifecycle, State
from rig.period import LIMIT_NAN, CompiledPeriod, ring_ok
from rig.port import Commands
from rig.recorder import Channel
from rig.safety import CommandLimiter, SensorCheck, Watchdog

log = logging.getLogger("rig.loop")

_ACTIVE, _INACTIVE, _FAULT = State.ACTIVE, State.INACTIVE, State.FAULT
_unpack_cmd4 = struct.Struct("<4d").unpack_from

# Per-row flag columns recorded after the per-mount channels.
FLAG_CHANNELS = (
    Channel("lifecycle_state", "", description="0 UNCONFIGURED, 1 INACTIVE, 2 ACTIVE, 3 FAULT"),
    Channel("isolation_on", "", description="1 when isolation is enabled in the controllers"),
    Channel("fault", "", description="1 from the period a fault was detected on"),
    Channel("overruns", "", description="cumulative count of cycles that ended after their period"),
    Channel("skipped_periods", "", description="cumulative count of periods skipped (skip policy)"),
    Channel("cmd_limited", "", description="1 when a command was clamped or slew-limited this period"),
    Channel("wake_latency_us", "us", description="wake-up time minus the period's deadline"),
    Channel("compute_prev_us", "us", description="compute time of the previous period (read..record)"),
)


def loop_channels(n_mounts: int, state_len: int, names: tuple[str, ...]) -> list[Channel]:
    """The recording layout of a loop run (rows pushed by Loop in this order)."""
    ch = [Channel("time_s", "s", description="loop time of the period (deadline) since start"),
          Channel("accel_mps2", "m/s^2", n_mounts, names, "absolute vertical acceleration at the mount"),
          Channel("stroke_m", "m", n_mounts, names, "displacement transducer, piston relative to housing"),
          Channel("valve_cmd_V", "V", n_mounts, names, "valve command written to the port (after limits)"),
          Channel("valve_cmd_raw_V", "V", n_mounts, names, "controller output before clamp and slew limit")]
    if state_len:
        labels = tuple(f"{m}[{j}]" for m in names for j in range(state_len))
        ch.append(Channel("controller_state", "", n_mounts * state_len, labels,
                          "controller states, mount-major"))
    return ch + list(FLAG_CHANNELS)


def _make_bank(controllers):
    """The compiled bank for IsolationControllers (None for other controllers, or without numba/controllers)."""
    try:
        from controllers.bank import IsolationBank, make_bank
    except ImportError:
        return None
    if isinstance(controllers, IsolationBank):
        return controllers
    return make_bank(controllers)


class Loop:
    MAX_HELD_STEPS = 50     # skipped periods replayed into the controllers at most (longer gaps fault anyway)

    def __init__(self, cfg: Config, port, controllers: list, *, clock=None, recorder=None,
                 rate_hz: float | None = None, overrun_policy: str | None = None, isolation: bool = True,
                 keep_timing: int = 1 << 15, names: tuple[str, ...] | None = None,
                 stop_on_fault: bool = True, watchdog_thread: bool | None = None,
                 use_bank: bool = True) -> None:
        self.cfg = cfg
        self.port = port
        self.n = int(port.n_mounts)
        bank = _make_bank(controllers) if use_bank else None
        if not isinstance(controllers, (list, tuple)) and hasattr(controllers, "ctrls"):
            controllers = controllers.ctrls            # a bank was passed: its controllers
        if len(controllers) != self.n:
            raise ValueError(f"{len(controllers)} controllers for {self.n} mounts")
        self.ctrls = list(controllers)
        self.clock = clock if clock is not None else MonotonicClock()
        if getattr(self.clock, "spin_ns", 0) is None:      # a real clock whose wait was not chosen: [loop]
            self.clock.spin_ns = int(round(getattr(cfg.loop, "spin_us", 0.0) * 1e3))
        self.rate_hz = float(rate_hz or cfg.loop.rate_hz)
        self.period_ns = int(round(1e9 / self.rate_hz))
        self.dt = self.period_ns * 1e-9
        if bank is not None and abs(bank.dt - self.dt) > 1e-6 * self.dt:
            bank = None                        # the controllers refuse this dt: stepped (and fault) in Python
        self.bank = bank
        self.policy = overrun_policy or cfg.loop.overrun_policy
        if self.policy not in ("skip", "catch_up"):
            raise ValueError(f"overrun policy {self.policy!r}")
        self.names = names or (MOUNTS[:self.n] if self.n <= len(MOUNTS) else
                               tuple(f"mount{i}" for i in range(self.n)))
        self.lc = Lifecycle()
        self.check = SensorCheck(cfg, self.n, self.names)
        self.limiter = CommandLimiter(cfg, self.n, self.dt)
        self.watchdog_ns = int(round(cfg.safety.watchdog_s * 1e9))
        self._row = None                       # preallocated recording row (bank path), per recorder
        self.recorder = recorder
        self.stop_on_fault = stop_on_fault
        self._use_wd_thread = self.clock.is_real if watchdog_thread is None else watchdog_thread
        self.wd: Watchdog | None = None

        self.isolation = bool(isolation)
        self._iso_request: bool | None = None
        self._active_request: bool | None = None
        self.stop_reason: str | None = None
        self.states = self._fresh_states()
        self.state_len = max((len(s) for s in self.states), default=0)
        self.raw = [0.0] * self.n
        self.cmd = [0.0] * self.n
        self._commands = Commands(self.cmd)            # the port must copy, not keep, the list
        self._null = Commands([0.0] * self.n)
        self.last_meas = None
        self._prev_acc = [0.0] * self.n       # last period's measurement (replay interpolation)
        self._prev_xs = [0.0] * self.n
        self._failed = None
        self._stepped = False
        self._kran = False
        self._susp_every = max(1, int(round(0.1 * self.rate_hz)))   # suspension watch (event/log), 10 Hz
        self._susp_count = self._susp_every
        self._susp = [False] * self.n
        if bank is not None and self.n == 4:
            # check -> bank -> limit -> record in one compiled call (rig/period.py), which leaves the
            # measurement, commands and states in the recording row itself (loop_channels layout: time,
            # accel 4, stroke 4, cmd 4, raw 4, states, flags); the check and limiter objects are the kernel's
            # (same decisions, state in its block), and so are the controller states
            self._iflag = 17 + self.states.size
            self._kern = CompiledPeriod(cfg, bank, self.names, self.dt, len(FLAG_CHANNELS), self._iflag + 5)
            self._kern.states[:] = self.states
            self.states = self._kern.states
            self._rowbuf = self._kern.row
            self._rowmv = memoryview(self._rowbuf)
            self.check, self.limiter = self._kern.check, self._kern.limiter
        else:
            self._rowbuf = None
            self._kern = None

        # counters and timing (ring of the last keep_timing periods)
        self.iterations = 0
        self.overruns = 0
        self.skipped = 0
        self.keep = int(keep_timing)
        self.wake_ns = array.array("q", bytes(8 * self.keep))
        self.compute_ns = array.array("q", bytes(8 * self.keep))
        self.t0_ns: int | None = None
        self.t_ns = 0
        self._last_cycle_t = None            # start of the previous cycle (skipped periods in between)
        self.fault_t_ns: int | None = None

    @property
    def raw(self) -> list:
        """The controllers' commands of the last step, before the limits."""
        if self._kern is not None:
            return self._rowbuf[13:17].tolist()
        return self._raw

    @raw.setter
    def raw(self, v) -> None:
        self._raw = v

    @property
    def recorder(self):
        return self._recorder

    @recorder.setter
    def recorder(self, rec) -> None:
        self._recorder = rec
        self._row = None                       # the row layout is checked against the new recorder
        self._kring = None                     # its ring, for the compiled period
        self._row_flags = None                 # flags last packed into the row buffer

    # ---- lifecycle ----------------------------------------------------------------------------------
    @property
    def state(self) -> State:
        return self.lc.state

    def configure(self) -> None:
        """Open the port (slow set-up happens here, never in the period) -> INACTIVE."""
        self.port.open()
        self.lc.configure()
        self._start_watchdog()
        self._event("configured: INACTIVE")

    def _start_watchdog(self) -> None:
        # Started here, before enter_realtime: the thread keeps the normal policy and any CPU, and its
        # stack is not faulted in (mlockall) inside the first period.
        if self._use_wd_thread and self.wd is None:
            self.wd = Watchdog(self.cfg.safety.watchdog_s, self._watchdog_trip).start()

    def activate(self) -> None:
        """INACTIVE -> ACTIVE. Fresh controller states, limiter from null: no jump on (re-)activation."""
        self.lc.activate()
        # warm states from INACTIVE; isolation switched on the controllers' bumpless way; the limiter
        # ramps from the null the valve held
        self.states = self._set_enabled(self.states, self.isolation)
        self.limiter.reset()
        self._event("ACTIVE")

    def deactivate(self) -> None:
        """ACTIVE -> INACTIVE: the valve goes to null (written every period while inactive)."""
        if self.lc.state is State.ACTIVE:
            self.lc.deactivate()
            self.states = self._set_enabled(self.states, False)
            self.limiter.reset()
            for i in range(self.n):
                self.cmd[i] = 0.0
            self._safe_write_null()
            self._event("INACTIVE")

    def _fresh_states(self):
        if self.bank is not None:
            fresh = self.bank.set_enabled(self.bank.initial_state(), False)
            kern = getattr(self, "_kern", None)
            if kern is not None:                 # in place: the compiled period's block holds the states
                kern.states[:] = fresh
                return kern.states
            return fresh
        return [c.set_enabled(c.initial_state(), False) for c in self.ctrls]

    def _set_enabled(self, states, on: bool):
        if self.bank is not None:
            return self.bank.set_enabled(states, on)
        return [c.set_enabled(s, on) for c, s in zip(self.ctrls, states)]

    def reset_fault(self) -> None:
        """FAULT -> INACTIVE after the cause is cleared (explicit acknowledgement); fresh controller states."""
        self.lc.reset()
        self.check.reset()
        self.states = self._fresh_states()
        self._event("fault reset: INACTIVE")

    def request_active(self, on: bool) -> None:
        """Thread/signal-safe: (de)activate at the next period boundary."""
        self._active_request = bool(on)

    def request_isolation(self, on: bool) -> None:
        """Thread/signal-safe: switch isolation at the next period boundary (bumpless, in the controllers)."""
        self._iso_request = bool(on)

    def toggle_isolation(self) -> None:
        self._iso_request = not (self.isolation if self._iso_request is None else self._iso_request)

    def stop(self, reason: str) -> None:
        """Thread/signal-safe: leave the loop at the next period boundary, then stop safely."""
        if self.stop_reason is None:
            self.stop_reason = reason

    def fault(self, reason: str) -> None:
        """FAULT: valve to null via port.safe_state(), reason logged once."""
        if self.lc.fault(reason):
            self.fault_t_ns = self.t_ns
            try:
                self.port.safe_state()
            except Exception as e:          # noqa: BLE001 - report, the state is FAULT regardless
                log.error("safe_state failed after fault: %s", e)
            self.limiter.reset()
            for i in range(self.n):
                self.cmd[i] = 0.0
            self._event(f"FAULT: {reason}")
            if self.stop_on_fault:
                self.stop("fault")

    def _event(self, text: str) -> None:
        if self.recorder is not None:
            t = 0.0 if self.t0_ns is None else (self.t_ns - self.t0_ns) * 1e-9
            self.recorder.event(t, text)

    def _safe_write_null(self) -> None:
        try:
            self.port.write(self.t_ns, self._null)
        except Exception as e:              # noqa: BLE001
            self.fault(f"port write failed: {e.__class__.__name__}: {e}")

    # ---- one period -----------------------------------------------------------------------------------
    def cycle(self, t_ns: int, wake_lat_ns: int = 0, compute_prev_ns: int = 0) -> None:
        """read -> check -> update -> limit -> write -> record for the period starting at t_ns."""
        prev_t, self._last_cycle_t = self._last_cycle_t, t_ns
        self.t_ns = t_ns
        lc = self.lc
        if self._active_request is not None or self._iso_request is not None:
            self._requests()
        try:
            m = self.port.read(t_ns)
        except Exception as e:              # noqa: BLE001 - a driver error is a fault, not a dead loop
            self.fault(f"port read failed: {e.__class__.__name__}: {e}")
            return
        self.last_meas = m
        st = lc.state
        kern = self._kern
        if kern is not None and st is not _FAULT and not m.device_fault:
            recorded = self._cycle_compiled(kern, m, t_ns, prev_t, st, wake_lat_ns, compute_prev_ns)
            if not recorded and self._recorder is not None:
                self._record(t_ns, m.accel_mps2, m.stroke_m, wake_lat_ns, compute_prev_ns)
        else:
            self._cycle_stages(m, t_ns, prev_t, st)
            if self._recorder is not None:
                self._record(t_ns, m.accel_mps2, m.stroke_m, wake_lat_ns, compute_prev_ns)
        self._susp_count -= 1
        if self._susp_count <= 0:
            self._susp_count = self._susp_every
            self._watch_suspension()

    def _cycle_compiled(self, kern, m, t_ns: int, prev_t, st, wake_lat_ns: int, compute_prev_ns: int) -> bool:
        """The four-mount bank path: check -> update -> limit -> record in one compiled call (rig/period.py).
        True when the period's row went to the recorder's ring (else the caller records it)."""
        acc = m.accel_mps2
        xs = m.stroke_m
        bank = self.bank
        states = self.states
        active = st is _ACTIVE
        try:
            ns = m.new_samples
            step = True
            if ns is None:
                if prev_t is not None and t_ns - prev_t > self.period_ns:
                    # periods were skipped: the filters must still see the time pass (their double
                    # integration of acceleration would otherwise lose it); outputs are not written
                    bank.replay(states, (self._prev_acc, self._prev_xs), (acc, xs),
                                (t_ns - prev_t) // self.period_ns - 1, self.MAX_HELD_STEPS)
            elif ns:
                # sample-driven port: one step per conversion, in order (outputs of the older ones are not
                # written); skipped periods are among the conversions
                for a_old in m.accel_older:
                    bank.step_into(states, a_old, xs)
            else:
                step = False                      # no new conversion: the command holds
            a0, a1, a2, a3 = acc
            s0, s1, s2, s3 = xs
            t0, t1, t2, t3 = m.sample_t_ns
            ring, slot = self._ring_slot(st)
            code = kern.call(kern.mem, ring, slot, a0, a1, a2, a3, s0, s1, s2, s3, t0, t1, t2, t3, t_ns,
                            (t_ns - self.t0_ns) * 1e-9 if self.t0_ns is not None else 0.0,
                            wake_lat_ns * 1e-3, compute_prev_ns * 1e-3, step, active)
        except Exception as e:              # noqa: BLE001
            self._stepped = self._kran = False
            self.fault(f"controller {self._failed_name()} failed: {e.__class__.__name__}: {e}")
            return False
        self._prev_acc = acc
        self._prev_xs = xs
        if code:
            self._kran = code >= LIMIT_NAN    # the kernel wrote the limited flag into the row
            if code < LIMIT_NAN:               # the check failed: nothing was stepped
                self._stepped = False
                self.fault(kern.check.reason(code, acc, xs, m.sample_t_ns, t_ns))
            else:
                self._stepped = step
                self.fault(kern.limiter.reason(code))
            return slot < 0 and ring is not kern.no_ring    # a full ring: the row is dropped (counted once)
        if active:
            self.cmd[:] = _unpack_cmd4(self._rowbuf, 8 * CompiledPeriod.ICMD)     # the limited commands
            try:
                self.port.write(t_ns, self._commands)
            except Exception as e:  # noqa: BLE001
                self._kran = self._stepped = True
                self.fault(f"port write failed: {e.__class__.__name__}: {e}")
                return False                   # recorded again by the caller, with the fault
        else:
            self._safe_write_null()
            if self.lc.state is _FAULT:        # the null could not be written
                self._kran = self._stepped = True
                return False
        if slot >= 0:
            self._recorder.commit()
            return True
        self._kran = self._stepped = True
        return ring is not kern.no_ring        # full ring: dropped and counted; no recorder: nothing to do

    def _ring_slot(self, st):
        """The recorder's ring and the row index for this period's compiled record (ring rows of the loop's
        layout), or (no_ring, -1) without a row-compatible recorder (then _record does it); the rare flags
        are refreshed in the row first."""
        rec = self._recorder
        if rec is None or (self._row is None and not self._bind_row()) or self._kring is None:
            return self._kern.no_ring, -1
        self._pack_flags(st)
        return self._kring, rec.next_row()

    def _bind_row(self) -> bool:
        """Once per recorder: whether the bank's row goes to it as it is (push_row), and its ring for the
        compiled period to write into (None: the compiled period leaves the record to _record)."""
        rec = self._recorder
        row = self._row = self._row_ok(rec)
        ring = rec.ring_rows() if row and self._kern is not None and hasattr(rec, "ring_rows") else None
        self._kring = ring if ring is not None and ring_ok(ring) else None
        return row

    def _pack_flags(self, st) -> None:
        """The rare flags into the row buffer, only when they changed (the buffer keeps them between periods)."""
        flags = (st, self.isolation, self.overruns, self.skipped)
        if flags != self._row_flags:
            self._row_flags = flags
            mv = self._rowmv
            k = self._iflag
            mv[k] = float(st)
            mv[k + 1] = 1.0 if self.isolation else 0.0
            mv[k + 2] = 1.0 if st is _FAULT else 0.0
            mv[k + 3] = float(self.overruns)
            mv[k + 4] = float(self.skipped)

    def _cycle_stages(self, m, t_ns: int, prev_t, st) -> None:
        """The stages one by one: Python controllers, other mount counts, a device fault, FAULT."""
        lc = self.lc
        self._kran = False
        if st is not _FAULT:
            try:
                reason = self.check.check(m, t_ns)
            except Exception as e:          # noqa: BLE001 - a malformed measurement (a driver bug)
                reason = f"sensor check failed: {e.__class__.__name__}: {e}"
            if reason is not None:
                self.fault(reason)
                st = lc.state
        acc = m.accel_mps2
        xs = m.stroke_m
        self._stepped = False
        if st is _ACTIVE or st is _INACTIVE:
            # INACTIVE steps the controllers too (isolation disabled, output discarded): their filters stay
            # warm, so activation under floor motion starts from a settled state instead of a cold one.
            try:
                bank = self.bank
                ns = m.new_samples
                if bank is not None:
                    if ns is None:
                        if prev_t is not None and t_ns - prev_t > self.period_ns:
                            # periods were skipped: the filters must still see the time pass (their double
                            # integration of acceleration would otherwise lose it); outputs are not written
                            bank.replay(self.states, (self._prev_acc, self._prev_xs), (acc, xs),
                                        (t_ns - prev_t) // self.period_ns - 1, self.MAX_HELD_STEPS)
                        raw = self.raw = bank.step_into(self.states, acc, xs).tolist()   # (self.raw rebound)
                        self._stepped = True
                    elif ns:
                        # sample-driven port: one step per conversion, in order (outputs of the older ones
                        # are not written); skipped periods are among the conversions
                        for a_old in m.accel_older:
                            bank.step_into(self.states, a_old, xs)
                        raw = self.raw = bank.step_into(self.states, acc, xs).tolist()
                        self._stepped = True
                    else:
                        raw = self.raw                # no new conversion: the command holds
                else:
                    raw = self.raw
                    if ns is None:
                        self._step_python(prev_t, t_ns, acc, xs, raw)
                    elif ns:
                        for a_old in m.accel_older:
                            self._step_python(None, t_ns, a_old, xs, raw)
                        self._step_python(None, t_ns, acc, xs, raw)
                self._prev_acc = acc
                self._prev_xs = xs
            except Exception as e:          # noqa: BLE001
                self.fault(f"controller {self._failed_name()} failed: {e.__class__.__name__}: {e}")
            else:
                if st is _INACTIVE:
                    self._safe_write_null()
                else:
                    reason = self.limiter.limit(raw, self.cmd)
                    if reason is not None:
                        self.fault(reason)
                    else:
                        try:
                            self.port.write(t_ns, self._commands)
                        except Exception as e:  # noqa: BLE001
                            self.fault(f"port write failed: {e.__class__.__name__}: {e}")

    def _watch_suspension(self) -> None:
        """Log (once per change) the controllers' saturation recovery suspending or resuming isolation."""
        ctrls = self.ctrls
        for i in range(self.n):
            f = getattr(ctrls[i], "suspended", None)
            if f is None:
                continue
            s = bool(f(self.states[i]))
            if s != self._susp[i]:
                self._susp[i] = s
                text = (f"{self.names[i]}: isolation suspended (output held at the valve clamp: saturation "
                        f"recovery, centring alone)" if s else f"{self.names[i]}: isolation resumed")
                (log.warning if s else log.info)(text)
                self._event(text)

    def _requests(self) -> None:
        """Pending (de)activation and isolation requests, applied at the period boundary."""
        lc = self.lc
        if self._active_request is not None:
            req, self._active_request = self._active_request, None
            if req and lc.state is State.INACTIVE:
                self.activate()
            elif not req and lc.state is State.ACTIVE:
                self.deactivate()
        if self._iso_request is not None:
            on, self._iso_request = self._iso_request, None
            if on != self.isolation:
                self.isolation = on
                if lc.state is State.ACTIVE:
                    self.states = self._set_enabled(self.states, on)
                self._event(f"isolation {'on' if on else 'off'}")

    def _step_python(self, prev_t, t_ns, acc, xs, raw) -> None:
        """Controllers one by one (any controller with the step interface)."""
        ctrls, states, dt, n = self.ctrls, self.states, self.dt, self.n
        self._failed = None
        if prev_t is not None and t_ns - prev_t > self.period_ns:
            miss = (t_ns - prev_t) // self.period_ns - 1
            pa, px = self._prev_acc, self._prev_xs
            for j in range(max(0, miss - self.MAX_HELD_STEPS), miss):
                f = (j + 1) / (miss + 1)
                for i in range(n):
                    self._failed = i
                    raw[i], states[i] = ctrls[i].step(
                        states[i], (pa[i] + f * (acc[i] - pa[i]), px[i] + f * (xs[i] - px[i])), dt)
        for i in range(n):
            self._failed = i
            raw[i], states[i] = ctrls[i].step(states[i], (acc[i], xs[i]), dt)

    def _failed_name(self) -> str:
        if self.bank is not None:
            return "bank (" + ", ".join(self.names) + ")"
        i = getattr(self, "_failed", None)
        return self.names[i] if i is not None else "?"

    def _record(self, t_ns, acc, xs, wake_lat_ns, compute_prev_ns) -> None:
        rec = self._recorder
        if rec is None:
            return
        lst = self.lc.state
        t_s = (t_ns - self.t0_ns) * 1e-9 if self.t0_ns is not None else 0.0
        cmd = self.cmd
        row = self._row
        if row is None:
            row = self._bind_row()
        if row:
            # the bank wrote accel, stroke, raw commands and states into the row; add the rest, one copy
            mv = self._rowmv
            if not self._stepped:                  # controllers not stepped (FAULT): this measurement
                buf = self._rowbuf
                buf[1:5] = acc
                buf[5:9] = xs
            mv[0] = t_s
            mv[9], mv[10], mv[11], mv[12] = cmd
            k = self._iflag
            self._pack_flags(lst)
            if not self._kran:
                mv[k + 5] = 1.0 if self.limiter.limited else 0.0
            mv[k + 6] = wake_lat_ns * 1e-3
            mv[k + 7] = compute_prev_ns * 1e-3
            rec.push_row(self._rowbuf)
            return
        row = [t_s]
        row += acc
        row += xs
        row += cmd
        row += self.raw
        if self.state_len:
            if self.bank is not None:
                row += self.states.ravel().tolist()
            else:
                for s in self.states:
                    row += s
        row += (float(lst), 1.0 if self.isolation else 0.0, 1.0 if lst is _FAULT else 0.0,
                float(self.overruns), float(self.skipped), 1.0 if self.limiter.limited else 0.0,
                wake_lat_ns * 1e-3, compute_prev_ns * 1e-3)
        rec.push(*row)

    def _row_ok(self, rec) -> bool:
        """True when the bank's row can go to the recorder as it is (Recorder.push_row, same layout); False:
        build the generic row (Python controllers, not four mounts, or an adapter with push only)."""
        return (self._rowbuf is not None and hasattr(rec, "push_row")
                and getattr(rec, "ncols", None) == len(self._rowbuf))

    # ---- the loop ---------------------------------------------------------------------------------------
    def run(self, seconds: float | None = None, iterations: int | None = None,
            activate_after_s: float | None = None) -> str:
        """Run periods until `seconds` of loop time, `iterations`, stop() or (with stop_on_fault) a fault.
        With activate_after_s, go ACTIVE after that long INACTIVE (sensors read and checked first).
        Then stop safely: deactivate, valve to null. Returns the stop reason."""
        if self.lc.state is State.UNCONFIGURED:
            self.configure()
        clock = self.clock
        period = self.period_ns
        skip = self.policy == "skip"
        keep = self.keep
        wake_a, comp_a = self.wake_ns, self.compute_ns
        t = clock.now_ns() + period
        if self.t0_ns is None:
            self.t0_ns = t
        end_t = t + int(round(seconds * 1e9)) if seconds is not None else None
        max_it = self.iterations + iterations if iterations is not None else None
        act_it = (self.iterations + max(1, int(round(activate_after_s * self.rate_hz)))
                  if activate_after_s is not None else -1)
        wd_limit = self.watchdog_ns
        self._start_watchdog()
        wd = self.wd
        prev_wake = None
        compute_prev = 0
        cycle = self.cycle
        # optional Port.idle(): work that does not depend on the period's data (the simulated plant draws its
        # next block of floor motion there), run only when at least half a period is left before the deadline
        idle = getattr(self.port, "idle", None) if clock.is_real else None
        idle_ns = period // 2
        try:
            while self.stop_reason is None:
                if end_t is not None and t >= end_t:
                    self.stop("time")
                    break
                if max_it is not None and self.iterations >= max_it:
                    self.stop("iterations")
                    break
                clock.sleep_until(t)
                wake = clock.now_ns()
                if prev_wake is not None and wake - prev_wake > wd_limit and self.lc.state is not State.FAULT:
                    self.t_ns = t
                    self.fault(f"watchdog: {(wake - prev_wake) / 1e6:.3f} ms between periods "
                               f"(limit watchdog_s = {wd_limit / 1e6:g} ms)")
                if wd is not None:
                    wd.beat += 1
                    if wd.tripped and self.lc.state is not State.FAULT:
                        self.fault(wd.tripped)
                prev_wake = wake
                if self.iterations == act_it:
                    self._active_request = True
                cycle(t, wake - t, compute_prev)
                done = clock.now_ns()
                j = self.iterations % keep
                wake_a[j] = wake - t
                comp_a[j] = compute_prev = done - wake
                self.iterations += 1
                t += period
                if done > t:
                    self.overruns += 1
                    if skip:
                        missed = (done - t) // period + 1
                        self.skipped += missed
                        t += missed * period
                elif idle is not None and t - done > idle_ns:
                    idle()                      # the port's housekeeping, in the slack before the next period
        except KeyboardInterrupt:
            self.stop("SIGINT")
        finally:
            self.safe_stop()
        return self.stop_reason or "stopped"

    def _watchdog_trip(self) -> None:
        self.port.safe_state()

    def safe_stop(self) -> None:
        """After the loop: valve to null (deactivate), safe state, watchdog off. Port stays open."""
        if self.lc.state is State.ACTIVE:
            self.deactivate()
        try:
            self.port.safe_state()
        except Exception as e:              # noqa: BLE001
            log.error("safe_state at stop failed: %s", e)
        if self.wd is not None:
            self.wd.stop()
            self.wd = None

    # ---- figures --------------------------------------------------------------------------------------------
    @property
    def missed_deadline_fraction(self) -> float:
        sched = self.iterations + self.skipped
        return (self.overruns + self.skipped) / sched if sched else 0.0

    def timing_us(self) -> dict:
        """p50/p99/max of wake latency and compute over the kept periods, in microseconds."""
        import numpy as np
        n = min(self.iterations, self.keep)
        out = {}
        for key, arr in (("wake_latency_us", self.wake_ns), ("compute_us", self.compute_ns)):
            a = np.frombuffer(arr, dtype=np.int64)[:n] * 1e-3
            if n:
                out[key] = {"p50": float(np.percentile(a, 50)), "p99": float(np.percentile(a, 99)),
                            "max": float(a.max())}
            else:
                out[key] = {"p50": math.nan, "p99": math.nan, "max": math.nan}
        return out
