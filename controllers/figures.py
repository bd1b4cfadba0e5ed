"""Figures and the Markdown report of `rig design --out DIR` (paper Figs. 4, 10-14, and beyond the paper)."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from controllers.analysis import (ACTUATOR_KEYS, BANDS, DiscreteRig, attenuation_db, disk_gm_pm, mimo,
                                  scaled_for_margins, siso, with_actuator)
from controllers.isolation import IsolationController, params_from_config
from controllers.tracking import TrackingPID, bandwidth_hz, pid_from_config, tracking_response
from controllers.vibration_criteria import plot_vc
from rig.config import MOUNTS
from sim_backend.linear import ActuatorParams
from sim_backend.rig_plant import I_TABLE, I_TOOL

BAND_LABELS = {"1hz": "1 Hz", "5_10hz": "5-10 Hz", "20_60hz": "20-60 Hz", "60_100hz": "60-100 Hz",
               "min_1_100hz": "min 1-100 Hz"}


def _plt():
    # matplotlib loads only when figures are drawn: `rig design` without --out never pays for it
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def _db(x):
    return 20 * np.log10(np.abs(x))


class _Saver:
    """Saves a figure into the output folder and keeps the files in the order written (design.md shows them
    in that order)."""

    def __init__(self, out: Path, plt) -> None:
        self.out, self.plt, self.files = out, plt, []

    def __call__(self, fig, name: str) -> None:
        p = self.out / name
        fig.tight_layout()
        fig.savefig(p, dpi=110)
        self.plt.close(fig)
        self.files.append(p)


def write_all(out: Path, cfg, dt, rig, ctrls, data, result, paper, log, ffs=None) -> list[Path]:
    """Every figure of the design (one function each, in the order design.md lists them), then design.md."""
    plt = _plt()
    save = _Saver(out, plt)
    f = rig.f
    band = (f >= 0.5) & (f <= 200)
    _nyquist_figure(save, plt, data, result)
    _ground_figures(save, plt, f, band, data, result)
    _cross_figure(save, plt, f, band, data)
    pi_note = _pi_figure(save, plt, cfg, dt, rig, band, data)
    _mimo_figure(save, plt, f, band, data, result)
    _sensitivity_figure(save, plt, f, dt, data, result)
    if ffs is not None:
        _feedforward_figures(save, plt, cfg, dt, rig, ctrls, ffs, data, result)
    bw = _tracking_figure(save, plt, cfg, dt)
    files = save.files
    (out / "design.md").write_text(markdown(result, paper, pi_note, bw, cfg, [p.name for p in files]))
    files.append(out / "design.md")
    return files


def _nyquist_figure(save, plt, data, result) -> None:
    """Fig. 11: Nyquist per mount, with the disk the tuner keeps L out of."""
    fig, axs = plt.subplots(2, 2, figsize=(10, 9))
    th = np.linspace(0, 2 * np.pi, 200)
    for ax, m in zip(axs.flat, MOUNTS):
        L = data["siso"][m]["L"]
        r = result["mounts"][m]
        ax.plot(L.real, L.imag, "b-", lw=1, label="L(e^{jwT})")
        ax.plot(L.real, -L.imag, "b:", lw=0.6)
        ax.plot(np.cos(th), np.sin(th), "k:", lw=0.6)
        ax.fill(-1.25 + 0.75 * np.cos(th), 0.75 * np.sin(th), color="r", alpha=0.12,
                label="excluded: disk margin 2/3")
        ax.plot([-1], [0], "r+", ms=12, mew=2)
        ax.set_xlim(-3, 3)
        ax.set_ylim(-3, 3)
        ax.set_aspect("equal")
        ax.set_xlabel("Re L")
        ax.set_ylabel("Im L")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="lower right")
        ax.set_title(f"{m}: GM {r['gain_margin_db']:.1f} dB, PM {r['phase_margin_deg']:.1f} deg, "
                     f"disk {r['disk_margin']:.2f}", fontsize=9)
    fig.suptitle("Nyquist, one mount's loop (others nulled), ZOH + 1 period delay (cf. paper Fig. 11)")
    save(fig, "fig11_nyquist.png")


def _ground_figures(save, plt, f, band, data, result) -> None:
    """Figs. 12, 13: ground -> table / tool (Y), passive vs controlled (feedback, feedback + feedforward)."""
    for fig_no, name, o in ((12, "table", I_TABLE + 1), (13, "tool", I_TOOL + 1)):
        fig, axs = plt.subplots(2, 2, figsize=(11, 8), sharex=True)
        for ax, m in zip(axs.flat, MOUNTS):
            r = data["siso"][m]
            ax.semilogx(f[band], _db(r["tr_passive"][band, o]), "k-", lw=1, label="passive")
            ax.semilogx(f[band], _db(r["tr_controlled"][band, o]), "b-", lw=1.2, label="feedback")
            if "siso_fbff" in data:
                ax.semilogx(f[band], _db(data["siso_fbff"][m]["tr_controlled"][band, o]), "g-", lw=1,
                            label="feedback + feedforward")
            a = result["attenuation_db"][f"ground_to_{name}"][m]
            ax.set_title(f"{m}: {a['1hz']:.1f} dB at 1 Hz, min {a['min_1_100hz']:.1f} dB (1-100 Hz)", fontsize=9)
            ax.set_ylabel(f"|x_{name}/x_g| [dB]")
            ax.grid(alpha=0.3, which="both")
            ax.legend(fontsize=8)
        for ax in axs[1]:
            ax.set_xlabel("frequency [Hz]")
        fig.suptitle(f"Ground at the mount -> {name} (Y), SISO view (cf. paper Fig. {fig_no})")
        save(fig, f"fig{fig_no}_ground_to_{name}.png")


def _cross_figure(save, plt, f, band, data) -> None:
    """Fig. 14: cross paths for the front-left mount."""
    r = data["siso"]["front_left"]
    fig, axs = plt.subplots(2, 2, figsize=(11, 8), sharex=True)
    for ax, (lab, o) in zip(axs.flat, (("table X", I_TABLE), ("tool X", I_TOOL), ("table Z", I_TABLE + 2),
                                       ("tool Z", I_TOOL + 2))):
        att = attenuation_db(r["tr_passive"][:, o], r["tr_controlled"][:, o])
        sel = (f >= 1) & (f <= 100)
        ax.semilogx(f[band], _db(r["tr_passive"][band, o]), "k-", lw=1, label="passive")
        ax.semilogx(f[band], _db(r["tr_controlled"][band, o]), "b-", lw=1.2, label="controlled")
        ax.set_title(f"ground (front_left) -> {lab}: min {np.min(att[sel]):.1f} dB (1-100 Hz)", fontsize=9)
        ax.set_ylabel(f"|{lab} / ground Y| [dB]")
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=8)
    for ax in axs[1]:
        ax.set_xlabel("frequency [Hz]")
    fig.suptitle("Cross transmissibilities, front-left mount (cf. paper Fig. 14)")
    save(fig, "fig14_cross_front_left.png")


def _pi_figure(save, plt, cfg, dt, rig, band, data) -> str:
    """Fig. 10: PI alone vs PI + compensator (front-left, tool Y); returns the note for design.md."""
    f = rig.f
    r = data["siso"]["front_left"]
    p0 = params_from_config(cfg, 0)

    def make(g):
        return IsolationController(p0.with_(kp_V_per_m=p0.kp_V_per_m * g), dt, compensator=False)
    g = scaled_for_margins(rig, make)
    fig, ax = plt.subplots(figsize=(8, 5))
    o = I_TOOL + 1
    ax.semilogx(f[band], _db(r["tr_passive"][band, o]), "k-", lw=1, label="passive")
    pi_note = "PI alone: no stable gain found"
    if math.isfinite(g):
        rp = siso(rig, make(g), 0)
        att = attenuation_db(rp["tr_passive"][:, o], rp["tr_controlled"][:, o])
        sel = (f >= 1) & (f <= 100)
        pi_note = (f"PI alone (Kp x {g:.3g} for GM >= 6 dB, PM >= 35 deg): {att[np.argmin(abs(f - 1))]:.1f} dB "
                   f"at 1 Hz, min {np.min(att[sel]):.1f} dB")
        ax.semilogx(f[band], _db(rp["tr_controlled"][band, o]), "g-", lw=1.2, label="PI alone")
    ax.semilogx(f[band], _db(r["tr_controlled"][band, o]), "b-", lw=1.2, label="PI + compensator")
    ax.set_title(pi_note, fontsize=9)
    ax.set_xlabel("frequency [Hz]")
    ax.set_ylabel("|x_tool/x_g| [dB]")
    ax.grid(alpha=0.3, which="both")
    ax.legend()
    save(fig, "fig10_pi_vs_compensator.png")
    return pi_note


def _mimo_figure(save, plt, f, band, data, result) -> None:
    """All four loops closed: uniform and independent floor, feedback / feedforward / both, and the
    generalised Nyquist plot."""
    fig, axs = plt.subplots(1, 3, figsize=(16, 4.8))
    o = I_TABLE + 1
    mm = data["mimo"]
    views = [("feedback", mm, "b-")]
    if "mimo_fbff" in data:
        views += [("feedforward", data["mimo_ff"], "m--"), ("feedback + feedforward", data["mimo_fbff"], "g-")]
    for ax, key, lab in ((axs[0], "uniform", "same floor motion at every mount"),
                         (axs[1], "independent", "independent floor motion at each mount")):
        ax.semilogx(f[band], _db(mm[f"tr_{key}_passive"][band, o]), "k-", lw=1, label="passive")
        for name, d, st in views:
            tag = name.replace(" + ", "_")
            a = result["mimo"][tag][key]["ground_to_table"]["min_1_100hz"]
            ax.semilogx(f[band], _db(d[f"tr_{key}_controlled"][band, o]), st, lw=1.1,
                        label=f"{name} (min {a:.1f} dB)")
        ax.set_title(f"table Y, all four loops closed: {lab}", fontsize=9)
        ax.set_xlabel("frequency [Hz]")
        ax.set_ylabel("|x_table / x_g| [dB]")
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=7)
    d = mm["det"] - 1.0
    axs[2].plot(d.real, d.imag, "b-", lw=1)
    axs[2].plot([-1], [0], "r+", ms=12, mew=2)
    axs[2].set_xlim(-4, 4)
    axs[2].set_ylim(-4, 4)
    axs[2].set_aspect("equal")
    axs[2].set_xlabel("Re (det(I+L) - 1)")
    axs[2].set_ylabel("Im (det(I+L) - 1)")
    axs[2].grid(alpha=0.3)
    axs[2].set_title(f"generalised Nyquist det(I+L)-1; stable={mm['stable']}", fontsize=9)
    save(fig, "mimo_transmissibility.png")


def _sensitivity_figure(save, plt, f, dt, data, result) -> None:
    """Sensitivity per mount: where the attenuation is paid back (Bode's integral)."""
    fig, ax = plt.subplots(figsize=(9, 5))
    for m in MOUNTS:
        ax.semilogx(f, _db(1 / (1 + data["siso"][m]["L"])), lw=1, label=m)
    ax.axhline(20 * math.log10(2.0), color="r", ls=":", lw=1, label="|S| = 2 (bound from disk margin 2/3)")
    ax.axvline(100, color="0.5", ls=":", lw=0.8)
    si = result["sensitivity_integral"]["front_left"]
    ax.set_title(f"|S| = |1/(1+L)|; front-left: area of ln|S| below 100 Hz {si['below_hz_nepers']:.0f} Hz Np, "
                 f"above {si['above_hz_nepers']:.0f} Hz Np", fontsize=9)
    ax.set_xlabel("frequency [Hz]")
    ax.set_ylabel("|S| [dB]")
    ax.set_xlim(0.5, 0.5 / dt)
    ax.set_ylim(-45, 12)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    save(fig, "sensitivity.png")


def _tracking_figure(save, plt, cfg, dt) -> float:
    """Fig. 4: actuator alone, reference tracking PID; returns its bandwidth in Hz."""
    pid = TrackingPID(pid_from_config(cfg), dt)
    ft = np.geomspace(0.5, 1000, 800)
    T = tracking_response(ActuatorParams.from_config(cfg), pid, ft)
    bw = bandwidth_hz(ft, T)
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    a1.semilogx(ft, _db(T))
    a1.axhline(-3, color="k", ls=":")
    a1.set_ylabel("|x_p / x_ref| [dB]")
    a1.set_title(f"actuator alone, PID tracking: bandwidth {bw:.1f} Hz (paper Fig. 4: ~95 Hz)")
    a2.semilogx(ft, np.degrees(np.unwrap(np.angle(T))))
    a2.set_ylabel("phase [deg]")
    a2.set_xlabel("frequency [Hz]")
    for a in (a1, a2):
        a.grid(alpha=0.3, which="both")
    save(fig, "fig4_tracking.png")
    return bw


def _feedforward_figures(save, plt, cfg, dt, rig, ctrls, ffs, data, result):
    """The feedforward filter against the inverse it approximates; feedback + feedforward on the nominal plant
    and on the worst plant of the +-10 % model-error check; the predicted VC curves."""
    f = rig.f
    band = (f >= 0.5) & (f <= 300)
    fig, axs = plt.subplots(1, 3, figsize=(16, 4.8))
    F = ffs[0].frf(rig.w)
    ax = axs[0]
    ax.loglog(f[band], np.abs(F[band]), "g-", lw=1.2, label="|u_ff / a_g| (discrete)")
    ax.set_xlabel("frequency [Hz]")
    ax.set_ylabel("V per m/s^2")
    ax.grid(alpha=0.3, which="both")
    ax.set_title(f"feedforward filter, mount 1 (lead {ffs[0].tau_s * 1e3:.2f} ms, roll-off "
                 f"{ffs[0].p.lowpass_hz:g} Hz)", fontsize=9)
    ax.legend(fontsize=8)
    o = I_TABLE + 1
    me = result["feedforward"]["model_error"]
    worst = me["worst_plant_factors"]
    plant = with_actuator(cfg, **{k: getattr(cfg.actuator if ACTUATOR_KEYS[k] == "actuator" else cfg.valve, k) * x
                                  for k, x in worst.items()})
    rig_w = DiscreteRig(plant, dt, f)
    mw = mimo(rig_w, ctrls, ffs=ffs, check_stability=False)
    mw_fb = mimo(rig_w, ctrls, check_stability=False)
    ax = axs[1]
    mm = data["mimo"]
    ax.semilogx(f[band], _db(mm["tr_uniform_passive"][band, o]), "k-", lw=1, label="passive")
    ax.semilogx(f[band], _db(mm["tr_uniform_controlled"][band, o]), "b-", lw=1, label="feedback, model = plant")
    ax.semilogx(f[band], _db(data["mimo_fbff"]["tr_uniform_controlled"][band, o]), "g-", lw=1,
                label="feedback + feedforward, model = plant")
    ax.semilogx(f[band], _db(mw_fb["tr_uniform_controlled"][band, o]), "b:", lw=1, label="feedback, worst plant")
    ax.semilogx(f[band], _db(mw["tr_uniform_controlled"][band, o]), "g:", lw=1.2,
                label="feedback + feedforward, worst plant")
    w = me["worst_attenuation_db"]["feedback_feedforward"]["uniform"]["min_1_100hz"]
    ax.set_title(f"uniform floor -> table, actuator +-10 % off the model: worst {w:.1f} dB (1-100 Hz)",
                 fontsize=9)
    ax.set_xlabel("frequency [Hz]")
    ax.set_ylabel("|x_table / x_g| [dB]")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7)
    rep = result["predicted_vc"]
    v = cfg.vibration
    plot_vc(axs[2], rep, title=f"table, predicted ({v.rms_m * 1e6:g} um rms floor, {v.band_lo_hz:g}-"
                               f"{v.band_hi_hz:g} Hz, {v.spectrum})")
    save(fig, "feedforward.png")


def _band_row(a) -> str:
    return " | ".join(f"{a[k]:.1f}" for k in BANDS)


def markdown(result, paper, pi_note, tracking_bw_hz, cfg, figures) -> str:
    """design.md: the design's figures beside the paper's, one section function each."""
    L = _md_margins(result, paper, cfg)
    L += _md_attenuation(result, paper)
    L += _md_mimo(result)
    L += _md_robust(result)
    L += _md_feedforward(result)
    L += _md_predicted_demo(result)
    L += _md_sensitivity_integral(result)
    L += _md_tuning_slack(result)
    L += ["## Other figures", "", f"- Fig. 10 (front-left, tool): {pi_note}.",
          f"- Fig. 4: actuator-alone PID tracking bandwidth {tracking_bw_hz:.1f} Hz (paper ~95 Hz).", ""]
    L += [f"![{n}]({n})" for n in figures] + [""]
    return "\n".join(L)


def _md_margins(result, paper, cfg) -> list[str]:
    """Title, the loop's set-up, each mount's margins beside the paper's, the multiloop disk margin and
    whether the design meets the paper."""
    L = ["# rig design: isolation loops on the discrete rig", "",
         f"Loop rate {cfg.loop.rate_hz:g} Hz, ZOH + one period of computation delay. Actuator model: "
         f"{result['design_model']['actuator']}. SISO view (paper Fig. 5): one mount's loop closed, the other "
         "valves nulled, ground moving at that mount.", "",
         "## Margins", "",
         "| mount | stable | GM [dB] | PM [deg] | gain crossover [Hz] | phase crossover [Hz] | disk margin "
         "(GM / PM it guarantees together) | peak of S [dB] |",
         "|---|---|---|---|---|---|---|---|"]
    for m, r in result["mounts"].items():
        L.append(f"| {m} | {r['stable']} | {r['gain_margin_db']:.2f} | {r['phase_margin_deg']:.1f} | "
                 f"{r['gain_crossover_hz']:.0f} | {r['phase_crossover_hz']:.0f} | {r['disk_margin']:.3f} "
                 f"({r['disk_gain_margin_db']:.2f} dB / {r['disk_phase_margin_deg']:.1f} deg) | "
                 f"{r['sensitivity_peak_db']:.1f} |")
    L.append(f"| paper | yes | {paper['gain_margin_db']} | {paper['phase_margin_deg']} | "
             f"{paper['gain_crossover_hz']} | {paper['phase_crossover_hz']} | - | - |")
    mdm = result["mimo_disk_margin"]
    gm, pm = disk_gm_pm(mdm)
    L += ["", f"All four loops closed on the coupled machine: stable = {result['mimo_stable']}; multiloop disk "
              f"margin {mdm:.3f} (every loop's gain within {gm:.1f} dB and phase within {pm:.1f} deg at once).", ""]
    mp = result["meets_paper"]
    L += [f"At or above the paper in every band: {mp['bands']}; GM >= 6 dB and PM >= 35 deg on every mount: "
          f"{mp['margins']}; robustly stable (below): {mp['robust']}.", ""]
    return L


def _md_attenuation(result, paper) -> list[str]:
    """Attenuation ground -> table and ground -> tool per mount (SISO), beside the paper's targets."""
    L = []
    for name in ("table", "tool"):
        L += [f"## Attenuation ground -> {name} (Y), feedback, dB (band entries: minimum over the band)", "",
              "| view | 1 Hz | 5-10 Hz | 20-60 Hz | 60-100 Hz | min 1-100 Hz |", "|---|---|---|---|---|---|"]
        for m, a in result["attenuation_db"][f"ground_to_{name}"].items():
            L.append(f"| {m} (SISO) | " + _band_row(a) + " |")
        if name == "table":
            tg = result["paper_targets_db"]["ground_to_table"]
            for m in ("front_left", "rear_left"):
                t = tg[m]
                L.append(f"| paper target, {m.split('_')[0]} | " + " | ".join(f"{t[k]:.0f}" for k in
                                                                                t) + " | - |")
        p = paper[name]
        L.append(f"| paper (text) | {p['1hz']} | {p['5_10hz']} | {p['20_60hz']} | {p['60_100hz']} | 5-25 overall |")
        L.append("")
    return L


def _md_mimo(result) -> list[str]:
    """All four loops closed: ground -> table under uniform and independent floor motion."""
    L = ["## All four loops closed: what the machine feels (ground -> table Y, dB)", "",
         "Uniform: the same floor motion at every mount. Independent: uncorrelated floor motion of equal spectrum "
         "at each mount (the table's responses add in power).", "",
         "| path | floor | 1 Hz | 5-10 Hz | 20-60 Hz | 60-100 Hz | min 1-100 Hz |", "|---|---|---|---|---|---|---|"]
    for tag, v in result["mimo"].items():
        for key in ("uniform", "independent"):
            L.append(f"| {tag.replace('_', ' + ')} | {key} | " + _band_row(v[key]["ground_to_table"]) + " |")
    return L


def _md_robust(result) -> list[str]:
    """Robust stability over the perturbed plants."""
    rb = result["robust"]
    return ["", "## Robust stability", "",
            f"All four loops on {rb['corners'] + rb['random']} plants: every actuator's gain within +-"
            f"{100 * rb['gain_tol']:.0f} % and every machine mode's frequency within +-{100 * rb['mode_tol']:.0f} % "
            f"(rigid-body modes on the actuators included), independently: the {rb['corners']} corners "
            f"(2^4 gain corners x modes all low / nominal / all high) and {rb['random']} uniform random draws.", "",
            f"- all stable: {rb['all_stable']} ({rb['unstable']} unstable)",
            f"- slowest fast closed-loop pole decay: {rb['worst_decay_1_per_s']:.2f} 1/s",
            f"- worst multiloop disk margin: {rb['worst_disk_margin_mimo']:.3f}",
            f"- worst single-loop GM / PM on a perturbed plant: {rb['worst_siso_gm_db']:.2f} dB / "
            f"{rb['worst_siso_pm_deg']:.1f} deg", ""]


def _md_feedforward(result) -> list[str]:
    """The floor feedforward: its filter, and the worst attenuation with the actuator off the model."""
    ff = result["feedforward"]
    me = ff["model_error"]
    L = ["## Floor feedforward", "",
         f"Inverse of the actuator's own model G_EHA (valve Eq. 1 x actuator Eq. 8, Eq. 10) on the "
         f"floor accelerometer: high-pass {ff['params']['hp_hz']:g} Hz, roll-off {ff['params']['lowpass_hz']:g} Hz "
         f"(order {ff['params']['lowpass_order']}), lead {ff['lead_s'] * 1e3:.3f} ms for the ZOH, the period of "
         "computation and the roll-off's delay.", "",
         f"Model error: the plant's K_L, C, w_nv, zeta, K_Q, K_C each +-{100 * me['tol']:.0f} % from the model the "
         f"controllers were designed on ({me['plants']} plants: all corners). Feedback stable on all: "
         f"{me['feedback_stable_all']}. Worst attenuation ground -> table, all four loops closed (dB):", "",
         "| path | floor | 1 Hz | 5-10 Hz | 20-60 Hz | 60-100 Hz | min 1-100 Hz |", "|---|---|---|---|---|---|---|"]
    for tag, v in me["worst_attenuation_db"].items():
        for key in ("uniform", "independent"):
            L.append(f"| {tag.replace('_', ' + ')}, worst plant | {key} | " + _band_row(v[key]) + " |")
    wp = me["worst_plant_factors"]
    L += ["", "Worst plant (factors on the model): " + ", ".join(f"{k} x {x:.2f}" for k, x in wp.items()) + ".", ""]
    return L


def _md_predicted_demo(result) -> list[str]:
    """The predicted `rig demo` figure per case, and the vibration criteria the predicted table meets."""
    pd = result["predicted_demo"]
    L = ["## Predicted `rig demo` figure (linear, same floor statistics in both halves)", "",
         f"Table Y rms in {pd['feedback']['band_hz'][0]:g}-{pd['feedback']['band_hz'][1]:g} Hz under the configured "
         "floor (spectrum, rms, correlation between mounts), with the simulated sensors' noise:", "",
         "| case | passive [um] | controlled [um] | from the floor | from accelerometer noise | from floor "
         "accelerometer noise | reduction [dB] | noise-free [dB] |", "|---|---|---|---|---|---|---|---|"]
    for tag, r in pd.items():
        L.append(f"| {tag.replace('_', ' + ').replace('model + error', '(actuator +-10 % off, worst)')} | "
                 f"{r['passive_um']:.3f} | {r['controlled_um']:.3f} | {r['from_floor_um']:.3f} | "
                 f"{r['from_accel_noise_um']:.4f} | {r['from_floor_accel_noise_um']:.4f} | {r['reduction_db']:.1f} | "
                 f"{r['reduction_noise_free_db']:.1f} |")
    if "predicted_vc" in result:
        vc = result["predicted_vc"]["vc_class"]
        L += ["", "Vibration criterion met by the predicted table motion: " + ", ".join(
            f"{k}: {v}" for k, v in vc.items()) + "."]
    return L


def _md_sensitivity_integral(result) -> list[str]:
    """What limits the feedback: Bode's sensitivity integral per mount."""
    si = result["sensitivity_integral"]
    L = ["", "## What limits the feedback", "",
         "Bode's sensitivity integral: for this loop (stable, one period of delay) the area of ln|S| over "
         "0 Hz to Nyquist is zero, so every neper of attenuation below 100 Hz is paid back above it. The disk "
         "margin of 2/3 bounds |S| by 2 (6 dB), so the payback needs at least (area / ln 2) Hz of amplification, "
         "and it can only sit where the loop is still active: below the machine-on-actuator modes "
         "(~250-320 Hz), whose phase, with the valve's, the flow integrator's and the delay's, ends the loop's "
         "reach.", "",
         "| mount | area below 100 Hz [Hz Np] | area above [Hz Np] | sum | peak of S [dB] at [Hz] | amplified from "
         "[Hz] | minimum width at S = 2 [Hz] |", "|---|---|---|---|---|---|---|"]
    for m, s in si.items():
        L.append(f"| {m} | {s['below_hz_nepers']:.1f} | {s['above_hz_nepers']:.1f} | {s['total_hz_nepers']:.2f} | "
                 f"{s['peak_db']:.1f} at {s['peak_hz']:.0f} | {s['amplified_from_hz']:.0f} | "
                 f"{-s['below_hz_nepers'] / math.log(2):.0f} |")
    return L


def _md_tuning_slack(result) -> list[str]:
    """The tuner's constraints and which of them, and which bands, are at their limit for this design."""
    ts = result["tuning_slack"]
    dm = min(ts["disk_margin"].values())
    active = []
    if dm - ts["disk_margin_min"] < 0.01:
        active.append(f"the disk margin ({dm:.3f}, limit {ts['disk_margin_min']:.3f})")
    if ts["hf_gain_V_per_mps2"] > 0.98 * ts["hf_gain_max_V_per_mps2"]:
        active.append(f"the accelerometer -> valve gain above {ts['from_hz']:g} Hz ({ts['hf_gain_V_per_mps2']:.1f}, "
                      f"limit {ts['hf_gain_max_V_per_mps2']:g} V per m/s^2)")
    if ts["loop_gain_above_db"] > ts["loop_gain_above_max_db"] - 0.2:
        active.append(f"the loop gain above {ts['from_hz']:g} Hz ({ts['loop_gain_above_db']:.1f} dB)")
    ex = ts["band_excess_db"]
    worst = min(ex.values())
    tight = [BAND_LABELS[b] for b, v in ex.items() if v < worst + 0.2]
    return ["", "The tuner (controllers/tune.py, `rig design --tune`) maximises the worst band's excess over the "
                f"paper with the disk margin >= {ts['disk_margin_min']:.3f} on every mount, |L| <= "
                f"{ts['loop_gain_above_max_db']:g} dB and the accelerometer -> valve gain <= "
                f"{ts['hf_gain_max_V_per_mps2']:g} V per m/s^2 from {ts['from_hz']:g} Hz on as hard constraints. "
                "For this design the band excesses over the paper are " + ", ".join(
                    f"{BAND_LABELS[b]} {v:+.2f} dB" for b, v in ex.items()) + f" (worst mount); the tightest: "
                f"{', '.join(tight)}; constraints at their limit: {', '.join(active) or 'none'}. Where a band and a "
                "constraint are both at their limit, more of that band costs margin, high-frequency gain or "
                "another band.", ""]
