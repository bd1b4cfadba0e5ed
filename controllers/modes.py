"""Operating modes of one mount, switchable while live: the prototype actuator on demand.

  off      valve null (the sensors are still read and checked every period)
  hold     hold the piston at a position (the tracking controller on a held reference)
  track    follow a reference: setpoint, step, sine, chirp or a CSV profile (controllers/reference.py), the
           paper's Fig. 4 PID with the reference fed forward (controllers/tracking.py)
  isolate  keep the load still against base motion: the isolation controller (controllers/isolation.py),
           designed for the stand's load

`modes_step` (numba) is the law of this controller kind: it runs the active mode's law on that mode's own
state and coefficients (both kept in this controller's, one after the other). The isolation filters are
stepped in every mode (their output discarded outside `isolate`), so that mode starts from an estimate that
has followed the sensors all along. Switching (`switch`, between periods, from rig/runtime/kernel.py) is bumpless:
the new mode takes the valve from the command last written (`take_over` of the tracking and isolation
builders) and a new reference starts from the current one; the kernel's slew limit stays the last word.
The published state (`mode`, `reference_m`, `tracking_error_m`; NaN outside hold/track) becomes recording
channels of their own (rig/runtime/layout.py).

Requests as text (the control file, the command line, the console): `off`, `hold [POS]`, `track REFERENCE`,
`isolate`, `mode NAME [ARG]`, `setpoint POS` (hold there). `parse_request` turns them into a ModeRequest.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numba
import numpy as np

from controllers.isolation import IsolationController, isolation_step, isolation_suspend, params_from_config
from controllers.reference import Reference, parse_reference
from controllers.tracking import _E as _T_ERR
from controllers.tracking import _R as _T_REF
from controllers.tracking import TrackingPID, track_step, tracking_from_config
from controllers.timebase import same_period
from rig.config import layout_mounts
from rig.errors import RigError
from sim_backend.linear import ActuatorParams

KIND = 4                      # rig/runtime/kernel.py dispatches on it
MODES = ("off", "hold", "track", "isolate")
OFF, HOLD, TRACK, ISOLATE = range(len(MODES))

SCALAR_STATES = ("mode", "reference_m", "tracking_error_m")
_MODE, _REF, _ERR = range(3)
COEFFICIENTS = ("n_track_coef", "n_track_state", "n_iso_coef", "n_iso_state", "warm_isolation")
_H = len(COEFFICIENTS)
_S = len(SCALAR_STATES)
# (channel name, unit, description, state index) published as recording channels (rig/runtime/layout.py)
PUBLISHED = (("mode", "", "operating mode: 0 off, 1 hold, 2 track, 3 isolate", _MODE),
             ("reference_m", "m", "position reference the loop closes on (NaN outside hold/track)", _REF),
             ("tracking_error_m", "m", "reference minus transducer position (NaN outside hold/track)", _ERR))


@dataclass(frozen=True)
class ModeRequest:
    mode: str
    reference: Reference | None = None

    def __str__(self) -> str:
        return self.mode + (f" {self.reference}" if self.reference is not None else "")


def parse_request(text: str, dt: float, *, max_profile_s: float = math.inf,
                  where: str = "mode request") -> ModeRequest:
    """`off` | `hold [POS]` | `track REFERENCE` | `isolate` | `setpoint POS` | `mode NAME [ARG]` -> ModeRequest
    (RigError naming what is wrong)."""
    words = text.strip().split(None, 1)
    if not words:
        raise RigError(f"{where}: empty")
    head, arg = words[0].lower(), (words[1].strip() if len(words) > 1 else "")
    if head == "mode":
        return parse_request(arg, dt, max_profile_s=max_profile_s, where=where)
    if head == "setpoint":
        head, arg = "hold", arg
    if head not in MODES:
        raise RigError(f"{where}: {text.strip()!r}: expected off, hold [POS], track REFERENCE, isolate or "
                       f"setpoint POS")
    if head in ("off", "isolate"):
        if arg:
            raise RigError(f"{where}: {text.strip()!r}: {head} takes no argument")
        return ModeRequest(head)
    if head == "hold":
        ref = parse_reference(f"hold:{arg}" if arg and ":" not in arg else (arg or "hold"), dt,
                              max_s=max_profile_s, where=where)
        if ref.kind not in ("hold", "setpoint"):
            raise RigError(f"{where}: {text.strip()!r}: hold takes a position (track follows {ref.kind})")
        return ModeRequest("hold", replace(ref, text=arg) if arg else None)
    if not arg:
        raise RigError(f"{where}: {text.strip()!r}: track needs a reference, e.g. track sine:amp=10um,freq=5")
    return ModeRequest("track", parse_reference(arg, dt, max_s=max_profile_s, where=where))


class OperatingModes:
    """One mount's modes: a tracking controller (hold, track) and an isolation controller (isolate), built for
    the same period. `current` is the last accepted request: it is applied again at each activation (the
    valve was at null before), so a reference given before the start begins when the valve goes live."""

    kind = KIND
    published = PUBLISHED

    def __init__(self, track: TrackingPID, isolate: IsolationController, start: ModeRequest | None = None,
                 name: str = "", warm_isolation: bool = True) -> None:
        if not same_period(isolate.dt, track.dt):
            raise ValueError(f"modes: tracking built for dt={track.dt}, isolation for dt={isolate.dt}")
        self.track, self.iso, self.name = track, isolate, name
        self.dt = track.dt
        self.warm = bool(warm_isolation)
        self._tc, self._ic = track.coefficients(), isolate.coefficients()
        self._nts, self._nis = len(track.state_names), len(isolate.initial_state())
        self.state_names = (SCALAR_STATES + tuple(f"track.{s}" for s in track.state_names)
                            + tuple(f"isolate.{s}" for s in isolate.state_names))
        self._t0 = _S                                  # tracking state, then isolation state
        self._i0 = _S + self._nts
        self.current = start or ModeRequest("hold")
        self.check(self.current)

    def coefficients(self) -> np.ndarray:
        """The head, the isolation controller's coefficients, then the tracking controller's, whose profile
        table comes last: what every period reads stays together, ahead of the table."""
        head = (len(self._tc), self._nts, len(self._ic), self._nis, 1.0 if self.warm else 0.0)
        return np.concatenate([np.array(head, dtype=np.float64), self._ic, self._tc])

    def track_coefficients(self, coef):
        """The tracking controller's part of this controller's coefficients (a view: its profile table)."""
        return coef[_H + len(self._ic):_H + len(self._ic) + len(self._tc)]

    def initial_state(self) -> list[float]:
        st = [0.0] * _S + self.track.initial_state() + self.iso.set_enabled(self.iso.initial_state(), False)
        st[_MODE] = float(MODES.index(self.current.mode))
        st[_REF] = st[_ERR] = math.nan
        return st

    def set_enabled(self, state, on: bool):
        """Isolation on/off is a mode here (`isolate`): nothing to switch."""
        return state

    def suspended(self, state) -> bool:
        return int(state[_MODE]) == ISOLATE and self.iso.suspended(list(state[self._i0:]))

    def mode(self, state) -> str:
        return MODES[int(state[_MODE])]

    # ---- requests (between periods) -------------------------------------------------------------------
    def check(self, req: ModeRequest, state=None) -> None:
        """RigError (one line) for a request the mount cannot follow (TrackingPID.check)."""
        if req.mode not in MODES:
            raise RigError(f"mode {req.mode!r}: expected one of {', '.join(MODES)}")
        if req.reference is not None:
            ts = None if state is None else list(state[self._t0:self._i0])
            self.track.check(req.reference, ts)

    def switch(self, state, req: ModeRequest | None, u_V: float, x_m: float, coef=None) -> list:
        """The state after a request (None: the current one again, as at activation), taking the valve from the
        command u_V last written with the piston at x_m; coef: the kernel's view of coefficients()."""
        st = list(state)
        again = req is None
        req = self.current if again else req
        old, new = int(st[_MODE]), MODES.index(req.mode)
        ts, is_ = st[self._t0:self._i0], st[self._i0:]
        if new in (HOLD, TRACK):
            if again or old not in (HOLD, TRACK):
                ts = self.track.take_over(ts, u_V, x_m)
            tcoef = self.track_coefficients(coef) if coef is not None else None
            ts = self.track.apply(ts, req.reference, tcoef)
        elif new == ISOLATE and (again or old != ISOLATE):
            is_ = self.iso.take_over(is_, u_V)
        st[_MODE] = float(new)
        self.current = req
        return st[:self._t0] + list(ts) + list(is_)

    # ---- design tools and tests -----------------------------------------------------------------------
    def step(self, state, meas, dt: float):
        """One period through the compiled law; meas = (accel_mps2, position_m)."""
        st = np.asarray(state, dtype=np.float64)
        u = modes_step(st, self._coef(), float(meas[0]), float(meas[1]))
        state[:] = st.tolist()
        return u, state

    def _coef(self):
        if not hasattr(self, "_cf"):
            self._cf = self.coefficients()
        return self._cf


@numba.njit(cache=True)
def modes_suspend(st, cf):
    """Conversions were lost: the isolation part suspended (controllers/isolation.py isolation_suspend)."""
    nts, nic, nis = int(cf[1]), int(cf[2]), int(cf[3])
    isolation_suspend(st[_S + nts:_S + nts + nis], cf[_H:_H + nic])


@numba.njit(cache=True)
def modes_step(st, cf, a, x):
    """One period of the active mode: acceleration a [m/s^2], position x [m] -> valve command [V]."""
    ntc = int(cf[0])
    nts = int(cf[1])
    nic = int(cf[2])
    nis = int(cf[3])
    ic = cf[_H:_H + nic]
    tc = cf[_H + nic:_H + nic + ntc]
    ts = st[_S:_S + nts]
    iso = st[_S + nts:_S + nts + nis]
    mode = int(st[_MODE])
    if mode == ISOLATE:
        u = isolation_step(iso, ic, a, x)
        st[_REF] = np.nan
        st[_ERR] = np.nan
        return u
    if cf[4] > 0.5:
        isolation_step(iso, ic, a, x)                 # warm: the estimate follows the sensors
    if mode == OFF:
        st[_REF] = np.nan
        st[_ERR] = np.nan
        return 0.0
    u = track_step(ts, tc, x)
    st[_REF] = ts[_T_REF]
    st[_ERR] = ts[_T_ERR]
    return u


def make_operating_controllers(cfg, dt: float, start: ModeRequest | None = None) -> list[OperatingModes]:
    """One OperatingModes per mount of the layout, from the config: the tracking controller of [controller]
    track_* (the actuator with [layout] load_kg on its piston) and the isolation controller of [controller]
    (tuned for the stand in drivers/devicemaps/prototype.toml). start: the mode at activation (default hold)."""
    act = ActuatorParams.from_config(cfg, loaded_mass_kg=cfg.actuator.M + cfg.layout.load_kg)
    return [OperatingModes(tracking_from_config(cfg, dt, m, act), IsolationController(params_from_config(cfg, i), dt,
                                                                                      name=m), start, m)
            for i, m in enumerate(layout_mounts(cfg))]
