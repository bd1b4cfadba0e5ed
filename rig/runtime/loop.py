"""The fixed-rate control loop: read -> kernel (check, controllers, limit, row) -> write -> record, once per
period. Loop puts together the parts, each with one concern:

  rig/runtime/scheduler.py  deadlines, overrun policy, timing statistics, gap check and watchdog thread
  rig/runtime/gate.py       the lifecycle gate: requests from other threads, activation, faults, safe stop
  rig/runtime/kernel.py     the compiled period over its memory block (the rules: rig/runtime/safety.py, controllers/)
  rig/runtime/tap.py        the recording tap (the kernel's row into the recorder's ring)

Controllers: one per mount, any kind the kernel runs (controllers/isolation.py, tracking.py, playback.py),
built at the loop's period; anything else raises ConfigError here, at construction. Sample-driven ports
(Measurements.new_samples set: an accelerometer module converting on SYNC into a FIFO, drivers/port.py) step
the controllers once per conversion, in order, older ones first; a period without a new conversion holds the
command. Skipped periods are replayed into the controllers (at most MAX_HELD_STEPS; longer gaps fault on the
watchdog anyway). Any exception of the port is a fault, never a silent death. The controllers' saturation
recovery suspending or resuming a mount's isolation is logged and recorded as an event once per change
(checked at 10 Hz; on the real clock in the slack after a period, not in its time: rare code runs from cold
caches, tens of us), and so is the recorder's writer process: if it dies while the loop records, the run
faults at once (valves to null) and says so. A run stops through one INACTIVE period
(rig/runtime/scheduler.py): its last recorded row has the valve at null. With floor feedforward filters (one per
mount) the loop takes the port's floor accelerometers (Measurements.floor_accel_mps2) and the isolation mode
(off / feedback / feedback_feedforward) is switched through the gate's requests.
"""
from __future__ import annotations

import logging

from controllers.modes import ModeRequest
from rig.runtime.clock import MonotonicClock
from rig.config import Config, mount_names
from rig.errors import ConfigError
from rig.runtime.exchange import FUTEX_CMD
from rig.runtime.gate import LifecycleGate
from rig.runtime.kernel import (BEHIND, CHECK_STROKE_STALE, DEVICE_FAULT, DEVICE_SILENT, MODE_ACTIVE, MODE_FAULT,
                                MODE_INACTIVE, OLDER_CAP, PeriodKernel)
from rig.runtime.measured import MalformedMeasurement, MeasuredPort
from rig.runtime.lifecycle import State
from rig.runtime.safety import CHECK_FLOOR, LIMIT_NAN, LIMIT_OSC, floor_reason
from rig.runtime.scheduler import Scheduler
from rig.runtime.supervisor import HarmSupervisor
from rig.runtime.tap import RecordingTap

log = logging.getLogger("rig.loop")

_ACTIVE, _INACTIVE, _FAULT = State.ACTIVE, State.INACTIVE, State.FAULT
_MODE = (MODE_FAULT, MODE_INACTIVE, MODE_ACTIVE, MODE_FAULT)     # by State (an IntEnum: indexing is cheap)


class Loop:
    MAX_HELD_STEPS = 50     # skipped periods replayed into the controllers at most

    def __init__(self, cfg: Config, port, controllers: list, *, clock=None, recorder=None,
                 rate_hz: float | None = None, overrun_policy: str | None = None, isolation: bool = True,
                 keep_timing: int = 1 << 15, names: tuple[str, ...] | None = None,
                 stop_on_fault: bool = True, watchdog_thread: bool | None = None, rate_check: bool = True,
                 feedforward: list | None = None, feedforward_on: bool = False) -> None:
        self.cfg = cfg
        self.port = port
        self.n = int(port.n_mounts)
        if len(controllers) != self.n:
            raise ConfigError(f"loop: {len(controllers)} controllers for {self.n} mounts")
        self.ctrls = list(controllers)
        self.clock = clock if clock is not None else MonotonicClock()
        if getattr(self.clock, "spin_ns", 0) is None:      # a real clock whose wait was not chosen: [loop]
            self.clock.spin_ns = int(round(cfg.loop.spin_us * 1e3))
        sf = cfg.safety
        self.sched = Scheduler(self.clock, rate_hz or cfg.loop.rate_hz, overrun_policy or cfg.loop.overrun_policy,
                               sf.watchdog_s, keep_timing,
                               self.clock.is_real if watchdog_thread is None else watchdog_thread,
                               lag_limit_s=sf.lag_limit_s, missed_limit=sf.missed_limit,
                               missed_window_s=sf.missed_window_s, period_budget=sf.period_budget,
                               rate_check=rate_check)
        self.rate_hz, self.period_ns, self.policy = self.sched.rate_hz, self.sched.period_ns, self.sched.policy
        self.dt = self.period_ns * 1e-9
        self.names = names or mount_names(self.n)
        if feedforward and not getattr(port, "floor_sensors", False):
            raise ConfigError(f"loop: the floor feedforward needs floor accelerometers, and the {port.name} port "
                              f"has none ([sensors] floor_accel)")
        self.kernel = PeriodKernel(cfg, self.ctrls, self.names, self.dt, self.MAX_HELD_STEPS, feedforward)
        self._call, self._at = self.kernel.call, self.kernel.at      # the compiled period, bound once
        self.channels = self.kernel.layout.channels         # the recording layout of this loop
        self.tap = RecordingTap(self.kernel)
        self.gate = LifecycleGate(self.kernel, port, self._event, isolation=isolation,
                                  stop_on_fault=stop_on_fault, feedforward=feedforward_on)
        self.gate.bind_recorder = self.tap.bind
        self.gate.loop_time_s = lambda: self._t_s(self.gate.t_ns)
        self.check, self.limiter, self.states = self.kernel.check, self.kernel.limiter, self.kernel.states
        self._bind_port(port)
        self.recorder = recorder
        self._read = False                   # a period has taken a measurement (last_meas)
        self._susp_every = max(1, int(round(0.1 * self.rate_hz)))   # suspension watch (event/log), 10 Hz
        self._susp_count = self._susp_every
        # the 10 Hz watch runs in the period when its count reaches this: 0 in simulated time; on the real clock
        # it runs in the slack after a period (_slack) and in the period only when no slack came for another
        # 0.1 s: rare code is slow code (tens of us from cold caches), kept out of the period's time
        self._watch_late = 0 if not self.clock.is_real else -self._susp_every
        self._susp = [False] * self.n
        self._ff_held = 0.0                 # the feedforward's restart: the hold it had at the last watch, s
        self._lost_seen = -1                # the last period that took lost conversions, as last logged
        self._port_idle = getattr(port, "idle", None)      # the port's slack housekeeping (optional), bound once
        # the do-no-harm supervisor (rig/runtime/supervisor.py), at the 10 Hz watch
        self.supervisor = (HarmSupervisor(cfg.supervisor, self.n, self.exchange.nf, self.rate_hz, self.names)
                           if cfg.supervisor.enabled else None)
        if self.supervisor is not None:     # the watch often enough for the ring of conversions it reads
            self._susp_every = min(self._susp_every, self.supervisor.look_periods(self.exchange.io))
            self._susp_count = self._susp_every
            self._watch_late = 0 if not self.clock.is_real else -self._susp_every

    def _bind_port(self, port) -> None:
        """The port's exchange block (rig/runtime/exchange.py), or one of the loop's own for a port that only
        reads and writes (rig/runtime/measured.py); its steps before the period (`update`) and after it
        (`commit`), bound once."""
        block = getattr(port, "exchange", None)
        if block is None:
            feed = MeasuredPort(port, self.n, self.kernel.nf)
            block, self._update, self._commit, self._feed = feed.exchange, feed.update, feed.commit, feed
        else:
            self._update, self._commit = getattr(port, "update", None), getattr(port, "commit", None)
            self._feed = None
        if block.n != self.n or block.nf < self.kernel.nf:
            raise ConfigError(f"loop: the {port.name} port's exchange block has {block.n} mounts and {block.nf} floor "
                              f"accelerometers; the loop has {self.n} and {self.kernel.nf}")
        self.exchange = block
        self.kernel.bind_io(block.io)

    def slow_down(self, extra) -> None:
        """extra() runs in every period before the port's update (fault rehearsal: rig/runtime/inject.py)."""
        update = self._update

        def slowed(t_ns: int) -> None:
            extra()
            if update is not None:
                update(t_ns)
        self._update = slowed

    # ---- one period ----------------------------------------------------------------------------------
    def cycle(self, t_ns: int, wake_lat_ns: int = 0, compute_prev_ns: int = 0) -> None:
        """The port's update -> kernel (takes the inputs from the exchange block, checks, controls, limits,
        writes the commands there, records) -> the port's commit, for the period starting at t_ns."""
        gate = self.gate
        gate.t_ns = t_ns
        if gate.pending:
            gate.apply_requests()
        self._susp_count -= 1
        if self._susp_count <= self._watch_late:    # 10 Hz: suspension events; the recorder's writer alive
            self._watch()
        if self._update is not None and not self._updated(t_ns):
            return
        st = gate.lc.state
        tap, sched = self.tap, self.sched
        if tap.waits:
            tap.wait_room()                 # simulated time: the writer's room for the row
        t0 = sched.t0_ns
        code = self._call(self._at, t_ns, (t_ns - t0) * 1e-9 if t0 is not None else 0.0, wake_lat_ns * 1e-3,
                          compute_prev_ns * 1e-3, _MODE[st], st, gate.isolation, sched.overruns, sched.skipped)
        self._read = True
        if code or self._commit is not None or tap.pushes:     # else nothing more to do in the period
            self._after(code, st, t_ns)

    def _updated(self, t_ns: int) -> bool:
        """The port's update before the kernel (a port that steps in the period: the simulated plant), and the
        watchdog's trip meanwhile; False: the period faulted."""
        gate = self.gate
        try:
            self._update(t_ns)
        except MalformedMeasurement as e:       # a driver bug
            gate.fault(f"malformed measurement from the port: {e}")
            return False
        except Exception as e:          # noqa: BLE001 - a driver error is a fault, not a dead loop
            gate.fault(f"port read failed: {e.__class__.__name__}: {e}")
            return False
        wd = self.sched.wd
        if wd is not None and wd.tripped and gate.lc.state is not _FAULT:
            gate.fault(wd.tripped)              # (in this period: its line, not the aftermath)
        return True

    def _after(self, code: int, st, t_ns: int) -> None:
        """After the compiled call, when it has more to do: a rule fired (fault), the valves' I/O waits for the
        commands (wake it), the port commits, the row goes to a recorder without a ring."""
        gate, kernel, tap, sched = self.gate, self.kernel, self.tap, self.sched
        if code > 0:
            gate.fault(self._reason(code, t_ns))
        elif code:                          # WAKE_COMMANDS: the valves' I/O waits for this period's commands
            self.exchange.wake(FUTEX_CMD)
        if code <= 0 and self._commit is not None:
            try:
                self._commit(t_ns)
            except Exception as e:          # noqa: BLE001
                gate.fault(f"port write failed: {e.__class__.__name__}: {e}")
        faulted = gate.lc.state is not st
        if faulted:                          # the period is recorded with its fault and nothing written
            kernel.null_commands()
            kernel.record_flags(gate.lc.state, gate.isolation, sched.overruns, sched.skipped)
        if tap.recorder is not None and (faulted or code > 0 or tap.pushes):    # the kernel recorded the row
            tap.close(True)

    @property
    def last_meas(self):
        """The measurement the last period took (rig.port.Measurements; the port's own read when it has no
        exchange block), None before the first."""
        if not self._read:
            return None
        return self._feed.last if self._feed is not None else self.kernel.measurements()

    def _watch(self) -> None:
        """The 10 Hz watch: the controllers' saturation recovery (events), the recorder's writer alive."""
        self._susp_count = self._susp_every
        self._watch_suspension()
        if self.supervisor is not None:
            self._watch_harm()
        if self.tap.recorder is not None:
            self._watch_recorder()

    def _slack(self) -> None:
        """The real clock's slack after a period (the scheduler calls it when half a period is left): the 10 Hz
        watch when due, then the port's own housekeeping."""
        if self._susp_count <= 0:
            self._watch()
        if self._port_idle is not None:
            self._port_idle()

    def _reason(self, code: int, t_ns: int) -> str:
        """The one-line fault text of a rule's code (off the hot path)."""
        k = self.kernel
        if code >= CHECK_STROKE_STALE:
            return self._input_reason(code)
        m = k.measurements()
        if code - code % 100 == CHECK_FLOOR:
            return floor_reason(code, self.names, m.floor_accel_mps2, k.floor_range)
        if code < LIMIT_NAN:
            text = self.check.reason(code, k.check_state, m.accel_mps2, m.stroke_m, m.sample_t_ns, t_ns)
            named = getattr(self.port, "stale_reason", None)      # a port that knows which device went quiet
            if named is not None and ": stale sample:" in text:
                text = named(t_ns, float(self.check.stale_ns)) or text
            return text
        if code >= LIMIT_OSC:
            return k.osc.reason(code, k.osc_state)
        return self.limiter.reason(code)

    def _input_reason(self, code: int) -> str:
        """The text of an input rule (rig/runtime/kernel.py _take): a device's own line, a device silent, the
        transducer's sample too old, the loop behind the accelerometer module."""
        k, block = self.kernel, self.exchange
        what = k.mem[k.mem_index("x_age")] / 1e6
        if code == CHECK_STROKE_STALE:
            lim = block.io[block.part("stroke") + 1] / 1e6
            return (f"displacement transducers: newest sample {what:.1f} ms old (limit {lim:g} ms, the "
                    f"transducer's own staleness limit): the amplifier's frames stopped")
        if DEVICE_FAULT <= code < DEVICE_SILENT:
            return f"device fault: {block.text(code - DEVICE_FAULT)}"
        if DEVICE_SILENT <= code < BEHIND:
            d = code - DEVICE_SILENT
            lim = block.device_row(d)[2] / 1e6
            why = getattr(self.port, "silent_reason", lambda d: None)(d)
            return (f"device fault: {block.device_name(d)}: {why or 'its I/O process has not reported'} "
                    f"(nothing for {what:.1f} ms, limit {lim:g} ms)")
        if code == BEHIND:
            held = int(k.mem[k.mem_index("held_up")])
            return (f"{held} accelerometer conversions came in one period (the loop takes at most {OLDER_CAP}): the "
                    f"loop or the module's I/O was held up for about {held * self.dt * 1e3:.0f} ms")
        return "no measurement from the port yet (no accelerometer conversion or transducer sample)"

    def _t_s(self, t_ns: int) -> float:
        t0 = self.sched.t0_ns
        return (t_ns - t0) * 1e-9 if t0 is not None else 0.0

    def _event(self, text: str) -> None:
        self.tap.event(self._t_s(self.gate.t_ns), text)

    def _watch_suspension(self) -> None:
        """Log (once per change) isolation suspended or resumed (the controllers' saturation recovery, or
        conversions lost), and the floor feedforward held off after lost conversions or let back."""
        lost = self.kernel.last_loss_ns()
        if lost != self._lost_seen:             # a period took conversions the module had lost
            self._lost_seen = lost
            text = ("accelerometer conversions lost past the module's FIFO (a hold-up), estimated across the gap: "
                    "isolating mounts suspended until their estimate settles"
                    + (f", floor feedforward held off {self.kernel.feedforward_restarting_s():.1f} s and "
                       f"restarted" if self.kernel.nf else "")
                    + " (the estimate's error would be a velocity to their double integrations)")
            log.warning(text)
            self._event(text)
        why = "conversions lost" if lost >= 0 and self.gate.t_ns - lost < 2e8 else (
            "output held at the valve clamp: saturation recovery")
        for i, s in enumerate(self.kernel.suspended()):
            if s != self._susp[i]:
                self._susp[i] = s
                text = (f"{self.names[i]}: isolation suspended ({why}, centring alone)" if s
                        else f"{self.names[i]}: isolation resumed")
                (log.warning if s else log.info)(text)
                self._event(text)
        held, was = self.kernel.feedforward_restarting_s(), self._ff_held
        self._ff_held = held
        if was > 0 and held == 0:
            text = "floor feedforward restarted: its output back" + (
                "" if self.kernel.feedforward_enabled() else " (switched off meanwhile: stays off)")
            log.info(text)
            self._event(text)

    def isolating(self) -> bool | None:
        """Isolation acting on the valves: ACTIVE with isolation on (operating modes: a mount isolating; None
        while one tracks a reference: its motion is neither isolation nor a passive reference)."""
        if self.gate.lc.state is not _ACTIVE:
            return False
        modes = [c.current.mode for c in self.ctrls if hasattr(c, "switch")]
        if not modes:
            return bool(self.gate.isolation)
        return True if "isolate" in modes else None if "track" in modes else False

    def _watch_harm(self) -> None:
        """The do-no-harm supervisor's look: isolation that made the table worse -> one line, an event, isolation
        off (bumpless) and held off; stands: every mount to hold."""
        sup = self.supervisor
        t_s = self._t_s(self.gate.t_ns)
        harm = sup.look(self.exchange.io, self.isolating(), t_s)
        said = sup.no_reference_line()
        if said:
            log.warning("%s", said)
            self._event(said)
        if harm is None:
            return
        log.warning("%s", harm)            # a warning: the run goes on, isolation off
        self._event(harm)
        self.gate.hold_isolation_off(harm)
        for m, c in enumerate(self.ctrls):
            if hasattr(c, "switch") and c.current.mode == "isolate":
                self.gate.request_mode(m, ModeRequest("hold"))

    @property
    def harm(self) -> str | None:
        """The do-no-harm supervisor's line when it switched isolation off, else None."""
        return self.supervisor.harm if self.supervisor is not None else None

    @property
    def suspended_mounts(self) -> list[str]:
        """Mounts whose isolation the saturation recovery holds off (as last seen, at 10 Hz)."""
        return [m for m, s in zip(self.names, self._susp) if s]

    def _watch_recorder(self) -> None:
        """The recorder's writer gone while recording: FAULT now (the rows it had not flushed are lost; the
        ring would fill and drop every row after them). Rows dropped since the last watch (the writer fell
        behind the real clock): said at once, and an event in the recording where its time base has the gap."""
        tap = self.tap
        died = getattr(tap.recorder, "writer_died", None)
        text = died() if died is not None else None
        if text and self.gate.lc.state is not _FAULT:
            self.gate.fault(f"recorder: {text}")
        dropped = tap.new_drops()
        if dropped:
            t_s = self._t_s(self.gate.t_ns)
            text = (f"recorder: {dropped} rows dropped in the 0.1 s before t = {t_s:.3f} s (the writer fell behind; "
                    f"{tap.dropped_seen} in all): the recording has a gap there")
            log.warning("%s", text)
            tap.event(t_s, text)

    # ---- the run --------------------------------------------------------------------------------------
    def configure(self) -> None:
        """Open the port (slow set-up happens here, never in the period) -> INACTIVE."""
        self.gate.configure()
        self.sched.start_watchdog(self.port.safe_state)

    def run(self, seconds: float | None = None, iterations: int | None = None,
            activate_after_s: float | None = None) -> str:
        """Run periods until `seconds` of loop time, `iterations`, stop() or (with stop_on_fault) a fault.
        With activate_after_s, go ACTIVE after that long INACTIVE (sensors read and checked first).
        Then stop safely: deactivate, valve to null. Returns the stop reason."""
        if self.gate.state is State.UNCONFIGURED:
            self.configure()
        self.sched.start_watchdog(self.port.safe_state)
        try:
            self.sched.run(self.cycle, self.gate, seconds=seconds, iterations=iterations,
                           activate_after_s=activate_after_s, idle=self._slack)
        except KeyboardInterrupt:
            self.gate.stop("SIGINT")
        finally:
            self.safe_stop()
        return self.gate.stop_reason or "stopped"

    def safe_stop(self) -> None:
        """After the loop: valve to null (deactivate), safe state, watchdog off, the last row published. Port
        stays open."""
        self.gate.safe_stop()
        self.sched.stop_watchdog()
        self.tap.publish()

    # ---- the gate's requests and transitions, and the figures, as the loop's -------------------------
    def request_active(self, on: bool) -> None:
        """Thread/signal-safe: (de)activate at the next period boundary."""
        self.gate.request_active(on)

    def request_isolation(self, on: bool) -> None:
        """Thread/signal-safe: switch isolation at the next period boundary (bumpless, in the controllers)."""
        self.gate.request_isolation(on)

    def toggle_isolation(self) -> None:
        self.gate.toggle_isolation()

    def request_isolation_mode(self, mode: str) -> None:
        """Thread/signal-safe: off / feedback / feedback_feedforward at the next period boundary (bumpless)."""
        self.gate.request_isolation_mode(mode)

    def request_mode(self, mount: int, request) -> None:
        """Thread/signal-safe: an operating mode for one mount at the next period boundary (bumpless)."""
        self.gate.request_mode(mount, request)

    def stop(self, reason: str) -> None:
        """Thread/signal-safe: leave the loop at the next period boundary, then stop safely."""
        self.gate.stop(reason)

    def activate(self) -> None:
        self.gate.activate()

    def deactivate(self) -> None:
        self.gate.deactivate()

    def reset_fault(self) -> None:
        self.gate.reset_fault()

    def fault(self, reason: str) -> None:
        self.gate.fault(reason)

    def timing_us(self) -> dict:
        return self.sched.timing_us()

    @property
    def recorder(self):
        return self.tap.recorder

    @recorder.setter
    def recorder(self, rec) -> None:
        self.tap.bind(rec)

    lc = property(lambda self: self.gate.lc)
    state = property(lambda self: self.gate.lc.state)
    isolation = property(lambda self: self.gate.isolation)
    isolation_mode = property(lambda self: self.gate.isolation_mode)
    stop_reason = property(lambda self: self.gate.stop_reason,
                           lambda self, v: setattr(self.gate, "stop_reason", v))
    stop_on_fault = property(lambda self: self.gate.stop_on_fault,
                             lambda self, v: setattr(self.gate, "stop_on_fault", v))
    fault_t_ns = property(lambda self: self.gate.fault_t_ns)
    t_ns = property(lambda self: self.gate.t_ns)
    t0_ns = property(lambda self: self.sched.t0_ns)
    cmd = property(lambda self: list(self.kernel.commands()))          # commands of the last period
    raw = property(lambda self: self.kernel.raw_commands())            # the controllers' commands
    state_len = property(lambda self: len(self.kernel.state_labels))
    iterations = property(lambda self: self.sched.iterations)
    overruns = property(lambda self: self.sched.overruns)
    skipped = property(lambda self: self.sched.skipped, lambda self, v: setattr(self.sched, "skipped", v))
    keep = property(lambda self: self.sched.keep)
    wake_ns = property(lambda self: self.sched.wake_ns)
    compute_ns = property(lambda self: self.sched.compute_ns)
    cpu_ns = property(lambda self: self.sched.cpu_ns)
    missed_deadline_fraction = property(lambda self: self.sched.missed_deadline_fraction)
