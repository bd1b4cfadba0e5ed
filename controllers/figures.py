"""Figures and the Markdown table of `rig design --out DIR` (paper Figs. 4, 10-14)."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from controllers.analysis import BANDS, attenuation_db, scaled_for_margins, siso
from controllers.isolation import IsolationController, params_from_config
from rig.config import MOUNTS
from sim_backend.rig_plant import I_TABLE, I_TOOL


def _plt():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def _db(x):
    return 20 * np.log10(np.abs(x))


def write_all(out: Path, cfg, dt, rig, ctrls, data, result, mimo, paper, log) -> list[Path]:
    plt = _plt()
    f = rig.f
    band = (f >= 0.5) & (f <= 200)
    files = []

    def save(fig, name):
        p = out / name
        fig.tight_layout()
        fig.savefig(p, dpi=110)
        plt.close(fig)
        files.append(p)

    # Fig. 11: Nyquist per mount
    fig, axs = plt.subplots(2, 2, figsize=(10, 9))
    th = np.linspace(0, 2 * np.pi, 200)
    for ax, m in zip(axs.flat, MOUNTS):
        L = data["siso"][m]["L"]
        r = result["mounts"][m]
        ax.plot(L.real, L.imag, "b-", lw=1, label="L(e^{jwT})")
        ax.plot(L.real, -L.imag, "b:", lw=0.6)
        ax.plot(np.cos(th), np.sin(th), "k:", lw=0.6)
        ax.plot([-1], [0], "r+", ms=12, mew=2)
        ax.set_xlim(-3, 3)
        ax.set_ylim(-3, 3)
        ax.set_aspect("equal")
        ax.grid(alpha=0.3)
        ax.set_title(f"{m}: GM {r['gain_margin_db']:.1f} dB, PM {r['phase_margin_deg']:.1f} deg")
    fig.suptitle("Nyquist, one mount's loop (others nulled), ZOH + 1 period delay (cf. paper Fig. 11)")
    save(fig, "fig11_nyquist.png")

    # Figs. 12, 13: ground -> table / tool (Y), passive vs controlled
    for fig_no, name, o in ((12, "table", I_TABLE + 1), (13, "tool", I_TOOL + 1)):
        fig, axs = plt.subplots(2, 2, figsize=(11, 8), sharex=True)
        for ax, m in zip(axs.flat, MOUNTS):
            r = data["siso"][m]
            ax.semilogx(f[band], _db(r["tr_passive"][band, o]), "k-", lw=1, label="passive")
            ax.semilogx(f[band], _db(r["tr_controlled"][band, o]), "b-", lw=1.2, label="PI + compensator")
            a = result["attenuation_db"][f"ground_to_{name}"][m]
            ax.set_title(f"{m}: {a['1hz']:.1f} dB at 1 Hz, min {a['min_1_100hz']:.1f} dB (1-100 Hz)")
            ax.set_ylabel(f"|x_{name}/x_g| [dB]")
            ax.grid(alpha=0.3, which="both")
            ax.legend(fontsize=8)
        for ax in axs[1]:
            ax.set_xlabel("frequency [Hz]")
        fig.suptitle(f"Ground at the mount -> {name} (Y), SISO view (cf. paper Fig. {fig_no})")
        save(fig, f"fig{fig_no}_ground_to_{name}.png")

    # Fig. 14: cross paths for the front-left mount
    r = data["siso"]["front_left"]
    fig, axs = plt.subplots(2, 2, figsize=(11, 8), sharex=True)
    for ax, (lab, o) in zip(axs.flat, (("table X", I_TABLE), ("tool X", I_TOOL), ("table Z", I_TABLE + 2),
                                       ("tool Z", I_TOOL + 2))):
        att = attenuation_db(r["tr_passive"][:, o], r["tr_controlled"][:, o])
        sel = (f >= 1) & (f <= 100)
        ax.semilogx(f[band], _db(r["tr_passive"][band, o]), "k-", lw=1, label="passive")
        ax.semilogx(f[band], _db(r["tr_controlled"][band, o]), "b-", lw=1.2, label="controlled")
        ax.set_title(f"ground (front_left) -> {lab}: min {np.min(att[sel]):.1f} dB (1-100 Hz)")
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=8)
    fig.suptitle("Cross transmissibilities, front-left mount (cf. paper Fig. 14)")
    save(fig, "fig14_cross_front_left.png")

    # Fig. 10: PI alone vs PI + compensator (front-left, tool Y)
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

    # MIMO: uniform ground, all four loops closed
    mm = data["mimo"]
    fig, axs = plt.subplots(1, 3, figsize=(15, 4.5))
    for ax, (lab, o) in zip(axs[:2], (("table", I_TABLE + 1), ("tool", I_TOOL + 1))):
        ax.semilogx(f[band], _db(mm["tr_uniform_passive"][band, o]), "k-", lw=1, label="passive")
        ax.semilogx(f[band], _db(mm["tr_uniform_controlled"][band, o]), "b-", lw=1.2, label="4 loops closed")
        a = mimo["uniform"][f"ground_to_{lab}"]
        ax.set_title(f"uniform ground -> {lab} Y: min {a['min_1_100hz']:.1f} dB (1-100 Hz)")
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=8)
        ax.set_xlabel("frequency [Hz]")
    d = mm["det"] - 1.0
    axs[2].plot(d.real, d.imag, "b-", lw=1)
    axs[2].plot([-1], [0], "r+", ms=12, mew=2)
    axs[2].set_xlim(-4, 4)
    axs[2].set_ylim(-4, 4)
    axs[2].set_aspect("equal")
    axs[2].grid(alpha=0.3)
    axs[2].set_title(f"generalised Nyquist det(I+L)-1; stable={mm['stable']}")
    save(fig, "mimo_uniform_ground.png")

    # Fig. 4: actuator alone, reference tracking PID
    from controllers.tracking import TrackingPID, bandwidth_hz, pid_from_config, tracking_response
    from sim_backend.linear import ActuatorParams
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

    (out / "design.md").write_text(markdown(result, mimo, paper, pi_note, bw, cfg))
    files.append(out / "design.md")
    return files


def markdown(result, mimo, paper, pi_note, tracking_bw_hz, cfg) -> str:
    L = ["# rig design: isolation loops on the discrete rig", "",
         f"Loop rate {cfg.loop.rate_hz:g} Hz, ZOH + one period of computation delay. SISO view (paper Fig. 5): "
         "one mount's loop closed, the other valves nulled, ground moving at that mount.", "",
         "| mount | stable | GM [dB] | PM [deg] | gain crossover [Hz] | phase crossover [Hz] |",
         "|---|---|---|---|---|---|"]
    for m, r in result["mounts"].items():
        L.append(f"| {m} | {r['stable']} | {r['gain_margin_db']:.1f} | {r['phase_margin_deg']:.1f} | "
                 f"{r['gain_crossover_hz']:.0f} | {r['phase_crossover_hz']:.0f} |")
    L.append(f"| paper | yes | {paper['gain_margin_db']} | {paper['phase_margin_deg']} | "
             f"{paper['gain_crossover_hz']} | {paper['phase_crossover_hz']} |")
    L += ["", f"MIMO (all four loops closed on the coupled machine): stable = {result['mimo_stable']}.", ""]
    for name in ("table", "tool"):
        L += [f"## Attenuation ground -> {name} (Y), dB (band entries: minimum over the band)", "",
              "| mount | 1 Hz | 5-10 Hz | 20-60 Hz | 60-100 Hz | min 1-100 Hz |", "|---|---|---|---|---|---|"]
        for m, a in result["attenuation_db"][f"ground_to_{name}"].items():
            L.append(f"| {m} | " + " | ".join(f"{a[k]:.1f}" for k in BANDS) + " |")
        u = mimo["uniform"][f"ground_to_{name}"]
        L.append("| MIMO, uniform ground | " + " | ".join(f"{u[k]:.1f}" for k in BANDS) + " |")
        p = paper[name]
        L.append(f"| paper | {p['1hz']} | {p['5_10hz']} | {p['20_60hz']} | {p['60_100hz']} | 5-25 overall |")
        L.append("")
    L += ["## Other figures", "", f"- Fig. 10 (front-left, tool): {pi_note}.",
          f"- Fig. 4: actuator-alone PID tracking bandwidth {tracking_bw_hz:.1f} Hz (paper ~95 Hz).", ""]
    return "\n".join(L)
