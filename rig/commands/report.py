"""`rig report REC`: the vibration-criterion report of a run recording (rig run --record, rig hil --record):
one-third-octave rms velocity of the machine at its mounts per isolation mode (off / feedback / feedback +
feedforward) against the VC-A..G and ISO lines, the class met, and with floor accelerometers the floor's and
the transmissibility mount / floor per band (rig/report.py).

  rig report REC [--settle S] [--out DIR] [--json]
--out DIR writes report.png and report.json; --json prints only the JSON on stdout.
"""
from __future__ import annotations

import json
import sys

from rig import cliargs, report


def add_arguments(p) -> None:
    p.add_argument("recording", metavar="REC", help="HDF5 recording of rig run --record or rig hil")
    p.add_argument("--settle", type=cliargs.seconds(ge=0, le=60), default=1.0, metavar="S",
                   help="seconds left out at the start of each mode (switching fade; default 1)")
    cliargs.output_arg(p, "--out", kind="folder", metavar="DIR", default=None,
                       help="write report.png and report.json to DIR")
    cliargs.output_arg(p, "--plot", metavar="FILE", default=None, suffix=".png",
                       help="write the VC curves of each isolation mode (report.png of --out) to FILE")
    p.add_argument("--json", action="store_true", help="print only the JSON result on stdout")


def run(args) -> int:
    cliargs.log_to_stderr("report")          # the readers' warnings: `rig report: warning: ...`
    rep = report.vc_of_recording(args.recording, settle_s=args.settle)
    for mode, why in rep["skipped_modes"].items():
        print(f"rig report: warning: {args.recording}: {mode}: too short for a VC report ({why})", file=sys.stderr)
    if args.out is not None:
        cliargs.make_out_dir(args.out)
        report.plot(args.out / "report.png", rep)
        (args.out / "report.json").write_text(json.dumps(rep, indent=2))
        print(f"rig report: wrote {args.out / 'report.png'} and {args.out / 'report.json'}", file=sys.stderr)
    if args.plot is not None:
        report.plot(args.plot, rep)
        print(f"rig report: wrote {args.plot}", file=sys.stderr)
    if args.json:
        print(json.dumps(rep, indent=2))
        return 0
    print(f"{rep['recording']}: {rep['measured']}")
    floor = "vc_class_floor" in rep
    print(f"  {'mode':22s} {'stretch':>17s}  {'machine (worst mount)':24s}" +
          (f"{'floor':24s} mount/floor (band mean)" if floor else ""))
    for mode, seg in rep["segments"].items():
        line = f"  {mode:22s} {seg['t0_s']:7.1f}-{seg['t1_s']:7.1f} s  {rep['vc_class'][mode]:24s}"
        if floor:
            tr = [x for x in rep["transmissibility_db"][mode] if x is not None]
            line += f"{rep['vc_class_floor'][mode]:24s} {sum(tr) / len(tr):+.1f} dB"
        print(line)
    if "off" in rep["absent_modes"]:
        print(f"  off: {rep['absent_modes']['off']}")
    print(report.summary(rep))
    return 0
