"""The rig model the diagnosis fits: the configured four-mount rig (sim_backend/rig_plant.py rig_state_space, Eqs.
1-15) at a point of its parameters, and its frequency responses at the recording's frequencies.

Parameters (`Theta`, named arrays; 1 / 0 = as configured):
  act        common factors on the four actuators' K_L, K_Q, K_C, w_nv, zeta (Eq. 11's x_d, refit like an
             identification; C is not seen through a 16 t machine)
  modal_zeta common factor on every flexible mode's damping (Table 2 gives none; the model assumes 0.03)
  latency_s  delay from writing a command to the valve's zero-order hold starting it (this rig: one period)
  the deviations (sim_backend/rig_error.py, the simulator's own terms): mode_f, mode_z (per flexible mode),
  extra (a mode the model lacks: Hz, damping, shape at the four mounts in the modal model's unit),
  mount_K, mount_C (per mount), gain_a, gain_s, gain_g (the sensors), delay_s (per valve), deadband_ma, null_V

Responses (`Responses`), from the modal decomposition of the continuous state space:
  valve commands   exact for a zero-order hold of each command delayed by latency_s + delay_s[i] (fractions of
                   a period included: the hold's two parts, Eq. 1 onwards), z = exp(j w T); in the replay's
                   prediction (predict) a deadband valve's chamber is fed from its spool's samples interpolated
                   linearly (Eq. 3's K_Q x_v past the overlap, spool.py), as the simulated rig steps it
  floor motion     continuous (x_g and v_g = j w x_g: the floor moves smoothly), per metre at each mount
  transient        one column per mode: what the states at the record's two ends add to its DFT
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from controllers.analysis import with_actuator
from controllers.feedforward import FeedforwardFilter, make_feedforward_filters
from controllers.isolation import IsolationController, make_isolation_controllers
from rig.config import Config
from sim_backend.machine import ModalModel, modal_model_from_config
from sim_backend.rig_error import RigDeviation
from sim_backend.rig_plant import I_ACCEL, rig_state_space, state_index

ACT_KEYS = ("K_L", "K_Q", "K_C", "w_nv", "zeta")
N_OUT = 8                        # accelerometers (4), stroke transducers (4)


def neutral(n_flex: int) -> dict[str, np.ndarray]:
    """The configured model: every factor 1, every offset 0; latency one period is set by the caller."""
    return {"act": np.ones(len(ACT_KEYS)), "modal_zeta": np.ones(1), "latency_s": np.zeros(1),
            "mode_f": np.ones(n_flex), "mode_z": np.ones(n_flex), "extra": np.zeros(6),
            "mount_K": np.ones(4), "mount_C": np.ones(4), "gain_a": np.ones(4), "gain_s": np.ones(4),
            "gain_g": np.ones(4), "delay_s": np.zeros(4), "deadband_ma": np.zeros(4), "null_V": np.zeros(4)}


def copy_theta(th: dict) -> dict:
    return {k: np.array(v, dtype=float) for k, v in th.items()}


@dataclass
class Base:
    """The configured rig: its config, its modal model, the loop period of the recording and its controllers
    at that period (built once, when first asked for: the transmissibility and the margins close their loops
    with the same objects)."""
    cfg: Config
    modal: ModalModel
    dt: float

    @classmethod
    def of(cls, cfg: Config, dt: float) -> "Base":
        return cls(cfg, modal_model_from_config(cfg), dt)

    @cached_property
    def controllers(self) -> list[IsolationController]:
        """The configured isolation controllers, one per mount (controllers/isolation.py)."""
        return make_isolation_controllers(self.cfg, self.dt)

    @cached_property
    def feedforward(self) -> list[FeedforwardFilter]:
        """The configured floor feedforward filters, one per mount (controllers/feedforward.py)."""
        return make_feedforward_filters(self.cfg, self.dt)

    @property
    def n_flex(self) -> int:
        return int(np.sum(self.modal.w_n > 0))

    def deviation(self, th: dict) -> RigDeviation:
        """theta's machine, mount, sensor and valve terms as the simulator's RigDeviation."""
        ex = th["extra"]
        extra = None
        if ex[0] > 0:
            extra = (float(ex[0]), float(ex[1]), tuple(float(x) * self.modal.shape_unit_scale for x in ex[2:6]))
        return RigDeviation(tuple(th["mode_f"]), tuple(th["mode_z"] * th["modal_zeta"][0]), extra,
                            {"K_L": th["mount_K"], "C": th["mount_C"]}, th["gain_a"], th["gain_s"], th["gain_g"],
                            th["delay_s"], th["deadband_ma"], th["null_V"])

    def config(self, th: dict) -> Config:
        """The config whose actuators carry theta's common factors."""
        a, v = self.cfg.actuator, self.cfg.valve
        f = dict(zip(ACT_KEYS, th["act"]))
        vals = {"K_L": a.K_L * f["K_L"], "K_Q": v.K_Q * f["K_Q"], "K_C": v.K_C * f["K_C"],
                "w_nv": v.w_nv * f["w_nv"], "zeta": v.zeta * f["zeta"]}
        return with_actuator(self.cfg, **vals) if np.any(th["act"] != 1.0) else self.cfg

    def state_space(self, th: dict):
        dev = self.deviation(th)
        return rig_state_space(self.config(th), dev.modal(self.modal), dev.mount_factors()), dev


@dataclass
class Modal:
    """The model at theta in modal coordinates: what every response at any bin is built from."""
    lam: np.ndarray             # continuous eigenvalues (1/s)
    mu: np.ndarray              # exp(lam T)
    CV: np.ndarray              # (8, n) outputs
    VBu: np.ndarray             # (n, 4) valve commands
    VBx: np.ndarray             # (n, 4) floor position
    VBv: np.ndarray             # (n, 4) floor velocity
    E: np.ndarray               # (4, n) the hold's early part per valve (fractional delay)
    F: np.ndarray               # (4, n) its late part
    d: np.ndarray               # (4,) whole periods of delay per valve
    Dx: np.ndarray              # (8, 4) floor position feedthrough
    Dv: np.ndarray              # (8, 4) floor velocity feedthrough
    T: float
    gain_out: np.ndarray        # (8,) accelerometers then strokes
    gain_floor: np.ndarray      # (4,)
    VBs: np.ndarray             # (n, 4) each chamber's flow per mA of its spool (Eq. 3's K_Q x_v as an input: nothing
                                # drives a valve back, so it excites the chamber's and machine's modes only)
    CVs: np.ndarray             # (4, n) the spools (x_v, mA)
    overlap: np.ndarray         # (4,) bool: the valves with a deadband (their chambers fed from the spool's samples)


def modal(base: Base, th: dict) -> Modal:
    """theta's state space diagonalised (valve commands held over the period, delayed by latency_s plus
    the valve's own delay: the hold's two parts, early u[k-d-1] over phi T and late u[k-d] over (1-phi) T)."""
    ss, dev = base.state_space(th)
    A, B = ss.A, ss.B
    at = state_index(len(ss.modal.w_n))
    ixv, ipl = at["x_v"], at["P_L"]
    Bs = np.zeros((A.shape[0], 4))
    Bs[ipl:ipl + 4] = np.diag(np.diag(A[ipl:ipl + 4, ixv:ixv + 4]))
    C = ss.C[I_ACCEL:I_ACCEL + N_OUT]
    D = ss.D[I_ACCEL:I_ACCEL + N_OUT]
    lam, V = np.linalg.eig(A)
    Vi = np.linalg.inv(V)
    T = base.dt
    mu = np.exp(lam * T)
    tau = th["latency_s"][0] + dev.valve_delay_s
    d = np.floor(tau / T + 1e-9)
    phi = tau / T - d
    F = (np.exp(np.outer(1.0 - phi, lam) * T) - 1.0) / lam[None, :]
    E = (mu - 1.0)[None, :] / lam[None, :] - F
    c = np.ascontiguousarray
    return Modal(lam.astype(complex), mu.astype(complex), c(C @ V, dtype=complex),
                 *(c(Vi @ B[:, a:a + 4], dtype=complex) for a in (0, 4, 8)), c(E, dtype=complex),
                 c(F, dtype=complex), d, c(D[:, 4:8]), c(D[:, 8:12]), T,
                 np.concatenate([dev.accel_gain, dev.stroke_gain]), np.asarray(dev.floor_gain, dtype=float),
                 c(Vi @ Bs, dtype=complex), c(V[ixv:ixv + 4], dtype=complex), np.asarray(dev.valve_deadband_ma) > 0)


@dataclass
class Responses:
    """Frequency responses at the bins w (rad/s): Hu (K, 8, 4) per volt of each valve's recorded command, Hg
    (K, 8, 4) per metre of floor motion at each mount, Tb (K, 8, n_states) the end-state columns; gains on
    the outputs (8) and on the floor accelerometers (4) applied by the caller."""
    Hu: np.ndarray
    Hg: np.ndarray
    Tb: np.ndarray
    gain_out: np.ndarray
    gain_floor: np.ndarray
    valve_w_nv: np.ndarray      # rad/s, per mount (for the deadband's spool)
    valve_zeta: np.ndarray
    valve_K_v: float
    lam: np.ndarray             # the continuous eigenvalues (1/s), one per column of Tb


def responses(base: Base, th: dict, w: np.ndarray, *, floor: bool = True, valves: bool = True, ends: bool = True,
              md: Modal | None = None) -> Responses:
    """The model at theta, at the bins w (rad/s); floor=False skips the floor responses, valves=False the
    valves', ends=False the end-state columns (zero)."""
    md = md or modal(base, th)
    w = np.asarray(w, dtype=float)
    K = len(w)
    z = np.exp(1j * w * md.T)
    jw = 1j * w
    Hu = np.zeros((K, N_OUT, 4), dtype=complex)
    Hg = np.zeros((K, N_OUT, 4), dtype=complex)
    CVT = md.CV.T
    if valves:
        P = 1.0 / (z[:, None] - md.mu[None, :])
        for i in range(4):
            coef = P * (md.E[i][None, :] / z[:, None] + md.F[i][None, :]) * (z ** -md.d[i])[:, None]
            Hu[:, :, i] = (coef * md.VBu[:, i][None, :]) @ CVT
    if floor:
        Pc = 1.0 / (jw[:, None] - md.lam[None, :])
        for i in range(4):
            Hg[:, :, i] = (Pc * (md.VBx[:, i][None, :] + jw[:, None] * md.VBv[:, i][None, :])) @ CVT \
                + md.Dx[None, :, i] + jw[:, None] * md.Dv[None, :, i]
    Tb = md.CV[None, :, :] * (1.0 / (1.0 - md.mu[None, :] / z[:, None]))[:, None, :] if ends else None
    a = base.config(th)
    return Responses(Hu, Hg, Tb, md.gain_out, md.gain_floor, a.valve.w_nv * np.ones(4), a.valve.zeta * np.ones(4),
                     a.valve.K_v, md.lam)


def linear_hold(md: Modal, z: np.ndarray) -> np.ndarray:
    """(K, n) per mode: the state's response to an input known at its samples and interpolated linearly between
    them (a first-order hold: x[k+1] = mu x[k] + g0 s[k] + g1 s[k+1]), as the simulated rig steps its floor and a
    deadband valve's flow."""
    T, lam = md.T, md.lam
    lt = lam * T
    small = np.abs(lt) < 1e-6
    lts = np.where(small, 1.0, lt)
    g1 = np.where(small, T * (0.5 + lt / 6), (md.mu - 1.0 - lt) / (lts * lts / T))     # late part (x s[k+1])
    g0 = np.where(small, T * (1.0 + lt / 2), (md.mu - 1.0) * T / lts) - g1             # early part (x s[k])
    return (g0[None, :] + g1[None, :] * z[:, None]) / (z[:, None] - md.mu[None, :])


def predict(md: Modal, w: np.ndarray, U: np.ndarray, X: np.ndarray | None) -> np.ndarray:
    """The physics' prediction (K, 8) before the sensors' gains: sum_i Hu U_i (+ sum_j Hg X_j), mode by mode
    (K x modes) without forming Hu and Hg; a deadband valve's U_i (its effective command) through its spool's
    samples, held linearly into its chamber (Hu holds the valve's response to the command between samples)."""
    w = np.asarray(w, dtype=float)
    z = np.exp(1j * w * md.T)
    zU = U * np.exp(-1j * np.outer(w * md.T, md.d))               # each valve's whole periods of delay
    P = 1.0 / (z[:, None] - md.mu[None, :])
    q = ((zU @ (md.E * md.VBu.T)) / z[:, None] + zU @ (md.F * md.VBu.T)) * P
    lin = linear_hold(md, z) if np.any(md.overlap) else None
    for i in np.flatnonzero(md.overlap):   # a deadband valve's chamber fed from its spool's samples, held linearly
        held = (zU[:, i:i + 1] * (md.E[i][None, :] / z[:, None] + md.F[i][None, :])) * P * md.VBu[:, i][None, :]
        spool = held @ md.CVs[i]                                    # its spool at the samples (mA)
        q += lin * (spool[:, None] * md.VBs[:, i][None, :]) - held
    out = q @ md.CV.T
    if X is not None:
        jw = 1j * w
        qg = (X @ md.VBx.T + jw[:, None] * (X @ md.VBv.T)) / (jw[:, None] - md.lam[None, :])
        out = out + qg @ md.CV.T + X @ md.Dx.T + jw[:, None] * (X @ md.Dv.T)
    return out
