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
import dataclasses
import json
import math
import sys
import time
import numpy as np
import scipy.signal

from controllers.vibration_criteria import plot_vc, vc_report
from rig import cliargs
from rig.runtime.clock import SimClock
from rig.config import load_config
from rig.errors import RigError
from rig.runtime.gate import ISOLATION_MODES as MODES
from rig.runtime.lifecycle import State
from rig.runtime.session import Session

LABELS = {"off": "isolation off", "feedback": "feedback", "feedback_feedforward": "feedback + feedforward"}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--seconds", type=cliargs.seconds(ge=0.5, le=600), default=10.0, metavar="N",
                   help="simulated seconds metered per mode (off, feedback, feedback + feedforward; default 10)")
    p.add_argument("--settle", type=cliargs.seconds(ge=0, le=60), default=1.0, metavar="S",
                   help="seconds run before metering in each mode (default 1)")
    p.add_argument("--rms-um", type=cliargs.Number(gt=0, le=1000, unit="um"), default=None, metavar="UM",
                   help="floor displacement rms in um (default: [vibration] rms_m of the config)")
    p.add_argument("--model-error", type=cliargs.Number(ge=0, le=50, unit="%"), default=10.0, metavar="PCT",
                   help="the plant's actuator parameters PCT %% off the controllers' model, in the worst corner "
                        "for the feedforward (default 10; 0: the plant as [plant_error] of the config says)")
    cliargs.output_arg(p, "--out", kind="folder", metavar="DIR", default=None,
                       help="write demo.png (traces, spectra, VC curves of the three modes) and demo.json to DIR")
    p.add_argument("--json", action="store_true", help="print only the JSON result on stdout")


def _rms(x):
    x = np.asarray(x, dtype=float)
    return float(np.sqrt(np.mean((x - x.mean()) ** 2)))


def _band(x, fs, lo=1.0, hi=100.0):
    sos = scipy.signal.butter(4, (lo, hi), btype="bandpass", fs=fs, output="sos")
    return scipy.signal.sosfiltfilt(sos, np.asarray(x, dtype=float))


def run(args) -> int:
    cfg, plant = _demo_config(args)
    rate = cfg.loop.rate_hz
    v = cfg.vibration
    _log(f"floor vibration {v.band_lo_hz:g}-{v.band_hi_hz:g} Hz, {v.rms_m * 1e6:g} um rms (seed {v.seed}); loop "
         f"{rate:g} Hz in simulated time; three runs over the same floor: {', '.join(LABELS.values())}, "
         f"{args.settle:g} s + {args.seconds:g} s each")
    s = int(round(args.settle * rate))
    n = s + int(round(args.seconds * rate))
    traces, wall = {}, 0.0
    for mode in MODES:
        traces[mode], w = _simulate(cfg, n, mode)
        wall += w
    _log(f"{3 * n} periods in {wall:.1f} s wall ({wall / (3 * n) * 1e6:.1f} us per period)")
    same = max(float(np.max(np.abs(traces[m]["floor"] - traces["off"]["floor"]))) for m in MODES)
    if same != 0.0:
        raise RigError(f"demo: the runs saw different floor motion (largest difference {same:g} m)")
    res = _figures(traces, slice(s, n), rate)
    res["comparison"] = (f"three runs over the same floor realisation (seed {v.seed}) and sensor noise: the "
                         f"reductions are the isolation alone, table (or tool) rms with isolation over without")
    res["plant"] = plant
    res["loop"] = {"periods": 3 * n, "wall_s": wall, "path": "rig.runtime.session.Session over SimBackend(RigPlant)"}
    if args.json:
        print(json.dumps(res, indent=2))
    else:
        _print(res, v)
    if args.out is not None:
        cliargs.make_out_dir(args.out)
        _plot(args.out / "demo.png", 1.0 / rate, traces, slice(s, n), res)
        (args.out / "demo.json").write_text(json.dumps(res, indent=2))
        _log(f"wrote {args.out / 'demo.png'} and {args.out / 'demo.json'}")
    return 0


def _log(text: str) -> None:
    print(f"rig demo: {text}", file=sys.stderr, flush=True)


def _demo_config(args):
    """The config of the demo (floor accelerometers fitted) and the description of its plant."""
    cfg = load_config(args.config)
    if args.rms_um is not None:
        cfg = cfg.replace(vibration=dataclasses.replace(cfg.vibration, rms_m=args.rms_um * 1e-6))
    cfg = cfg.replace(sensors=dataclasses.replace(cfg.sensors, floor_accel=True))
    if args.model_error == 0:
        pe = dataclasses.asdict(cfg.plant_error)
        return cfg, {"model_error_pct": 0.0, "factors": pe,
                     "chosen": "as configured ([plant_error])" if any(x != 1 for x in pe.values()) else "as modelled"}
    from controllers.analysis import worst_model_error
    from controllers.feedforward import make_feedforward_filters
    from controllers.isolation import make_isolation_controllers
    dt = 1.0 / cfg.loop.rate_hz
    t0 = time.perf_counter()
    fac, db = worst_model_error(cfg, dt, make_isolation_controllers(cfg, dt), make_feedforward_filters(cfg, dt),
                                tol=args.model_error / 100)
    _log(f"model error: the worst of the 64 corners (+-{args.model_error:g} %) for the feedforward, by linear "
         f"prediction ({db:.1f} dB), found in {time.perf_counter() - t0:.1f} s")
    cfg = cfg.replace(plant_error=dataclasses.replace(cfg.plant_error, **fac))
    return cfg, {"model_error_pct": args.model_error, "factors": fac, "predicted_reduction_db": db,
                 "chosen": "the corner where the linear prediction of feedback + feedforward is worst"}


def _simulate(cfg, n: int, mode: str):
    """n periods in one isolation mode from activation on, in simulated time: the plant's traces."""
    tr = {"table": np.empty(n), "tool": np.empty(n), "floor": np.empty(n), "cmd": np.empty((n, 4)),
          "ff": np.zeros((n, 4)), "stroke": np.empty((n, 4)), "limited": np.zeros(n, dtype=bool)}
    dt = 1.0 / cfg.loop.rate_hz
    with Session(cfg, "sim", clock=SimClock(), isolation=mode != "off", feedforward=mode == MODES[2],
                 port_options={"cmd_delay_periods": 1}) as session:
        loop, plant = session.loop, session.port.plant
        lay, row = loop.kernel.layout, loop.kernel.row
        rf = lay["ff_cmd_V"]
        loop.activate()
        t0 = time.perf_counter()
        for k in range(n):
            loop.cycle(k * loop.period_ns)
            if loop.state is State.FAULT:
                raise RigError(f"demo: the loop faulted at t = {k * dt:.3f} s ({LABELS[mode]}): "
                               f"{loop.lc.fault_reason}")
            tr["table"][k] = plant.table_m
            tr["tool"][k] = plant.tool_m
            tr["floor"][k] = sum(plant.floor_m) * 0.25
            tr["cmd"][k] = loop.cmd
            tr["ff"][k] = row[rf:rf + 4]
            tr["stroke"][k] = plant.stroke_m
            tr["limited"][k] = loop.limiter.limited
        return tr, time.perf_counter() - t0


def _figures(traces, sl, fs) -> dict:
    res = {"floor_rms_um": _rms(traces["off"]["floor"][sl]) * 1e6, "table_rms_um": {}, "tool_rms_um": {},
           "reduction_db": {}, "valve_limited_fraction": {}, "valve_rms_V": {}, "feedforward_rms_V": {},
           "max_abs_stroke_um": {}}
    for mode, tr in traces.items():
        res["table_rms_um"][mode] = _rms(tr["table"][sl]) * 1e6
        res["tool_rms_um"][mode] = _rms(tr["tool"][sl]) * 1e6
        res["table_rms_um"][mode + "_1_100hz"] = _rms(_band(tr["table"][sl], fs)) * 1e6
        res["tool_rms_um"][mode + "_1_100hz"] = _rms(_band(tr["tool"][sl], fs)) * 1e6
        res["valve_limited_fraction"][mode] = float(tr["limited"][sl].mean())
        res["valve_rms_V"][mode] = float(np.sqrt(np.mean(tr["cmd"][sl] ** 2)))
        res["feedforward_rms_V"][mode] = float(np.sqrt(np.mean(tr["ff"][sl] ** 2)))
        res["max_abs_stroke_um"][mode] = float(np.max(np.abs(tr["stroke"][sl]))) * 1e6
    for key in ("table", "tool"):
        r = res[f"{key}_rms_um"]
        for mode in MODES[1:]:
            res["reduction_db"].setdefault(key, {})[mode] = 20 * math.log10(r["off"] / r[mode])
            res["reduction_db"].setdefault(key + "_1_100hz", {})[mode] = \
                20 * math.log10(r["off_1_100hz"] / r[mode + "_1_100hz"])
    res["vc"] = {key: vc_report({m: traces[m][key][sl] for m in MODES}, fs) for key in ("table", "tool")}
    res["vc_class"] = res["vc"]["table"]["vc_class"]
    res["vc_class_tool"] = res["vc"]["tool"]["vc_class"]
    # per one-third-octave band, like with like: the band's rms velocity with isolation over without (null for
    # a band no frequency bin of the record falls in: a record shorter than a few seconds at the lowest bands)
    vt = res["vc"]["table"]["velocity_um_s"]
    res["band_reduction_db"] = {m: [20 * math.log10(a / b) if a > 0 and b > 0 else None
                                    for a, b in zip(vt["off"], vt[m])] for m in MODES[1:]}
    res["max_band_amplification_db"] = {m: max([0.0] + [-x for x in v if x is not None])
                                        for m, v in res["band_reduction_db"].items()}
    return res


def _print(res: dict, v) -> None:
    print(f"rig demo: floor {res['floor_rms_um']:.2f} um rms ({v.band_lo_hz:g}-{v.band_hi_hz:g} Hz), the same "
          f"realisation in all three runs: reductions are like with like")
    p = res["plant"]
    if p["model_error_pct"]:
        fac = ", ".join(f"{k} {100 * (x - 1):+.0f} %" for k, x in p["factors"].items())
        print(f"plant: actuator {p['model_error_pct']:g} % off the controllers' model ({fac}; {p['chosen']})")
    else:
        print(f"plant: {p['chosen']}")
    w = 26

    def row(label, cells):
        print(f"{label:28s}" + "".join(f"{c:>{w}s}" for c in cells))
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
