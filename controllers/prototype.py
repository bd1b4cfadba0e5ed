"""The prototype's loops on its test stand, analysed as they run: the tracking loop (paper Fig. 4) and the
isolation loop, each on the discrete loop (ZOH, `delay` periods of computation) with the very controller
objects the runtime steps (controllers/tracking.py, controllers/isolation.py, controllers/modes.py).

  plant      the stand's linear physics (sim_backend/actuator.py stand_state_space: Eqs. 1, 3, 6, 7, the
             actuator's moving mass plus [layout] load_kg, the base mode of [stand] if on); the valve path
             sampled with a ZOH, the floor (base motion) continuous
  tracking   feedback loop L = C G z^-delay: bandwidth of T = L / (1 + L) (Fig. 4), gain and phase margins;
             with the reference feedforward F (previewed), r -> x_p = (L + G F) / (1 + L); the 2 um step and
             the 10 um 5 Hz sine run through the compiled law on the sampled plant (time domain)
  isolation  L = -(K_a G_acc + K_s G_pos) z^-delay: margins; floor -> load transmissibility x_p / x_g, and the
             load's motion under the [vibration] floor spectrum with isolation off (valve null) and on

`tune_isolation` designs the isolation controller for the stand (what drivers/devicemaps/prototype*.toml
carry); `tracking.tune_tracking` designs the PID. `python -m controllers.prototype --rate HZ --delay N`
prints both as a [controller] section. `rig design --layout prototype` prints the report and writes the
figures.
"""
from __future__ import annotations

import argparse
import math
from dataclasses import replace

import numpy as np
import scipy.linalg
import scipy.optimize
import scipy.signal

from controllers.isolation import IsolationController, params_from_config
from controllers.reference import parse_reference
from controllers.tracking import _R
from controllers.tracking import (TrackingPID, bandwidth_hz, loop_margins, track_step, tracking_from_config,
                                  tracking_response, tune_tracking)
from rig.config import Config, load_config
from sim_backend.actuator import Effects, stand_state_space
from sim_backend.linear import ActuatorParams

PAPER_BANDWIDTH_HZ = 95.0          # Fig. 4: ~95 Hz (-3 dB)


def stand_actuator(cfg: Config) -> ActuatorParams:
    """The actuator of the stand layout: Table 1 values of the config with [layout] load_kg on the piston."""
    return ActuatorParams.from_config(cfg, loaded_mass_kg=cfg.actuator.M + cfg.layout.load_kg)


class StandLoops:
    """The stand's sampled responses at frequencies f_hz: the valve path (ZOH at dt, `delay` periods) to the
    transducer and the accelerometer, and the floor path (continuous) to them and to the load."""

    def __init__(self, cfg: Config, dt: float, delay: int = 1) -> None:
        self.cfg, self.dt, self.delay = cfg, float(dt), int(delay)
        self.act = stand_actuator(cfg)
        self.fx = replace(Effects(), base_frequency_hz=cfg.stand.base_frequency_hz,
                          base_damping_ratio=cfg.stand.base_damping_ratio, base_mass_kg=cfg.stand.base_mass_kg)
        self.A, self.B, self.C, self.D = stand_state_space(self.act, self.fx)
        n = self.A.shape[0]
        big = np.zeros((n + 1, n + 1))
        big[:n, :n], big[:n, n] = self.A * dt, self.B[:, 0] * dt
        e = scipy.linalg.expm(big)
        self.Ad, self.Bd = e[:n, :n], e[:n, n]           # the valve path, command held over the period
        self._memo: dict = {}

    def valve(self, f_hz) -> tuple[np.ndarray, np.ndarray]:
        """(G_pos, G_acc): u -> transducer, u -> accelerometer, sampled, with the loop's delay."""
        key = ("valve", np.asarray(f_hz, dtype=float).tobytes())
        if key not in self._memo:
            self._memo[key] = self._valve(f_hz)
        return self._memo[key]

    def _valve(self, f_hz):
        z = np.exp(2j * np.pi * np.asarray(f_hz, dtype=float) * self.dt)
        n = self.Ad.shape[0]
        out = np.array([self.C[:2] @ np.linalg.solve(zk * np.eye(n) - self.Ad, self.Bd) for zk in z])
        d = z ** (-self.delay)
        return out[:, 0] * d, out[:, 1] * d

    def floor(self, f_hz) -> np.ndarray:
        """(len(f), 3): x_g -> transducer, accelerometer, load x_p (continuous; v_g = j w x_g)."""
        key = ("floor", np.asarray(f_hz, dtype=float).tobytes())
        if key not in self._memo:
            self._memo[key] = self._floor(f_hz)
        return self._memo[key]

    def _floor(self, f_hz):
        w = 2 * np.pi * np.asarray(f_hz, dtype=float)
        n = self.A.shape[0]
        out = []
        for wk in w:
            bg = self.B[:, 1] + 1j * wk * self.B[:, 2]
            x = np.linalg.solve(1j * wk * np.eye(n) - self.A, bg)
            out.append(self.C @ x + self.D[:, 1] + 1j * wk * self.D[:, 2])
        return np.array(out)

    def simulate(self, law, n: int) -> np.ndarray:
        """The transducer over n periods with u_k = law(k, position_k) applied `delay` periods later (the
        runtime's ordering: read, compute, the command acts from the next period on)."""
        x = np.zeros(self.Ad.shape[0])
        pipe = [0.0] * self.delay
        pos = np.empty(n)
        for k in range(n):
            pos[k] = self.C[0] @ x
            pipe.append(law(k, pos[k]))
            x = self.Ad @ x + self.Bd * pipe.pop(0)
        return pos


# ---- tracking ----------------------------------------------------------------------------------------------
def tracking_report(cfg: Config, dt: float, delay: int = 1, loops: StandLoops | None = None) -> dict:
    """Fig. 4 on the stand: the PID's closed loop (bandwidth, margins, peak), the same with the reference
    feedforward, and two runs of the compiled law on the sampled plant (2 um step, 10 um 5 Hz sine)."""
    loops = loops or StandLoops(cfg, dt, delay)
    act = loops.act
    c = tracking_from_config(cfg, dt, act=act)
    f = np.geomspace(0.5, 0.999 / (2 * dt), 3000)
    T = tracking_response(act, c, f, delay)
    Tff = tracking_response(act, c, f, delay, feedforward=True)
    gm, pm = loop_margins(act, c, f, delay)
    step = _step_run(c, loops, 2e-6)
    sine = _sine_run(c, loops, 10e-6, 5.0)
    return {"rate_hz": 1 / dt, "delay_periods": delay, "preview_periods": c.preview,
            "bandwidth_hz": bandwidth_hz(f, T), "bandwidth_ff_hz": bandwidth_hz(f, Tff),
            "gain_margin_db": gm, "phase_margin_deg": pm, "peak_db": float(np.max(20 * np.log10(np.abs(T)))),
            "hold_range_um": c.hold_range_m() * 1e6, "step_2um": step, "sine_10um_5hz": sine,
            "paper_bandwidth_hz": PAPER_BANDWIDTH_HZ, "_f": f, "_T": T, "_Tff": Tff}


def _run(c: TrackingPID, loops: StandLoops, ref_text: str, seconds: float):
    """The compiled law on the sampled plant from rest, then the request: (t, reference, position, command)."""
    st = np.asarray(c.apply(c.take_over(c.initial_state(), 0.0, 0.0), parse_reference(ref_text, c.dt)),
                    dtype=np.float64)
    cf = c.coefficients()
    n = int(round(seconds / c.dt))
    r, u = np.empty(n), np.empty(n)

    def law(k, x):
        u[k] = track_step(st, cf, x)
        r[k] = st[_R]
        return u[k]
    pos = loops.simulate(law, n)
    return np.arange(n) * c.dt, r, pos, u


def _step_run(c: TrackingPID, loops: StandLoops, amp_m: float) -> dict:
    t, r, x, u = _run(c, loops, f"step:amp={amp_m!r}m", 0.08)
    return step_figures(t, x, u, amp_m, c.p.limit_V)


def step_figures(t, x, u, amp_m: float, limit_V: float) -> dict:
    """A step's settling time to 2 % of the final value (from the request at t[0]), overshoot, peak command."""
    final = amp_m
    out = np.abs(x - final) > 0.02 * abs(amp_m)
    k = int(np.nonzero(out)[0][-1]) + 1 if out.any() else 0
    settle = float(t[k] - t[0]) if k < len(t) else math.inf
    return {"amplitude_um": amp_m * 1e6, "settling_2pct_ms": settle * 1e3,
            "overshoot_pct": max(0.0, float(np.max(x) - final) / abs(amp_m) * 100),
            "peak_command_V": float(np.max(np.abs(u))), "at_clamp": bool(np.any(np.abs(u) >= limit_V))}


def _sine_run(c: TrackingPID, loops: StandLoops, amp_m: float, f_hz: float) -> dict:
    t, r, x, u = _run(c, loops, f"sine:amp={amp_m!r}m,freq={f_hz!r}", 2.0)
    sel = t >= 1.0                       # after the fade-in, whole cycles
    e = r[sel] - x[sel]
    return {"amplitude_um": amp_m * 1e6, "frequency_hz": f_hz, "rms_error_um": float(np.sqrt(np.mean(e ** 2))) * 1e6,
            "rms_error_pct": float(np.sqrt(np.mean(e ** 2))) / amp_m * 100, "peak_command_V": float(np.max(np.abs(u)))}


# ---- isolation ---------------------------------------------------------------------------------------------
def isolation_report(cfg: Config, dt: float, delay: int = 1, loops: StandLoops | None = None,
                     ctrl: IsolationController | None = None) -> dict:
    """The isolation controller of the config on the stand: stability margins, the floor -> load
    transmissibility, and the load's rms motion under the [vibration] floor spectrum (plus the sensors'
    noise through the loop), valve null against isolating."""
    loops = loops or StandLoops(cfg, dt, delay)
    ctrl = ctrl or IsolationController(params_from_config(cfg, 0), dt)
    f = np.geomspace(0.05, 0.999 / (2 * dt), 3000)
    L, Tiso, Tpass = _isolation_frf(loops, ctrl, f)
    gm, pm, gc = _margins(f, L)
    band = (f >= 1.0) & (f <= 100.0)
    floor_psd = _floor_psd(cfg, f)
    off = math.sqrt(np.trapezoid(floor_psd * np.abs(Tpass) ** 2, f))
    on = math.sqrt(np.trapezoid(floor_psd * np.abs(Tiso) ** 2, f) + _noise_var(cfg, loops, ctrl, f))
    att = 20 * np.log10(np.abs(Tpass) / np.abs(Tiso))
    at = {f"{h:g}hz": float(np.interp(h, f, att)) for h in (1, 5, 10, 20, 50, 100)}
    closed_stable = bool(np.all(np.abs(np.linalg.eigvals(_closed_loop_matrix(loops, ctrl))) < 1.0))
    return {"stable": closed_stable, "gain_margin_db": gm, "phase_margin_deg": pm, "gain_crossover_hz": gc,
            "attenuation_db": at, "min_attenuation_1_100hz_db": float(np.min(att[band])),
            "load_rms_off_um": off * 1e6, "load_rms_on_um": on * 1e6,
            "isolation_db": 20 * math.log10(off / on) if on > 0 else math.inf,
            "_f": f, "_L": L, "_Tiso": Tiso, "_Tpass": Tpass}


def _isolation_frf(loops: StandLoops, ctrl: IsolationController, f):
    Gp, Ga = loops.valve(f)
    Ka, Ks = ctrl.frf(2 * np.pi * f)
    H = loops.floor(f)                         # x_g -> (pos, acc, x_p)
    L = -(Ka * Ga + Ks * Gp)
    u = (Ka * H[:, 1] + Ks * H[:, 0]) / (1 + L)   # u per x_g (u = K y, y = G u + H x_g)
    Tiso = H[:, 2] + Gp * u                    # the valve moves the load as it moves the transducer
    return L, Tiso, H[:, 2]


def _margins(f, L):
    mag, ph = np.abs(L), np.unwrap(np.angle(L))
    i = np.nonzero((mag[:-1] >= 1) & (mag[1:] < 1))[0]
    gc = float(f[i[-1]]) if len(i) else math.nan
    pm = 180.0 + math.degrees(ph[i[-1]]) if len(i) else math.inf
    pm = (pm + 180.0) % 360.0 - 180.0
    j = np.nonzero((ph[:-1] > -math.pi) & (ph[1:] <= -math.pi))[0]
    j = j[f[j] > (gc if math.isfinite(gc) else 0.0)]
    gm = -20 * math.log10(mag[j[0]]) if len(j) else math.inf
    return gm, pm, gc


def _floor_psd(cfg: Config, f):
    """One-sided PSD [m^2/Hz] of the [vibration] floor displacement (its band-pass, scaled to rms_m)."""
    v = cfg.vibration
    fs = 5000.0
    sos = scipy.signal.butter(4, (v.band_lo_hz, v.band_hi_hz), btype="bandpass", fs=fs, output="sos")
    if v.spectrum == "velocity_flat":
        sos = np.vstack([sos, scipy.signal.butter(1, v.band_lo_hz, fs=fs, output="sos")])
    _, h = scipy.signal.sosfreqz(sos, worN=np.asarray(f, dtype=float), fs=fs)
    p = np.abs(h) ** 2
    return p * v.rms_m ** 2 / np.trapezoid(p, f)


def _noise_var(cfg: Config, loops: StandLoops, ctrl: IsolationController, f) -> float:
    """The load motion the loop makes of the sensors' white noise ([stand] position and accel noise rms)."""
    Gp, Ga = loops.valve(f)
    Ka, Ks = ctrl.frf(2 * np.pi * f)
    L = -(Ka * Ga + Ks * Gp)
    fn = 0.5 / loops.dt
    var = 0.0
    for sd, K in ((cfg.stand.position_noise_m, Ks), (cfg.stand.accel_noise_mps2, Ka)):
        psd = sd ** 2 / fn
        var += np.trapezoid(psd * np.abs(Gp * K / (1 + L)) ** 2, f)
    return float(var)


def _closed_loop_matrix(loops: StandLoops, ctrl: IsolationController) -> np.ndarray:
    """The closed loop's state matrix (plant, delay line, controller) for its eigenvalues."""
    Ad, Bd = loops.Ad, loops.Bd
    Cp, Ca = loops.C[0], loops.C[1]
    Ak, Bk, Ck, Dk = ctrl.ss()
    n, m, d = Ad.shape[0], Ak.shape[0], loops.delay
    N = n + d + m
    A = np.zeros((N, N))
    Y = np.vstack([Ca, Cp])                      # controller inputs (accel, stroke) from the plant state
    A[:n, :n] = Ad
    if d:
        A[:n, n + d - 1] = Bd                    # the oldest command in the delay line acts
        A[n, :n] = Dk @ Y
        A[n, n + d:] = Ck
        for i in range(1, d):
            A[n + i, n + i - 1] = 1.0
    else:
        A[:n, :n] += np.outer(Bd, Dk @ Y)
        A[:n, n:] += np.outer(Bd, Ck)
    A[n + d:, :n] = Bk @ Y
    A[n + d:, n + d:] = Ak
    return A


def tune_isolation(cfg: Config, dt: float, delay: int = 1, *, min_gm_db: float = 6.0, min_pm_deg: float = 45.0,
                   progress=None) -> dict:
    """The isolation controller's [controller] values for the stand: the PI's corner on the actuator's lag
    corner makes the loop an integrator (as the tracking PID does, ~kp K_v K_Q/A_p / s); a lag/lead section
    (lead1) adds low-frequency gain, lead2 phase at the crossover, a roll-off keeps the noise out. Gain, blend
    and corners are chosen (Nelder-Mead, from a stable start) for the least load motion under the floor
    spectrum and the sensors' noise, with GM >= min_gm_db and PM >= min_pm_deg on the discrete loop."""
    loops = StandLoops(cfg, dt, delay)
    base = params_from_config(cfg, 0)
    act = loops.act
    lag_hz = act.lag_corner / (2 * math.pi)
    fn = 0.5 / dt
    cross = min(25.0, 0.05 * fn)                  # a first crossover well inside the valve and the delay
    names = ("kp_V_per_m", "pi_corner_hz", "blend_hz", "lead1_zero_hz", "lead1_pole_hz", "lead2_zero_hz",
             "lead2_pole_hz", "rolloff_hz")
    starts = [np.log([2 * math.pi * c * cross / (act.K_v * act.K_Q / act.A_p), lag_hz, blend, 2 * cross,
                      2 * cross, 2 * cross, 12 * cross, min(0.4 * fn, 40 * cross)])
              for blend in (0.2, 1.0, 3.0) for c in (1.0, 0.5)]

    def params(x):
        v = dict(zip(names, np.exp(x)))
        v["rolloff_hz"] = min(v["rolloff_hz"], 0.45 * fn)
        v["lead2_pole_hz"] = min(v["lead2_pole_hz"], 0.45 * fn)
        v["lead1_pole_hz"] = min(v["lead1_pole_hz"], 0.45 * fn)
        return base.with_(notch_hz=0.0, prewarp_hz=min(cross, 0.2 * fn), **v)

    def cost(x):
        try:
            c = IsolationController(params(x), dt)
            r = isolation_report(cfg, dt, delay, loops, c)
        except (ValueError, np.linalg.LinAlgError):
            return 1e6
        if not r["stable"]:
            return 1e6
        pen = max(0.0, min_gm_db + 0.5 - r["gain_margin_db"]) + max(0.0, (min_pm_deg + 2 - r["phase_margin_deg"]) / 5)
        return math.log(r["load_rms_on_um"]) + 10 * pen

    best = None
    for x0 in starts:                             # from a stable start (at low rates the sampled
        if cost(x0) >= 1e6:                       # accelerometer makes some conditionally stable)
            continue
        r = scipy.optimize.minimize(cost, x0, method="Nelder-Mead", options={"maxiter": 600, "xatol": 1e-3,
                                                                           "fatol": 1e-4})
        if progress:
            progress(f"isolation design from blend {math.exp(x0[2]):g} Hz: cost {r.fun:.3f}")
        if best is None or r.fun < best.fun:
            best = r
    if best is None:
        raise ValueError(f"no stable isolation design found at {1 / dt:g} Hz with {delay} period(s) of delay")
    p = params(best.x)
    keys = ("blend_hz", "kp_V_per_m", "pi_corner_hz", "lead1_zero_hz", "lead1_pole_hz", "lead2_zero_hz",
            "lead2_pole_hz", "rolloff_hz", "rolloff_zeta", "notch_hz", "prewarp_hz")
    return {k: float(getattr(p, k)) for k in keys}


def design_report(cfg: Config, dt: float, delay: int = 1) -> dict:
    """Both loops of the prototype on its stand (rig design --layout prototype)."""
    loops = StandLoops(cfg, dt, delay)
    return {"tracking": tracking_report(cfg, dt, delay, loops), "isolation": isolation_report(cfg, dt, delay, loops)}


def tune(cfg: Config, dt: float, delay: int = 1, bandwidth_hz: float = 100.0, progress=None) -> dict:
    """Both loops tuned for the stand at this rate and delay: the [controller] values (isolation, then the
    tracking PID of Fig. 4 for bandwidth_hz), ready for a config file."""
    pid = tune_tracking(stand_actuator(cfg), dt, bandwidth_hz, cfg.safety.valve_limit_V, cfg.safety.slew_V_per_s,
                        delay, noise_m=cfg.stand.position_noise_m)
    out = tune_isolation(cfg, dt, delay, progress=progress)
    out.update(track_kp_V_per_m=pid.kp_V_per_m, track_ki_V_per_ms=pid.ki_V_per_ms, track_kd_Vs_per_m=pid.kd_Vs_per_m,
               track_deriv_hz=pid.deriv_hz, track_delay_periods=int(delay))
    return out


def toml(values: dict) -> str:
    """The [controller] table of `tune`'s values."""
    return "[controller]\n" + "".join(f"{k} = {v}\n" if isinstance(v, int) else f"{k} = {v:.6g}\n"
                                      for k, v in values.items())


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(prog="python -m controllers.prototype",
                                 description="design the prototype's tracking and isolation controllers "
                                             "(as `rig design --layout prototype --tune`, at any rate and delay)")
    ap.add_argument("--config", default=None)
    ap.add_argument("--rate", type=float, default=5000.0)
    ap.add_argument("--delay", type=int, default=1)
    ap.add_argument("--bandwidth", type=float, default=100.0, help="tracking bandwidth target, Hz")
    a = ap.parse_args(argv)
    print(toml(tune(load_config(a.config), 1.0 / a.rate, a.delay, a.bandwidth)), end="")


if __name__ == "__main__":
    main()


def write_figures(rep: dict, out, cfg: Config, dt: float, delay: int = 1) -> list:
    """The report's figures as PNG in `out`: Fig. 4 on the stand (|T| and phase, PID alone and with the
    feedforward), the 2 um step and the isolation transmissibility. Returns the paths."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from pathlib import Path
    out = Path(out)
    tr, iso = rep["tracking"], rep["isolation"]
    paths = []
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(7.5, 6.5), sharex=True)
    for T, style, label in ((tr["_T"], dict(color="tab:blue"), f"PID (Fig. 4): {tr['bandwidth_hz']:.1f} Hz"),
                            (tr["_Tff"], dict(color="tab:orange", ls="--"),
                             f"with the reference feedforward: {tr['bandwidth_ff_hz']:.1f} Hz")):
        a1.semilogx(tr["_f"], 20 * np.log10(np.abs(T)), label=label, **style)
        a2.semilogx(tr["_f"], np.degrees(np.unwrap(np.angle(T))), **style)
    a1.axhline(-3, color="0.5", lw=0.8, ls=":")
    a1.axvline(PAPER_BANDWIDTH_HZ, color="0.5", lw=0.8, ls=":")
    a1.set_ylim(-20, 6)
    a1.set_ylabel("|x_p / r| [dB]")
    a2.set_ylabel("phase [deg]")
    a2.set_xlabel("frequency [Hz]")
    a1.legend(loc="lower left", fontsize=8)
    a1.set_title(f"tracking on the stand at {tr['rate_hz']:g} Hz: GM {tr['gain_margin_db']:.1f} dB, "
                 f"PM {tr['phase_margin_deg']:.0f} deg (paper Fig. 4: ~95 Hz)", fontsize=9)
    for a in (a1, a2):
        a.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    paths.append(out / "prototype_fig4_tracking.png")
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)
    loops = StandLoops(cfg, dt, delay)
    c = tracking_from_config(cfg, dt, act=loops.act)
    t, r, x, u = _run(c, loops, "step:amp=2um", 0.05)
    st = tr["step_2um"]
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(7.5, 5), sharex=True)
    a1.plot(t * 1e3, r * 1e6, color="tab:orange", ls="--", label="reference")
    a1.plot(t * 1e3, x * 1e6, color="tab:blue", label="position")
    a1.axhspan(2 * 0.98, 2 * 1.02, color="0.85")
    a1.set_ylabel("[um]")
    a1.legend(fontsize=8)
    a1.set_title(f"2 um step: settles within 2 % in {st['settling_2pct_ms']:.1f} ms, overshoot "
                 f"{st['overshoot_pct']:.1f} %, command peak {st['peak_command_V']:.2f} V", fontsize=9)
    a2.plot(t * 1e3, u, color="0.3")
    a2.set_ylabel("valve [V]")
    a2.set_xlabel("time since the request [ms]")
    for a in (a1, a2):
        a.grid(True, alpha=0.3)
    fig.tight_layout()
    paths.append(out / "prototype_step.png")
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)
    fig, a = plt.subplots(figsize=(7.5, 4.5))
    a.semilogx(iso["_f"], 20 * np.log10(np.abs(iso["_Tpass"])), color="0.5", label="valve null (passive)")
    a.semilogx(iso["_f"], 20 * np.log10(np.abs(iso["_Tiso"])), color="tab:green", label="isolating")
    a.set_xlim(0.1, 0.5 / dt)
    a.set_ylabel("floor -> load |x_p / x_g| [dB]")
    a.set_xlabel("frequency [Hz]")
    a.set_title(f"isolation on the stand: GM {iso['gain_margin_db']:.1f} dB, PM {iso['phase_margin_deg']:.0f} deg; "
                f"load rms {iso['load_rms_off_um']:.2f} -> {iso['load_rms_on_um']:.2f} um "
                f"({iso['isolation_db']:.1f} dB)", fontsize=9)
    a.legend(fontsize=8)
    a.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    paths.append(out / "prototype_isolation.png")
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)
    return paths


def clean(rep: dict) -> dict:
    """The report without its arrays (JSON)."""
    return {k: clean(v) if isinstance(v, dict) else v for k, v in rep.items() if not k.startswith("_")}
