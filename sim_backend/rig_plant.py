"""The four-mount rig: the flexible machine (Eq. 15 modal model) on four valve-controlled actuators.

Each actuator obeys Eqs. 1-7 with the machine as its load; the machine is coupled to all four through the
mount forces, and ground motion enters at each mount through the stroke (Eq. 13: F = K (x_g - x_p) in
the hydraulic and membrane springs):

  valve (Eq. 1)        x_v'' = w_nv^2 (K_v u - x_v) - 2 zeta w_nv x_v'
  chambers (Eqs. 3,6)  V_t/(4 beta) P_L' = K_Q x_v - K_C P_L - A_p (v_p - v_g)
  mount force (Eq. 7)  f = A_p P_L - K_L (x_p - x_g) - C (v_p - v_g)
  machine (Eq. 15)     (I + M Phi Phi^T) q'' + 2 zeta W q' + W^2 q = Phi f,   x_p = Phi^T q

The piston mass M moves with the machine's mount point. The linear system is discretised exactly for a
command and ground motion held over each loop period (ZOH), so one period costs one matrix-vector product.
Inputs: u [V] (4), x_g [m] (4), v_g [m/s] (4). Outputs: see OUTPUTS.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numba
import numpy as np
import scipy.signal

from rig.config import MOUNTS, Config
from sim_backend.linear import ActuatorParams, discretize_zoh, discretize_zoh_foh
from sim_backend.machine import ModalModel, modal_model_from_config
from sim_backend.rig_error import ROCKING_PATTERNS, RigDeviation

OUTPUTS = tuple([f"accel_{m}" for m in MOUNTS] + [f"stroke_{m}" for m in MOUNTS] + [f"x_{m}" for m in MOUNTS]
                + ["table_x", "table_y", "table_z", "tool_x", "tool_y", "tool_z"]
                + [f"spool_{m}" for m in MOUNTS] + [f"P_L_{m}" for m in MOUNTS])
I_ACCEL, I_STROKE, I_X, I_TABLE, I_TOOL, I_SPOOL, I_PL = 0, 4, 8, 12, 15, 18, 22


@dataclass(frozen=True)
class RigStateSpace:
    A: np.ndarray
    B: np.ndarray       # columns: u(4), x_g(4), v_g(4)
    C: np.ndarray
    D: np.ndarray
    modal: ModalModel
    act: ActuatorParams

    def to_control(self):
        import control
        return control.ss(self.A, self.B, self.C, self.D,
                          inputs=[f"u_{m}" for m in MOUNTS] + [f"xg_{m}" for m in MOUNTS]
                          + [f"vg_{m}" for m in MOUNTS], outputs=list(OUTPUTS))

    def frf(self, w: np.ndarray) -> np.ndarray:
        """Frequency response, shape (len(w), n_out, n_in), with ground displacement and velocity inputs."""
        n = self.A.shape[0]
        out = np.empty((len(w), self.C.shape[0], self.B.shape[1]), dtype=complex)
        for k, wk in enumerate(np.asarray(w, dtype=float)):
            out[k] = self.C @ np.linalg.solve(1j * wk * np.eye(n) - self.A, self.B) + self.D
        return out

    def ground_frf(self, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(G_u, G_g): responses to valve voltage (n_out x 4) and to ground displacement x_g (v_g = j w x_g)."""
        H = self.frf(w)
        jw = 1j * np.asarray(w, dtype=float)[:, None, None]
        return H[:, :, 0:4], H[:, :, 4:8] + jw * H[:, :, 8:12]


def state_index(n_modes: int) -> dict[str, int]:
    """First state of each group in rig_state_space: q, q', x_v, x_v', P_L (four each for the valves and
    chambers, mount order)."""
    n = n_modes
    return {"q": 0, "qd": n, "x_v": 2 * n, "v_v": 2 * n + 4, "P_L": 2 * n + 8}


def rig_state_space(cfg: Config, modal: ModalModel | None = None, mounts: dict | None = None) -> RigStateSpace:
    """Continuous-time state space of the coupled four-mount rig (see module docstring). mounts: per-mount
    factors on the actuator's parameters, {"K_L": (4,), "C": (4,), ...} (sim_backend/rig_error.py MOUNT_KEYS;
    None: the four actuators alike)."""
    mm = modal or modal_model_from_config(cfg)
    p = ActuatorParams.from_config(cfg)
    per = {k: np.full(4, float(getattr(p, k))) * np.asarray((mounts or {}).get(k, 1.0), dtype=float)
           for k in ("K_L", "C", "K_Q", "K_C", "w_nv", "zeta")}
    n = len(mm.w_n)
    Phi = mm.phi_mounts                                  # (n, 4)
    Mq = np.eye(n) + p.M * Phi @ Phi.T
    Mi = np.linalg.inv(Mq)
    ns = 2 * n + 12
    iq, iqd, ixv, ivv, ipl = 0, n, 2 * n, 2 * n + 4, 2 * n + 8
    A = np.zeros((ns, ns))
    B = np.zeros((ns, 12))
    K, Cm = np.diag(per["K_L"]), np.diag(per["C"])
    # machine: q'' = Mi (Phi f - 2 zeta W q' - W^2 q)
    A[iq:iq + n, iqd:iqd + n] = np.eye(n)
    A[iqd:iqd + n, iq:iq + n] = Mi @ (-np.diag(mm.w_n ** 2) - Phi @ K @ Phi.T)
    A[iqd:iqd + n, iqd:iqd + n] = Mi @ (-np.diag(2 * mm.zeta * mm.w_n) - Phi @ Cm @ Phi.T)
    A[iqd:iqd + n, ipl:ipl + 4] = Mi @ Phi * p.A_p
    B[iqd:iqd + n, 4:8] = Mi @ Phi @ K
    B[iqd:iqd + n, 8:12] = Mi @ Phi @ Cm
    # valve, Eq. 1 (x_v in mA-equivalent)
    w_nv = per["w_nv"]
    A[ixv:ixv + 4, ivv:ivv + 4] = np.eye(4)
    A[ivv:ivv + 4, ixv:ixv + 4] = -np.diag(w_nv ** 2)
    A[ivv:ivv + 4, ivv:ivv + 4] = -np.diag(2 * per["zeta"] * w_nv)
    B[ivv:ivv + 4, 0:4] = np.diag(w_nv ** 2) * p.K_v
    # chambers, Eqs. 3 and 6
    g = 4 * p.beta / p.V_t
    A[ipl:ipl + 4, ixv:ixv + 4] = g * np.diag(per["K_Q"])
    A[ipl:ipl + 4, ipl:ipl + 4] = -g * np.diag(per["K_C"])
    A[ipl:ipl + 4, iqd:iqd + n] = -g * p.A_p * Phi.T
    B[ipl:ipl + 4, 8:12] = g * p.A_p * np.eye(4)
    # outputs
    no = len(OUTPUTS)
    C = np.zeros((no, ns))
    D = np.zeros((no, 12))
    C[I_ACCEL:I_ACCEL + 4] = Phi.T @ A[iqd:iqd + n]      # accelerometer: absolute mount acceleration
    D[I_ACCEL:I_ACCEL + 4] = Phi.T @ B[iqd:iqd + n]
    C[I_STROKE:I_STROKE + 4, iq:iq + n] = Phi.T         # displacement transducer: x_p - x_g
    D[I_STROKE:I_STROKE + 4, 4:8] = -np.eye(4)
    C[I_X:I_X + 4, iq:iq + n] = Phi.T
    C[I_TABLE:I_TABLE + 3, iq:iq + n] = mm.phi_table.T
    C[I_TOOL:I_TOOL + 3, iq:iq + n] = mm.phi_tool.T
    C[I_SPOOL:I_SPOOL + 4, ixv:ixv + 4] = np.eye(4)
    C[I_PL:I_PL + 4, ipl:ipl + 4] = np.eye(4)
    return RigStateSpace(A, B, C, D, mm, p)


def discretize(ss: RigStateSpace, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact ZOH discretisation: x[k+1] = Ad x[k] + Bd w[k] for inputs held over [t_k, t_k + dt)."""
    return discretize_zoh(ss.A, ss.B, dt)


def discretize_foh_ground(ss: RigStateSpace, dt: float) -> tuple[np.ndarray, ...]:
    """Exact discretisation with the valve command held (ZOH) and the ground interpolated linearly between
    samples (first-order hold): x[k+1] = Ad x[k] + Bu u[k] + G0 g[k] + G1 g[k+1], g = (x_g, v_g).

    Holding the ground instead would put a spurious K_L/m (x_g[k+1] - x_g[k]) into the accelerometer at
    the next sample, larger than the true acceleration below ~1.5 Hz: the floor moves continuously."""
    return discretize_zoh_foh(ss.A, ss.B[:, 0:4], ss.B[:, 4:12], dt)


@numba.njit(cache=True)
def _simulate_modal(lam, Bz, Cz, D, W, Y):
    """Diagonal recursion z <- lam z + Bz w; y = Re(Cz z) + D w (conjugate pairs folded into Cz)."""
    nz = lam.shape[0]
    z = np.zeros(nz, dtype=np.complex128)
    nw = W.shape[1]
    no = Y.shape[1]
    for k in range(W.shape[0]):
        for i in range(no):
            acc = 0.0
            for j in range(nz):
                acc += (Cz[i, j] * z[j]).real
            for j in range(nw):
                acc += D[i, j] * W[k, j]
            Y[k, i] = acc
        for i in range(nz):
            acc = lam[i] * z[i]
            for j in range(nw):
                acc += Bz[i, j] * W[k, j]
            z[i] = acc


def _modal_form(Ad, Bd, C):
    """Diagonalise the discrete system; keep one of each conjugate pair (outputs use 2 Re)."""
    lam, V = np.linalg.eig(Ad)
    Vi = np.linalg.inv(V)
    keep = lam.imag >= 0
    scale = np.where(np.abs(lam.imag) > 0, 2.0, 1.0)[keep]
    Bz = (Vi @ Bd)[keep]
    Cz = (C @ V)[:, keep] * scale
    return np.ascontiguousarray(lam[keep]), np.ascontiguousarray(Bz), np.ascontiguousarray(Cz)


class FloorMotion:
    """Broadband vertical floor motion at the mounts (four unless n_mounts says), streamed in blocks.

    White noise through a 4th-order Butterworth band-pass (paper: 1-50 Hz, 1-50 um). With spectrum
    "velocity_flat" (default) a first-order low-pass at the lower band edge makes the displacement fall as 1/f
    across the band, as measured floors do (tens of um at 1 Hz, about 1 um at 50 Hz); "displacement_flat"
    keeps it flat. Part of the motion is common to all mounts (correlation rho), so the machine both heaves and
    rocks. Velocity is the derivative of the band-limited displacement (central difference)."""

    def __init__(self, dt: float, band_hz=(1.0, 50.0), rms_m: float = 10e-6, seed: int = 1, rho: float = 0.5,
                 block: int = 256, spectrum: str = "velocity_flat", n_mounts: int = 4, rocking_rms_m: float = 0.0,
                 rocking_pattern=None):
        self.dt = dt
        self.n = n = int(n_mounts)
        self.rms_m = rms_m
        self.rho = rho
        self.rng = np.random.default_rng(seed)
        # rocking: a component of its own (same band and spectrum) with a +-1 pattern over the mounts, from a
        # generator of its own, so a floor without it draws exactly the sequence it drew before
        self.rocking_rms_m = float(rocking_rms_m)
        self.rocking = None
        if self.rocking_rms_m > 0:
            pat = np.asarray(rocking_pattern if rocking_pattern is not None else ROCKING_PATTERNS["pitch"], float)
            if pat.shape != (n,):
                raise ValueError(f"rocking pattern: expected {n} values (one per mount), got {pat.shape}")
            self.rocking = pat
            self._rock_rng = np.random.default_rng([seed, 0x40C4])
            self._rock_zi = None
        sos = scipy.signal.butter(4, band_hz, btype="bandpass", fs=1.0 / dt, output="sos")
        if spectrum == "velocity_flat":
            sos = np.vstack([sos, scipy.signal.butter(1, band_hz[0], fs=1.0 / dt, output="sos")])
        elif spectrum != "displacement_flat":
            raise ValueError(f"floor spectrum {spectrum!r}: expected velocity_flat or displacement_flat")
        self.sos = sos
        self.zi = np.zeros((n + 1, self.sos.shape[0], 2))     # the mounts + common component
        if self.rocking is not None:
            self._rock_zi = np.zeros((1, self.sos.shape[0], 2))
        # noise gain of the filter, so rms_m is the displacement rms at every mount
        w, h = scipy.signal.sosfreqz(self.sos, worN=1 << 15, fs=1.0 / dt)
        self.gain = math.sqrt(np.mean(np.abs(h) ** 2))
        self.block = block
        self._x = np.zeros((0, n))
        self._prev = np.zeros(n)
        self._i = 0

    @classmethod
    def from_config(cls, cfg: Config, dt: float, **kw) -> "FloorMotion":
        v = cfg.vibration
        if v.rocking_rms_m > 0 and kw.get("n_mounts", 4) == 4:
            kw.setdefault("rocking_rms_m", v.rocking_rms_m)
            kw.setdefault("rocking_pattern", ROCKING_PATTERNS[v.rocking_axis])
        return cls(dt, band_hz=(v.band_lo_hz, v.band_hi_hz), rms_m=v.rms_m, seed=v.seed,
                   spectrum=v.spectrum, **kw)

    def _more(self):
        # small blocks through a compiled filter: a stepped plant refills every `block` periods inside the
        # control period (8192 samples through scipy took 2.5-3.5 ms: an overrun at 5 kHz each time)
        n = self.n
        white = self.rng.standard_normal((n + 1, self.block))
        out = np.empty_like(white)
        _sosfilt_rows(self.sos, white, self.zi, out)
        out *= self.rms_m / self.gain
        x = (math.sqrt(1 - self.rho) * out[:n] + math.sqrt(self.rho) * out[n]).T
        if self.rocking is not None:
            rock = np.empty((1, self.block))
            _sosfilt_rows(self.sos, self._rock_rng.standard_normal((1, self.block)), self._rock_zi, rock)
            x = x + (rock[0] * (self.rocking_rms_m / self.gain))[:, None] * self.rocking[None, :]
        self._x = np.concatenate([self._x[self._i:], x])
        self._i = 0

    def next_block(self, n: int) -> np.ndarray:
        """The next n periods as an (n, 3 n_mounts) array: x_g, v_g, then a_g per mount, the floor acceleration
        (what a floor accelerometer at the mount reads, before its noise)."""
        while self._i + n + 1 > len(self._x):
            self._more()
        seg = self._x[self._i:self._i + n + 1]
        prev = np.vstack([self._prev[None, :], seg[:-2]]) if n > 1 else self._prev[None, :]
        v = (seg[1:] - prev) / (2 * self.dt)          # central difference, exact for the band-limited signal
        a = (seg[1:] - 2 * seg[:n] + prev) / (self.dt * self.dt)     # central second difference
        self._prev = seg[n - 1].copy()
        self._i += n
        return np.ascontiguousarray(np.hstack([seg[:n], v, a]))

    def take(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        g = self.next_block(n)
        return g[:, :self.n], g[:, self.n:2 * self.n]


def plant_config(cfg: Config) -> Config:
    """The configured model with [plant_error] applied: what the simulated rig's actuators really are (the
    controllers and the feedforward keep the configured values)."""
    e = cfg.plant_error
    if all(getattr(e, k) == 1.0 for k in ("K_L", "C", "w_nv", "zeta", "K_Q", "K_C")):
        return cfg
    a, v = cfg.actuator, cfg.valve
    return cfg.replace(actuator=dataclasses.replace(a, K_L=a.K_L * e.K_L, C=a.C * e.C),
                       valve=dataclasses.replace(v, w_nv=v.w_nv * e.w_nv, zeta=v.zeta * e.zeta, K_Q=v.K_Q * e.K_Q,
                                                 K_C=v.K_C * e.K_C))


class RigPlant:
    """The four-mount rig stepped one loop period at a time (the simulated hardware behind the port).

    After `step(valve_cmd_V)` the attributes hold the values at the new instant: accel_mps2 and stroke_m
    (with sensor noise), floor_accel_mps2 (the floor accelerometers, [sensors] floor_accel, with their own
    noise), and the true table_m / tool_m (Y), spool and floor_m for evaluation. The actuators are the
    configured ones with [plant_error] applied (plant_config); the machine, the mounts, the sensors and the
    valves carry [rig_error]'s deviations (sim_backend/rig_error.py). With a valve delay or deadband the step
    takes the general path (_advance_general: each valve's command delayed exactly, fractions of a period
    included; a deadband valve's spool computed first and its flow fed to the chamber, interpolated
    linearly over the period); otherwise one matrix-vector product (_advance)."""

    n_mounts = 4
    BLOCK = 256                     # periods of floor and sensor noise drawn at once (a refill costs ~20 us)

    ACCEL_NOISE_DENSITY = 1e-6      # m/s^2/sqrt(Hz): a seismic (low-frequency) accelerometer, ~0.1 ug/sqrt(Hz)

    def __init__(self, cfg: Config, dt: float, *, floor: FloorMotion | None = None, seed: int = 0,
                 accel_noise_mps2: float | None = None, stroke_noise_m: float = 2e-8,
                 modal: ModalModel | None = None, floor_accel: bool | None = None,
                 floor_noise_mps2: float | None = None):
        self.cfg = cfg
        self.dt = dt
        modal = modal or modal_model_from_config(cfg)
        self.dev = dev = RigDeviation.from_config(cfg, modal)
        self.ss = rig_state_space(plant_config(cfg), dev.modal(modal), dev.mount_factors())
        self.C = np.ascontiguousarray(self.ss.C)
        self.D = np.ascontiguousarray(self.ss.D)
        self.x = np.zeros(self.ss.A.shape[0])
        self._xn = np.zeros_like(self.x)
        self.y = np.zeros(len(OUTPUTS))
        self._null = dev.valve_null_V.tolist() if dev.null_offsets else None
        self._gains = (dev.accel_gain.tolist() + dev.stroke_gain.tolist()) if dev.sensor_gains else None
        self._floor_gain = dev.floor_gain if np.any(dev.floor_gain != 1) else None
        self.general = dev.delays or dev.deadbands
        if self.general:
            self._general_matrices(dev, dt)
        else:
            self.Ad, Bu, G0, G1 = discretize_foh_ground(self.ss, dt)
            self.Bd = np.ascontiguousarray(np.hstack([Bu, G0, G1]))      # inputs: u[k], g[k], g[k+1]
            self.w = np.zeros(12)
        self.floor = floor
        self.rng = np.random.default_rng(seed)
        if accel_noise_mps2 is None:                  # white noise of that density, sampled at 1/dt
            accel_noise_mps2 = self.ACCEL_NOISE_DENSITY * math.sqrt(0.5 / dt)
        self.noise_scale = np.array([accel_noise_mps2] * 4 + [stroke_noise_m] * 4)
        # floor accelerometers: their noise from a generator of their own, so that fitting them leaves every
        # other sequence of the simulation as it was
        self.floor_sensors = cfg.sensors.floor_accel if floor_accel is None else bool(floor_accel)
        if floor_noise_mps2 is None:
            floor_noise_mps2 = cfg.sensors.floor_noise_mps2_per_rthz * math.sqrt(0.5 / dt)
        self.floor_noise_mps2 = floor_noise_mps2
        self._floor_rng = np.random.default_rng([seed, 0xF100])
        self.floor_accel_mps2 = [0.0] * 4
        self.t_s = 0.0
        self.k = 0
        self._next = None
        self._refill()
        self._advance([0.0] * 4, False)
        self._publish()

    def _general_matrices(self, dev: RigDeviation, dt: float) -> None:
        """The general step's matrices: each valve's command split over the period by its delay
        tau = (d + phi) dt (u[k-d-1] for phi dt, then u[k-d]: columns E and F of the exact hold), the floor
        interpolated linearly (G0, G1), and for a deadband valve its chamber fed from the spool input instead
        of the spool state (its flow, interpolated linearly over the period like the floor)."""
        A = self.ss.A.copy()
        idx = state_index(len(self.ss.modal.w_n))
        spools = np.flatnonzero(dev.valve_deadband_ma > 0)
        Bs = np.zeros((A.shape[0], len(spools)))
        for j, i in enumerate(spools):
            r, c = idx["P_L"] + i, idx["x_v"] + i
            Bs[r, j], A[r, c] = A[r, c], 0.0
        Bu = self.ss.B[:, 0:4]
        Ad, Bud, G0, G1 = discretize_zoh_foh(A, Bu, np.hstack([self.ss.B[:, 4:12], Bs]), dt)
        steps = dev.valve_delay_s / dt
        self._delay = np.floor(steps + 1e-9).astype(int)
        F = np.empty_like(Bud)
        for i in range(4):
            phi = steps[i] - self._delay[i]
            F[:, i] = discretize_zoh(A, Bu[:, i:i + 1], (1.0 - phi) * dt)[1][:, 0] if phi > 1e-9 else Bud[:, i]
        self.Ad = Ad
        self._Bab = np.ascontiguousarray(np.hstack([Bud - F, F]))      # u[k-d-1], u[k-d]
        self._G0, self._G1 = np.ascontiguousarray(G0), np.ascontiguousarray(G1)
        self._Dg = np.ascontiguousarray(self.ss.D[:, 4:12])
        self._sp_rows = np.ascontiguousarray(idx["x_v"] + spools)
        self._sp_width = np.ascontiguousarray(dev.valve_deadband_ma[spools].astype(float))
        self._gs = np.zeros(8 + len(spools))                          # floor and spool inputs at t_k
        self._uab = np.zeros(8)
        self._hist = [[0.0] * 4 for _ in range(int(self._delay.max()) + 2)]   # commands, newest first

    def _advance(self, cmd, advance: bool = True) -> None:
        if not self.general:
            _advance(self.Ad, self.Bd, self.C, self.D, self.x, self._xn, self.w, self._g, self._nz, self._gi,
                     cmd[0], cmd[1], cmd[2], cmd[3], self.y, advance)
            return
        if advance:
            h = self._hist
            h.insert(0, list(cmd))
            h.pop()
            for i, d in enumerate(self._delay):
                self._uab[i], self._uab[4 + i] = h[d + 1][i], h[d][i]
        _advance_general(self.Ad, self._Bab, self._G0, self._G1, self.C, self._Dg, self.x, self._xn, self._uab,
                         self._gs, self._g, self._nz, self._gi, self._sp_rows, self._sp_width, self.y, advance)

    def _draw(self):
        g = self.floor.next_block(self.BLOCK) if self.floor is not None else np.zeros((self.BLOCK, 12))
        nz = np.ascontiguousarray(self.rng.standard_normal((self.BLOCK, 8)) * self.noise_scale)
        fa = None
        if self.floor_sensors:          # a_g plus the sensor's noise (a floor without a_g: noise alone)
            fa = self._floor_rng.standard_normal((self.BLOCK, 4)) * self.floor_noise_mps2
            if g.shape[1] >= 12:
                fa += g[:, 8:12]
            if self._floor_gain is not None:
                fa *= self._floor_gain
            fa = fa.tolist()
        return g, nz, fa

    def _refill(self):
        nxt, self._next = self._next, None
        self._g, self._nz, self._fa = nxt if nxt is not None else self._draw()
        self._gi = 0

    def prefetch(self) -> None:
        """Draw the next block of floor motion and sensor noise ahead of time (the loop calls this in its idle
        time, so the refill stays out of the control period; the sequence is the same either way)."""
        if self._next is None and self._gi >= self.BLOCK // 2:
            self._next = self._draw()

    def _publish(self):
        y = self.y.tolist()
        if self._gains is not None:                      # the sensors' sensitivities (sign included)
            y[0:8] = [g * v for g, v in zip(self._gains, y[0:8])]
        self.accel_mps2 = y[0:4]
        self.stroke_m = y[4:8]
        self.table_m = y[I_TABLE + 1]
        self.tool_m = y[I_TOOL + 1]
        self.spool = y[I_SPOOL:I_SPOOL + 4]
        self.floor_m = (self._gs[0:4] if self.general else self.w[4:8]).tolist()
        if self._fa is not None:
            self.floor_accel_mps2 = self._fa[self._gi]

    def step(self, valve_cmd_V) -> None:
        """Hold valve_cmd_V (4 volts) over one period and advance; outputs then refer to the new instant."""
        self._gi += 1
        if self._gi >= self.BLOCK:
            self._refill()                                  # w[4:12] still holds the ground at t_k
        if self._null is not None:                          # the amplifiers' null offsets
            valve_cmd_V = [u + u0 for u, u0 in zip(valve_cmd_V, self._null)]
        self._advance(valve_cmd_V)
        self.k += 1
        self.t_s = self.k * self.dt
        self._publish()


@numba.njit(cache=True)
def _sosfilt_rows(sos, x, zi, out):
    """scipy.signal.sosfilt (transposed direct form II sections, state zi[row, section, 2]) along each row."""
    ns = sos.shape[0]
    for r in range(x.shape[0]):
        for k in range(x.shape[1]):
            v = x[r, k]
            for q in range(ns):
                b0, b1, b2 = sos[q, 0], sos[q, 1], sos[q, 2]
                a1, a2 = sos[q, 4], sos[q, 5]
                y = b0 * v + zi[r, q, 0]
                zi[r, q, 0] = b1 * v - a1 * y + zi[r, q, 1]
                zi[r, q, 1] = b2 * v - a2 * y
                v = y
            out[r, k] = v


@numba.njit(cache=True)
def _advance(Ad, Bd, C, D, x, xn, w, G, NZ, gi, u0, u1, u2, u3, y, advance):
    """Advance one period (if advance) with the command held and the ground interpolated from w[4:12]
    (ground at t_k) to G[gi] (ground at t_k+1); then load the new ground into w and compute the outputs at
    t_k+1, adding sensor noise NZ[gi] to accel (0-3) and stroke (4-7). Bd = [Bu | G0 | G1]."""
    ns = x.shape[0]
    if advance:
        w[0] = u0; w[1] = u1; w[2] = u2; w[3] = u3
        for i in range(ns):
            acc = 0.0
            for j in range(ns):
                acc += Ad[i, j] * x[j]
            for j in range(12):
                acc += Bd[i, j] * w[j]
            for j in range(8):
                acc += Bd[i, 12 + j] * G[gi, j]
            xn[i] = acc
        for i in range(ns):
            x[i] = xn[i]
    for j in range(8):
        w[4 + j] = G[gi, j]
    for i in range(C.shape[0]):
        acc = 0.0
        for j in range(ns):
            acc += C[i, j] * x[j]
        for j in range(12):
            acc += D[i, j] * w[j]
        y[i] = acc
    for i in range(8):
        y[i] += NZ[gi, i]


@numba.njit(cache=True)
def _advance_general(Ad, Bab, G0, G1, C, Dg, x, xn, uab, gs, G, NZ, gi, sp_rows, sp_width, y, advance):
    """_advance with each valve's command split over the period (uab = u[k-d-1], u[k-d] per mount: Bab) and
    the deadband valves' spool inputs: their spool at t_k+1 first (the valve states depend on the commands
    alone), through the overlap, then the whole state. gs holds the floor (8) and the spool inputs at t_k."""
    ns = x.shape[0]
    nl = sp_rows.shape[0]
    if advance:
        sp = np.empty(nl)
        for j in range(nl):
            r = sp_rows[j]
            acc = 0.0
            for c in range(ns):
                acc += Ad[r, c] * x[c]
            for c in range(8):
                acc += Bab[r, c] * uab[c]
            over = abs(acc) - sp_width[j]
            sp[j] = (over if acc > 0 else -over) if over > 0 else 0.0
        for i in range(ns):
            acc = 0.0
            for c in range(ns):
                acc += Ad[i, c] * x[c]
            for c in range(8):
                acc += Bab[i, c] * uab[c]
            for c in range(8 + nl):
                acc += G0[i, c] * gs[c]
            for c in range(8):
                acc += G1[i, c] * G[gi, c]
            for j in range(nl):
                acc += G1[i, 8 + j] * sp[j]
            xn[i] = acc
        for i in range(ns):
            x[i] = xn[i]
        for j in range(nl):
            gs[8 + j] = sp[j]
    for c in range(8):
        gs[c] = G[gi, c]
    for i in range(C.shape[0]):
        acc = 0.0
        for j in range(ns):
            acc += C[i, j] * x[j]
        for j in range(8):
            acc += Dg[i, j] * gs[j]
        y[i] = acc
    for i in range(8):
        y[i] += NZ[gi, i]


def simulate_rig(cfg: Config, dt: float, valve_cmd_V: np.ndarray, x_g: np.ndarray, v_g: np.ndarray,
                 modal: ModalModel | None = None, outputs=None) -> np.ndarray:
    """Batch open-loop simulation: inputs (N, 4) each; returns the selected outputs (indices into OUTPUTS,
    default all) at t_k, shape (N, n_selected)."""
    ss = rig_state_space(cfg, modal)
    Ad, Bu, G0, G1 = discretize_foh_ground(ss, dt)
    Bd = np.hstack([Bu, G0, G1])
    g = np.hstack([x_g, v_g])
    g_next = np.vstack([g[1:], g[-1:]])                     # the last period holds its ground
    W = np.ascontiguousarray(np.hstack([valve_cmd_V, g, g_next]), dtype=float)
    sel = list(outputs) if outputs is not None else list(range(len(OUTPUTS)))
    lam, Bz, Cz = _modal_form(Ad, Bd, ss.C[sel])
    Y = np.empty((W.shape[0], len(sel)))
    D = np.hstack([ss.D[sel], np.zeros((len(sel), 8))])     # outputs at t_k see g[k], not g[k+1]
    _simulate_modal(lam, Bz, Cz, np.ascontiguousarray(D), W, Y)
    return Y
