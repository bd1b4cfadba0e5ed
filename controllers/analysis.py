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
import weakref
from dataclasses import dataclass, replace

import numpy as np

from rig.config import MOUNTS
from sim_backend.machine import ModalModel, modal_model_from_config
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

    def __init__(self, cfg, dt: float, f_hz: np.ndarray | None = None, ground: str | None = "continuous", *,
                 modal=None, valve_gain=None, mounts=None):
        """modal: a ModalModel instead of the configured one (perturbed_modal); valve_gain: per-mount factors on
        the valve input (an actuator's gain off its model); mounts: per-mount factors on the actuators'
        parameters (rig_state_space); ground=None skips the ground responses."""
        self.cfg = cfg
        self.dt = dt
        self.ground = ground
        self.ss = rig_state_space(cfg, modal, mounts)
        if valve_gain is not None:
            g = np.ones(self.ss.B.shape[1])
            g[0:4] = valve_gain
            self.ss = replace(self.ss, B=self.ss.B * g[None, :])
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
        if ground is None:
            self.Gg = None
        elif ground == "held":
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


def channel_delays(delay) -> tuple[int, int]:
    """(accelerometer, stroke) delays in periods from a delay that is one for both (an int) or per channel (a
    pair: rig.config.channel_delays, the drivers' timing: the transducer's sample comes later than the
    accelerometers' conversion). The command's own delay is the accelerometers'."""
    if isinstance(delay, (tuple, list)):
        return int(delay[0]), max(int(delay[1]), int(delay[0]))
    return int(delay), int(delay)


def closed_loop_poles(rig: DiscreteRig, ctrls, loops=(0, 1, 2, 3), delay=1) -> np.ndarray:
    """Eigenvalues of the discrete interconnection: plant (ZOH) + controllers of `loops` (the others' valves
    nulled) + `delay` periods of computation delay per loop (a pair: the stroke's measurement comes the
    difference later still, a delay line before the controller). Stable iff all |z| < 1."""
    delay, ds = channel_delays(delay)
    extra = ds - delay                          # the stroke's delay line, before the controller
    Ad, Bu = rig.Ad, rig.Bd[:, 0:4]
    n = Ad.shape[0]
    blocks = [ctrls[i].ss() for i in loops]
    nk = sum(b[0].shape[0] for b in blocks) + (delay + extra) * len(loops)
    A = np.zeros((n + nk, n + nk))
    A[:n, :n] = Ad
    off = n
    N = n + nk
    for (Ak, Bk, Ck, Dk), i in zip(blocks, loops):
        m = Ak.shape[0]
        ik = slice(off, off + m)
        s0 = off + m + delay                                         # the stroke's delay line s1..s_extra
        # the controller's inputs as rows over the whole state: the accelerometer now, the stroke `extra` late
        Y = np.zeros((2, N))
        Y[0, :n] = rig.C[I_ACCEL + i]
        if extra:
            Y[1, s0 + extra - 1] = 1.0
            A[s0, :n] = rig.C[I_STROKE + i]
            for j in range(1, extra):
                A[s0 + j, s0 + j - 1] = 1.0
        else:
            Y[1, :n] = rig.C[I_STROKE + i]                           # (2, n): u has no feedthrough
        A[ik, ik] = Ak
        A[ik, :] += Bk @ Y
        if delay:
            d0 = off + m                                             # delay line d1..d_delay
            A[d0, ik] = Ck[0]
            A[d0, :] += (Dk @ Y)[0]
            for j in range(1, delay):
                A[d0 + j, d0 + j - 1] = 1.0
            A[:n, d0 + delay - 1] = Bu[:, i]
        else:
            A[:n, ik] += np.outer(Bu[:, i], Ck[0])
            A[:n, :] += np.outer(Bu[:, i], (Dk @ Y)[0])
        off += m + delay + extra
    if not np.all(np.isfinite(A)):      # a controller whose discretised coefficients overflowed
        return np.full(A.shape[0], np.inf)
    return np.linalg.eigvals(A)


SLOW_HZ = 0.5     # closed-loop poles below this are judged on the continuous-time twin
_CSS = weakref.WeakKeyDictionary()


def _css(ctrl):
    """ctrl.css(), once per controller object (python-control builds it slowly; robustness checks reuse it)."""
    if ctrl not in _CSS:
        _CSS[ctrl] = ctrl.css()
    return _CSS[ctrl]


def slow_poles_continuous(rig: DiscreteRig, ctrls, loops=(0, 1, 2, 3)) -> np.ndarray:
    """Closed-loop poles (1/s) below SLOW_HZ of the continuous plant with the controllers' continuous twins
    (IsolationController.css). Near z = 1 the discrete eigenvalues of the blend's and the PI's slow poles
    lose their digits (clustered poles, four identical loops), while at these frequencies the sampling and the
    delay do not matter; so the slow poles are judged here, the fast ones on the discrete loop."""
    A0, Bu = rig.ss.A, rig.ss.B[:, 0:4]
    n = A0.shape[0]
    blocks = [_css(ctrls[i]) for i in loops]
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
    if not np.all(np.isfinite(M)):
        return np.full(1, np.inf)         # overflowed coefficients: judged unstable
    ev = np.linalg.eigvals(M)
    return ev[np.abs(ev) < 2 * np.pi * SLOW_HZ]


def is_stable(rig: DiscreteRig, ctrls, loops=(0, 1, 2, 3), delay=1) -> tuple[bool, np.ndarray]:
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


def floor_accel(rig: DiscreteRig) -> np.ndarray:
    """What a floor accelerometer at a mount reads per metre of floor motion there: -w^2 (the floor moves
    continuously, so its sampled acceleration follows exactly for a sinusoid)."""
    return -(rig.w ** 2)


def siso(rig: DiscreteRig, ctrl, i: int, delay=1, ff=None) -> dict:
    """One mount's loop closed, the others nulled; ground at that mount. Returns L, transmissibilities.
    ff: that mount's FeedforwardFilter (its command, computed from the floor accelerometer with the same
    `delay`, is added to the feedback's); ctrl None: feedforward alone (no feedback loop). delay: periods, or
    (accelerometer, stroke) periods (channel_delays)."""
    da, ds = channel_delays(delay)
    zd, zs = rig.zi ** da, rig.zi ** (ds - da)               # the stroke comes ds - da periods later still
    P, G = rig.Pu, rig.Gg
    if ctrl is not None:
        K_a, K_s = ctrl.frf(rig.w)
        K_s = K_s * zs
        L = -zd * (K_a * P[:, I_ACCEL + i, i] + K_s * P[:, I_STROKE + i, i])
        drive = K_a * G[:, I_ACCEL + i, i] + K_s * G[:, I_STROKE + i, i]
    else:
        L = np.zeros_like(rig.zi)
        drive = np.zeros_like(rig.zi)
    if ff is not None:
        drive = drive + ff.frf(rig.w) * floor_accel(rig)
    u = zd * drive / (1 + L)
    tr_c = G[:, :, i] + P[:, :, i] * u[:, None]
    tr_p = G[:, :, i]
    if ctrl is None:
        return {"L": L, "tr_controlled": tr_c, "tr_passive": tr_p}
    stable, poles = is_stable(rig, [ctrl] * 4, loops=(i,), delay=delay)
    return {"L": L, "tr_controlled": tr_c, "tr_passive": tr_p, "poles": poles,
            "margins": margins(rig.f, L, stable)}


def mimo(rig: DiscreteRig, ctrls, delay=1, ffs=None, check_stability: bool = True) -> dict:
    """All four loops closed. TR for uniform ground ('uniform', all mounts in phase) and for ground at each
    mount in turn (tr_controlled[..., j]); plus det(I + L) for the generalised Nyquist view.
    ffs: one FeedforwardFilter per mount (each reads the floor accelerometer at its own mount); ctrls None:
    feedforward alone. delay: periods, or (accelerometer, stroke) periods (channel_delays)."""
    nf = len(rig.f)
    da, ds = channel_delays(delay)
    zd, zs = rig.zi ** da, rig.zi ** (ds - da)
    P, G = rig.Pu, rig.Gg
    I4 = np.eye(4)[None]
    if ctrls is not None:
        Ka = np.empty((nf, 4), dtype=complex)
        Ks = np.empty((nf, 4), dtype=complex)
        for i, c in enumerate(ctrls):
            Ka[:, i], Ks[:, i] = c.frf(rig.w)
        Ks *= zs[:, None]
        Pa, Ps = P[:, I_ACCEL:I_ACCEL + 4, :], P[:, I_STROKE:I_STROKE + 4, :]
        Ga, Gs = G[:, I_ACCEL:I_ACCEL + 4, :], G[:, I_STROKE:I_STROKE + 4, :]
        Lm = -zd[:, None, None] * (Ka[:, :, None] * Pa + Ks[:, :, None] * Ps)
        rhs = zd[:, None, None] * (Ka[:, :, None] * Ga + Ks[:, :, None] * Gs)
    else:
        Lm = np.zeros((nf, 4, 4), dtype=complex)
        rhs = np.zeros((nf, 4, 4), dtype=complex)
    if ffs is not None:
        F = np.stack([ff.frf(rig.w) for ff in ffs], axis=1)              # (nf, 4)
        rhs = rhs + (zd * floor_accel(rig))[:, None, None] * (F[:, :, None] * I4)
    U = np.linalg.solve(I4 + Lm, rhs)                       # (nf, 4 valves, 4 ground inputs)
    tr_c = G + np.einsum("fou,fug->fog", P, U)
    stable, poles = (is_stable(rig, ctrls, loops=(0, 1, 2, 3), delay=delay)
                     if ctrls is not None and check_stability else (ctrls is None, None))
    return {"L": Lm, "det": np.linalg.det(I4 + Lm), "tr_controlled": tr_c, "tr_passive": G,
            "tr_uniform_controlled": tr_c.sum(axis=2), "tr_uniform_passive": G.sum(axis=2),
            "tr_independent_controlled": np.sqrt(np.sum(np.abs(tr_c) ** 2, axis=2)),
            "tr_independent_passive": np.sqrt(np.sum(np.abs(G) ** 2, axis=2)),
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


def design_report(cfg, ctrls, dt: float, rig: DiscreteRig | None = None, delay: int = 1, ffs=None) -> dict:
    """Everything `rig design` prints: per-mount margins (classic and disk), MIMO stability, attenuation
    bands per mount (SISO view) and with all four loops closed (feedback; with ffs also feedforward alone and
    feedback + feedforward), plus the arrays for the figures under '_data'."""
    rig = rig or DiscreteRig(cfg, dt)
    mounts, att_t, att_q, data = {}, {}, {}, {"f": rig.f, "siso": {}, "rig": rig}
    for i, m in enumerate(MOUNTS):
        r = siso(rig, ctrls[i], i, delay)
        mg = r["margins"]
        alpha = disk_margin(r["L"])
        gm, pm = disk_gm_pm(alpha)
        mounts[m] = {"stable": mg.stable, "gain_margin_db": mg.gain_margin_db,
                     "phase_margin_deg": mg.phase_margin_deg, "gain_crossover_hz": mg.gain_crossover_hz,
                     "phase_crossover_hz": mg.phase_crossover_hz, "disk_margin": alpha,
                     "disk_gain_margin_db": gm, "disk_phase_margin_deg": pm,
                     "sensitivity_peak_db": float(20 * np.log10(np.max(np.abs(1 / (1 + r["L"])))))}
        att_t[m] = band_summary(rig.f, attenuation_db(r["tr_passive"][:, I_TABLE + 1],
                                                      r["tr_controlled"][:, I_TABLE + 1]))
        att_q[m] = band_summary(rig.f, attenuation_db(r["tr_passive"][:, I_TOOL + 1],
                                                      r["tr_controlled"][:, I_TOOL + 1]))
        data["siso"][m] = r
    mm = mimo(rig, ctrls, delay)
    data["mimo"] = mm
    views = {"feedback": mimo_summary(rig, mm)}
    if ffs is not None:
        data["mimo_ff"] = mimo(rig, None, delay, ffs=ffs)
        data["mimo_fbff"] = mimo(rig, ctrls, delay, ffs=ffs, check_stability=False)
        views["feedforward"] = mimo_summary(rig, data["mimo_ff"])
        views["feedback_feedforward"] = mimo_summary(rig, data["mimo_fbff"])
        data["siso_fbff"] = {m: siso(rig, ctrls[i], i, delay, ff=ffs[i]) for i, m in enumerate(MOUNTS)}
    return {"mounts": mounts, "mimo_stable": mm["stable"],
            "mimo_disk_margin": disk_margin_mimo(mm["L"]),
            "attenuation_db": {"ground_to_table": att_t, "ground_to_tool": att_q}, "mimo": views,
            "_data": data}


def sensitivity_integral(f: np.ndarray, L: np.ndarray, split_hz: float = 100.0) -> dict:
    """Bode's sensitivity integral of a discrete loop on the grid f (Hz, up to Nyquist): the area of
    ln|S| (Hz x nepers) below and above split_hz. For a stable L with a delay it sums to zero (the
    attenuation bought below split_hz is paid back above it), so the split shows where the price is paid."""
    lnS = np.log(np.abs(1.0 / (1.0 + L)))
    lo = f <= split_hz
    area = lambda m: float(np.trapezoid(lnS[m], f[m]))                # noqa: E731
    hi = ~lo
    above = f[hi][lnS[hi] > 0]
    return {"below_hz_nepers": area(lo), "above_hz_nepers": area(hi), "total_hz_nepers": area(np.ones_like(lo)),
            "split_hz": split_hz, "peak_db": float(20 * np.max(lnS) / math.log(10)),
            "peak_hz": float(f[int(np.argmax(lnS))]),
            "amplified_from_hz": float(above.min()) if len(above) else math.nan,
            "amplified_to_hz": float(above.max()) if len(above) else math.nan}


def mimo_summary(rig: DiscreteRig, mm: dict) -> dict:
    """Attenuation bands with all four loops closed: uniform ground (the same floor motion at every mount),
    independent ground (uncorrelated motion of equal spectrum at each mount: the table's response adds in
    power, sqrt(sum_j |TR_j|^2)), and ground at each mount in turn."""
    out = {"uniform": {}, "independent": {}, "per_mount": {}}
    for name, o in (("table", I_TABLE + 1), ("tool", I_TOOL + 1)):
        out["uniform"][f"ground_to_{name}"] = band_summary(
            rig.f, attenuation_db(mm["tr_uniform_passive"][:, o], mm["tr_uniform_controlled"][:, o]))
        out["independent"][f"ground_to_{name}"] = band_summary(
            rig.f, attenuation_db(mm["tr_independent_passive"][:, o], mm["tr_independent_controlled"][:, o]))
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


# ---- margins as disks, robustness ----------------------------------------------------------------------

def disk_margin(L: np.ndarray) -> float:
    """Balanced disk margin alpha of a SISO return ratio on a grid: 1 / max |S - 1/2|, S = 1/(1 + L).

    The loop stays stable for any simultaneous gain and phase change f with |(f - 1)/(f + 1)| < alpha/2, i.e.
    gain within [(1 - alpha/2)/(1 + alpha/2), (1 + alpha/2)/(1 - alpha/2)] and phase within +-2 atan(alpha/2)
    (MATLAB's diskmargin with skew 0). alpha = 2/3 guarantees GM >= 6.02 dB and PM >= 36.9 deg at once."""
    return float(1.0 / np.max(np.abs(1.0 / (1.0 + L) - 0.5)))


def disk_margin_mimo(Lm: np.ndarray) -> float:
    """Multiloop balanced disk margin of a (nf, n, n) return ratio: 1 / max sigma_max(S - I/2). Guarantees
    stability for independent simultaneous gain/phase changes in every loop within the disk of that size."""
    n = Lm.shape[1]
    S = np.linalg.inv(np.eye(n)[None] + Lm)
    return float(1.0 / np.max(np.linalg.svd(S - 0.5 * np.eye(n)[None], compute_uv=False)[:, 0]))


def disk_gm_pm(alpha: float) -> tuple[float, float]:
    """(gain margin dB, phase margin deg) guaranteed by a balanced disk margin alpha."""
    a = 0.5 * alpha
    gm = 20 * math.log10((1 + a) / (1 - a)) if a < 1 else math.inf
    return gm, math.degrees(2 * math.atan(a))


def perturbed_modal(modal: ModalModel, factors) -> ModalModel:
    """The machine with every mode's frequency times factors[r] (modes in ModalModel order, rigid-body first).

    Flexible modes: w_n scaled. Rigid-body modes (0 Hz free, ~250-320 Hz on the actuators' stiffness): their
    mass-normalised shapes scaled by the factor, i.e. the modal mass by 1/factor^2, so their frequency on the
    actuators moves by about the factor (+10 % on all three moves the coupled ~250-280 Hz modes by 6-10 %:
    they mix with each other and with the flexible modes through the mounts)."""
    k = np.asarray(factors, dtype=float)
    if k.shape != modal.w_n.shape:
        raise ValueError(f"{len(modal.w_n)} mode factors expected, got {k.shape}")
    rigid = modal.w_n == 0
    shape = np.where(rigid, k, 1.0)[:, None]
    return ModalModel(modal.names, modal.w_n * np.where(rigid, 1.0, k), modal.zeta, modal.phi_mounts * shape,
                      modal.phi_table * shape, modal.phi_tool * shape, modal.mass_kg, modal.source)


def _fast_decay(rig: "DiscreteRig", ctrls, loops, delay: int = 1) -> float:
    """Slowest decay rate (1/s) of the fast closed-loop poles (|s| >= 2 pi SLOW_HZ): > 0 means stable there."""
    z = closed_loop_poles(rig, ctrls, loops, delay).astype(complex)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.log(z) / rig.dt
    fast = np.abs(s) >= 2 * np.pi * SLOW_HZ
    return float(-np.max(s[fast].real))


def robust_check(cfg, dt: float, ctrls, *, gain_tol: float = 0.3, mode_tol: float = 0.1, n_random: int = 200,
                 seed: int = 0, delay: int = 1, f_hz: np.ndarray | None = None, log=None) -> dict:
    """All four loops closed on plants off the model: every actuator's gain within +-gain_tol and every machine
    mode's frequency within +-mode_tol, independently.

    Draws: the 2^4 gain corners with the modes all low, nominal and all high (48), plus n_random uniform draws
    of all 4 + n_modes factors. For each: MIMO stability (closed-loop poles; slow ones on the continuous twin),
    the slowest fast-pole decay, the multiloop disk margin, and each mount's SISO GM/PM on that plant."""
    import itertools
    modal0 = modal_model_from_config(cfg)
    nm = len(modal0.w_n)
    f = np.geomspace(5.0, 0.49 / dt, 500) if f_hz is None else f_hz
    draws = []
    for g in itertools.product((1 - gain_tol, 1 + gain_tol), repeat=4):
        for m in (1 - mode_tol, 1.0, 1 + mode_tol):
            draws.append(("corner", np.array(g), np.full(nm, m)))
    rng = np.random.default_rng(seed)
    for _ in range(n_random):
        draws.append(("random", rng.uniform(1 - gain_tol, 1 + gain_tol, 4),
                      rng.uniform(1 - mode_tol, 1 + mode_tol, nm)))
    rows = []
    for k, (kind, g, m) in enumerate(draws):
        rig = DiscreteRig(cfg, dt, f, ground=None, modal=perturbed_modal(modal0, m), valve_gain=g)
        stable, _ = is_stable(rig, ctrls, delay=delay)
        Ka = np.empty((len(f), 4), dtype=complex)
        Ks = np.empty_like(Ka)
        da, ds = channel_delays(delay)
        for i, c in enumerate(ctrls):
            Ka[:, i], Ks[:, i] = c.frf(rig.w)
        Ks *= (rig.zi ** (ds - da))[:, None]
        zd = rig.zi ** da
        P = rig.Pu
        Lm = -zd[:, None, None] * (Ka[:, :, None] * P[:, I_ACCEL:I_ACCEL + 4, :]
                                   + Ks[:, :, None] * P[:, I_STROKE:I_STROKE + 4, :])
        siso_m = [margins(f, Lm[:, i, i], True) for i in range(4)]
        rows.append({"kind": kind, "gains": g.tolist(), "modes": m.tolist(), "stable": bool(stable),
                     "decay_1_per_s": _fast_decay(rig, ctrls, (0, 1, 2, 3), delay),
                     "disk_margin_mimo": disk_margin_mimo(Lm),
                     "gm_db": min(x.gain_margin_db for x in siso_m), "pm_deg": min(x.phase_margin_deg for x in siso_m)})
        if log and (k + 1) % 50 == 0:
            log(f"robust check: {k + 1}/{len(draws)} plants")
    worst = min(rows, key=lambda r: r["disk_margin_mimo"] if r["stable"] else -1.0)
    return {"gain_tol": gain_tol, "mode_tol": mode_tol, "corners": sum(r["kind"] == "corner" for r in rows),
            "random": sum(r["kind"] == "random" for r in rows), "all_stable": all(r["stable"] for r in rows),
            "unstable": sum(not r["stable"] for r in rows),
            "worst_decay_1_per_s": min(r["decay_1_per_s"] for r in rows),
            "worst_disk_margin_mimo": min(r["disk_margin_mimo"] for r in rows),
            "worst_siso_gm_db": min(r["gm_db"] for r in rows), "worst_siso_pm_deg": min(r["pm_deg"] for r in rows),
            "worst_plant": {"gains": worst["gains"], "modes": worst["modes"]}}


ACTUATOR_KEYS = {"K_L": "actuator", "C": "actuator", "w_nv": "valve", "zeta": "valve", "K_Q": "valve",
                 "K_C": "valve"}          # Eq. 11's x_d: the parameters an identification moves


def with_actuator(cfg, **values):
    """cfg with actuator/valve parameters (Eq. 11's x_d, SI) replaced: the plant a model error describes."""
    sec = {"actuator": {}, "valve": {}}
    for k, v in values.items():
        sec[ACTUATOR_KEYS[k]][k] = float(v)
    return cfg.replace(actuator=replace(cfg.actuator, **sec["actuator"]), valve=replace(cfg.valve, **sec["valve"]))


def model_error_check(cfg, dt: float, ctrls, ffs, *, tol: float = 0.1, n_random: int = 0, seed: int = 0,
                      delay: int = 1, log=None) -> dict:
    """The controllers and feedforward (designed on cfg's actuator) on plants whose actuator parameters
    (K_L, C, w_nv, zeta, K_Q, K_C) are each moved by +-tol: the 2^6 corners plus n_random uniform draws.
    Per plant: all four loops' stability, and the attenuation bands ground -> table with all loops closed,
    feedback alone and feedback + feedforward, uniform and independent floor. Returns the worst of each band
    over the plants, and the plant that gave the worst 1-100 Hz figure with feedforward."""
    import itertools
    f = np.unique(np.concatenate([np.geomspace(1.0, 100.0, 160), [1.0, 5.0, 10.0, 20.0, 60.0, 100.0]]))
    keys = list(ACTUATOR_KEYS)
    base = {k: getattr(cfg.actuator if ACTUATOR_KEYS[k] == "actuator" else cfg.valve, k) for k in keys}
    facs = [np.array(c) for c in itertools.product((1 - tol, 1 + tol), repeat=len(keys))]
    rng = np.random.default_rng(seed)
    facs += [rng.uniform(1 - tol, 1 + tol, len(keys)) for _ in range(n_random)]
    o = I_TABLE + 1
    worst = {}
    stable_all, worst_plant, worst_val = True, None, math.inf
    for n, fac in enumerate(facs):
        plant = with_actuator(cfg, **{k: base[k] * x for k, x in zip(keys, fac)})
        rig = DiscreteRig(plant, dt, f)
        for tag, ff in (("feedback", None), ("feedback_feedforward", ffs)):
            mm = mimo(rig, ctrls, delay, ffs=ff, check_stability=(ff is None))
            if ff is None:
                stable_all &= bool(mm["stable"])
            for view in ("uniform", "independent"):
                b = band_summary(f, attenuation_db(mm[f"tr_{view}_passive"][:, o], mm[f"tr_{view}_controlled"][:, o]))
                w = worst.setdefault(tag, {}).setdefault(view, {k: math.inf for k in b})
                for k, v in b.items():
                    w[k] = min(w[k], v)
                if tag == "feedback_feedforward" and view == "uniform" and b["min_1_100hz"] < worst_val:
                    worst_val = b["min_1_100hz"]
                    worst_plant = {k: float(x) for k, x in zip(keys, fac)}
        if log and (n + 1) % 32 == 0:
            log(f"model error check: {n + 1}/{len(facs)} plants")
    return {"tol": tol, "plants": len(facs), "corners": 2 ** len(keys), "random": n_random,
            "feedback_stable_all": stable_all, "worst_attenuation_db": worst,
            "worst_plant_factors": worst_plant}


def floor_psd(floor, f_hz: np.ndarray) -> np.ndarray:
    """One-sided PSD (m^2/Hz) of a FloorMotion's displacement at one mount (its filter, scaled to its rms)."""
    import scipy.signal
    fs = 1.0 / floor.dt
    _, h = scipy.signal.sosfreqz(floor.sos, worN=np.asarray(f_hz, dtype=float), fs=fs)
    return (floor.rms_m / floor.gain) ** 2 * np.abs(h) ** 2 / (0.5 * fs)


def floor_response_psd(S: np.ndarray, rho: float, tr: np.ndarray) -> np.ndarray:
    """PSD of one output under the floor motion of FloorMotion (PSD S at every mount, a part rho of it common
    to all four): tr (nf, 4) the output's responses to the ground at each mount."""
    return S * (rho * np.abs(tr.sum(1)) ** 2 + (1 - rho) * np.sum(np.abs(tr) ** 2, 1))


def worst_model_error(cfg, dt: float, ctrls, ffs, *, tol: float = 0.1, band_hz=(1.0, 100.0), n_f: int = 120,
                      delay: int = 1, log=None) -> tuple[dict, float]:
    """The corner of the six actuator parameters (K_L, C, w_nv, zeta, K_Q, K_C, each moved by +-tol) where the
    linear prediction of `rig demo`'s figure is lowest: the table's rms in band_hz from the floor motion, all
    four loops and the feedforward closed (designed on cfg), over the plant with those parameters.
    (factors by key, the predicted reduction in dB there)."""
    import itertools
    from sim_backend.rig_plant import FloorMotion
    f = np.geomspace(band_hz[0], band_hz[1], n_f)
    floor = FloorMotion.from_config(cfg, dt)
    S, rho, o = floor_psd(floor, f), floor.rho, I_TABLE + 1
    keys = list(ACTUATOR_KEYS)
    base = {k: getattr(cfg.actuator if ACTUATOR_KEYS[k] == "actuator" else cfg.valve, k) for k in keys}
    worst, worst_db = None, math.inf
    for n, fac in enumerate(itertools.product((1 - tol, 1 + tol), repeat=len(keys))):
        rig = DiscreteRig(with_actuator(cfg, **{k: base[k] * x for k, x in zip(keys, fac)}), dt, f)
        mm = mimo(rig, ctrls, delay, ffs=ffs, check_stability=False)
        ratio = (np.trapezoid(floor_response_psd(S, rho, rig.Gg[:, o, :]), f)
                 / np.trapezoid(floor_response_psd(S, rho, mm["tr_controlled"][:, o, :]), f))
        db = 10 * math.log10(ratio)
        if db < worst_db:
            worst, worst_db = dict(zip(keys, (float(x) for x in fac))), db
        if log and (n + 1) % 16 == 0:
            log(f"model error: {n + 1}/{2 ** len(keys)} corners")
    return worst, worst_db


def predicted_table_psd(cfg, dt: float, ctrls, ffs=None, f_hz: np.ndarray | None = None, *,
                        accel_noise_density: float | None = None, stroke_noise_m: float | None = None,
                        floor_accel_noise_density: float | None = None, delay=1) -> dict:
    """One-sided PSDs (m^2/Hz) of the table's vertical motion on the grid f_hz under the configured floor
    (FloorMotion: spectrum, rms, correlation rho between mounts), passive and with the loops (ctrls; None: open)
    and feedforward (ffs) closed, split by cause: the floor, and each sensor's noise.

    Sensor noise as RigPlant draws it: the mount accelerometers white at accel_noise_density (m/s^2/sqrt(Hz)),
    the stroke transducers white at stroke_noise_m per sample, the floor accelerometers (feedforward) white at
    floor_accel_noise_density (default: the mount accelerometers')."""
    from sim_backend.rig_plant import FloorMotion, RigPlant
    floor = FloorMotion.from_config(cfg, dt)
    f = np.geomspace(0.8, 120.0, 1500) if f_hz is None else np.asarray(f_hz, dtype=float)
    rig = DiscreteRig(cfg, dt, f)
    S = floor_psd(floor, f)
    rho = floor.rho
    o = I_TABLE + 1
    nd_a = RigPlant.ACCEL_NOISE_DENSITY if accel_noise_density is None else accel_noise_density
    nd_g = nd_a if floor_accel_noise_density is None else floor_accel_noise_density
    sx = 2e-8 if stroke_noise_m is None else stroke_noise_m

    def from_floor(tr):                                              # tr: (nf, 4 ground inputs)
        return floor_response_psd(S, rho, tr)
    out = {"f_hz": f, "passive": from_floor(rig.Gg[:, o, :])}
    if ctrls is None and ffs is None:
        return out
    mm = mimo(rig, ctrls, delay, ffs=ffs, check_stability=False)
    out["floor"] = from_floor(mm["tr_controlled"][:, o, :])
    da, ds = channel_delays(delay)
    zd = rig.zi ** da
    Sinv = np.linalg.inv(np.eye(4)[None] + mm["L"])                  # valves per injected command

    def from_noise(gain, psd):                                       # gain (nf, 4): command per noise unit
        t = np.einsum("fu,fuv,fv->fv", rig.Pu[:, o, :], Sinv, zd[:, None] * gain)
        return psd * np.sum(np.abs(t) ** 2, 1)
    zero = np.zeros_like(f)
    if ctrls is not None:
        out["accel_noise"] = from_noise(np.stack([c.frf(rig.w)[0] for c in ctrls], axis=1), nd_a ** 2)
        out["stroke_noise"] = from_noise(np.stack([c.frf(rig.w)[1] * rig.zi ** (ds - da) for c in ctrls], axis=1),
                                         sx ** 2 / (0.5 / dt))
    else:
        out["accel_noise"] = out["stroke_noise"] = zero
    out["floor_accel_noise"] = (from_noise(np.stack([ff.frf(rig.w) for ff in ffs], axis=1), nd_g ** 2)
                                if ffs is not None else zero)
    out["controlled"] = out["floor"] + out["accel_noise"] + out["stroke_noise"] + out["floor_accel_noise"]
    return out


def predicted_rms(cfg, dt: float, ctrls, ffs=None, *, band_hz=(1.0, 100.0), delay=1, **noise) -> dict:
    """Linear prediction of `rig demo`'s figure over the same floor realisation statistics: rms table motion
    (Y) in band_hz, passive and controlled, split by cause (predicted_table_psd), and the reduction in dB."""
    f = np.geomspace(band_hz[0], band_hz[1], 1200)
    p = predicted_table_psd(cfg, dt, ctrls, ffs, f, delay=delay, **noise)
    um = {k: math.sqrt(float(np.trapezoid(v, f))) * 1e6 for k, v in p.items() if k != "f_hz"}
    return {"band_hz": list(band_hz), "passive_um": um["passive"], "controlled_um": um["controlled"],
            "from_floor_um": um["floor"], "from_accel_noise_um": um["accel_noise"],
            "from_stroke_noise_um": um["stroke_noise"], "from_floor_accel_noise_um": um["floor_accel_noise"],
            "reduction_db": 20 * math.log10(um["passive"] / um["controlled"]),
            "reduction_noise_free_db": 20 * math.log10(um["passive"] / um["floor"])}
