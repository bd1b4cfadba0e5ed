"""Linear models of the valve-controlled actuator (Law et al. 2015, Eqs. 1-10) with python-control.

`ActuatorParams` holds the paper's symbols in SI units (K_Q per mA, K_v in mA/V). Fast numpy evaluators of
the frequency responses are given beside the python-control objects, for fitting loops.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, asdict, replace

import numpy as np
import scipy.linalg

from rig.config import ActuatorConfig, Config, FluidConfig, ValveConfig

IDENTIFIED = ("K_L", "C", "w_nv", "zeta", "K_Q", "K_C")   # x_d of Eq. 11


_A, _V, _F = ActuatorConfig(), ValveConfig(), FluidConfig()     # Table 1: rig/config.py is the one source


@dataclass(frozen=True)
class ActuatorParams:
    M: float = _A.M              # kg, moving mass
    A_p: float = _A.A_p          # m^2
    C: float = _A.C              # N s/m
    V_t: float = _A.V_t          # m^3
    K_L: float = _A.K_L          # N/m
    K_v: float = _V.K_v          # mA/V
    K_Q: float = _V.K_Q          # m^3/s/mA
    K_C: float = _V.K_C          # m^3/s/Pa
    w_nv: float = _V.w_nv        # rad/s
    zeta: float = _V.zeta
    beta: float = _F.beta        # Pa

    @classmethod
    def from_config(cls, cfg: Config, *, loaded_mass_kg: float | None = None) -> "ActuatorParams":
        a, v, f = cfg.actuator, cfg.valve, cfg.fluid
        return cls(M=a.M if loaded_mass_kg is None else loaded_mass_kg, A_p=a.A_p, C=a.C, V_t=a.V_t,
                   K_L=a.K_L, K_v=v.K_v, K_Q=v.K_Q, K_C=v.K_C, w_nv=v.w_nv, zeta=v.zeta, beta=f.beta)

    def with_(self, **kw) -> "ActuatorParams":
        return replace(self, **kw)

    def identified(self) -> dict[str, float]:
        return {k: getattr(self, k) for k in IDENTIFIED}

    def as_dict(self) -> dict[str, float]:
        return asdict(self)

    # Derived figures -------------------------------------------------------------------------------
    @property
    def w_h(self) -> float:
        """Hydro-mechanical natural frequency sqrt(4 beta A_p^2 / (V_t M)), rad/s (after Eq. 9)."""
        return math.sqrt(4 * self.beta * self.A_p ** 2 / (self.V_t * self.M))

    @property
    def delta_h(self) -> float:
        """Hydraulic damping ratio (K_C/A_p) sqrt(beta M / V_t) (after Eq. 9)."""
        return self.K_C / self.A_p * math.sqrt(self.beta * self.M / self.V_t)

    @property
    def K_h(self) -> float:
        """Hydraulic stiffness 4 beta A_p^2 / V_t, N/m (Eq. 13)."""
        return 4 * self.beta * self.A_p ** 2 / self.V_t

    @property
    def lag_corner(self) -> float:
        """Low-frequency lag K_C K_L / A_p^2, rad/s (Eq. 9)."""
        return self.K_C * self.K_L / self.A_p ** 2

    @property
    def dc_gain_m_per_V(self) -> float:
        """x_p / v at 0 Hz of G_EHA: K_v (K_Q/A_p) / (K_C K_L / A_p^2)."""
        return self.K_v * (self.K_Q / self.A_p) / self.lag_corner


def actuator_params(cfg: Config | None = None, **overrides) -> ActuatorParams:
    p = ActuatorParams() if cfg is None else ActuatorParams.from_config(cfg)
    return p.with_(**overrides) if overrides else p


# ---- python-control transfer functions -------------------------------------------------------------

def _ct():
    import control
    return control


def g_valve(p: ActuatorParams):
    """Eq. 1: x_v/v = K_v / (1 + (2 zeta/w_nv) s + (s/w_nv)^2); x_v in mA-equivalent spool units."""
    ct = _ct()
    return ct.tf([p.K_v], [1 / p.w_nv ** 2, 2 * p.zeta / p.w_nv, 1.0])


def _eq8_den(p: ActuatorParams) -> list[float]:
    b4 = 4 * p.beta
    A2 = p.A_p ** 2
    return [p.V_t * p.M / (b4 * A2),
            p.K_C * p.M / A2 + p.C * p.V_t / (b4 * A2),
            1 + p.C * p.K_C / A2 + p.K_L * p.V_t / (b4 * A2),
            p.K_C * p.K_L / A2]


def g_act_full(p: ActuatorParams):
    """Eq. 8, x_p/x_v with F_L = 0 (the full third-order actuator)."""
    return _ct().tf([p.K_Q / p.A_p], _eq8_den(p))


def g_act_load(p: ActuatorParams):
    """Eq. 8, x_p/F_L: -(K_C/A_p^2)(1 + V_t s/(4 beta K_C)) / den."""
    K = p.K_C / p.A_p ** 2
    return _ct().tf([-K * p.V_t / (4 * p.beta * p.K_C), -K], _eq8_den(p))


def g_act(p: ActuatorParams):
    """Eq. 9, reduced: (K_Q/A_p) / ((s + K_C K_L/A_p^2)(s^2/w_h^2 + 2 delta_h s/w_h + 1))."""
    ct = _ct()
    lag = ct.tf([1.0], [1.0, p.lag_corner])
    hyd = ct.tf([1.0], [1 / p.w_h ** 2, 2 * p.delta_h / p.w_h, 1.0])
    return (p.K_Q / p.A_p) * lag * hyd


def g_eha(p: ActuatorParams, *, full: bool = True):
    """Eq. 10: G_EHA = G_valve G_act, volts -> metres (full Eq. 8 actuator by default)."""
    return g_valve(p) * (g_act_full(p) if full else g_act(p))


# ---- fast numpy frequency responses (for fitting) ---------------------------------------------------

def g_eha_frf(p: ActuatorParams, w: np.ndarray, *, full: bool = True) -> np.ndarray:
    """G_EHA(j w) as complex array, m/V (Eqs. 1, 8/9, 10)."""
    s = 1j * np.asarray(w, dtype=float)
    valve = p.K_v / (1 + (2 * p.zeta / p.w_nv) * s + (s / p.w_nv) ** 2)
    if full:
        d3, d2, d1, d0 = _eq8_den(p)
        act = (p.K_Q / p.A_p) / (((d3 * s + d2) * s + d1) * s + d0)
    else:
        act = (p.K_Q / p.A_p) / ((s + p.lag_corner) * ((s / p.w_h) ** 2 + 2 * p.delta_h * s / p.w_h + 1))
    return valve * act


def zoh_delay(w: np.ndarray, fs: float) -> np.ndarray:
    """The zero-order hold's half-sample delay exp(-j w /(2 fs)) (its sinc magnitude is < 0.01 dB here)."""
    return np.exp(-0.5j * np.asarray(w) / fs)


def model_figures(p: ActuatorParams, machine_mass_kg: float, n_mounts: int = 4) -> dict[str, float]:
    """The headline numbers of `rig model` (see PHYSICS_NOTES: formulas are the truth of the model)."""
    loaded = p.with_(M=machine_mass_kg / n_mounts)
    return {
        "valve_natural_frequency_hz": p.w_nv / (2 * math.pi),
        "hydraulic_natural_frequency_hz": p.w_h / (2 * math.pi),
        "loaded_hydraulic_natural_frequency_hz": loaded.w_h / (2 * math.pi),
        "hydraulic_damping_ratio": p.delta_h,
        "loaded_hydraulic_damping_ratio": loaded.delta_h,
        "lag_corner_rad_s": p.lag_corner,
        "lag_corner_hz": p.lag_corner / (2 * math.pi),
        "dc_gain_m_per_V": p.dc_gain_m_per_V,
        "hydraulic_stiffness_N_per_m": p.K_h,
        "mount_stiffness_N_per_m": p.K_L + p.K_h,
    }


def discretize_zoh(A: np.ndarray, B: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact zero-order-hold discretisation x[k+1] = Ad x[k] + Bd u[k], inputs held over [t_k, t_k + dt):
    discretize_zoh_foh without a linearly interpolated input. For models built once per run or per fit step
    (the rig's plant and its analysis, the actuator's identification); the diagnosis's per-evaluation ZOH,
    balanced for any plant family's scaling and with fractional delays, is rig/plant/zoh.py."""
    Ad, Bd, _, _ = discretize_zoh_foh(A, B, np.zeros((A.shape[0], 0)), dt)
    return Ad, Bd


def discretize_zoh_foh(A: np.ndarray, Bu: np.ndarray, Bg: np.ndarray, dt: float) -> tuple[np.ndarray, ...]:
    """Exact discretisation of x' = A x + Bu u + Bg g with u held over the period (ZOH) and g interpolated
    linearly between samples (first-order hold, the floor moves continuously):
    x[k+1] = Ad x[k] + Bud u[k] + G0 g[k] + G1 g[k+1]. Returns (Ad, Bud, G0, G1)."""
    n, nu, m = A.shape[0], Bu.shape[1], Bg.shape[1]
    big = np.zeros((n + nu + 2 * m, n + nu + 2 * m))
    big[:n, :n] = A * dt
    big[:n, n:n + nu] = Bu * dt
    big[:n, n + nu:n + nu + m] = Bg * dt
    big[n + nu:n + nu + m, n + nu + m:] = np.eye(m)
    e = scipy.linalg.expm(big)
    gam0 = e[:n, n + nu:n + nu + m]        # int_0^T e^{A s} ds B_g
    gam1 = e[:n, n + nu + m:]              # (1/T) int_0^T e^{A (T - s)} s ds B_g
    return (np.ascontiguousarray(e[:n, :n]), np.ascontiguousarray(e[:n, n:n + nu]),
            np.ascontiguousarray(gam0 - gam1), np.ascontiguousarray(gam1))
