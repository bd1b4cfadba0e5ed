"""Offline tuning of the isolation compensator on the discrete loop (how the [controller] defaults were found).

Maximise the smallest attenuation from 1 to 100 Hz (table and tool point, every mount, SISO view) subject to
gain margin >= gm_min and phase margin >= pm_min on every mount, with scipy.optimize (Nelder-Mead on log
parameters, a few restarts). Run: `python -m controllers.tune` (prints a [controller] TOML section).
"""
from __future__ import annotations

import math
import sys

import numpy as np

from controllers.analysis import DiscreteRig, attenuation_db, is_stable, margins
from controllers.isolation import IsolationController, IsolationParams
from rig.config import MOUNTS
from sim_backend.rig_plant import I_ACCEL, I_STROKE, I_TABLE, I_TOOL  # noqa: F401

KEYS = ("kp_V_per_m", "pi_corner_hz", "lead1_zero_hz", "lead1_pole_hz", "lead2_zero_hz", "lead2_pole_hz",
        "rolloff_hz", "rolloff_zeta", "notch_hz", "notch_zeta_zero", "notch_zeta_pole")


def evaluate(rig: DiscreteRig, params: IsolationParams, dt: float, delay: int = 1, at_1hz: list | None = None):
    """(worst attenuation 1-100 Hz over mounts/points, worst GM, worst PM, per-mount margins); the worst
    attenuation at 1 Hz is appended to at_1hz if given."""
    ctrl = IsolationController(params, dt)
    K_a, K_s = ctrl.frf(rig.w)
    zd = rig.zi ** delay
    sel = (rig.f >= 1.0) & (rig.f <= 100.0)
    worst_att, gms, pms, per = math.inf, [], [], []
    for i in range(4):
        P, G = rig.Pu, rig.Gg
        L = -zd * (K_a * P[:, I_ACCEL + i, i] + K_s * P[:, I_STROKE + i, i])
        u = zd * (K_a * G[:, I_ACCEL + i, i] + K_s * G[:, I_STROKE + i, i]) / (1 + L)
        for o in (I_TABLE + 1, I_TOOL + 1):
            att = attenuation_db(G[:, o, i], G[:, o, i] + P[:, o, i] * u)
            worst_att = min(worst_att, float(np.min(att[sel])))
            if at_1hz is not None:
                at_1hz.append(float(np.interp(0.0, np.log(rig.f), att)))
        mg = margins(rig.f, L, True)
        gms.append(mg.gain_margin_db)
        pms.append(mg.phase_margin_deg)
        per.append(mg)
    return worst_att, min(gms), min(pms), per


BOUNDS = {"kp_V_per_m": (1e5, 1e8), "pi_corner_hz": (0.3, 30.0), "lead1_zero_hz": (2.0, 150.0),
          "lead1_ratio": (1.5, 300.0), "lead2_zero_hz": (20.0, 600.0), "lead2_ratio": (1.5, 100.0),
          "rolloff_hz": (300.0, 2400.0), "rolloff_zeta": (0.2, 1.5), "notch_hz": (150.0, 400.0),
          "notch_zeta_zero": (0.02, 1.0), "notch_zeta_pole": (0.1, 2.0)}


def _unpack(start: IsolationParams, x) -> IsolationParams:
    v = {k: math.exp(xi) for k, xi in zip(BOUNDS, x)}
    return start.with_(kp_V_per_m=v["kp_V_per_m"], pi_corner_hz=v["pi_corner_hz"],
                       lead1_zero_hz=v["lead1_zero_hz"], lead1_pole_hz=v["lead1_zero_hz"] * v["lead1_ratio"],
                       lead2_zero_hz=v["lead2_zero_hz"], lead2_pole_hz=v["lead2_zero_hz"] * v["lead2_ratio"],
                       rolloff_hz=v["rolloff_hz"], rolloff_zeta=v["rolloff_zeta"], notch_hz=v["notch_hz"],
                       notch_zeta_zero=v["notch_zeta_zero"], notch_zeta_pole=v["notch_zeta_pole"])


def _pack(p: IsolationParams) -> np.ndarray:
    v = {"kp_V_per_m": p.kp_V_per_m, "pi_corner_hz": p.pi_corner_hz, "lead1_zero_hz": p.lead1_zero_hz,
         "lead1_ratio": p.lead1_pole_hz / p.lead1_zero_hz, "lead2_zero_hz": p.lead2_zero_hz,
         "lead2_ratio": p.lead2_pole_hz / p.lead2_zero_hz, "rolloff_hz": p.rolloff_hz,
         "rolloff_zeta": p.rolloff_zeta, "notch_hz": p.notch_hz or 250.0,
         "notch_zeta_zero": p.notch_zeta_zero, "notch_zeta_pole": p.notch_zeta_pole}
    return np.array([math.log(v[k]) for k in BOUNDS])


def cost(x, rig: DiscreteRig, start: IsolationParams, dt: float, gm_min: float, pm_min: float,
         s_max_db: float) -> float:
    """-(worst attenuation) plus penalties: margins, sensitivity peak max|1/(1+L)| and closed-loop poles."""
    p = _unpack(start, x)
    if max(p.lead1_pole_hz, p.lead2_pole_hz, p.rolloff_hz) >= 0.45 / dt:
        return 1e3
    one = []
    att, gm, pm, per = evaluate(rig, p, dt, at_1hz=one)
    pen = 3.0 * max(0.0, gm_min - gm) + 0.5 * max(0.0, pm_min - pm) + max(0.0, 21.0 - min(one))
    c = IsolationController(p, dt)
    K_a, K_s = c.frf(rig.w)
    for i in range(4):
        L = -rig.zi * (K_a * rig.Pu[:, I_ACCEL + i, i] + K_s * rig.Pu[:, I_STROKE + i, i])
        s_db = float(np.max(-20 * np.log10(np.abs(1 + L))))
        pen += max(0.0, s_db - s_max_db)
    for loops in ((0,), (1,), (2,), (3,), (0, 1, 2, 3)):          # each SISO loop, and all four (MIMO)
        if not is_stable(rig, [c] * 4, loops=loops)[0]:
            return 500.0 - att
    return -att + 10 * pen


def tune(cfg, dt: float, start: IsolationParams, gm_min: float = 6.3, pm_min: float = 35.5,
         s_max_db: float = 6.0, maxiter: int = 60, seed: int = 1, log=None) -> IsolationParams:
    """Differential evolution over BOUNDS (log scale), then a Nelder-Mead polish."""
    import scipy.optimize
    f = np.unique(np.concatenate([np.geomspace(0.01, 0.49 / dt, 700), np.linspace(1, 100, 120)]))
    rig = DiscreteRig(cfg, dt, f)
    args = (rig, start, dt, gm_min, pm_min, s_max_db)
    bounds = [(math.log(lo), math.log(hi)) for lo, hi in BOUNDS.values()]
    x0 = np.clip(_pack(start), [b[0] for b in bounds], [b[1] for b in bounds])
    res = scipy.optimize.differential_evolution(cost, bounds, args=args, x0=x0, maxiter=maxiter, popsize=12,
                                                seed=seed, tol=1e-6, polish=False, init="sobol")
    if log:
        log(f"de: cost {res.fun:.3f}")
    res2 = scipy.optimize.minimize(cost, res.x, args=args, method="Nelder-Mead",
                                   options={"maxiter": 800, "xatol": 1e-4, "fatol": 1e-4, "adaptive": True})
    x = res2.x if res2.fun < res.fun else res.x
    if log:
        log(f"final cost {min(res.fun, res2.fun):.3f} (check {cost(x, *args):.3f})")
    return _unpack(start, x)


def polish(cfg, dt: float, start: IsolationParams, gm_min: float = 6.3, pm_min: float = 35.5,
           s_max_db: float = 6.0, maxiter: int = 600, log=None) -> IsolationParams:
    """Nelder-Mead from a hand-made starting design (the landscape is rugged: start near a stable design)."""
    import scipy.optimize
    f = np.unique(np.concatenate([np.geomspace(0.01, 0.49 / dt, 700), np.linspace(1, 100, 120)]))
    rig = DiscreteRig(cfg, dt, f)
    args = (rig, start, dt, gm_min, pm_min, s_max_db)
    x = _pack(start)
    c0 = cost(x, *args)
    for r in range(4):
        res = scipy.optimize.minimize(cost, x, args=args, method="Nelder-Mead",
                                      options={"maxiter": maxiter, "xatol": 1e-4, "fatol": 1e-4,
                                               "adaptive": True})
        x = res.x
        if log:
            log(f"polish {r}: cost {c0:.3f} -> {res.fun:.3f}: " + ",".join(
                f"{k}={getattr(_unpack(start, x), k):.6g}" for k in KEYS))
    return _unpack(start, x)


def main() -> int:
    from rig.config import Config
    from controllers.isolation import params_from_config
    cfg = Config()
    dt = 1.0 / cfg.loop.rate_hz
    start = params_from_config(cfg)
    if len(sys.argv) > 1:          # key=value,... [gm_min pm_min s_max_db]: polish from this hand-made start
        kw = {k: float(v) for k, v in (a.split("=") for a in sys.argv[1].split(","))}
        lim = [float(v) for v in sys.argv[2:5]] or [6.3, 35.5, 6.0]
        p = polish(cfg, dt, start.with_(**kw), *lim, log=lambda s: print(s, file=sys.stderr))
    else:
        p = tune(cfg, dt, start, log=lambda s: print(s, file=sys.stderr))
    f = np.unique(np.concatenate([np.geomspace(0.01, 0.49 / dt, 2000), np.linspace(1, 100, 400)]))
    att, gm, pm, per = evaluate(DiscreteRig(cfg, dt, f), p, dt)
    print(f"# worst attenuation 1-100 Hz {att:.2f} dB, GM {gm:.2f} dB, PM {pm:.2f} deg", file=sys.stderr)
    for m, mg in zip(MOUNTS, per):
        print(f"#  {m}: GM {mg.gain_margin_db:.2f} dB PM {mg.phase_margin_deg:.2f} deg "
              f"gc {mg.gain_crossover_hz:.1f} Hz pc {mg.phase_crossover_hz:.1f} Hz", file=sys.stderr)
    print("[controller]")
    for k in KEYS:
        print(f"{k} = {getattr(p, k):.6g}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
