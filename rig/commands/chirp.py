"""`rig chirp --record REC`: the paper's identification run, through the runtime loop (rig/chirp.py runs it).

`--levels` plays the same sweep at several amplitudes back to back, `--multisine` an odd random-phase multisine
(rig/excitation.py); both are recorded the same way, with the signal's description in the file's attributes.
"""
from __future__ import annotations

import argparse
import sys


from rig import cliargs
from rig.backends import BACKENDS
from rig.config import load_config
from rig.errors import EXIT_SUSPECT, RigError


class _Renamed(argparse.Action):
    """`rig chirp --out FILE` of earlier versions: one line saying what it is now."""
    def __call__(self, parser, namespace, values, option_string=None):
        parser.error("--out: the chirp's recording is --record FILE now (--out names a folder of reports, "
                     "in every command)")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--backend", choices=tuple(BACKENDS), default=None,
                   help="backend (default: [backend] name in the config, else sim)")
    p.add_argument("--amplitude", type=cliargs.Number(gt=0, le=50, unit="V"), default=2.0, metavar="V",
                   help="chirp amplitude, V (default 2)")
    p.add_argument("--f0", type=cliargs.Number(ge=0, unit="Hz"), default=0.1, metavar="HZ",
                   help="start frequency, Hz (default 0.1)")
    p.add_argument("--f1", type=cliargs.Number(gt=0, unit="Hz"), default=100.0, metavar="HZ",
                   help="end frequency, Hz (default 100)")
    p.add_argument("--duration", "--seconds", dest="duration", type=cliargs.seconds(le=cliargs.MAX_CHIRP_S),
                   default=100.0, metavar="S", help="the whole chirp's length, s, as --seconds is the whole run in "
                   "rig run and hil (default 100; --settle comes before it)")
    p.add_argument("--rate", type=cliargs.rate_hz(), default=None, metavar="HZ",
                   help="loop (and recording) rate, Hz (default: [loop] rate_hz; hil: [hil] rate_hz)")
    p.add_argument("--mount", default="front_left",
                   help="mount whose valve is chirped (hil/hardware; a name of the config's layout)")
    p.add_argument("--settle", type=cliargs.seconds(ge=0, le=3600), default=0.05, metavar="S",
                   help="seconds INACTIVE (valve at null, sensors checked) before the chirp (default 0.05)")
    p.add_argument("--uncommissioned", action="store_true",
                   help="hardware: chirp without a calibration from `rig commission` (docs/COMMISSIONING.md)")
    p.add_argument("--realtime", action="store_true", help="sim backend: pace on the wall clock (default: "
                   "simulated time, as fast as possible)")
    p.add_argument("--seed", type=cliargs.seed(), default=None,
                   help="sim backend: sensor noise seed (default: [stand] seed)")
    cliargs.output_arg(p, "--record", metavar="FILE", required=True,
                       help="recording to write (HDF5; with --csv the shared CSV format, gzip if it ends in .gz)")
    p.add_argument("--out", action=_Renamed, help=argparse.SUPPRESS)
    p.add_argument("--csv", action="store_true", help="write the shared CSV format instead of HDF5")
    p.add_argument("--levels", type=level_list, default=None, metavar="V,V,...",
                   help="the same sweep at several amplitudes back to back, e.g. 0.5,1.5,3.0 (each --duration "
                        "long; rig diagnose then shows gain by level: saturation, deadband, linear)")
    p.add_argument("--multisine", action="store_true",
                   help="an odd random-phase multisine over f0..f1 instead of the chirp (--period per period, "
                        "--duration rounded to whole periods); its empty lines detect nonlinearity")
    p.add_argument("--period", type=cliargs.seconds(le=cliargs.MAX_CHIRP_S), default=10.0, metavar="S",
                   help="multisine period, s (default 10: 0.1 Hz line spacing)")
    p.add_argument("--json", action="store_true", help="print only the JSON result on stdout")


_LEVEL = cliargs.Number(gt=0, le=50, unit="V")


def level_list(text: str) -> list[float]:
    """`--levels 0.5,1.5,3.0` (argparse type): at least two amplitudes, each > 0 and <= 50 V."""
    levels = [_LEVEL(x.strip()) for x in text.split(",") if x.strip()]
    if len(levels) < 2:
        raise argparse.ArgumentTypeError(f"expected at least two levels like 0.5,1.5,3.0, got {text!r}")
    return levels


def run(args) -> int:
    from rich.console import Console
    from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

    name = args.record.name.lower()
    csv_name = name.endswith((".csv", ".csv.gz"))
    if args.csv != csv_name and (csv_name or name.endswith((".h5", ".hdf5"))):   # `rig identify` reads by name
        raise RigError(f"--record {args.record}: " + ("--csv writes CSV: expected a name ending in .csv or .csv.gz"
                                                      if args.csv else "expected --csv for a .csv name (without it "
                                                                       "the recording is HDF5), or a .h5 name"))
    from rig.chirp import run_chirp          # heavy (numba, scipy): after the arguments are checked
    cfg = load_config(args.config)
    backend = args.backend or cfg.backend.name
    if args.realtime and backend != "sim":
        raise RigError("--realtime: only for --backend sim (hil and hardware always run in real time)")
    if backend == "hardware" and not args.uncommissioned:
        from rig.commands.run import check_commissioned     # no uncommissioned hardware: the rule of rig run
        check_commissioned(cfg)
    bar = Progress(TextColumn("chirp"), BarColumn(), TextColumn("{task.completed:6.1f}/{task.total:.1f} s"),
                   TimeRemainingColumn(), console=Console(stderr=True), redirect_stdout=False)
    task = None

    def progress(t_s, total_s):
        nonlocal task
        if task is None:                    # the bar starts with the run: a refusal before it prints no empty line
            bar.start()
            task = bar.add_task("chirp", total=total_s)
        bar.update(task, completed=t_s)

    try:
        s = run_chirp(cfg, backend=backend, amplitude_V=args.amplitude, f0_hz=args.f0, f1_hz=args.f1,
                      duration_s=args.duration, rate_hz=args.rate, out=args.record, csv=args.csv, mount=args.mount,
                      settle_s=args.settle, sim_time=(backend == "sim" and not args.realtime), seed=args.seed,
                      progress=progress, levels_V=args.levels, multisine=args.multisine, period_s=args.period)
    finally:
        if task is not None:
            bar.stop()
    what = ("chirp at levels " + ",".join(f"{v:g}" for v in args.levels) + " V" if args.levels
            else f"odd multisine (period {args.period:g} s)" if args.multisine else "chirp")
    if args.json:
        import json
        print(json.dumps({"signal": what, "f0_hz": args.f0, "f1_hz": args.f1, "amplitude_V": args.amplitude,
                          "duration_s": args.duration, **s}))
    else:
        print(f"{what} {args.f0:g}->{args.f1:g} Hz, {args.amplitude:g} V, {args.duration:g} s on the {backend} backend at "
              f"{s['rate_hz']:g} Hz: {s['rows_written']} samples -> {s['recording']} ({s['format']}); "
              f"{s['wall_s']:.1f} s wall, overruns {s['overruns']}, dropped rows {s['dropped_rows']}")  # the result
    missing = s["skipped_periods"] + s["dropped_rows"]
    if missing:
        print(f"rig chirp: warning: the recording has gaps: {missing} rows missing ({s['skipped_periods']} loop periods skipped "
              f"by overruns, {s['dropped_rows']} rows dropped by the recorder); rig identify bridges gaps of a few "
              f"samples and otherwise uses the longest stretch without one. Lower --rate or free the CPU for a "
              f"whole recording", file=sys.stderr)
    print(f"next: rig identify {s['recording']}", file=sys.stderr)     # a hint, not a figure
    return EXIT_SUSPECT if missing else 0
