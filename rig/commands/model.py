"""`rig model`: the linear model's headline figures (Eqs. 1-10, Table 1) and a Bode plot of G_EHA."""
from __future__ import annotations

import json
import sys

import numpy as np

from rig import cliargs
from rig.config import load_config
from rig.errors import RigError

ROWS = [  # key, label, unit, paper's figure
    ("valve_natural_frequency_hz", "valve natural frequency w_nv/2pi", "Hz", "~84"),
    ("hydraulic_natural_frequency_hz", "hydro-mechanical w_h/2pi, actuator alone", "Hz", "~2180"),
    ("loaded_hydraulic_natural_frequency_hz", "w_h/2pi with 1/4 of the machine per mount", "Hz", "~257"),
    ("hydraulic_damping_ratio", "hydraulic damping ratio delta_h", "", "-"),
    ("lag_corner_rad_s", "low-frequency lag K_C K_L / A_p^2", "rad/s", "-"),
    ("dc_gain_m_per_V", "DC gain x_p / v of G_EHA", "m/V", "-"),
    ("hydraulic_stiffness_N_per_m", "hydraulic stiffness K_h = 4 beta A_p^2 / V_t", "N/m", "-"),
]


def add_arguments(p):
    p.add_argument("--json", action="store_true", help="print only the figures as JSON on stdout")
    cliargs.output_arg(p, "--plot", metavar="FILE", suffix=".png",
                       help="write a Bode plot of G_EHA (Eq. 10): PNG (.png added to a name without a suffix), "
                            "or PDF/SVG by the suffix")


def figures(cfg) -> dict:
    from sim_backend.linear import ActuatorParams, model_figures
    p = ActuatorParams.from_config(cfg)
    return model_figures(p, cfg.machine.mass_kg)


def plot_bode(cfg, path: str) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from sim_backend.linear import ActuatorParams, g_eha_frf
    p = ActuatorParams.from_config(cfg)
    f = np.logspace(-1, np.log10(3000), 800)
    w = 2 * np.pi * f
    fig, (a1, a2) = plt.subplots(2, 1, sharex=True, figsize=(8, 6))
    for full, style, label in ((True, "-", "Eq. 8 actuator (full)"), (False, "--", "Eq. 9 actuator (reduced)")):
        H = g_eha_frf(p, w, full=full)
        a1.semilogx(f, 20 * np.log10(np.abs(H)), style, label=label)
        a2.semilogx(f, np.unwrap(np.angle(H)) * 180 / np.pi, style, label=label)
    a1.set_ylabel("|x_p / v| [dB re 1 m/V]")
    a2.set_ylabel("phase [deg]")
    a2.set_xlabel("frequency [Hz]")
    for a in (a1, a2):
        a.grid(True, which="both", alpha=0.3)
        a.axvline(p.w_nv / (2 * np.pi), color="grey", lw=0.8, ls=":")
    a1.legend()
    a1.set_title("G_EHA = G_valve G_act (Eq. 10), Table 1 identified values")
    fig.tight_layout()
    try:
        fig.savefig(path, dpi=120)
    except OSError as e:
        raise RigError(f"{path}: cannot write plot ({e.strerror})") from None
    finally:
        plt.close(fig)


def run(args) -> int:
    cfg = load_config(args.config)
    fig = figures(cfg)
    if args.plot:
        plot_bode(cfg, args.plot)
    if args.json:
        json.dump(fig, sys.stdout, indent=2)
        print()
        return 0
    print(f"Linear model of the actuator ({cfg.source})")
    print(f"{'quantity':<46} {'value':>14} {'unit':<6} paper")
    for key, label, unit, paper in ROWS:
        v = fig[key]
        txt = f"{v:.4g}" if abs(v) < 1e-2 or abs(v) >= 1e5 else f"{v:.2f}" if v >= 1 else f"{v:.4f}"
        print(f"{label:<46} {txt:>14} {unit:<6} {paper}")
    if args.plot:
        print(f"Bode plot written to {args.plot}", file=sys.stderr)
    return 0
