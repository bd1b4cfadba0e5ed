"""What a physical four-mount rig may hide from its model (issue 28): the deviations the simulated rig can carry
([rig_error] of the config) and the diagnosis of a run recording names.

One definition of each term, used by the simulator (sim_backend/rig_plant.py RigPlant) and by the diagnosis's
model of the rig (rig/diagnose/machine/), so the physics the proof hides is the physics the diagnosis fits:

  machine (Eq. 15)   w_r -> f_w,r w_r, zeta_r -> f_z,r zeta_r for each flexible mode; a mode the model lacks
                     (frequency, damping, mass-normalised shape at the four mounts)
  mounts (Eq. 7)     K_L -> f_K,i K_L and C -> f_C,i C at mount i (the membrane spring and its viscous term)
  sensors            reading = gain_i x physical value (accelerometer, stroke transducer, floor accelerometer;
                     a negative gain is a sensor wired with its sign reversed)
  valves (Eq. 1)     u_i(t) -> u_i(t - tau_i) + u0_i at the amplifier; the spool's deadband (overlap): no flow
                     while |x_v| < w_i, flow from |x_v| - w_i
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from rig.config import MOUNTS, Config
from rig.errors import ConfigError
from sim_backend.machine import ModalModel

MOUNT_KEYS = ("K_L", "C", "K_Q", "K_C", "w_nv", "zeta")     # per-mount factors rig_state_space accepts
ROCKING_PATTERNS = {"pitch": (1.0, 1.0, -1.0, -1.0),       # front (-Z) against rear (+Z), MOUNTS order
                    "roll": (1.0, -1.0, 1.0, -1.0)}        # left (-X) against right (+X)


def _ones() -> np.ndarray:
    return np.ones(len(MOUNTS))


def _zeros() -> np.ndarray:
    return np.zeros(len(MOUNTS))


@dataclass(frozen=True)
class RigDeviation:
    """The deviations of one rig (all neutral by default). mode_* factors follow the modal model's flexible
    modes (empty: unchanged); extra_mode = (frequency_hz, damping_ratio, shape at the mounts in SI 1/sqrt(kg))."""
    mode_frequency_factor: tuple[float, ...] = ()
    mode_damping_factor: tuple[float, ...] = ()
    extra_mode: tuple[float, float, tuple[float, ...]] | None = None
    mount: dict = field(default_factory=dict)                # {"K_L": (4,), "C": (4,), ...} factors
    accel_gain: np.ndarray = field(default_factory=_ones)
    stroke_gain: np.ndarray = field(default_factory=_ones)
    floor_gain: np.ndarray = field(default_factory=_ones)
    valve_delay_s: np.ndarray = field(default_factory=_zeros)
    valve_deadband_ma: np.ndarray = field(default_factory=_zeros)
    valve_null_V: np.ndarray = field(default_factory=_zeros)

    @classmethod
    def from_config(cls, cfg: Config, modal: ModalModel) -> "RigDeviation":
        e = cfg.rig_error
        nflex = int(np.sum(modal.w_n > 0))
        for key in ("mode_frequency_factor", "mode_damping_factor"):
            v = getattr(e, key)
            if v and len(v) != nflex:
                raise ConfigError(f"{cfg.source}: rig_error.{key}: expected {nflex} factors (one per flexible mode: "
                                  f"{', '.join(modal.flexible_names)}), got {len(v)}")
        extra = None
        if e.extra_mode_hz > 0:
            extra = (e.extra_mode_hz, e.extra_mode_damping,
                     tuple(float(x) * modal.shape_unit_scale for x in e.extra_mode_shape))
        mount = {"K_L": np.array(e.mount_stiffness_factor), "C": np.array(e.mount_damping_factor)}
        return cls(tuple(e.mode_frequency_factor), tuple(e.mode_damping_factor), extra, mount,
                       np.array(e.accel_gain), np.array(e.stroke_gain), np.array(e.floor_gain),
                       np.array(e.valve_delay_s), np.array(e.valve_deadband_ma), np.array(e.valve_null_V))

    def modal(self, mm: ModalModel) -> ModalModel:
        """The machine as it is (ModalModel.altered); the model itself when nothing is altered."""
        if not self.mode_frequency_factor and not self.mode_damping_factor and self.extra_mode is None:
            return mm
        return mm.altered(self.mode_frequency_factor, self.mode_damping_factor, self.extra_mode)

    def mount_factors(self) -> dict | None:
        """Per-mount factors for rig_state_space (None: every mount as modelled)."""
        out = {k: np.asarray(v, dtype=float) for k, v in self.mount.items() if np.any(np.asarray(v) != 1.0)}
        return out or None

    @property
    def delays(self) -> bool:
        return bool(np.any(self.valve_delay_s > 0))

    @property
    def deadbands(self) -> bool:
        return bool(np.any(self.valve_deadband_ma > 0))

    @property
    def null_offsets(self) -> bool:
        return bool(np.any(self.valve_null_V != 0))

    @property
    def sensor_gains(self) -> bool:
        return bool(np.any(self.accel_gain != 1) or np.any(self.stroke_gain != 1))


def deadband(x: np.ndarray, width: float) -> np.ndarray:
    """The spool's overlap: no flow while |x_v| < width, flow from |x_v| - width (x_v in mA-equivalent)."""
    return np.sign(x) * np.maximum(np.abs(x) - width, 0.0)
