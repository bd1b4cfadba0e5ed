"""Shared pieces for the runtime tests: a small real plant and a small real controller (not mocks).

TinyPlant: per mount a valve-driven first-order actuator (stroke lag to the valve command, gain 2.68 um/V
like Table 1's DC gain, 7.43 Hz corner) with a load offset (stroke off-centre at null) under a sinusoidal
floor; accel = machine acceleration.
CentringP: proportional stroke centring (a compiled controller kind of the loop's kernel).
Command: a `rig` command as a background process, its stderr followed line by line.
"""
from __future__ import annotations

import math
import signal
import subprocess
import sys
import threading
import time

from controllers.tracking import PIDParams, TrackingPID


class TinyPlant:
    def __init__(self, n: int, dt: float, *, floor_amp_m: float = 10e-6, floor_hz: float = 5.0,
                 offset_m: float = 5e-6) -> None:
        self.n, self.dt = n, dt
        self.k = 0
        self.gain = 2.68e-6            # m/V, DC gain of Table 1's actuator (PHYSICS_NOTES)
        self.w_c = 46.7                # rad/s, the K_C K_L / A_p^2 lag corner
        self.offset = [offset_m * (i + 1) for i in range(n)]   # a load that pushes each piston off-centre
        self.x = list(self.offset)
        self.floor_amp, self.w_f = floor_amp_m, 2 * math.pi * floor_hz
        self.stroke_m = list(self.x)
        self.accel_mps2 = [0.0] * n
        self.t_s = 0.0

    def step(self, valve_cmd_V) -> None:
        a = math.exp(-self.w_c * self.dt)
        self.k += 1
        self.t_s = self.k * self.dt
        fl_acc = -self.floor_amp * self.w_f ** 2 * math.sin(self.w_f * self.t_s)
        for i in range(self.n):
            self.x[i] = a * self.x[i] + (1 - a) * (self.offset[i] + self.gain * valve_cmd_V[i])
            self.stroke_m[i] = self.x[i]
            self.accel_mps2[i] = fl_acc * (1.0 + 0.1 * i)


def CentringP(kp_V_per_m: float = 2e4, dt: float = 2e-4) -> TrackingPID:
    """Proportional stroke centring, valve = -kp * stroke: the tracking PID (a kernel controller kind) with
    reference 0, no integral, no derivative and no limits of its own (the loop's limiter does the limiting)."""
    return TrackingPID(PIDParams(kp_V_per_m, 0.0, 0.0, 1000.0, math.inf, math.inf), dt)


def default_sigint() -> None:
    """SIGINT at its default in a child (preexec_fn), as a command typed at a terminal has it: a job a shell starts
    in the background (a CI runner's, say) inherits SIGINT ignored, and Python then keeps it ignored."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


class Command:
    """A `rig` command in the background (a real process), its stderr collected line by line; waits for a
    line."""

    def __init__(self, *args, env=None, own_group=False):
        """own_group: in a process group of its own with SIGINT at its default, as a command at a terminal is
        (a Ctrl-C there reaches the whole group: os.killpg(proc.pid, SIGINT))."""
        self.proc = subprocess.Popen([sys.executable, "-m", "rig.cli", *args], stdout=subprocess.PIPE,
                                     stderr=subprocess.PIPE, text=True, env=env, start_new_session=own_group,
                                     preexec_fn=default_sigint if own_group else None)
        self.lines: list[str] = []
        self._closed = False
        self._seen = threading.Condition()
        threading.Thread(target=self._pump, daemon=True).start()

    def _pump(self):
        for line in self.proc.stderr:
            with self._seen:
                self.lines.append(line)
                self._seen.notify_all()
        with self._seen:
            self._closed = True
            self._seen.notify_all()

    def wait_for(self, text: str, timeout=120.0) -> bool:
        """True once a line containing `text` came; False after timeout s or when stderr closed without it."""
        end = time.monotonic() + timeout
        with self._seen:
            while not any(text in ln for ln in self.lines):
                if self._closed or time.monotonic() > end:
                    return False
                self._seen.wait(0.2)
        return True

    def finish(self, timeout=120) -> int:
        try:
            return self.proc.wait(timeout)
        finally:
            if self.proc.poll() is None:
                self.proc.kill()

    def drain(self, timeout=30.0) -> None:
        """Until stderr closes: every process that shares it (children too) has written its last line."""
        end = time.monotonic() + timeout
        with self._seen:
            while not self._closed and time.monotonic() < end:
                self._seen.wait(0.2)

    @property
    def text(self) -> str:
        return "".join(self.lines)


class ReadWritePort:
    """A port that only reads and writes (rig.port.Port), over another port: the loop then reaches it through
    a block of its own (rig/runtime/measured.py), so a test can change what read() returns."""

    def __init__(self, inner) -> None:
        self.inner = inner
        self.n_mounts, self.name = inner.n_mounts, inner.name
        self.floor_sensors = getattr(inner, "floor_sensors", False)

    def open(self) -> None:
        self.inner.open()

    def close(self) -> None:
        self.inner.close()

    def safe_state(self) -> None:
        self.inner.safe_state()

    def read(self, t_ns):
        return self.inner.read(t_ns)

    def write(self, t_ns, commands) -> None:
        self.inner.write(t_ns, commands)
