"""`rig prove`: blind proof of the diagnosis on simulated cases or on a folder of recordings with answers."""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from rig import cliargs
from rig.commands import prove_rig
from rig.errors import RigError


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--cases", metavar="DIR", type=Path, default=None,
                   help="grade the recordings of DIR against its answers.json (default: simulate blind cases)")
    p.add_argument("--seed", type=cliargs.seed(), default=1, help="seed of the blind cases (default 1)")
    p.add_argument("--n", type=cliargs.count(1, 10000), default=30, help="number of blind cases (default 30)")
    p.add_argument("--duration", type=cliargs.seconds(ge=1, le=1000), default=None, metavar="S",
                   help="chirp length of the blind cases, 0.1 -> 100 Hz (default 100 s, as the paper); with "
                        "--habits the longest a case may be (lengths are drawn from 20 s up; default 200 s)")
    p.add_argument("--habits", action="store_true",
                   help="every blind case also carries the habits of real recordings, with random sizes: sensor "
                        "offset, drift and wander, mains pickup, quantisation, coloured noise, mid-run starts, "
                        "any excitation type, sample rates 500 Hz - 10 kHz, lengths 20-200 s")
    p.add_argument("--plant", metavar="FILE", type=Path, default=None,
                   help="plant file (TOML, docs/PLANT.md): make the blind cases on its mechanical axis (friction, "
                        "deadband, delay, constant force, saturation; encoder terms; open and closed loop)")
    p.add_argument("--rig", action="store_true",
                   help="blind proof on the four-mount rig: closed-loop runs (isolation off, feedback, feedforward; "
                        "floor accelerometers or not) hiding machine-level effects, recorded as rig run --record "
                        "does and diagnosed (default --duration 60 s)")
    p.add_argument("--commission", action="store_true",
                   help="blind proof of rig commission on the emulated rig: each case wires it wrong in two or three "
                        "ways from drivers/devicemaps/hil_wiring_faults.md and grades what commissioning names "
                        "(real time: about 20 s a case; --config: the HIL configuration, default hil.toml)")
    p.add_argument("--clean", type=cliargs.count(0, 1000), default=10, metavar="N",
                   help="with --commission: also N rigs wired right, none of which may be flagged (default 10)")
    p.add_argument("--single", action="store_true",
                   help="with --commission: every fault of the table alone, named and corrected, then `rig hil` "
                        "with its calibration against the rig wired right, alternately (docs/COMMISSIONING.md "
                        "\"Single faults\"; about 70 min with the default --repeats 2 on a loaded 2-core machine)")
    p.add_argument("--kinds", metavar="FAULT,...", default=None,
                   help="with --single: only these faults of the table, e.g. accel_sign,valve_null (default all)")
    p.add_argument("--all-mounts", action="store_true",
                   help="with --single: each fault on every mount (default: the mount turns per fault, each "
                        "mount comes up)")
    p.add_argument("--repeats", type=cliargs.count(1, 20), default=2, metavar="N",
                   help="with --single: `rig hil` runs of each rig, calibrated and wired right, per case (default 2)")
    p.add_argument("--retries", type=cliargs.count(0, 5), default=0, metavar="N",
                   help="with --commission: run a commissioning (with --single also a `rig hil`) stopped by a fault (a "
                        "loaded host: a device stall, missed deadlines) again, up to N times; every stop is reported "
                        "(default 0)")
    p.add_argument("--hil-seconds", type=cliargs.seconds(ge=3, le=3600), default=None, metavar="S",
                   help="with --single: each `rig hil` run's length (default [hil] seconds of the config, 15 s)")
    cliargs.output_arg(p, "--keep", kind="folder", metavar="DIR", default=None,
                       help="with --rig: keep each case's recording and its graded row (JSON) in DIR")
    p.add_argument("--workers", type=cliargs.count(1, 64), default=2, help="processes (default 2)")
    p.add_argument("--scheduler", metavar="tcp://HOST:PORT", default=None,
                   help="run the cases on the Dask cluster of this scheduler instead of --workers processes "
                        "(docs/BATCH.md; --cases: the workers must see the folder at the same path)")
    cliargs.output_arg(p, "--out", kind="folder", metavar="DIR", default=None,
                   help="write the table, confusion matrix and score as DIR/proof.md and DIR/proof.json")
    p.add_argument("--json", action="store_true", help="print only the JSON result on stdout")


def _check(args) -> bool:
    """The options' checks; the default duration set. Whether --duration was given."""
    if args.workers < 1:
        raise RigError(f"--workers: expected at least 1, got {args.workers}")
    given = args.duration is not None
    if not given:
        args.duration = 200.0 if args.habits else 100.0
    if not 1.0 <= args.duration <= 1000.0:
        raise RigError(f"--duration: expected 1 to 1000 s, got {args.duration}")
    if args.habits and args.duration < 20.0:
        raise RigError(f"--duration: with --habits expected at least 20 s (cases are 20 s and longer), "
                       f"got {args.duration:g}")
    return given


def _where(args) -> str:
    if args.scheduler is None:
        return f"on {args.workers} processes"
    from rig.batch.pool import check_address
    return f"on the Dask cluster at {check_address(args.scheduler)}"


def _refuse_other_modes(args) -> None:
    """An option of another mode is refused, not ignored (the defaults: add_arguments)."""
    for option, given, mode, on in (("--kinds", args.kinds is not None, "--single", args.single),
                                    ("--all-mounts", args.all_mounts, "--single", args.single),
                                    ("--repeats", args.repeats != 2, "--single", args.single),
                                    ("--hil-seconds", args.hil_seconds is not None, "--single", args.single),
                                    ("--clean", args.clean != 10, "--commission", args.commission),
                                    ("--retries", args.retries != 0, "--commission", args.commission),
                                    ("--keep", args.keep is not None, "--rig", args.rig)):
        if given and not on:
            raise RigError(f"{option}: expected with {mode} (see rig prove --help)")


def run(args) -> int:
    _refuse_other_modes(args)
    if args.rig:                                    # the four-mount rig (issue 28): its own defaults
        return prove_rig.run(args)
    if args.single and not args.commission:
        raise RigError("--single: expected with --commission (rig prove --commission --single)")
    if args.commission:                             # the wiring checks (issue 27), on the emulated rig
        from rig.commands import prove_commission
        return prove_commission.run(args)
    from rig.config import load_config
    from rig.diagnose import grading, prove
    from sim_backend.linear import ActuatorParams

    cfg = load_config(args.config) if args.config else None
    p0 = ActuatorParams() if cfg is None else ActuatorParams.from_config(cfg)
    given = _check(args)

    def progress(done: int, total: int, label: str) -> None:
        print(f"[{done}/{total}] diagnosed {label}", file=sys.stderr, flush=True)

    where = _where(args)
    cases = None
    plant = None
    if args.plant is not None:
        from rig.plant.file import load_plant
        plant = load_plant(args.plant, p0)
        if plant.family == "eha":
            p0 = plant.actuator
            plant = None
    if plant is not None:
        from rig.diagnose import prove_axis
        if args.cases is not None:
            raise RigError("--plant and --cases: grade a folder against its answers.json, or make cases on the "
                           "plant, not both")
        title = f"rig prove --plant {args.plant} --n {args.n} --seed {args.seed}"
        print(f"rig prove: {args.n} blind cases from seed {args.seed} on {plant.describe()} {where}",
              file=sys.stderr, flush=True)
        cases, rows = prove_axis.prove_plant(args.n, args.seed, plant, workers=args.workers, progress=progress,
                                             scheduler=args.scheduler)
    elif args.cases is not None:
        title = f"rig prove --cases {args.cases}"
        n = len(prove.read_answers(args.cases))
        print(f"rig prove: grading {n} recordings of {args.cases} {where}", file=sys.stderr, flush=True)
        rows = prove.prove_folder(args.cases, p0, seed=args.seed, workers=args.workers, progress=progress,
                                  scheduler=args.scheduler)
    else:
        title = f"rig prove --n {args.n} --seed {args.seed}"
        if given:
            title += f" --duration {args.duration:g}"
        if args.habits:
            title += " --habits"
        what = "cases with the habits of real recordings" if args.habits else f"{args.duration:g} s chirps"
        print(f"rig prove: {args.n} blind cases from seed {args.seed} ({what}) "
              f"{where}", file=sys.stderr, flush=True)
        cases, rows = prove.prove_generated(args.n, args.seed, p0, duration_s=args.duration,
                                            workers=args.workers, progress=progress, habits=args.habits,
                                            scheduler=args.scheduler)

    result = grading.report_json(rows, title, cases)
    if args.out is not None:
        try:
            args.out.mkdir(parents=True, exist_ok=True)
            (args.out / "proof.md").write_text(grading.report_markdown(rows, title))
            (args.out / "proof.json").write_text(json.dumps(result, indent=1))
        except OSError as e:
            raise RigError(f"--out {args.out}: cannot write ({e.strerror})") from None
    if args.json:
        print(json.dumps(result, indent=1))
    else:
        print(grading.table_markdown(rows))
        print("confusion matrix (rows: truth, columns: named)\n")
        print(grading.confusion_markdown(result["confusion"]))
        hab = grading.habits_markdown(result["score"])
        if hab:
            print("by habit\n")
            print(hab)
        print(grading.score_text(result["score"]))
        if args.out is not None:
            print(f"\nwritten: {args.out / 'proof.md'}, {args.out / 'proof.json'}")
    return 0
