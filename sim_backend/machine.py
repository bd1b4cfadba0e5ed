"""The flexible machine on the four mounts: modal model (Eq. 15) and its receptances.

A modal model is a list of modes, each with a natural frequency, a damping ratio and mass-normalised shape
values at the four mounts (Y) and at the table and tool point (X, Y, Z). The free rigid-body heave, pitch and
roll (0 Hz) are built from the machine's mass, inertia and point positions; on the actuators' stiffness they
become the ~250-320 Hz modes that limit the isolation loop (PHYSICS_NOTES, "What limits the loop").
File format: docs/MODEL.md; the embedded default is sim_backend/data/machine_table2.toml (Table 2).
"""
from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rig.config import MOUNTS, Config, modal_model_path
from rig.errors import ConfigError
from rig.textfile import read_text

DEFAULT_MODEL = Path(__file__).parent / "data" / "machine_table2.toml"
POINTS = ("table", "tool")
AXES = ("x", "y", "z")
_UNIT_SCALE = {"1/sqrt(kg)": 1.0, "1/sqrt(t)": 1.0 / math.sqrt(1000.0)}   # -> SI, 1/sqrt(kg)


@dataclass(frozen=True)
class ModalModel:
    """All shapes in SI (1/sqrt(kg)); rows = modes (rigid-body first), so H = Phi_i diag(1/(..)) Phi_j^T."""
    names: tuple[str, ...]
    w_n: np.ndarray            # rad/s, 0 for rigid-body modes
    zeta: np.ndarray           # modal damping ratios
    phi_mounts: np.ndarray     # (n_modes, 4)   Y at the mounts
    phi_table: np.ndarray      # (n_modes, 3)   X, Y, Z at the table
    phi_tool: np.ndarray       # (n_modes, 3)   X, Y, Z at the tool point
    mass_kg: float
    source: str
    shape_unit_scale: float = 1.0   # the file's shape unit in SI (1/sqrt(t): 1/sqrt(1000)), for shapes given like it

    @property
    def n_rigid(self) -> int:
        return int(np.sum(self.w_n == 0))

    def receptance(self, resp: np.ndarray, exc: np.ndarray, w: np.ndarray) -> np.ndarray:
        """Eq. 15: H_ij(w) = sum_r phi_ir phi_jr / (-w^2 + 2 j zeta_r w w_r + w_r^2), m/N.

        resp, exc: shape vectors (n_modes,) for the response and excitation points/directions."""
        w = np.asarray(w, dtype=float)[:, None]
        den = -w ** 2 + 2j * self.zeta * w * self.w_n + self.w_n ** 2
        return np.sum(resp * exc / den, axis=1)

    @property
    def flexible_names(self) -> tuple[str, ...]:
        return tuple(n for n, w in zip(self.names, self.w_n) if w > 0)

    def altered(self, frequency_factor=(), damping_factor=(), extra_mode=None) -> "ModalModel":
        """The machine as it really is, off its model: each flexible mode's frequency and damping ratio times
        a factor (flexible modes in order; empty: unchanged), and optionally a mode the model lacks,
        extra_mode = (frequency_hz, damping_ratio, shape at the four mounts in SI), seen at the mounts only
        (its table and tool values are not known: zero). Rigid-body modes are left alone."""
        flex = np.flatnonzero(self.w_n > 0)
        w, z = self.w_n.copy(), self.zeta.copy()
        for key, f, arr in (("frequency", frequency_factor, w), ("damping", damping_factor, z)):
            f = np.asarray(f, dtype=float)
            if f.size and f.size != flex.size:
                raise ValueError(f"{f.size} {key} factors for {flex.size} flexible modes ({', '.join(self.flexible_names)})")
            if f.size:
                arr[flex] *= f
        names, pm, pt, pq = self.names, self.phi_mounts, self.phi_table, self.phi_tool
        if extra_mode is not None:
            hz, zeta, shape = extra_mode
            names = names + (f"extra mode at {hz:.4g} Hz",)
            w = np.append(w, 2 * math.pi * hz)
            z = np.append(z, zeta)
            pm = np.vstack([pm, np.asarray(shape, dtype=float)[None, :]])
            pt = np.vstack([pt, np.zeros((1, 3))])
            pq = np.vstack([pq, np.zeros((1, 3))])
        return ModalModel(tuple(names), w, z, pm, pt, pq, self.mass_kg, self.source, self.shape_unit_scale)

    def flexible_only(self) -> "ModalModel":
        keep = self.w_n > 0
        return ModalModel(tuple(n for n, k in zip(self.names, keep) if k), self.w_n[keep], self.zeta[keep],
                          self.phi_mounts[keep], self.phi_table[keep], self.phi_tool[keep], self.mass_kg,
                          self.source, self.shape_unit_scale)


def _vec(data, key, n, where):
    v = data.get(key)
    if not isinstance(v, list) or len(v) != n or not all(isinstance(x, (int, float)) and not isinstance(x, bool)
                                                          for x in v):
        raise ConfigError(f"{where}: '{key}': expected a list of {n} numbers, got {v!r}")
    return np.array(v, dtype=float)


def _num(data, key, where, default=None, positive=True):
    v = data.get(key, default)
    if v is None or isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise ConfigError(f"{where}: '{key}': expected a number, got {v!r}")
    if positive and v <= 0:
        raise ConfigError(f"{where}: '{key}': expected > 0, got {v!r}")
    return float(v)


def load_modal_model(path: str | Path | None = None, *, mass_kg: float | None = None,
                     damping_ratio: float | None = None) -> ModalModel:
    """Read a modal-model TOML file (docs/MODEL.md); errors name the file and the key."""
    p = Path(path) if path else DEFAULT_MODEL
    try:
        data = tomllib.loads(read_text(p, "modal model file", ConfigError))
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{p}: invalid modal model TOML: {e}") from None
    where = str(p)
    unit = data.get("mode_shape_unit", "1/sqrt(kg)")
    if unit not in _UNIT_SCALE:
        raise ConfigError(f"{where}: 'mode_shape_unit': expected one of {', '.join(_UNIT_SCALE)}, got {unit!r}")
    scale = _UNIT_SCALE[unit]
    m = mass_kg if mass_kg is not None else _num(data, "mass_kg", where)
    zeta_default = damping_ratio if damping_ratio is not None else _num(data, "damping_ratio", where, 0.03)
    pts = data.get("points")
    if not isinstance(pts, dict):
        raise ConfigError(f"{where}: [points]: expected a table with {', '.join(MOUNTS + POINTS)}")
    pos = {k: _vec(pts, k, 3, f"{where}: points") for k in MOUNTS + POINTS}
    rb = data.get("rigid_body")
    if not isinstance(rb, dict):
        raise ConfigError(f"{where}: [rigid_body]: expected a table with centre_of_gravity_m, inertia_*_kgm2")
    cg = _vec(rb, "centre_of_gravity_m", 3, f"{where}: rigid_body")
    J_pitch = _num(rb, "inertia_pitch_kgm2", f"{where}: rigid_body")
    J_roll = _num(rb, "inertia_roll_kgm2", f"{where}: rigid_body")

    # Rigid-body heave h, pitch theta_x, roll theta_z about the CoG: d = (-th_z*ry, h + th_z*rx - th_x*rz, th_x*ry)
    def rigid(r):
        rx, ry, rz = r - cg
        heave = np.array([0.0, 1.0, 0.0]) / math.sqrt(m)
        pitch = np.array([0.0, -rz, ry]) / math.sqrt(J_pitch)
        roll = np.array([-ry, rx, 0.0]) / math.sqrt(J_roll)
        return np.vstack([heave, pitch, roll])          # (3 modes, XYZ)

    names = ["rigid heave", "rigid pitch", "rigid roll"]
    w_n = [0.0, 0.0, 0.0]
    zeta = [0.0, 0.0, 0.0]
    phi_m = [[rigid(pos[k])[r, 1] for k in MOUNTS] for r in range(3)]
    phi_t = [rigid(pos["table"])[r] for r in range(3)]
    phi_q = [rigid(pos["tool"])[r] for r in range(3)]
    modes = data.get("mode", [])
    if not isinstance(modes, list) or not modes:
        raise ConfigError(f"{where}: [[mode]]: expected at least one flexible mode")
    for i, md in enumerate(modes):
        w = f"{where}: mode {i + 1}"
        if not isinstance(md, dict):
            raise ConfigError(f"{w}: expected a table")
        names.append(str(md.get("name", f"mode {i + 1}")))
        w_n.append(2 * math.pi * _num(md, "frequency_hz", w))
        z = _num(md, "damping_ratio", w, zeta_default)
        if z >= 1:
            raise ConfigError(f"{w}: 'damping_ratio': expected < 1, got {z}")
        zeta.append(z)
        phi_m.append(list(_vec(md, "mounts", 4, w) * scale))
        phi_t.append(_vec(md, "table", 3, w) * scale)
        phi_q.append(_vec(md, "tool", 3, w) * scale)
    return ModalModel(tuple(names), np.array(w_n), np.array(zeta), np.array(phi_m), np.array(phi_t),
                      np.array(phi_q), m, where, scale)


def modal_model_from_config(cfg: Config) -> ModalModel:
    return load_modal_model(modal_model_path(cfg), mass_kg=cfg.machine.mass_kg,
                            damping_ratio=cfg.machine.modal_damping)
