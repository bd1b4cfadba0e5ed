"""Closed-loop analysis of the isolation controllers on the coupled rig: the discrete loop as it runs.

The plant is the four-mount rig (sim_backend/rig_plant.py) discretised exactly with a zero-order hold at the
loop period (the same matrices RigPlant steps). The loop applies the command one period after the sample
it was computed from (computation delay z^-1, as SimBackend(cmd_delay_periods=1) and the real loop do), so
the return ratio of one mount is

    L(z) = -z^-1 (K_a(z) P_a(z) + K_s(z) P_s(z))

with K_a, K_s the discrete responses of the *same controller objects* the loop steps (IsolationController.frf
/ .ss) and P_a, P_s the plant from that mount's valve voltage to its accelerometer and stroke transducer.

Views:
- SISO (paper Fig. 5): one mount's loop closed, the other three valves nulled (their actuators passive-stiff);
  ground moving at that mount only.
- MIMO (beyond the paper): all four loops closed on the coupled machine; stability from the closed-loop
  eigenvalues of the full discrete interconnection; transmissibility for uniform ground (all mounts in phase)
  and for ground at each mount in turn.
Ground input: the plant's ground displacement and velocity inputs with v_g = j w x_g, continuous (the floor
does not move in steps); the sampled outputs then follow exactly for a sinusoidal floor.
Attenuation = 20 log10(|TR_passive| / |TR_controlled|).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from rig.config import MOUNTS
from sim_backend.rig_plant import I_ACCEL, I_STROKE, I_TABLE, I_TOOL, discretize, rig_state_space

BANDS = {"1hz": (1.0, 1.0), "5_10hz": (5.0, 10.0), "20_60hz": (20.0, 60.0), "60_100hz": (60.0, 100.0),
         "min_1_100hz": (1.0, 100.0)}
POINTS = {"table": I_TABLE, "tool": I_TOOL}


def default_grid(dt: float, n: int = 2400) -> np.ndarray:
    """Frequencies (Hz), log-spaced from 0.005 Hz to just below Nyquist, with the band edges included."""
    f = np.geomspace(0.005, 0.49 / dt, n)
    return np.unique(np.concatenate([f, [1.0, 5.0, 10.0, 20.0, 60.0, 100.0]]))


class DiscreteRig:
    """Frequency responses of the sampled rig at z = exp(j w dt).

    Valve inputs: the ZOH-discretised plant (exact at the sample instants, the same matrices RigPlant steps).
    Ground: continuous (ground="continuous", the physics: a sinusoidal floor motion sampled at t_k gives the
    continuous response exactly), or ground="held": x_g and v_g held over each period with the outputs
    using the newest sample, which is what RigPlant does today (see the report on issue 3: that convention puts
    a spurious D (x_g[k] - x_g[k-1]) term into the accelerometer, larger than the true acceleration below
    ~1.5 Hz)."""

    def __init__(self, cfg, dt: float, f_hz: np.ndarray | None = None, ground: str = "continuous"):
        self.cfg = cfg
        self.dt = dt
        self.ground = ground
        self.ss = rig_state_space(cfg)
        self.Ad, self.Bd = discretize(self.ss, dt)
        self.C, self.D = self.ss.C, self.ss.D
        self.f = default_grid(dt) if f_hz is None else np.asarray(f_hz, dtype=float)
        self.w = 2 * np.pi * self.f
        self.zi = np.exp(-1j * self.w * dt)
        lam, V = np.linalg.eig(self.Ad)
        CV = self.C @ V
        VB = np.linalg.solve(V, self.Bd)
        z = 1.0 / self.zi
        H = np.einsum("oi,fi,im->fom", CV, 1.0 / (z[:, None] - lam[None, :]), VB) + self.D[None]
        self.Pu = H[:, :, 0:4]                                         # valve voltage inputs (ZOH)
        if ground == "held":
            self.Gg = H[:, :, 4:8] + 1j * self.w[:, None, None] * H[:, :, 8:12]
        elif ground == "foh":
            # ground interpolated linearly between samples (first-order hold): the fix proposed for RigPlant
            import scipy.linalg
            n, m = self.ss.A.shape[0], 8
            big = np.zeros((n + 2 * m, n + 2 * m))
            big[:n, :n] = self.ss.A * dt
            big[:n, n:n + m] = self.ss.B[:, 4:12] * dt
            big[n:n + m, n + m:] = np.eye(m)
            e = scipy.linalg.expm(big)
            G0, G1 = e[:n, n:n + m], e[:n, n + m:]
            Bz = G0[None] + G1[None] * (z[:, None, None] - 1.0)             # (f, n, m)
            Hf = np.einsum("oi,fi,fim->fom", CV, 1.0 / (z[:, None] - lam[None, :]),
                           np.einsum("ij,fjm->fim", np.linalg.inv(V), Bz)) + self.D[None, :, 4:12]
            self.Gg = Hf[:, :, 0:4] + 1j * self.w[:, None, None] * Hf[:, :, 4:8]
        elif ground == "continuous":
            lam_c, Vc = np.linalg.eig(self.ss.A)
            CVc = self.C @ Vc
            VBc = np.linalg.solve(Vc, self.ss.B[:, 4:12])
            Hc = np.einsum("oi,fi,im->fom", CVc, 1.0 / (1j * self.w[:, None] - lam_c[None, :]), VBc)
            Hc = Hc + self.D[None, :, 4:12]
            self.Gg = Hc[:, :, 0:4] + 1j * self.w[:, None, None] * Hc[:, :, 4:8]
        else:
            raise ValueError(f"ground {ground!r} (expected continuous, held or foh)")


@dataclass
class Margins:
    stable: bool
    gain_margin_db: float
    phase_margin_deg: float
    gain_crossover_hz: float
    phase_crossover_hz: float


def margins(f: np.ndarray, L: np.ndarray, stable: bool) -> Margins:
    """Margins of the return ratio L on the grid f (interpolated between grid points).

    Gain crossovers: |L| = 1; the phase margin is the smallest over them and the reported gain crossover is
    the highest (the one the lead stages set). Phase crossovers: L crosses the negative real axis; the gain
    margin is the smallest |20 log10 |L|| over them, i.e. the gain may change by that much either way (a
    conditionally stable loop also has a gain *reduction* margin)."""
    mag = np.abs(L)
    lm = np.log(mag)
    gcs, pms = [], []
    for k in np.nonzero(np.sign(lm[:-1]) != np.sign(lm[1:]))[0]:
        t = lm[k] / (lm[k] - lm[k + 1])
        fc = math.exp(math.log(f[k]) + t * (math.log(f[k + 1]) - math.log(f[k])))
        Lc = L[k] + t * (L[k + 1] - L[k])
        pm = 180.0 - abs(math.degrees(np.angle(Lc)))        # distance of the phase from -180 deg
        gcs.append(fc)
        pms.append(pm)
    pcs, gms = [], []
    im = L.imag
    for k in np.nonzero((np.sign(im[:-1]) != np.sign(im[1:])))[0]:
        t = im[k] / (im[k] - im[k + 1])
        Lc = L[k] + t * (L[k + 1] - L[k])
        if Lc.real >= 0:
            continue
        fc = math.exp(math.log(f[k]) + t * (math.log(f[k + 1]) - math.log(f[k])))
        pcs.append(fc)
        gms.append(-20 * math.log10(abs(Lc.real)))
    pm = min(pms) if pms else math.inf
    gc = max(gcs) if gcs else math.nan
    if gms:
        j = int(np.argmin(np.abs(gms)))
        gm, pc = abs(gms[j]), pcs[j]
    else:
        gm, pc = math.inf, math.nan
    return Margins(bool(stable), gm, pm, gc, pc)


def closed_loop_poles(rig: DiscreteRig, ctrls, loops=(0, 1, 2, 3), delay: int = 1) -> np.ndarray:
    """Eigenvalues of the discrete interconnection: plant (ZOH) + controllers of `loops` (the others' valves
    nulled) + `delay` periods of computation delay per loop. Stable iff all |z| < 1."""
    Ad, Bu = rig.Ad, rig.Bd[:, 0:4]
    n = Ad.shape[0]
    blocks = [ctrls[i].ss() for i in loops]
    nk = sum(b[0].shape[0] for b in blocks) + delay * len(loops)
    A = np.zeros((n + nk, n + nk))
    A[:n, :n] = Ad
    off = n
    for (Ak, Bk, Ck, Dk), i in zip(blocks, loops):
        m = Ak.shape[0]
        Cy = np.vstack([rig.C[I_ACCEL + i], rig.C[I_STROKE + i]])       # (2, n): u has no feedthrough
        ik = slice(off, off + m)
        A[ik, ik] = Ak
        A[ik, :n] = Bk @ Cy
        if delay:
            d0 = off + m                                             # delay line d1..d_delay
            A[d0, ik] = Ck[0]
            A[d0, :n] = (Dk @ Cy)[0]
            for j in range(1, delay):
                A[d0 + j, d0 + j - 1] = 1.0
            A[:n, d0 + delay - 1] = Bu[:, i]
        else:
            A[:n, ik] += np.outer(Bu[:, i], Ck[0])
            A[:n, :n] += np.outer(Bu[:, i], (Dk @ Cy)[0])
        off += m + delay
    return np.linalg.eigvals(A)


SLOW_HZ = 0.5     # closed-loop poles below this are judged on the continuous-time twin


def slow_poles_continuous(rig: DiscreteRig, ctrls, loops=(0, 1, 2, 3)) -> np.ndarray:
    """Closed-loop poles (1/s) below SLOW_HZ of the continuous plant with the controllers' continuous twins
    (IsolationController.css). Near z = 1 the discrete eigenvalues of the blend's and the PI's slow poles
    lose their digits (clustered poles, four identical loops), while at these frequencies the sampling and the
    delay do not matter; so the slow poles are judged here, the fast ones on the discrete loop."""
    A0, Bu = rig.ss.A, rig.ss.B[:, 0:4]
    n = A0.shape[0]
    blocks = [ctrls[i].css() for i in loops]
    N = n + sum(b[0].shape[0] for b in blocks)
    M = np.zeros((N, N))
    M[:n, :n] = A0
    off = n
    for (Ak, Bk, Ck, Dk), i in zip(blocks, loops):
        m = Ak.shape[0]
        Cy = np.vstack([rig.C[I_ACCEL + i], rig.C[I_STROKE + i]])
        ik = slice(off, off + m)
        M[ik, ik] = Ak
        M[ik, :n] = Bk @ Cy
        M[:n, ik] += np.outer(Bu[:, i], Ck[0])
        M[:n, :n] += np.outer(Bu[:, i], (Dk @ Cy)[0])
        off += m
    ev = np.linalg.eigvals(M)
    return ev[np.abs(ev) < 2 * np.pi * SLOW_HZ]


def is_stable(rig: DiscreteRig, ctrls, loops=(0, 1, 2, 3), delay: int = 1) -> tuple[bool, np.ndarray]:
    """(stable, discrete poles): fast poles |z| < 1 on the discrete loop, slow poles Re s < 0 on the twin."""
    z = closed_loop_poles(rig, ctrls, loops, delay)
    with np.errstate(divide="ignore", invalid="ignore"):
        s_eq = np.log(z.astype(complex)) / rig.dt
    fast = np.abs(s_eq) >= 2 * np.pi * SLOW_HZ
    ok_fast = bool(np.all(np.abs(z[fast]) < 1.0))
    ok_slow = bool(np.all(slow_poles_continuous(rig, ctrls, loops).real < 0.0))
    return ok_fast and ok_slow, z


def unstable_loops(cfg, ctrls, dt: float, delay: int = 1) -> list[str]:
    """What `rig design` would call unstable, from the closed-loop poles alone (no frequency grid: about 0.2 s
    for the four SISO loops and the MIMO one): each mount's loop closed alone (the paper's SISO view) and all
    four together. Empty when all are stable; otherwise one entry per unstable view with its largest |z| and
    that pole's frequency."""
    rig = DiscreteRig(cfg, dt, f_hz=np.array([1.0]))
    ctrls = _same_models_once(ctrls)
    out = []
    views = [(MOUNTS[i], [ctrls[i]] * len(MOUNTS), (i,)) for i in range(len(ctrls))] + \
        [("all four loops (MIMO)", ctrls, tuple(range(len(ctrls))))]
    for name, cs, loops in views:
        ok, z = is_stable(rig, cs, loops=loops, delay=delay)
        if not ok:
            k = int(np.argmax(np.abs(z)))
            f = abs(np.angle(z[k])) / (2 * np.pi * dt)
            out.append(f"{name}: pole |z| = {abs(z[k]):.3f} at {f:.0f} Hz")
    return out


class _Models:
    """A controller's state-space models (ss, css), computed once and shared by controllers of equal
    parameters (the four mounts usually are): the continuous twin costs most of a stability check."""

    def __init__(self, ctrl) -> None:
        self.ctrl = ctrl
        self._ss = self._css = None

    def ss(self):
        if self._ss is None:
            self._ss = self.ctrl.ss()
        return self._ss

    def css(self):
        if self._css is None:
            self._css = self.ctrl.css()
        return self._css


def _same_models_once(ctrls) -> list:
    by_params: dict = {}
    out = []
    for c in ctrls:
        key = (type(c), getattr(c, "p", id(c)), getattr(c, "dt", None), getattr(c, "compensator", None))
        try:
            out.append(by_params.setdefault(key, _Models(c)))
        except TypeError:                 # unhashable parameters: no sharing
            out.append(_Models(c))
    return out


def siso(rig: DiscreteRig, ctrl, i: int, delay: int = 1) -> dict:
    """One mount's loop closed, the others nulled; ground at that mount. Returns L, transmissibilities."""
    K_a, K_s = ctrl.frf(rig.w)
    zd = rig.zi ** delay
    P, G = rig.Pu, rig.Gg
    L = -zd * (K_a * P[:, I_ACCEL + i, i] + K_s * P[:, I_STROKE + i, i])
    u = zd * (K_a * G[:, I_ACCEL + i, i] + K_s * G[:, I_STROKE + i, i]) / (1 + L)
    tr_c = G[:, :, i] + P[:, :, i] * u[:, None]
    tr_p = G[:, :, i]
    stable, poles = is_stable(rig, [ctrl] * 4, loops=(i,), delay=delay)
    return {"L": L, "tr_controlled": tr_c, "tr_passive": tr_p, "poles": poles,
            "margins": margins(rig.f, L, stable)}


def mimo(rig: DiscreteRig, ctrls, delay: int = 1) -> dict:
    """All four loops closed. TR for uniform ground ('uniform', all mounts in phase) and for ground at each
    mount in turn (tr_controlled[..., j]); plus det(I + L) for the generalised Nyquist view."""
    nf = len(rig.f)
    zd = rig.zi ** delay
    Ka = np.empty((nf, 4), dtype=complex)
    Ks = np.empty((nf, 4), dtype=complex)
    for i, c in enumerate(ctrls):
        Ka[:, i], Ks[:, i] = c.frf(rig.w)
    P, G = rig.Pu, rig.Gg
    Pa, Ps = P[:, I_ACCEL:I_ACCEL + 4, :], P[:, I_STROKE:I_STROKE + 4, :]
    Ga, Gs = G[:, I_ACCEL:I_ACCEL + 4, :], G[:, I_STROKE:I_STROKE + 4, :]
    Lm = -zd[:, None, None] * (Ka[:, :, None] * Pa + Ks[:, :, None] * Ps)
    rhs = zd[:, None, None] * (Ka[:, :, None] * Ga + Ks[:, :, None] * Gs)
    I4 = np.eye(4)[None]
    U = np.linalg.solve(I4 + Lm, rhs)                       # (nf, 4 valves, 4 ground inputs)
    tr_c = G + np.einsum("fou,fug->fog", P, U)
    stable, poles = is_stable(rig, ctrls, loops=(0, 1, 2, 3), delay=delay)
    return {"L": Lm, "det": np.linalg.det(I4 + Lm), "tr_controlled": tr_c, "tr_passive": G,
            "tr_uniform_controlled": tr_c.sum(axis=2), "tr_uniform_passive": G.sum(axis=2),
            "poles": poles, "stable": stable}


def attenuation_db(tr_p: np.ndarray, tr_c: np.ndarray) -> np.ndarray:
    return 20 * np.log10(np.abs(tr_p) / np.abs(tr_c))


def band_summary(f: np.ndarray, att: np.ndarray) -> dict:
    """Band entries: the minimum attenuation over each band (the value at 1 Hz for '1hz')."""
    out = {}
    for key, (lo, hi) in BANDS.items():
        if lo == hi:
            out[key] = float(np.interp(math.log(lo), np.log(f), att))
        else:
            sel = (f >= lo - 1e-9) & (f <= hi + 1e-9)
            out[key] = float(np.min(att[sel]))
    return out


def design_report(cfg, ctrls, dt: float, rig: DiscreteRig | None = None, delay: int = 1) -> dict:
    """Everything `rig design` prints: per-mount margins, MIMO stability, attenuation bands (the issue's JSON
    schema), plus the arrays for the figures under '_data'."""
    rig = rig or DiscreteRig(cfg, dt)
    mounts, att_t, att_q, data = {}, {}, {}, {"f": rig.f, "siso": {}, "rig": rig}
    for i, m in enumerate(MOUNTS):
        r = siso(rig, ctrls[i], i, delay)
        mg = r["margins"]
        mounts[m] = {"stable": mg.stable, "gain_margin_db": mg.gain_margin_db,
                     "phase_margin_deg": mg.phase_margin_deg, "gain_crossover_hz": mg.gain_crossover_hz,
                     "phase_crossover_hz": mg.phase_crossover_hz}
        att_t[m] = band_summary(rig.f, attenuation_db(r["tr_passive"][:, I_TABLE + 1],
                                                      r["tr_controlled"][:, I_TABLE + 1]))
        att_q[m] = band_summary(rig.f, attenuation_db(r["tr_passive"][:, I_TOOL + 1],
                                                      r["tr_controlled"][:, I_TOOL + 1]))
        data["siso"][m] = r
    mm = mimo(rig, ctrls, delay)
    data["mimo"] = mm
    return {"mounts": mounts, "mimo_stable": mm["stable"],
            "attenuation_db": {"ground_to_table": att_t, "ground_to_tool": att_q}, "_data": data}


def mimo_summary(rig: DiscreteRig, mm: dict) -> dict:
    """Attenuation bands with all four loops closed: uniform ground, and ground at each mount in turn."""
    out = {"uniform": {}, "per_mount": {}}
    for name, o in (("table", I_TABLE + 1), ("tool", I_TOOL + 1)):
        out["uniform"][f"ground_to_{name}"] = band_summary(
            rig.f, attenuation_db(mm["tr_uniform_passive"][:, o], mm["tr_uniform_controlled"][:, o]))
        out["per_mount"][f"ground_to_{name}"] = {
            m: band_summary(rig.f, attenuation_db(mm["tr_passive"][:, o, j], mm["tr_controlled"][:, o, j]))
            for j, m in enumerate(MOUNTS)}
    return out


def scaled_for_margins(rig: DiscreteRig, make, gm_min: float = 6.0, pm_min: float = 35.0, i: int = 0,
                       delay: int = 1) -> float:
    """Largest gain factor g (bisection on log g) for which `make(g)` (a controller) closes mount i's loop
    stably with GM >= gm_min and PM >= pm_min. Used for the 'PI alone' comparison (Fig. 10)."""
    def ok(g):
        r = siso(rig, make(g), i, delay)
        mg = r["margins"]
        return mg.stable and mg.gain_margin_db >= gm_min and mg.phase_margin_deg >= pm_min
    lo, hi = 1e-4, 1.0
    if ok(hi):
        return hi
    if not ok(lo):
        return math.nan
    for _ in range(40):
        mid = math.sqrt(lo * hi)
        lo, hi = (mid, hi) if ok(mid) else (lo, mid)
    return lo
