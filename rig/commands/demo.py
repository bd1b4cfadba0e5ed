"""`rig demo`: the four-mount rig on the simulated plant under broadband floor vibration, isolation off, then on.

Runs the product's control loop (rig/loop.py: read -> check -> update -> limit -> write) in simulated time
over the sim backend (RigPlant + FloorMotion from [vibration], one period of computation delay), with the
isolation controllers of controllers/isolation.py; switches isolation on half way (bumpless) and prints the rms
table and tool-point motion (Y) of each half and the reduction in dB.
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

from rig import cliargs
from rig.clock import SimClock
from rig.config import load_config
from rig.errors import RigError
from rig.lifecycle import State
from rig.session import Session


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--seconds", type=cliargs.seconds(ge=0.5, le=600), default=10.0, metavar="N",
                   help="simulated seconds per phase (isolation off, then on; default 10)")
    p.add_argument("--settle", type=cliargs.seconds(ge=0, le=600), default=1.0, metavar="S",
                   help="seconds discarded at the start of each phase (default 1)")
    p.add_argument("--rms-um", type=cliargs.Number(gt=0, le=1000, unit="um"), default=None, metavar="UM",
                   help="floor displacement rms in um (default: [vibration] rms_m of the config)")
    cliargs.output_arg(p, "--out", kind="folder", metavar="DIR", default=None,
                       help="write demo.png (time traces and spectra, off vs on) and demo.json to DIR")


def _rms(x):
    x = np.asarray(x, dtype=float)
    return float(np.sqrt(np.mean((x - x.mean()) ** 2)))


def _band(x, fs, lo=1.0, hi=100.0):
    sos = scipy.signal.butter(4, (lo, hi), btype="bandpass", fs=fs, output="sos")
    return scipy.signal.sosfiltfilt(sos, np.asarray(x, dtype=float))


def run(args) -> int:
    cfg = _demo_config(args)
    rate = cfg.loop.rate_hz
    dt = 1.0 / rate
    v = cfg.vibration
    _log(f"floor vibration {v.band_lo_hz:g}-{v.band_hi_hz:g} Hz, {v.rms_m * 1e6:g} um rms (seed {v.seed}); "
         f"loop {rate:g} Hz in simulated time; {args.seconds:g} s isolation off, then {args.seconds:g} s on")
    n = int(round(args.seconds * rate))
    tr, wall = _simulate(cfg, n)
    _log(f"{2 * n} periods in {wall:.1f} s wall ({wall / (2 * n) * 1e6:.1f} us per period)")
    s = int(round(args.settle * rate))
    off, on = slice(s, n), slice(n + s, 2 * n)
    res = _figures(tr, off, on, rate)
    res["loop"] = {"periods": 2 * n, "wall_s": wall, "path": "rig.loop.Loop.cycle over SimBackend(RigPlant)"}
    _print(res, v)
    if args.out is not None:
        try:
            args.out.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise RigError(f"--out {args.out}: cannot create directory ({e})") from None
        _plot(args.out / "demo.png", dt, n, tr["table"], tr["tool"], tr["floor"], off, on, res)
        (args.out / "demo.json").write_text(json.dumps(res, indent=2))
        _log(f"wrote {args.out / 'demo.png'} and {args.out / 'demo.json'}")
    return 0


def _log(text: str) -> None:
    print(f"rig demo: {text}", file=sys.stderr, flush=True)


def _demo_config(args):
    cfg = load_config(args.config)
    if not 0.5 <= args.seconds <= 600:
        raise RigError(f"--seconds: expected 0.5 to 600 s per phase, got {args.seconds}")
    if not 0 <= args.settle < args.seconds:
        raise RigError(f"--settle: expected 0 <= settle < seconds ({args.seconds}), got {args.settle}")
    if args.rms_um is not None:
        if not 0 < args.rms_um <= 1000:
            raise RigError(f"--rms-um: expected 0 < rms <= 1000 um, got {args.rms_um}")
        v = cfg.vibration
        cfg = cfg.replace(vibration=dataclasses.replace(v, rms_m=args.rms_um * 1e-6))
    return cfg


def _simulate(cfg, n: int):
    """n periods isolation off, then n on (bumpless switch), in simulated time: the plant's traces."""
    N = 2 * n
    tr = {"table": np.empty(N), "tool": np.empty(N), "floor": np.empty(N), "cmd": np.empty((N, 4)),
          "stroke": np.empty((N, 4)), "limited": np.zeros(N, dtype=bool)}
    dt = 1.0 / cfg.loop.rate_hz
    with Session(cfg, "sim", clock=SimClock(), isolation=False, port_options={"cmd_delay_periods": 1}) as session:
        loop, plant = session.loop, session.port.plant
        loop.activate()
        t0 = time.perf_counter()
        for k in range(N):
            if k == n:
                loop.request_isolation(True)
                _log(f"t = {k * dt:.1f} s: isolation on")
            loop.cycle(k * loop.period_ns)
            if loop.state is State.FAULT:
                raise RigError(f"demo: the loop faulted at t = {k * dt:.3f} s: {loop.lc.fault_reason}")
            tr["table"][k] = plant.table_m
            tr["tool"][k] = plant.tool_m
            tr["floor"][k] = sum(plant.floor_m) * 0.25
            tr["cmd"][k] = loop.cmd
            tr["stroke"][k] = plant.stroke_m
            tr["limited"][k] = loop.limiter.limited
        return tr, time.perf_counter() - t0


def _figures(tr, off, on, fs) -> dict:
    res = {"floor_rms_um": {}, "table_rms_um": {}, "tool_rms_um": {}, "reduction_db": {},
           "valve_limited_fraction": {}, "valve_rms_V": {}, "max_abs_stroke_um": {}}
    for tag, sl in (("off", off), ("on", on)):
        res["floor_rms_um"][tag] = _rms(tr["floor"][sl]) * 1e6
        res["table_rms_um"][tag] = _rms(tr["table"][sl]) * 1e6
        res["tool_rms_um"][tag] = _rms(tr["tool"][sl]) * 1e6
        res["table_rms_um"][tag + "_1_100hz"] = _rms(_band(tr["table"][sl], fs)) * 1e6
        res["tool_rms_um"][tag + "_1_100hz"] = _rms(_band(tr["tool"][sl], fs)) * 1e6
        res["valve_limited_fraction"][tag] = float(tr["limited"][sl].mean())
        res["valve_rms_V"][tag] = float(np.sqrt(np.mean(tr["cmd"][sl] ** 2)))
        res["max_abs_stroke_um"][tag] = float(np.max(np.abs(tr["stroke"][sl]))) * 1e6
    for key in ("table", "tool"):
        r = res[f"{key}_rms_um"]
        res["reduction_db"][key] = 20 * math.log10(r["off"] / r["on"])
        res["reduction_db"][key + "_1_100hz"] = 20 * math.log10(r["off_1_100hz"] / r["on_1_100hz"])
    return res


def _print(res: dict, v) -> None:
    print(f"rig demo: floor {res['floor_rms_um']['off']:.2f} um rms ({v.band_lo_hz:g}-{v.band_hi_hz:g} Hz)")
    print(f"{'':24s}{'isolation off':>15s}{'isolation on':>15s}{'reduction':>12s}")
    for key, lab in (("table", "table Y rms"), ("tool", "tool point Y rms")):
        r = res[f"{key}_rms_um"]
        print(f"{lab:24s}{r['off']:12.3f} um{r['on']:12.3f} um{res['reduction_db'][key]:9.1f} dB")
        print(f"{lab + ' (1-100 Hz)':24s}{r['off_1_100hz']:12.3f} um{r['on_1_100hz']:12.3f} um"
              f"{res['reduction_db'][key + '_1_100hz']:9.1f} dB")
    print(f"{'valve command rms':24s}{res['valve_rms_V']['off']:12.3f} V {res['valve_rms_V']['on']:12.3f} V")
    print(f"{'periods at valve limit':24s}{100 * res['valve_limited_fraction']['off']:12.1f} % "
          f"{100 * res['valve_limited_fraction']['on']:12.1f} %")
    print(f"{'max |stroke|':24s}{res['max_abs_stroke_um']['off']:12.1f} um{res['max_abs_stroke_um']['on']:12.1f} um")
    if res["valve_limited_fraction"]["on"] > 0.01:
        print(f"note: the valve was at its limit in {100 * res['valve_limited_fraction']['on']:.1f} % of the "
              f"isolated periods (the loop is then not linear; see --rms-um)")


def _plot(path, dt, n, table, tool, floor, off, on, res):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import scipy.signal
    t = np.arange(len(table)) * dt
    fig, axs = plt.subplots(2, 2, figsize=(13, 8))
    for ax, y, lab in ((axs[0, 0], table, "table"), (axs[0, 1], tool, "tool point")):
        ax.plot(t, floor * 1e6, color="0.7", lw=0.5, label="floor (mean of mounts)")
        ax.plot(t, y * 1e6, "b-", lw=0.6, label=f"{lab} Y")
        ax.axvline(n * dt, color="r", ls="--", lw=1)
        ax.set_xlabel("time [s]  (isolation on at the red line)")
        ax.set_ylabel("displacement [um]")
        ax.set_title(f"{lab} Y: {res['reduction_db']['table' if lab == 'table' else 'tool']:.1f} dB rms reduction")
        ax.legend(fontsize=8, loc="upper right")
        ax.grid(alpha=0.3)
    fs = 1.0 / dt
    for ax, y, lab in ((axs[1, 0], table, "table"), (axs[1, 1], tool, "tool point")):
        for sl, style, name in ((off, "k-", "isolation off"), (on, "b-", "isolation on")):
            f, P = scipy.signal.welch(y[sl], fs=fs, nperseg=min(1 << 14, sl.stop - sl.start))
            ax.loglog(f[1:], np.sqrt(P[1:]) * 1e6, style, lw=0.9, label=name)
        f, P = scipy.signal.welch(floor[off], fs=fs, nperseg=min(1 << 14, off.stop - off.start))
        ax.loglog(f[1:], np.sqrt(P[1:]) * 1e6, color="0.7", lw=0.8, label="floor")
        ax.set_xlim(0.3, 500)
        top = ax.get_ylim()[1]
        ax.set_ylim(top * 1e-7, top)            # seven decades: the band of interest, not the FFT floor
        ax.set_xlabel("frequency [Hz]")
        ax.set_ylabel("ASD [um/sqrt(Hz)]")
        ax.set_title(f"{lab} Y spectrum")
        ax.legend(fontsize=8)
        ax.grid(alpha=0.3, which="both")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
