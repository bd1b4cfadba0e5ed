"""`rig identify REC [--json] [--out DIR]`: the six actuator parameters from a chirp recording (Eq. 11, Fig. 3).

`rig identify REC... --out DIR` (several files, a folder or a glob): a batch (rig/batch/): each recording's
outputs in DIR/<name>/, on --workers processes or a Dask cluster (--scheduler), with DIR/summary.{csv,md,json}
and the trends of the identified parameters over the recordings' dates."""
from __future__ import annotations

import argparse
import json
import sys
import time
from functools import partial
from pathlib import Path

from rig import cliargs
from rig.batch import command as batch
from rig.batch.run import Job, file_identity
from rig.errors import EXIT_SUSPECT, RigError
from rig.runtime.signals import off_the_main_thread


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("recording", metavar="REC", type=Path, nargs="+",
                   help="chirp recording (CSV, CSV.gz, HDF5 or .mat; time_s,valve_cmd_V,position_m,accel_mps2); "
                        "several, a folder or a quoted glob ('runs/**/*.h5'): a batch (--out needed)")
    p.add_argument("--json", action="store_true",
                   help='print only {"parameters", "std", "fit", ...} as JSON (SI units, w_nv in rad/s)')
    cliargs.output_arg(p, "--out", kind="folder", metavar="DIR", default=None,
                       help="write identified.md (table beside Table 1), identify.json and fig3_bode.png here (a "
                            "batch: one folder per recording in it, and the summary; run again into it, it resumes)")
    cliargs.output_arg(p, "--plot", metavar="FILE", default=None, suffix=".png",
                       help="write the Bode plot of the identified model against the measured FRF (the paper's "
                            "Fig. 3) to FILE (.png added to a name without a suffix)")
    p.add_argument("--starts", type=cliargs.count(1, 1000), default=8,
                   help="multi-start count of the FRF fit (default 8)")
    p.add_argument("--seed", type=cliargs.seed(), default=0, help="seed of the multi-start points (default 0)")
    p.add_argument("--repeat", type=cliargs.count(1, 1000), default=1, metavar="N",
                   help="benchmark: identify N times and print p50/p99/max of the time on stderr")
    p.add_argument("--plant", metavar="FILE", type=Path, default=None,
                   help="plant file (TOML, docs/PLANT.md): identify its free parameters (mechanical_axis, "
                        "transfer_function) by output error; an eha plant file: the six actuator parameters; "
                        "[signals] names REC's own columns or variables and their units")
    p.add_argument("--no-refine", action="store_true",
                   help="skip the time-domain output-error refinement (FRF fit only, as the paper)")
    batch.add_arguments(p)


def table_markdown(res) -> str:
    """The identified parameters beside Table 1 (the design values the fit started from)."""
    from rig.identify import UNITS
    from sim_backend.linear import IDENTIFIED
    lines = ["| parameter | unit | Table 1 (design) | identified | 1-sigma | change | note |",
             "|---|---|---|---|---|---|---|"]
    change = res.change_pct()
    for k in IDENTIFIED:
        v0, v, s = getattr(res.p0, k), getattr(res.params, k), res.std[k]
        note = "weak (prior-held)" if k in res.weakly_identified else ""
        lines.append(f"| {k} | {UNITS[k]} | {v0:.4g} | {v:.4g} | {s:.2g} | {change[k]:+.1f} % | {note} |")
    f = res.fit
    lag = round(100 * (f['K_C*K_L'] / (res.p0.K_C * res.p0.K_L) - 1), 1) + 0.0      # (never -0.0)
    lines.append(f"| K_C*K_L | m^4/s | {res.p0.K_C * res.p0.K_L:.4g} | {f['K_C*K_L']:.4g} | "
                 f"{f['K_C*K_L'] * f['K_C*K_L_rel_std']:.2g} | {lag:+.1f} % | lag corner, well fixed |")
    return "\n".join(lines)


def fit_markdown(res) -> str:
    f = res.fit
    rows = [("time-domain NRMSE", f"{f['initial_nrmse']:.4f}", f"{f['nrmse']:.4f}"),
            ("time-domain residual rms", f"{f['initial_residual_rms_m'] * 1e9:.1f} nm",
             f"{f['residual_rms_m'] * 1e9:.1f} nm"),
            ("FRF error rms (magnitude)", f"{f['initial_frf_err_db']:.3f} dB", f"{f['frf_err_db']:.3f} dB"),
            ("FRF error rms (phase)", f"{f['initial_frf_err_deg']:.2f} deg", f"{f['frf_err_deg']:.2f} deg")]
    out = ["| fit quality | Table 1 model | identified model |", "|---|---|---|"]
    out += [f"| {a} | {b} | {c} |" for a, b, c in rows]
    out.append("")
    if "warning" in f:
        out.append(f"WARNING: {f['warning']}.")
    minima = f"{f['distinct_minima']} distinct {'minimum' if f['distinct_minima'] == 1 else 'minima'}"
    out.append(f"FRF band used: {f['band_hz'][0]:.3g}-{f['band_hz'][1]:.3g} Hz ({f['n_frf_bins']} bins, coherence >= "
               f"{f['coherence_min']:.3f}); {f['starts']} starts, {minima}; "
               f"time-domain refinement: {'yes' if f['refined_time_domain'] else 'no'}.")
    return "\n".join(out)


def weak_markdown(res) -> str:
    return "\n".join(f"- **{k}**: {v}" for k, v in res.weakly_identified.items())


def plot_fig3(res, path: Path) -> Path:
    """Fig. 3 of the paper: measured FRF vs the initial (Table 1) and the identified model, Bode."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np
    from rig.identify import model_frf

    frf = res.frf
    lo, hi = frf.band_hz
    sel = (frf.freqs_hz >= lo) & (frf.freqs_hz <= hi)
    f = frf.freqs_hz[sel]
    w = 2 * np.pi * f
    Hm = frf.H[sel]
    H0 = model_frf(res.p0, w, frf.fs_hz)
    H1 = model_frf(res.params, w, frf.fs_hz)
    fig, (a1, a2, a3) = plt.subplots(3, 1, figsize=(7.5, 8.5), sharex=True,
                                     gridspec_kw={"height_ratios": [3, 3, 1.3]})
    for H, style, label in ((Hm, dict(color="0.3", lw=0, marker=".", ms=3), "measured (H1)"),
                            (H0, dict(color="tab:orange", ls="--", lw=1.5), "initial model (Table 1)"),
                            (H1, dict(color="tab:blue", lw=1.5), "identified model")):
        a1.semilogx(f, 20 * np.log10(np.abs(H) * 1e6), label=label, **style)
        a2.semilogx(f, np.degrees(np.unwrap(np.angle(H))), **style)
    a3.semilogx(f, frf.coherence[sel], color="0.3", lw=1)
    a1.set_ylabel("|x_p / v| [dB re 1 um/V]")
    a2.set_ylabel("phase [deg]")
    a3.set_ylabel("coherence")
    a3.set_ylim(0, 1.05)
    a3.set_xlabel("frequency [Hz]")
    for a in (a1, a2, a3):
        a.grid(True, which="both", alpha=0.3)
    a1.legend(loc="lower left")
    fit = res.fit
    a1.set_title(f"Valve voltage -> position: {Path(res.frf_source).name}\n"
                 f"FRF error {fit['initial_frf_err_db']:.2f} dB / {fit['initial_frf_err_deg']:.1f} deg (initial) -> "
                 f"{fit['frf_err_db']:.2f} dB / {fit['frf_err_deg']:.2f} deg (identified)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def write_outputs(res, out: Path) -> dict[str, Path]:
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise RigError(f"--out {out}: cannot create folder ({e.strerror or e})") from None
    if not out.is_dir():
        raise RigError(f"--out {out}: exists and is not a folder")
    paths = {"table": out / "identified.md", "json": out / "identify.json", "fig3": out / "fig3_bode.png"}
    md = [f"# Identification of {res.frf_source}", "",
          "Six parameters x_d of Eq. 11 from the valve chirp; M, A_p, V_t, beta, K_v at their Table 1 values.", "",
          table_markdown(res), "", fit_markdown(res), "", "## Identifiability", "", weak_markdown(res), "",
          "Bounds: " + ", ".join(f"{k} {lo:.3g}..{hi:.3g}" for k, (lo, hi) in res.bounds.items()), "",
          "![Fig. 3 comparison](fig3_bode.png)", ""]
    try:
        paths["table"].write_text("\n".join(md))
        paths["json"].write_text(json.dumps(res.to_json(), indent=1))
        plot_fig3(res, paths["fig3"])
    except OSError as e:
        raise RigError(f"--out {out}: cannot write ({e.strerror or e})") from None
    return paths


def _run_plant(args, rec, plant, t0: float) -> int:
    """A mechanical_axis or transfer_function plant: its free parameters (rig.diagnose.refit)."""
    from rig.diagnose.refit import identify_plant

    def progress(stage: str, frac: float) -> None:
        print(f"[{time.perf_counter() - t0:5.2f} s] {100 * frac:3.0f} % {stage}", file=sys.stderr, flush=True)

    res = identify_plant(rec, plant, progress=progress)
    if "warning" in res:
        print(f"rig identify: warning: {res['warning']}", file=sys.stderr)
    if args.out:
        cliargs.make_out_dir(args.out)
        try:
            (args.out / "identify.json").write_text(json.dumps(res, indent=1))
        except OSError as e:
            raise RigError(f"--out {args.out}: cannot write ({e.strerror or e})") from None
    code = EXIT_SUSPECT if "warning" in res else 0
    if args.json:
        print(json.dumps(res, indent=1))
        return code
    print(f"Identified {plant.family} from {rec.source} ({rec.n} samples at {rec.fs_hz:g} Hz)\n")
    print("| parameter | start | identified | 1-sigma | bounds |\n|---|---|---|---|---|")
    for k, v in res["parameters"].items():
        if k in res["std"]:
            lo, hi = res["bounds"][k]
            print(f"| {k} | {res['start'][k]:.4g} | {v:.4g} | {res['std'][k]:.2g} | {lo:.3g}..{hi:.3g} |")
        else:
            print(f"| {k} | {v:.4g} (fixed) | | | |")
    f = res["fit"]
    print(f"\nNRMSE {f['nrmse']:.4f}, residual {f['residual_rms_m']:.3g} m rms (held-out blocks "
          f"{f['holdout_residual_rms_m']:.3g} m)" + (f"; {res['shooting']['segments']} segments (multiple shooting)"
                                                      if "shooting" in res else ""))
    if res["at_bounds"]:
        print("at their bounds: " + ", ".join(res["at_bounds"]) + " (the model lacks something: run rig diagnose)")
    return code


def identify_one(plant_path: Path | None, config: str | None, starts: int, seed: int, refine: bool, path: str,
                 out: str) -> dict:
    """A batch's work on one recording (in a worker): identify it into out, as `rig identify --out` does; its row."""
    from rig.batch.rows import identify_plant_row, identify_row
    from rig.diagnose.refit import identify_plant
    from rig.identify import identify, refuse_feedback_only
    from rig.plant.file import load_subject

    subject = load_subject(Path(path), plant_path, config)
    rec, plant = subject.rec, subject.plant
    if plant.family != "eha":
        res = identify_plant(rec, plant)
        cliargs.make_out_dir(Path(out))
        try:
            (Path(out) / "identify.json").write_text(json.dumps(res, indent=1))
        except OSError as e:
            raise RigError(f"{out}: cannot write ({e.strerror or e})") from None
        return identify_plant_row(res, rec)
    refuse_feedback_only(rec)
    res = identify(rec, plant.actuator, starts=starts, seed=seed, refine_time_domain=refine)
    write_outputs(res, Path(out))
    return identify_row(res, rec)


def run(args) -> int:
    cliargs.log_to_stderr("identify")          # the readers' warnings: `rig identify: warning: ...`
    if args.starts < 1:
        raise RigError(f"--starts: expected >= 1, got {args.starts}")
    if batch.wanted(args):
        if args.repeat > 1:
            raise RigError("--repeat: a benchmark of one recording, not of a batch (give one REC)")
        options = {"starts": args.starts, "seed": args.seed, "refine": not args.no_refine,
                   "plant": file_identity(args.plant), "config": file_identity(args.config)}
        work = partial(identify_one, args.plant, args.config, args.starts, args.seed, not args.no_refine)
        return batch.run_job(Job("identify", options, work), args)
    args.recording = args.recording[0]
    return off_the_main_thread("identify", run_single, args)


def run_single(args) -> int:
    from rig.plant.file import load_subject

    t0 = time.perf_counter()
    subject = load_subject(args.recording, args.plant, args.config)   # one line naming file and key, exit 2
    from rig.identify import identify, refuse_feedback_only            # heavy (numba): once the input is read
    rec, plant = subject.rec, subject.plant
    if rec.gaps:
        print(f"note: {rec.gaps}", file=sys.stderr)
    if plant.family != "eha":
        return _run_plant(args, rec, plant, t0)
    p0 = plant.actuator
    refuse_feedback_only(rec)

    def progress(stage: str, frac: float) -> None:
        print(f"[{time.perf_counter() - t0:5.2f} s] {100 * frac:3.0f} % {stage}", file=sys.stderr, flush=True)

    progress(f"loaded {rec.source}: {rec.n} samples at {rec.fs_hz:g} Hz", 0.0)
    if rec.closed_loop:
        from rig.recordings.recording import CLOSED_LOOP_NOTE
        print(f"note: {CLOSED_LOOP_NOTE}", file=sys.stderr)
    res = identify(rec, p0, starts=args.starts, seed=args.seed, refine_time_domain=not args.no_refine,
                   progress=progress)
    if "warning" in res.fit:                 # a poor fit or closed-loop data: exit 5 below
        print(f"rig identify: warning: {res.fit['warning']}", file=sys.stderr)
    if args.repeat > 1:
        import numpy as np
        runs = [res.timing_s]
        for _ in range(args.repeat - 1):
            runs.append(identify(rec, p0, starts=args.starts, seed=args.seed,
                                 refine_time_domain=not args.no_refine).timing_s)
        for key, what in (("total_s", "wall"), ("cpu_s", "cpu")):
            t = [r[key] for r in runs]
            print(f"identify {what} time over {len(t)} runs ({rec.n} samples at {rec.fs_hz:g} Hz): p50 "
                  f"{np.percentile(t, 50):.3f} s, p99 {np.percentile(t, 99):.3f} s, max {max(t):.3f} s", file=sys.stderr)
    paths = write_outputs(res, args.out) if args.out else {}
    if args.plot is not None:
        plot_fig3(res, args.plot)
        paths["plot"] = args.plot
    code = EXIT_SUSPECT if "warning" in res.fit else 0      # a poor fit or closed-loop data: said in the table
    if args.json:
        print(json.dumps(res.to_json(), indent=1))
        return code
    print(f"Identified from {rec.source} ({rec.n} samples at {rec.fs_hz:g} Hz) in {res.timing_s['total_s']:.2f} s "
          f"({res.timing_s['cpu_s']:.2f} s cpu)\n")
    print(table_markdown(res))
    print()
    print(fit_markdown(res))
    print("\nIdentifiability:")
    print(weak_markdown(res))
    if paths:
        print("\nwritten: " + ", ".join(str(p) for p in paths.values()))
    return code
