"""References for the tracking controller: what an operator asks the piston to do, as text and as data.

  hold[:x=POS]                       hold at POS (default: where the piston is)
  setpoint:x=POS                     move to POS (ramped at the rate limit) and hold
  step:amp=DX                        move the hold position by DX (ramped) and hold
  sine:amp=A,freq=F[,offset=POS][,seconds=S]           around POS (default: the hold position), whole cycles
  chirp:amp=A,f0=F0,f1=F1,duration=T[,offset=POS]      linear sweep F0 -> F1 over T seconds
  csv:FILE                           a profile `time_s, position_m` (absolute positions), resampled to the loop

Lengths need a unit suffix (m, mm, um or µm, nm; a bare number is refused unless it is 0: `hold 5` read as
5 m was a trap), times take s or ms (bare: s), frequencies Hz (bare: Hz). A
waveform starts once the hold position has reached its offset (the ramp comes first), and when it ends the
piston holds where it ended. Whether the actuator can follow a reference is the tracking controller's check
(controllers/tracking.py TrackingPID.check); this module only reads and writes the request.
"""
from __future__ import annotations

import io
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from rig.errors import RigError
from rig.textfile import read_text

KINDS = ("hold", "setpoint", "step", "sine", "chirp", "csv")
_LENGTH = {"m": 1.0, "mm": 1e-3, "um": 1e-6, "µm": 1e-6, "μm": 1e-6, "nm": 1e-9}
_TIME = {"s": 1.0, "ms": 1e-3}
_KEYS = {"hold": {"x": "length"}, "setpoint": {"x": "length"}, "step": {"amp": "length"},
         "sine": {"amp": "length", "freq": "hz", "offset": "length", "seconds": "time"},
         "chirp": {"amp": "length", "f0": "hz", "f1": "hz", "duration": "time", "offset": "length"}}
_REQUIRED = {"setpoint": ("x",), "step": ("amp",), "sine": ("amp", "freq"), "chirp": ("amp", "f0", "f1", "duration")}


@dataclass(frozen=True)
class Reference:
    """One reference request. target_m: the hold position asked for (None: keep the current one; for `step`
    it is the change). profile_m: a csv profile resampled at dt (absolute positions)."""
    kind: str
    target_m: float | None = None
    amp_m: float = 0.0
    f0_hz: float = 0.0
    f1_hz: float = 0.0
    span_s: float = 0.0
    profile_m: np.ndarray | None = field(default=None, compare=False, repr=False)
    text: str = ""

    def __str__(self) -> str:
        return self.text or self.kind


def _number(text: str, what: str, units: dict[str, float], where: str, unit_required: bool = False) -> float:
    t = text.strip().lower().replace(" ", "")
    scale = None
    for suffix in sorted(units, key=len, reverse=True):
        if t.endswith(suffix) and t[:-len(suffix)] and (t[-len(suffix) - 1].isdigit() or t[-len(suffix) - 1] == "."):
            t, scale = t[:-len(suffix)], units[suffix]
            break
    try:
        v = float(t) * (scale or 1.0)
    except ValueError:
        raise RigError(f"{where}: {what} {text!r} is not a number") from None
    if not math.isfinite(v):
        raise RigError(f"{where}: {what} {text!r} is not a finite number")
    if unit_required and scale is None and v != 0:
        raise RigError(f"{where}: {what} {text.strip()!r} has no unit: give one, e.g. {t}um or {t}mm (a bare "
                       f"number would be metres)")
    return v


def parse_length(text: str, what: str = "length", where: str = "reference") -> float:
    """A length with its unit (m, mm, um, µm, nm) in metres; a bare number only when it is 0 (RigError)."""
    return _number(text, what, _LENGTH, where, unit_required=True)


def _value(key: str, text: str, kind: str, where: str) -> float:
    how = _KEYS[kind][key]
    if how == "length":
        return parse_length(text, key, where)
    if how == "time":
        v = _number(text, key, _TIME, where)
    else:
        v = _number(text.lower().removesuffix("hz"), key, {}, where)
    if v <= 0:
        raise RigError(f"{where}: {key} must be > 0, got {text!r}")
    return v


def parse_reference(text: str, dt: float, *, max_s: float = math.inf, where: str = "reference") -> Reference:
    """A Reference from its text (module docstring); RigError with one line naming what is wrong."""
    text = text.strip()
    kind, _, rest = text.partition(":")
    kind = kind.strip().lower()
    if kind not in KINDS:
        raise RigError(f"{where}: {text!r}: unknown kind {kind!r} (expected one of {', '.join(KINDS)})")
    if kind == "csv":
        if not rest.strip():
            raise RigError(f"{where}: {text!r}: expected csv:FILE")
        prof = load_profile(rest.strip(), dt, max_s=max_s)
        return Reference("csv", target_m=float(prof[0]), span_s=(len(prof) - 1) * dt, profile_m=prof, text=text)
    vals: dict[str, float] = {}
    for item in filter(None, (p.strip() for p in rest.split(","))):
        key, eq, val = item.partition("=")
        key = key.strip().lower()
        if not eq and kind in ("hold", "setpoint") and not vals:
            key, val = "x", item                       # hold:5um, setpoint:5um
        if key not in _KEYS[kind]:
            raise RigError(f"{where}: {text!r}: unknown key {key!r} for {kind} (expected "
                           f"{', '.join(_KEYS[kind])})")
        if key in vals:
            raise RigError(f"{where}: {text!r}: {key} given twice (expected each key once)")
        vals[key] = _value(key, val, kind, where)
    missing = [k for k in _REQUIRED.get(kind, ()) if k not in vals]
    if missing:
        raise RigError(f"{where}: {text!r}: missing {', '.join(missing)} (e.g. {_example(kind)})")
    if kind in ("hold", "setpoint"):
        return Reference("setpoint" if "x" in vals else "hold", target_m=vals.get("x"), text=text)
    if kind == "step":
        return Reference("step", target_m=vals["amp"], text=text)
    if kind == "sine":
        f = vals["freq"]
        span = math.ceil(vals["seconds"] * f - 1e-9) / f if "seconds" in vals else 0.0    # whole cycles
        return Reference("sine", target_m=vals.get("offset"), amp_m=vals["amp"], f0_hz=f, f1_hz=f, span_s=span,
                         text=text)
    if vals["f1"] <= vals["f0"] or vals["f1"] >= 0.5 / dt:
        raise RigError(f"{where}: {text!r}: expected f0 < f1 < half the loop rate ({0.5 / dt:g} Hz)")
    return Reference("chirp", target_m=vals.get("offset"), amp_m=vals["amp"], f0_hz=vals["f0"], f1_hz=vals["f1"],
                     span_s=vals["duration"], text=text)


def positions_m(ref: Reference, now_m: float = 0.0) -> tuple[float, float, float]:
    """(the hold position it moves to or around, the lowest and the highest position) that `ref` asks for, from a
    piston held at now_m."""
    target = {"hold": None, "step": now_m + (ref.target_m or 0.0)}.get(ref.kind, ref.target_m)
    base = now_m if target is None else target
    if ref.kind == "csv":
        prof = np.asarray(ref.profile_m, dtype=float)
        return base, float(prof.min()), float(prof.max())
    return base, base - ref.amp_m, base + ref.amp_m


def check_stroke(ref: Reference, stroke_limit_m: float, now_m: float = 0.0, name: str | None = None) -> None:
    """RigError (one line) when `ref` asks for a position beyond the stroke limit (safety.stroke_limit_m). The
    one stroke rule: the tracking controller's check and `rig run`'s start options, before anything is built."""
    _, lo, hi = positions_m(ref, now_m)
    for x in (lo, hi):
        if abs(x) > stroke_limit_m:
            raise RigError(f"{name or f'reference {ref}'}: position {x * 1e6:.1f} um is outside the stroke limit "
                           f"(+-{stroke_limit_m * 1e6:.0f} um, safety.stroke_limit_m)")


def _example(kind: str) -> str:
    return {"setpoint": "setpoint:x=5um", "step": "step:amp=2um", "sine": "sine:amp=10um,freq=5",
            "chirp": "chirp:amp=1um,f0=1,f1=100,duration=20"}[kind]


def load_profile(path, dt: float, *, max_s: float = math.inf) -> np.ndarray:
    """A position profile from a CSV file with columns time_s, position_m (header required, order free),
    resampled at dt by linear interpolation from its first time on. RigError naming the file and line."""
    p = Path(path)
    text = read_text(p, "profile file", encoding="utf-8-sig")
    lines = [ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    if not lines:
        raise RigError(f"{p}: empty profile (expected a header time_s,position_m and rows)")
    head = [h.strip().strip('"') for h in lines[0].split(",")]
    if "time_s" not in head or "position_m" not in head:
        raise RigError(f"{p}: header {lines[0][:80]!r}: expected columns time_s and position_m")
    it, ix = head.index("time_s"), head.index("position_m")
    if len(lines) < 3:                                  # (numpy would only warn about an empty table)
        raise RigError(f"{p}: expected at least 2 rows of {len(head)} numbers, got {len(lines) - 1} rows")
    try:
        data = np.loadtxt(io.StringIO("\n".join(lines[1:])), delimiter=",", ndmin=2, dtype=float)
    except ValueError as e:
        raise RigError(f"{p}: not a numeric table after the header ({str(e).splitlines()[0][:80]})") from None
    if data.shape[0] < 2 or data.shape[1] != len(head):
        raise RigError(f"{p}: expected at least 2 rows of {len(head)} numbers, got {data.shape[0]} rows")
    t, x = data[:, it], data[:, ix]
    bad = ~np.isfinite(t) | ~np.isfinite(x)
    if bad.any():
        raise RigError(f"{p}: row {int(np.argmax(bad)) + 1} is not a finite number")
    if not (np.diff(t) > 0).all():
        k = int(np.argmax(np.diff(t) <= 0)) + 1
        raise RigError(f"{p}: time_s not increasing at row {k + 1} ({t[k - 1]:g} then {t[k]:g})")
    span = t[-1] - t[0]
    if span > max_s:
        raise RigError(f"{p}: the profile lasts {span:g} s, longer than controller.track_profile_s = {max_s:g} s")
    n = int(math.floor(span / dt + 1e-9)) + 1
    return np.interp(t[0] + np.arange(n) * dt, t, x)
