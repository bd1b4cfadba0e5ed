"""`rig demo`: the four-mount rig on the simulated plant under broadband floor vibration, isolation off, feedback,
and feedback + floor feedforward, compared over the SAME floor motion.

Runs the product's control loop (rig/runtime/session.py Session: read -> check -> controllers + feedforward -> limit ->
write) in simulated time over the sim backend (RigPlant + FloorMotion from [vibration], floor accelerometers
with their own noise, one period of computation delay), three times from the same seed, once per isolation
mode: each run sees the same floor realisation and the same sensor noise, so the reductions are the isolation
alone (like with like), both as rms and per one-third-octave band. The plant's actuators are off the
controllers' model by --model-error percent (default 10), in the corner of the six parameters where the linear
prediction of the feedforward's result is worst (controllers/analysis.py worst_model_error); the controllers
and the feedforward keep the configured model.

Prints the rms table and tool-point motion (Y) per mode and the reductions, the vibration criterion (VC) class
of each, and the largest amplification of any one-third-octave band of 1-100 Hz. --out DIR writes demo.png
(traces, spectra and the VC curves against the VC-A..G and ISO lines) and demo.json.
"""
from __future__ import annotations

import argparse
import json
import sys

import numpy as np
from controllers.vibration_criteria import plot_vc
from rig import cliargs
from rig.errors import EXIT_HARM


# the options' ranges, which rig.simulate_isolation (rig/api.py) holds its arguments to as well
RANGES = {"seconds": cliargs.seconds(ge=0.5, le=600), "settle_s": cliargs.seconds(ge=0, le=60),
          "rms_um": cliargs.Number(gt=0, le=1000, unit="um"), "model_error_pct": cliargs.Number(ge=0, le=50, unit="%")}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--seconds", type=RANGES["seconds"], default=10.0, metavar="N",
                   help="seconds PER MODE: three simulated runs of N s each (off, feedback, feedback + feedforward), "
                        "each after --settle; unlike run, hil and chirp, where --seconds is the whole run (default 10)")
    p.add_argument("--settle", type=RANGES["settle_s"], default=1.0, metavar="S",
                   help="seconds run before metering in each mode (default 1)")
    p.add_argument("--rms-um", type=RANGES["rms_um"], default=None, metavar="UM",
                   help="floor displacement rms in um (default: [vibration] rms_m of the config)")
    p.add_argument("--model-error", type=RANGES["model_error_pct"], default=10.0, metavar="PCT",
                   help="the plant's actuator parameters PCT %% off the controllers' model, in the worst corner "
                        "for the feedforward (default 10; 0: the plant as [plant_error] of the config says)")
    cliargs.output_arg(p, "--out", kind="folder", metavar="DIR", default=None,
                       help="write demo.png (traces, spectra, VC curves of the three modes) and demo.json to DIR")
    p.add_argument("--json", action="store_true", help="print only the JSON result on stdout")


def run(args) -> int:
    from rig.compare import LABELS, compare, demo_config     # heavy (numba, scipy): after the arguments are checked
    cfg, plant = demo_config(args.config, rms_um=args.rms_um, model_error_pct=args.model_error, log=_log)
    v = cfg.vibration
    _log(f"floor vibration {v.band_lo_hz:g}-{v.band_hi_hz:g} Hz, {v.rms_m * 1e6:g} um rms under each mount (seed {v.seed}); loop "
         f"{cfg.loop.rate_hz:g} Hz in simulated time; three runs over the same floor: {', '.join(LABELS.values())}, "
         f"{args.settle:g} s + {args.seconds:g} s each")
    res, traces = compare(cfg, seconds=args.seconds, settle_s=args.settle, log=_log)
    res["plant"] = plant
    for mode, line in res["harm"].items():       # isolation switched off mid-run: its figures are not the design's
        _log(f"warning: {LABELS[mode]}: {line}")
    if args.json:
        print(json.dumps(res, indent=2))
    else:
        _print(res, v)
    if args.out is not None:
        cliargs.make_out_dir(args.out)
        s = int(round(args.settle * cfg.loop.rate_hz))
        _plot(args.out / "demo.png", 1.0 / cfg.loop.rate_hz, traces, slice(s, s + int(round(args.seconds * cfg.loop.rate_hz))), res)
        (args.out / "demo.json").write_text(json.dumps(res, indent=2))
        _log(f"wrote {args.out / 'demo.png'} and {args.out / 'demo.json'}")
    return EXIT_HARM if res["harm"] else 0


def _log(text: str) -> None:
    print(f"rig demo: {text}", file=sys.stderr, flush=True)


def _print(res: dict, v) -> None:
    from rig.compare import LABELS, MODES, mode_row
    print(f"rig demo: floor {res['floor_rms_um']:.2f} um rms ({v.band_lo_hz:g}-{v.band_hi_hz:g} Hz) as the table "
          f"feels it (the mean of the four mounts' floor, each {v.rms_m * 1e6:g} um rms), the same realisation in all "
          f"three runs: reductions are like with like")
    p = res["plant"]
    if p["model_error_pct"]:
        fac = ", ".join(f"{k} {100 * (x - 1):+.0f} %" for k, x in p["factors"].items())
        print(f"plant: actuator {p['model_error_pct']:g} % off the controllers' model ({fac}; {p['chosen']})")
    else:
        print(f"plant: {p['chosen']}")

    def row(label, cells):
        print(mode_row(label, cells))
    row("", [LABELS[m] for m in MODES])
    for key, lab in (("table", "table Y rms"), ("tool", "tool point Y rms")):
        r = res[f"{key}_rms_um"]
        for suffix, band in (("_1_100hz", " (1-100 Hz)"), ("", "")):
            row(lab + band, [f"{r[m + suffix]:.3f} um" + (f" ({res['reduction_db'][key + suffix][m]:.1f} dB)"
                                                          if m != "off" else "") for m in MODES])
    row("VC class, table", [res["vc_class"][m] for m in MODES])
    row("VC class, tool point", [res["vc_class_tool"][m] for m in MODES])
    row("max band amplification", [""] + [f"{res['max_band_amplification_db'][m]:.1f} dB" for m in MODES[1:]])
    row("valve command rms", [f"{res['valve_rms_V'][m]:.3f} V" for m in MODES])
    row("periods at valve limit", [f"{100 * res['valve_limited_fraction'][m]:.1f} %" for m in MODES])
    row("max |stroke|", [f"{res['max_abs_stroke_um'][m]:.1f} um" for m in MODES])
    worst = max(res["valve_limited_fraction"].values())
    if worst > 0.01:
        print(f"note: the valve was at its limit in {100 * worst:.1f} % of the periods of a mode (the loop is "
              f"then not linear; see --rms-um)")


def _plot(path, dt, traces, sl, res):
    import matplotlib
    import scipy.signal
    from rig.compare import LABELS, MODES
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fs = 1.0 / dt
    styles = {"off": ("k", 0.8), "feedback": ("b", 0.7), "feedback_feedforward": ("g", 0.7)}
    fig, axs = plt.subplots(2, 2, figsize=(14, 9))
    t = np.arange(sl.stop) * dt
    ax = axs[0, 0]
    ax.plot(t[sl], traces["off"]["floor"][sl] * 1e6, color="0.75", lw=0.5, label="floor (mean of mounts)")
    for m in MODES:
        c, lw = styles[m]
        lab = LABELS[m] + ("" if m == "off" else f" ({res['reduction_db']['table_1_100hz'][m]:.1f} dB, 1-100 Hz)")
        ax.plot(t[sl], traces[m]["table"][sl] * 1e6, color=c, lw=lw, label=lab)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("table Y displacement [um]")
    ax.set_title("table Y, the same floor motion in each run")
    ax.legend(fontsize=8, loc="upper right")
    ax.grid(alpha=0.3)
    ax = axs[0, 1]
    nper = min(1 << 14, sl.stop - sl.start)
    f, P = scipy.signal.welch(traces["off"]["floor"][sl], fs=fs, nperseg=nper)
    ax.loglog(f[1:], np.sqrt(P[1:]) * 1e6, color="0.7", lw=0.8, label="floor")
    for m in MODES:
        f, P = scipy.signal.welch(traces[m]["table"][sl], fs=fs, nperseg=nper)
        ax.loglog(f[1:], np.sqrt(P[1:]) * 1e6, color=styles[m][0], lw=0.9, label=LABELS[m])
    ax.set_xlim(0.5, 500)
    top = ax.get_ylim()[1]
    ax.set_ylim(top * 1e-7, top)
    ax.set_xlabel("frequency [Hz]")
    ax.set_ylabel("ASD [um/sqrt(Hz)]")
    ax.set_title("table Y spectrum")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3, which="both")
    for ax, key, lab in ((axs[1, 0], "table", "table"), (axs[1, 1], "tool", "tool point")):
        rep = res["vc"][key]
        plot_vc(ax, {"band_hz": rep["band_hz"],
                     "velocity_um_s": {LABELS[m]: rep["velocity_um_s"][m] for m in MODES},
                     "vc_class": {LABELS[m]: rep["vc_class"][m] for m in MODES}},
                title=f"{lab} Y: one-third-octave rms velocity against the VC and ISO criteria")
    p = res["plant"]
    fig.suptitle("rig demo: isolation off / feedback / feedback + floor feedforward over the same floor; plant "
                 + (f"actuator {p['model_error_pct']:g} % off the controllers' model (worst corner)"
                    if p["model_error_pct"] else p["chosen"]), fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
