"""`rig export REC --to mat|csv [--out DIR]`: a recording for MATLAB or a spreadsheet, with its metadata and
units (rig/export.py says what goes where).

  rig export run.h5 --to mat                   -> run.mat (a variable per dataset, the struct meta)
  rig export run.h5 --to csv --out exported    -> exported/run.csv, run.meta.json, run.events.csv
The files take REC's name, beside REC or in the folder --out (made if missing, as every command's --out);
nothing is overwritten without --overwrite. What was
written goes to stdout (--json: only JSON), progress to stderr.
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

from rig import cliargs, export
from rig.errors import RigError

SUFFIX = {"mat": (".mat",), "csv": (".csv", ".csv.gz")}


def add_arguments(p) -> None:
    p.add_argument("recording", metavar="REC", help="HDF5 recording of rig run --record, rig chirp or rig hil")
    p.add_argument("--to", choices=export.FORMATS, required=True,
                   help="mat: MATLAB (scipy.io.savemat, v5); csv: one header line naming each column, with "
                        "FILE.meta.json (units, labels, attributes, events) and FILE.events.csv beside it")
    cliargs.output_arg(p, "--out", kind="folder", metavar="DIR", default=None,
                       help="folder to write REC's name with .mat or .csv into (and the CSV's sidecars; "
                            "default: REC's folder)")
    p.add_argument("--gzip", action="store_true", help="--to csv: gzip the table (.csv.gz)")
    p.add_argument("--json", action="store_true", help="print only the JSON result on stdout")


def output_path(rec: Path, fmt: str, out: Path | None, gzip: bool = False) -> Path:
    """The file to write: REC's name with the format's suffix, in --out (a folder) or beside REC."""
    if gzip and fmt != "csv":
        raise RigError(f"--gzip: for --to csv only (got --to {fmt})")
    return (out if out is not None else rec.parent) / (rec.stem + SUFFIX[fmt][1 if gzip else 0])


def run(args) -> int:
    cliargs.log_to_stderr("export")          # the readers' warnings: `rig export: warning: ...`
    rec = Path(args.recording)
    out = output_path(rec, args.to, args.out, args.gzip)
    files = [out] + (list(export.sidecars(out)) if args.to == "csv" else [])
    if out.resolve() == rec.resolve():      # before "exists": no --overwrite makes this right
        raise RigError(f"{out}: the export would write over the recording itself (it is already a .{args.to} "
                       f"file)")
    if not args.overwrite:                  # the default name is not an option check_outputs saw
        for f in files:
            if f.exists():
                raise RigError(f"{f}: file exists (add --overwrite to replace it)")
    exp = export.load(rec)
    out.parent.mkdir(parents=True, exist_ok=True)           # once REC is read: a refused REC leaves no folder
    if args.to == "mat":
        export.write_mat(exp, out)
    else:
        shown = [0]

        def progress(done: int, total: int) -> None:     # every tenth of a long table, and its end
            tenth = 10 * done // max(total, 1)
            if total >= 10 * export.CSV_CHUNK_ROWS and (tenth > shown[0] or done == total):
                shown[0] = tenth
                print(f"rig export: {done} / {total} rows", file=sys.stderr, flush=True)
        export.write_csv(exp, out, progress)
    cols = exp.columns()
    result = {"recording": str(rec), "format": args.to, "files": [str(f) for f in files], "rows": exp.rows,
              "datasets": len(exp.data), "columns": len(cols), "events": len(exp.events)}
    if args.json:
        print(json.dumps(result, indent=2))
        return 0
    print(f"{rec}: {exp.rows} rows, {len(exp.data)} datasets ({len(cols)} columns), {len(exp.events)} events")
    for f in files:
        print(f"  wrote {f}")
    return 0
