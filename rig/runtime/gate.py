"""The lifecycle gate: which commands reach the valve, and the requests that change it.

INACTIVE writes null (the controllers still run, output discarded, so their filters are warm: activating
with cold filters under floor motion can kick the loop into a latched saturation); ACTIVE writes the limited
commands; FAULT writes nothing after port.safe_state(). Requests (activation, isolation on/off, stop) are
thread- and signal-safe: they are single assignments, applied at the next period boundary. On activation
the controllers switch isolation on their own bumpless way and the limiter ramps from the null the valve
held, so (re-)activation never jumps. Operating-mode requests (a mount's mode and reference, controllers/
modes.py) are applied the same way, each mount's latest one, and so are timed requests (`schedule`: a script
of requests at given loop times, applied at the first period boundary at or after their time).

The isolation mode (not an operating mode): off, feedback, or feedback_feedforward (the floor feedforward
added, when the loop has it). `isolation` and `feedforward` are the two switches behind it; the feedforward
acts only while isolation is on.
"""
from __future__ import annotations

import logging

from rig.runtime.lifecycle import Lifecycle, State
from rig.port import Commands

log = logging.getLogger("rig.loop")

ISOLATION_MODES = ("off", "feedback", "feedback_feedforward")


class LifecycleGate:
    def __init__(self, kernel, port, event, *, isolation: bool, stop_on_fault: bool,
                 feedforward: bool = False) -> None:
        self.kernel = kernel
        self.port = port
        self._event = event                  # event(text): the recording's event list
        self.lc = Lifecycle()
        self.isolation = bool(isolation)
        self.stop_on_fault = stop_on_fault
        self.stop_reason: str | None = None
        self.fault_t_ns: int | None = None
        self.t_ns = 0                        # the period being run (fault times, events)
        self._active_request: bool | None = None
        self._iso_request: bool | None = None
        self.feedforward = bool(feedforward) and bool(getattr(kernel, "nf", 0))
        self._ff_request: bool | None = None
        self._reset_request = False
        self.pending = False                 # any request below is waiting (a plain flag: one load per period)
        self._recorder_request = None        # (recorder,) to record into from the next period
        self.bind_recorder = None            # set by the loop: where a recorder request goes
        self._null = Commands([0.0] * kernel.n)
        self._mode_requests: dict = {}       # mount index -> its latest operating-mode request
        self._script: list = []              # (loop time s, action), time order
        self.loop_time_s = lambda: 0.0       # set by the loop: the loop time of the period being run
        self.held_off: str | None = None     # why isolation is held off (the do-no-harm supervisor): on refused

    @property
    def state(self) -> State:
        return self.lc.state

    # ---- requests (any thread, signal handlers) -----------------------------------------------------------
    def request_active(self, on: bool) -> None:
        self._active_request = bool(on)
        self.pending = True

    def request_isolation(self, on: bool) -> None:
        self._iso_request = bool(on)
        self.pending = True

    def request_isolation_mode(self, mode: str) -> None:
        """off / feedback / feedback_feedforward (ValueError for another word, or feedforward without floor
        sensors): isolation and the feedforward switched together at the next period boundary."""
        if mode not in ISOLATION_MODES:
            raise ValueError(f"isolation mode {mode!r}: expected one of {', '.join(ISOLATION_MODES)}")
        if mode == "feedback_feedforward" and not getattr(self.kernel, "nf", 0):
            raise ValueError("isolation mode feedback_feedforward: the loop has no floor feedforward "
                             "([sensors] floor_accel = false)")
        self._ff_request = mode == "feedback_feedforward"
        self._iso_request = mode != "off"
        self.pending = True

    @property
    def isolation_mode(self) -> str:
        M = ISOLATION_MODES
        return M[0] if not self.isolation else M[2] if self.feedforward else M[1]

    def toggle_isolation(self) -> None:
        self._iso_request = not (self.isolation if self._iso_request is None else self._iso_request)
        self.pending = True

    def hold_isolation_off(self, reason: str) -> None:
        """Isolation off at the next boundary (bumpless) and held off for the rest of the run: a later request
        to switch it on is refused with one line (rig/runtime/supervisor.py)."""
        self.held_off = reason
        self._iso_request, self._ff_request = False, False
        self.pending = True

    def request_reset_fault(self) -> None:
        """FAULT -> INACTIVE at the next period boundary (the operator acknowledges the fault)."""
        self._reset_request = True
        self.pending = True

    def request_mode(self, mount: int, request) -> None:
        """Mount `mount` to an operating mode (a checked controllers.modes.ModeRequest) at the next boundary."""
        self._mode_requests = {**self._mode_requests, mount: request}     # one assignment: thread-safe
        self.pending = True

    def schedule(self, at_s: float, action) -> None:
        """action() at the first period boundary at or after loop time at_s (before the run: a script)."""
        self._script = sorted(self._script + [(float(at_s), action)], key=lambda e: e[0])
        self.pending = True

    def request_recorder(self, recorder) -> None:
        """Record into `recorder` (None: stop recording) from the next period boundary on."""
        self._recorder_request = (recorder,)
        self.pending = True

    def stop(self, reason: str) -> None:
        """Leave the loop at the next period boundary, then stop safely."""
        if self.stop_reason is None:
            self.stop_reason = reason

    def apply_requests(self) -> None:
        """Pending requests, at the period boundary (one arriving meanwhile waits for the next)."""
        self.pending = False
        lc = self.lc
        if self._script:
            now = self.loop_time_s()
            while self._script and self._script[0][0] <= now + 1e-12:
                self._script.pop(0)[1]()
            self.pending = self.pending or bool(self._script)     # keep looking while a script runs
        if self._recorder_request is not None:
            (rec,), self._recorder_request = self._recorder_request, None
            self.bind_recorder(rec)
        if self._reset_request:
            self._reset_request = False
            if lc.state is State.FAULT:
                self.reset_fault()
        if self._active_request is not None:
            req, self._active_request = self._active_request, None
            if req and lc.state is State.INACTIVE:
                self.activate()
            elif not req and lc.state is State.ACTIVE:
                self.deactivate()
        if self._mode_requests:
            reqs, self._mode_requests = self._mode_requests, {}
            for m, req in reqs.items():
                self.kernel.switch(m, req, lc.state is State.ACTIVE)
                self._event(f"{self.kernel.names[m]}: mode {req}")
        if self._iso_request is not None or self._ff_request is not None:
            before = self.isolation_mode
            on, self._iso_request = self._iso_request, None
            if on and self.held_off is not None:
                log.warning("isolation on refused: held off since %s", self.held_off)
                self._event("isolation on refused: held off by the do-no-harm supervisor")
                on, self._ff_request = None, None
            if on is not None and on != self.isolation:
                self.isolation = on
                if lc.state is State.ACTIVE:
                    self.kernel.set_enabled(on)
                log.info("isolation %s", "on" if on else "off")
                self._event(f"isolation {'on' if on else 'off'}")
            ff, self._ff_request = self._ff_request, None
            if ff is not None:
                self.feedforward = ff
            self._apply_feedforward()
            if self.isolation_mode != before and self.kernel.nf:
                log.info("isolation mode %s", self.isolation_mode)
                self._event(f"isolation mode {self.isolation_mode}")

    # ---- transitions (the loop's thread) ----------------------------------------------------------------
    def configure(self) -> None:
        self.port.open()
        self.lc.configure()
        self._event("configured: INACTIVE")

    def activate(self) -> None:
        """INACTIVE -> ACTIVE: warm states, isolation switched on bumplessly, the limiter from null."""
        self.lc.activate()
        self.kernel.set_enabled(self.isolation)
        self._apply_feedforward()
        self.kernel.activated()
        self.kernel.reset_limiter()
        self._event("ACTIVE")

    def deactivate(self) -> None:
        """ACTIVE -> INACTIVE: the valve goes to null (written every period while inactive)."""
        if self.lc.state is State.ACTIVE:
            self.lc.deactivate()
            self.kernel.set_enabled(False)
            self._apply_feedforward()
            self.kernel.reset_limiter()
            self.kernel.null_commands()
            self.write_null()
            self._event("INACTIVE")

    def _apply_feedforward(self) -> None:
        """The kernel's feedforward switch from the mode and the lifecycle: on only while ACTIVE and isolating."""
        if self.kernel.nf:
            self.kernel.set_feedforward(self.isolation and self.feedforward and self.lc.state is State.ACTIVE)

    def reset_fault(self) -> None:
        """FAULT -> INACTIVE after the cause is cleared (explicit acknowledgement); fresh controller states."""
        self.lc.reset()
        self.kernel.reset_check()
        self.kernel.fresh_states()
        self._event("fault reset: INACTIVE")

    def fault(self, reason: str) -> None:
        """FAULT: valve to null via port.safe_state(), reason logged and recorded once."""
        if self.lc.fault(reason):
            self.fault_t_ns = self.t_ns
            try:
                self.port.safe_state()
            except Exception as e:          # noqa: BLE001 - report, the state is FAULT regardless
                log.error("safe_state failed after fault: %s", e)
            self.kernel.reset_limiter()
            self.kernel.null_commands()
            self._event(f"FAULT: {reason}")
            if self.stop_on_fault:
                self.stop("fault")

    def write_null(self) -> None:
        try:
            self.port.write(self.t_ns, self._null)
        except Exception as e:              # noqa: BLE001
            self.fault(f"port write failed: {e.__class__.__name__}: {e}")

    def safe_stop(self) -> None:
        """After the loop: valve to null (deactivate), safe state. The port stays open."""
        if self.lc.state is State.ACTIVE:
            self.deactivate()
        try:
            self.port.safe_state()
        except Exception as e:              # noqa: BLE001
            log.error("safe_state at stop failed: %s", e)
