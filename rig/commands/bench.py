"""`rig bench`: benchmarks, printed as distributions (never pass/fail).

  rig bench loop --rate HZ --seconds N [--json]   the control loop, four mounts on the simulated backend,
                                                  real clock, real-time hygiene where allowed, recording on
  rig bench loop --empty ...                      the same deadlines and wait with nothing in the period:
                                                  what the machine itself allows (same JSON)
  rig bench loop --layout prototype ...           the prototype instead: one mount on its stand, tracking a
                                                  sine (the isolation filters stepped alongside)
  rig bench loop --layout both [--rounds R] [--block-s S] ...
                                                  four mounts and one in one run, both sessions open, in short
                                                  alternating blocks (about S = 0.2 s each, starting on the
                                                  wall clock's 20 ms grid, R = 3 rounds of
                                                  --seconds / R, half of it per layout): per round each
                                                  layout's compute p50/p99/max pooled over its blocks, the
                                                  p99 ratio (prototype / machine), whether one mount's p99
                                                  <= four mounts' held over the whole run (pooled) and in
                                                  every round; "kernel_us": the
                                                  compiled period alone, per layout (the least of 5 x 20000
                                                  back-to-back calls: the code's cost without the host's noise)
  rig bench loop --feedforward [--rounds R] ...   the feedback-only loop and the loop with the floor
                                                  accelerometers and feedforward, alternating in one run
  rig bench loop --console ...                    blocks without and with the operator console and a browser
                                                  on its page, alternating (rig/console/bench.py)
  rig bench recorder [--seconds N] [--json]       the recording writer's CPU time and the recording's size per
                                                  hour, gzip against none (rig/commands/bench_recorder.py)
  rig bench stalls [--seconds N] [--json]         where stalls come from: an empty loop at real-time and at normal
                                                  priority, a pty echo and a socket echo, side by side; then
                                                  what the host takes from busy loops on one CPU and on every
                                                  CPU (rig/commands/bench_stalls.py)
  rig bench idle-poll [--rounds R] [--seconds N]  `rig hil` with idle CPUs kept polling and without, alternating
                                                  (rig/commands/bench_idle_poll.py)
  rig bench sim ...                               simulation speed of the plant
  rig bench batch [--n N] [--json]                a batch of simulated recordings diagnosed one by one, on the
                                                  local pool, on a Dask LocalCluster, and killed and resumed
                                                  (rig/commands/bench_batch.py)
  rig bench prototype [--json]                    the prototype's tracking targets on the simulated stand,
                                                  in simulated time (rig/commands/prototype_bench.py)

`loop --json` prints exactly: {"rate_hz", "iterations", "wake_latency_us": {"p50","p99","max"},
"compute_us": {"p50","p99","max"}, "overruns", "missed_deadline_fraction"}; compute is read + check +
update + limit + write + record-push within one period; missed_deadline_fraction is
(overruns + skipped periods) / (iterations + skipped periods). A loop run that faulted (its rest at null) is
said in a `rig bench: warning:` line and exits 1 (`faulted_exit`), its figures printed still. Ctrl-C stops a
loop run safely: its figures, a line saying it was interrupted, exit 130 (`interrupted_exit`); in a benchmark of
several runs or blocks (--feedforward, --layout both, --console) it ends the benchmark, no figures, exit 130.

`loop --feedforward` runs R rounds of two runs of --seconds each, feedback only ([sensors] floor_accel off:
the loop as without the feedforward) and feedback + feedforward (floor accelerometers read, checked and
recorded, the feedforward in every period), in the order AB, BA, AB, ... so that a drift of the shared machine
falls on both alike; its --json prints {"rate_hz", "rounds", "seconds", "feedback": {...}, "feedback_feedforward":
{...}} (each: "compute_us" and "wake_latency_us" {"p50","p99","max"} over all its periods, "compute_p99_us_by_round",
"overruns", "iterations"), "compute_p99_difference_us", "compute_p50_difference_us" (feedforward minus
feedback, pooled) and "compute_p99_paired_difference_us" (the median over rounds of the difference of the two
runs of a round, which sit next to each other in time: the figure least moved by a drifting shared machine).
"""
from __future__ import annotations

import argparse
import contextlib
import json
import logging
import math
import os
import signal
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from rig import cliargs
from rig.commands import bench_cli, bench_idle_poll, bench_stalls
from rig.runtime.clock import MonotonicClock
from rig.config import load_config
from rig.console import bench as console_bench
from rig.errors import EXIT_FAULT, EXIT_STOPPED_BY, RigError
from rig.runtime.lifecycle import State
from rig.runtime.rt import cpu_steal_ms, enter_realtime, leave_realtime
from rig.runtime.signals import interrupt

log = logging.getLogger("rig.bench")


def add_arguments(p) -> None:
    sub = p.add_subparsers(dest="bench_what", metavar="WHAT")
    lp = sub.add_parser("loop", help="control loop timing: four mounts on the simulated backend")
    _config_arg(lp)
    lp.add_argument("--rate", type=cliargs.rate_hz(), default=None, metavar="HZ",
                    help="loop rate (default [loop] rate_hz)")
    lp.add_argument("--seconds", type=cliargs.seconds(le=3600), default=10.0, metavar="N",
                    help="duration (default 10)")
    lp.add_argument("--policy", choices=("skip", "catch_up"), default=None, help="overrun policy")
    lp.add_argument("--no-realtime", action="store_true", help="do not try SCHED_FIFO/affinity/mlockall")
    lp.add_argument("--spin-us", type=cliargs.Number(ge=0, le=1000, unit="us"), default=None, metavar="US",
                    help="hybrid wait: sleep to US before each deadline, then spin (default [loop] spin_us)")
    cliargs.output_arg(lp, "--record", metavar="FILE", default=None,
                       help="keep the recording here (default: a temporary file, deleted)")
    lp.add_argument("--empty", action="store_true",
                    help="the same clock, real-time set-up and deadlines with nothing to do in the period: the "
                         "machine's own floor under these figures (same JSON)")
    lp.add_argument("--layout", choices=("machine", "prototype", "both"), default="machine",
                    help="machine: four mounts (default); prototype: one mount on its stand, tracking; both: "
                         "alternately in one run, with the ratio of their compute p99")
    lp.add_argument("--feedforward", action="store_true",
                    help="compare the feedback-only loop with the loop with floor feedforward, alternating runs")
    lp.add_argument("--json", action="store_true", help="print only the JSON figures on stdout")
    console_bench.add_arguments(lp)
    sp = sub.add_parser("sim", help="simulation speed of the plant")
    _config_arg(sp)
    add_sim_arguments(sp)
    pp = sub.add_parser("prototype", help="the prototype's tracking targets on the simulated stand")
    _config_arg(pp)
    pp.add_argument("--switches", type=cliargs.count(1, 100000), default=100, metavar="N", help="random mode switches (default 100)")
    pp.add_argument("--seed", type=cliargs.seed(), default=18, metavar="N", help="seed of the switches (default 18)")
    pp.add_argument("--json", action="store_true", help="print only the JSON figures on stdout")
    st = sub.add_parser("stalls", help="where stalls come from: real-time and normal empty loops, pty and socket "
                                       "echoes side by side; then busy loops on one CPU and on every CPU")
    _config_arg(st)
    bench_stalls.add_arguments(st)
    ip = sub.add_parser("idle-poll", help="rig hil with idle CPUs kept polling and without, alternating runs")
    _config_arg(ip)
    bench_idle_poll.add_arguments(ip)
    cp = sub.add_parser("cli", help="the command line's --help time against a bare interpreter start")
    bench_cli.add_arguments(cp)
    rp = sub.add_parser("recorder", help="recording writer: CPU time and size per hour, compressed or not")
    _config_arg(rp)
    rp.add_argument("--seconds", type=cliargs.seconds(ge=1, le=600), default=10.0, metavar="N",
                    help="seconds of `rig run` (sim backend, simulated time) recorded, then replayed (default 10)")
    rp.add_argument("--rounds", type=cliargs.count(1, 100), default=3,
                    help="replays of each mode, alternating (default 3; medians are printed)")
    rp.add_argument("--json", action="store_true", help="print only the JSON figures on stdout")
    bp = sub.add_parser("batch", help="a batch of recordings: one by one, local pool, Dask LocalCluster, resumed")
    bp.add_argument("--n", type=cliargs.count(2, 10000), default=40, help="recordings (default 40)")
    bp.add_argument("--duration", type=cliargs.seconds(ge=5, le=1000), default=12.0, metavar="S",
                    help="length of each (default 12 s: the shortest the diagnosis makes a claim on)")
    bp.add_argument("--fs", type=cliargs.rate_hz(le=20000), default=1000.0, metavar="HZ",
                    help="sample rate (default 1000 Hz)")
    bp.add_argument("--workers", type=cliargs.count(1, 64), default=2,
                    help="processes of the pool and of the LocalCluster (default 2)")
    bp.add_argument("--keep", metavar="DIR", type=Path, default=None,
                    help="make the recordings and the outputs here and keep them (default: a temporary folder)")
    bp.add_argument("--memory", action="store_true",
                    help="only the local pool, for the batch's peak memory against one recording diagnosed alone")
    bp.add_argument("--json", action="store_true", help="print only the JSON figures on stdout")


def _config_arg(p) -> None:
    # `rig bench --config F loop` and `rig bench loop --config F` both work
    p.add_argument("--config", metavar="FILE", default=argparse.SUPPRESS, help="TOML configuration")


def run(args) -> int:
    what = getattr(args, "bench_what", None)
    if what == "loop":
        return bench_loop(args)
    if what == "sim":
        return bench_sim(args)
    if what == "prototype":
        from rig.commands import prototype_bench
        from rig.commands.run import LAYOUTS
        cfg = load_config(getattr(args, "config", None) or LAYOUTS["prototype"][None])
        if cfg.layout.plant != "stand":
            raise RigError(f"bench prototype: {cfg.source} is not a stand layout ([layout] plant = \"stand\")")
        res = prototype_bench.run(cfg, switch_count=args.switches, seed=args.seed,
                                  progress=lambda m: print(f"rig bench prototype: {m}", file=sys.stderr))
        print(json.dumps(res, indent=1) if args.json else prototype_bench.text(res))
        return 0
    if what == "recorder":
        return bench_recorder(args)
    if what == "stalls":
        return bench_stalls.run(args)
    if what == "cli":
        return bench_cli.run(args)
    if what == "idle-poll":
        return bench_idle_poll.run(args)
    if what == "batch":
        from rig.commands import bench_batch
        return bench_batch.run(args)
    raise RigError("bench: expected a benchmark: loop, sim, recorder, stalls, idle-poll, cli, batch or prototype (see "
                   "rig bench --help)")


# ---- rig bench sim (owner: the plant engineer) ---------------------------------------------------------
def add_sim_arguments(p) -> None:
    """Arguments of `rig bench sim`."""
    p.add_argument("--seconds", type=cliargs.seconds(le=3600), default=100.0, metavar="N",
                   help="simulated time (default 100)")
    p.add_argument("--rate", type=cliargs.rate_hz(), default=5000.0, metavar="HZ", help="loop rate (default 5000)")
    p.add_argument("--repeats", type=cliargs.count(1, 1000), default=3, help="batch runs to time (default 3)")
    p.add_argument("--json", action="store_true", help="print only the JSON figures on stdout")


def bench_sim(args) -> int:
    from sim_backend.bench import bench_sim as run_bench
    if args.seconds <= 0 or args.rate <= 0 or args.repeats < 1:
        raise RigError("bench sim: expected --seconds > 0, --rate > 0 and --repeats >= 1")
    cfg = load_config(getattr(args, "config", None))
    cliargs.check_rate(cfg, args.rate, "--rate", sections=("vibration",))   # timing only: any controller
    cliargs.check_periods(args.seconds, args.rate)
    res = run_bench(cfg, args.seconds, args.rate, args.repeats,
                    progress=lambda m: print(f"bench sim: {m}", file=sys.stderr))
    if args.json:
        print(json.dumps(res, indent=2))
        return 0
    fm, st, su = res["four_mount"], res["stand_chirp"], res["four_mount_step_us"]
    print(f"four-mount rig, {fm['states']} states, {fm['simulated_s']:g} s at {fm['rate_hz']:g} Hz: "
          f"wall p50 {fm['wall_s']['p50']:.3f} s, max {fm['wall_s']['max']:.3f} s -> "
          f"{fm['realtime_factor']:.0f}x real time")
    print(f"four-mount plant step (per period): p50 {su['p50']:.2f} us, p99 {su['p99']:.2f} us, "
          f"max {su['max']:.1f} us")
    print(f"stand chirp {st['simulated_s']:g} s at {st['rate_hz']:g} Hz: {st['wall_s']:.2f} s -> "
          f"{st['realtime_factor']:.0f}x real time")
    return 0


# ---- rig bench recorder ----------------------------------------------------------------------------------
def bench_recorder(args) -> int:
    from rig.commands.bench_recorder import bench_recorder as measure
    cfg = load_config(getattr(args, "config", None))
    res = measure(cfg, args.seconds, cfg.loop.rate_hz, args.rounds,
                    progress=lambda m: print(f"bench recorder: {m}", file=sys.stderr, flush=True))
    if args.json:
        print(json.dumps(res, indent=2))
        return 0
    print(f"recording of `rig run` at {res['rate_hz']:g} Hz: {res['columns']} columns a row "
          f"({res['controller_state_columns']} of them controller states); medians of {res['rounds']} rounds")
    for m, r in res["modes"].items():
        print(f"  {m:5s} writer {r['writer_rows_per_cpu_s']:>9,} rows per CPU s = "
              f"{r['writer_cpu_percent_at_rate']:5.1f} % of a core at {res['rate_hz']:g} Hz; "
              f"{r['bytes_per_row']:7.1f} B/row = {r['MB_per_s_at_rate']:.2f} MB/s = {r['GB_per_hour_at_rate']:.2f} GB/h; "
              f"rows lost {r['rows_lost']}")
    print(f"  gzip/none: size x{res['gzip_size_ratio']}, writer CPU x{res['gzip_cpu_ratio']}")
    return 0


# ---- rig bench loop --------------------------------------------------------------------------------------
def bench_loop(args) -> int:
    from rig.runtime.session import Session
    cliargs.log_to_stderr("bench")
    cfg = load_config(getattr(args, "config", None))
    rate = args.rate or cfg.loop.rate_hz
    cliargs.check_rate(cfg, rate, "--rate", sections=("vibration",))    # timing only: any controller
    cliargs.check_periods(args.seconds, rate)
    if not (0 < rate <= 100000):
        raise RigError(f"--rate: expected 0 < HZ <= 100000, got {rate}")
    if not (0 < args.seconds <= 3600):
        raise RigError(f"--seconds: expected 0 < N <= 3600, got {args.seconds}")
    if args.spin_us is not None and not (0 <= args.spin_us <= 1000):
        raise RigError(f"--spin-us: expected 0 <= US <= 1000, got {args.spin_us}")
    clock = MonotonicClock(None if args.spin_us is None else int(round(args.spin_us * 1e3)))
    if args.empty:
        return _empty_loop(cfg, args, rate, clock)
    layout = getattr(args, "layout", "machine")
    if args.feedforward and layout != "machine":
        raise RigError("--feedforward: the machine's loop (the stand layouts have no floor accelerometers)")
    rounds, block_s = (3, 0.2) if layout == "both" else (4, 6.0)     # (the options: rig/console/bench.py)
    args.rounds = rounds if getattr(args, "rounds", None) is None else args.rounds
    args.block_s = block_s if getattr(args, "block_s", None) is None else args.block_s
    if args.feedforward:
        return _feedforward_ab(cfg, args, rate)
    if layout != "machine":
        return _bench_layouts(cfg, args, rate, layout)
    if args.console:
        out, faults, reason = console_bench.bench_console(args, cfg, rate, clock)
        stop_if_interrupted(reason)
        console_bench.print_figures(out, args.json)
        return faulted_exit(faults, BLOCKS_LEFT_OUT)
    path, tmp = args.record, None
    if path is None:
        fd, tmp = tempfile.mkstemp(suffix=".h5", prefix="rig-bench-")
        os.close(fd)
        path = tmp
    realtime = cfg.loop.realtime and not args.no_realtime
    session = Session(cfg, "sim", clock=clock, rate_hz=rate, overrun_policy=args.policy,
                      keep_timing=int(math.ceil(args.seconds * rate)) + 16, stop_on_fault=False, rate_check=False,
                      record=path,
                      record_attrs={"command": "rig bench loop"}, realtime=realtime)
    try:
        with session:
            loop = session.loop
            loop.activate()
            print(f"rig bench loop: {loop.n} mounts at {rate:g} Hz for {args.seconds:g} s, compiled period "
                  f"kernel, policy {loop.policy}, spin {clock.spin_ns / 1e3:g} us, "
                  f"{'real-time set-up where allowed' if realtime else 'no real-time hygiene'}", file=sys.stderr)
            cpu = _loop_cpu(cfg) if realtime else None
            steal0 = cpu_steal_ms(cpu)
            reason = session.run(seconds=args.seconds)
            steal1 = cpu_steal_ms(cpu)
    finally:
        if tmp:
            os.unlink(tmp)
    if realtime:
        print(f"rig bench loop: {session.rt_summary}", file=sys.stderr)
    tm = loop.timing_us()
    out = {"rate_hz": rate, "iterations": loop.iterations,
           "wake_latency_us": {k: round(v, 2) for k, v in tm["wake_latency_us"].items()},
           "compute_us": {k: round(v, 2) for k, v in tm["compute_us"].items()},
           "overruns": loop.overruns, "missed_deadline_fraction": loop.missed_deadline_fraction}
    n = min(loop.iterations, loop.keep)
    _print_host_stalls(np.frombuffer(loop.wake_ns, dtype="<i8")[:n], loop.period_ns, steal0, steal1, cpu)
    _print_loop_figures(out, args.json, loop.skipped)
    code = faulted_exit({"loop": loop.lc.fault_reason})
    return interrupted_exit(reason, loop.iterations / rate, args.seconds) or code


def interrupted_exit(reason: str | None, ran_s: float, seconds: float) -> int:
    """The exit status of a benchmark run its loop stopped on Ctrl-C (a safe stop; a SIGTERM unwinds through
    rig.cli: 143): its figures, printed still, are of the part that ran, so one line says so and the exit is
    EXIT_STOPPED_BY's (130), as every command's after an interrupt; 0 for a run that was not interrupted."""
    if reason not in EXIT_STOPPED_BY:
        return 0
    print(f"rig bench loop: interrupted ({reason}) at t = {ran_s:.1f} s of {seconds:g} s: the figures are of "
          f"that part alone", file=sys.stderr)
    return EXIT_STOPPED_BY[reason]


def stop_if_interrupted(reason: str | None) -> None:
    """A benchmark of several runs or blocks ends at one its session stopped on Ctrl-C (the loop's safe stop):
    its figures would pool a round cut short, so none are printed and rig.cli says `interrupted` (130)."""
    if reason in EXIT_STOPPED_BY:
        interrupt(signal.Signals[reason])


FIGURES_AT_NULL = "these figures are not the loop's (valves at null from the fault on)"
BLOCKS_LEFT_OUT = "those blocks are left out of the figures"     # a benchmark of blocks (--layout both, --console)


def faulted_exit(faults: dict, consequence: str = FIGURES_AT_NULL) -> int:
    """The exit status of a benchmark ({what ran: its fault reason or None}): a loop that faulted spent the rest
    of its run or block at FAULT (valves at null, controllers not run), so the benchmark did not measure what it
    claims: one warning line per faulted run (what that did to the figures: `consequence`) and EXIT_FAULT
    (rig/errors.py), as every command exits after a fault. Whole runs, --layout both (its faulted blocks left
    out) and --console alike."""
    bad = {what: why for what, why in faults.items() if why}
    for what, why in bad.items():
        log.warning("%s: the simulated rig faulted (%s): %s", what, why, consequence)
    return EXIT_FAULT if bad else 0


def _feedforward_ab(cfg, args, rate: float) -> int:
    """Feedback only and feedback + feedforward, alternating runs (AB BA AB ...), recording on, each run its
    own session; pooled compute and wake-up figures per path and their difference."""
    from rig.runtime.session import Session
    import dataclasses
    if not 1 <= args.rounds <= 100:              # (--rounds is shared with --console: rig/console/bench.py)
        raise RigError(f"--rounds: expected 1 to 100, got {args.rounds}")
    realtime = cfg.loop.realtime and not args.no_realtime
    paths = ("feedback", "feedback_feedforward")
    comp, wake = {p: [] for p in paths}, {p: [] for p in paths}
    out = {"rate_hz": rate, "rounds": args.rounds, "seconds": args.seconds}
    per_round = {p: [] for p in paths}
    counts = {p: {"iterations": 0, "overruns": 0} for p in paths}
    faults: dict = {}
    for r in range(args.rounds):
        for path in (paths if r % 2 == 0 else paths[::-1]):
            ff = path == paths[1]
            c = cfg.replace(sensors=dataclasses.replace(cfg.sensors, floor_accel=ff))
            clock = MonotonicClock(None if args.spin_us is None else int(round(args.spin_us * 1e3)))
            fd, tmp = tempfile.mkstemp(suffix=".h5", prefix="rig-bench-")
            os.close(fd)
            try:
                session = Session(c, "sim", clock=clock, rate_hz=rate, overrun_policy=args.policy,
                                  keep_timing=int(math.ceil(args.seconds * rate)) + 16, stop_on_fault=False,
                                  record=tmp, record_attrs={"command": "rig bench loop --feedforward"},
                                  realtime=realtime, feedforward=ff)
                with session:
                    loop = session.loop
                    loop.activate()
                    reason = session.run(seconds=args.seconds)
            finally:
                os.unlink(tmp)
            stop_if_interrupted(reason)
            n = min(loop.iterations, loop.keep)
            cu = np.frombuffer(loop.compute_ns, dtype="<i8")[:n] * 1e-3
            comp[path].append(cu)
            wake[path].append(np.frombuffer(loop.wake_ns, dtype="<i8")[:n] * 1e-3)
            per_round[path].append(round(float(np.percentile(cu, 99)), 2))
            counts[path]["iterations"] += loop.iterations
            counts[path]["overruns"] += loop.overruns
            if loop.lc.fault_reason:
                faults.setdefault(f"{path} (round {r + 1})", loop.lc.fault_reason)
            print(f"rig bench loop --feedforward: round {r + 1}/{args.rounds} {path}: compute p99 "
                  f"{per_round[path][-1]:.2f} us (mode {loop.isolation_mode})", file=sys.stderr)

    def pct(a):
        return {"p50": round(float(np.percentile(a, 50)), 2), "p99": round(float(np.percentile(a, 99)), 2),
                "max": round(float(a.max()), 2)}
    for p in paths:
        cu, wu = np.concatenate(comp[p]), np.concatenate(wake[p])
        out[p] = {"compute_us": pct(cu), "wake_latency_us": pct(wu), "compute_p99_us_by_round": per_round[p],
                  **counts[p]}
    for q in ("p99", "p50"):
        out[f"compute_{q}_difference_us"] = round(out[paths[1]]["compute_us"][q] - out[paths[0]]["compute_us"][q], 2)
    out["compute_p99_paired_difference_us"] = round(float(np.median(np.subtract(per_round[paths[1]],
                                                                                per_round[paths[0]]))), 2)
    if args.json:
        print(json.dumps(out))
        return faulted_exit(faults)
    print(f"{args.rounds} rounds of {args.seconds:g} s per path at {rate:g} Hz, alternating (AB BA ...)")
    for p in paths:
        c, w = out[p]["compute_us"], out[p]["wake_latency_us"]
        print(f"  {p:21s} compute p50 {c['p50']:6.2f} us  p99 {c['p99']:6.2f} us  max {c['max']:8.1f} us | "
              f"wake p99 {w['p99']:6.1f} us | p99 by round {out[p]['compute_p99_us_by_round']} | "
              f"overruns {out[p]['overruns']}")
    print(f"  feedforward - feedback: compute p50 {out['compute_p50_difference_us']:+.2f} us, "
          f"p99 {out['compute_p99_difference_us']:+.2f} us (pooled); p99 paired by round (median) "
          f"{out['compute_p99_paired_difference_us']:+.2f} us")
    return faulted_exit(faults)


def _loop_cpu(cfg) -> int | None:
    """The CPU the loop thread is pinned to ([loop] cpu, -1 = the last one)."""
    n = os.cpu_count() or 1
    return n - 1 if cfg.loop.cpu < 0 else cfg.loop.cpu


def _print_host_stalls(wake_ns, period_ns: int, steal0, steal1, cpu) -> None:
    """stderr: the wake-ups that came more than a period late (the machine, not the loop's work: the same
    shows in --empty) and the hypervisor's steal time on the loop's CPU over the run."""
    late = wake_ns > period_ns
    edges = np.flatnonzero(np.diff(np.concatenate(([False], late)).astype(np.int8)) == 1)
    text = (f"rig bench loop: wake-ups more than one period late: {int(late.sum())} in {len(edges)} stalls, "
            f"longest {wake_ns.max() / 1e3:.0f} us")
    if steal0 is not None and steal1 is not None:
        text += f"; hypervisor steal time on CPU {cpu}: {steal1 - steal0:.0f} ms"
    print(text, file=sys.stderr)


def _print_loop_figures(out: dict, as_json: bool, skipped: int) -> None:
    if as_json:
        print(json.dumps(out))
        return
    w, c = out["wake_latency_us"], out["compute_us"]
    print(f"{out['iterations']} periods at {out['rate_hz']:g} Hz\n"
          f"  wake latency  p50 {w['p50']:8.1f} us  p99 {w['p99']:8.1f} us  max {w['max']:9.1f} us\n"
          f"  compute       p50 {c['p50']:8.1f} us  p99 {c['p99']:8.1f} us  max {c['max']:9.1f} us\n"
          f"  overruns {out['overruns']}, skipped periods {skipped}, missed deadlines "
          f"{100 * out['missed_deadline_fraction']:.4f} %")


def _empty_loop(cfg, args, rate: float, clock) -> int:
    """Absolute deadlines, the same wait and real-time set-up as the loop, nothing in the period: a period
    counts as missed when the wake-up came after the next deadline (catch-up, like the loop's default)."""
    period = int(round(1e9 / rate))
    n = int(math.ceil(args.seconds * rate))
    if clock.spin_ns is None:                           # as the Loop does: [loop] spin_us unless --spin-us
        clock.spin_ns = int(round(cfg.loop.spin_us * 1e3))
    wake = np.empty(n, dtype=np.int64)
    comp = np.empty(n, dtype=np.int64)
    rt = None
    if cfg.loop.realtime and not args.no_realtime:
        rt = enter_realtime(priority=cfg.loop.rt_priority, cpu=cfg.loop.cpu,
                            cpu_latency_us=cfg.loop.cpu_latency_us)
    print(f"rig bench loop --empty: {rate:g} Hz for {args.seconds:g} s, spin {clock.spin_ns / 1e3:g} us, "
          f"{rt.summary() if rt else 'no real-time hygiene'}", file=sys.stderr)
    missed = 0
    steal0 = cpu_steal_ms(rt.cpu if rt else None)
    try:
        t = clock.now_ns() + period
        for i in range(n):
            clock.sleep_until(t)
            w = clock.now_ns()
            done = clock.now_ns()
            wake[i], comp[i] = w - t, done - w
            t += period
            if done > t:
                missed += 1
    finally:
        if rt is not None:
            leave_realtime(rt)

    def pct(a):
        a = a * 1e-3
        return {"p50": round(float(np.percentile(a, 50)), 2), "p99": round(float(np.percentile(a, 99)), 2),
                "max": round(float(a.max()), 2)}
    out = {"rate_hz": rate, "iterations": n, "wake_latency_us": pct(wake), "compute_us": pct(comp),
           "overruns": missed, "missed_deadline_fraction": missed / n}
    _print_host_stalls(wake, period, steal0, cpu_steal_ms(rt.cpu if rt else None), rt.cpu if rt else None)
    _print_loop_figures(out, args.json, 0)
    return 0


PROTOTYPE_BENCH_MODE = "track sine:amp=10um,freq=5"


def _bench_once(cfg, args, rate: float, seconds: float, mode=None, announce: str | None = None) -> dict:
    """One timed run on the simulated backend (cfg's layout; mode: the stand's operating mode), recording to a
    temporary file: the loop figures. announce: a line said once the run is built (a Ctrl-C before it ends the
    command without figures)."""
    from rig.runtime.session import Session
    fd, tmp = tempfile.mkstemp(suffix=".h5", prefix="rig-bench-")
    os.close(fd)
    realtime = cfg.loop.realtime and not args.no_realtime
    clock = MonotonicClock(None if args.spin_us is None else int(round(args.spin_us * 1e3)))
    try:
        with Session(cfg, "sim", clock=clock, rate_hz=rate, overrun_policy=args.policy, mode=mode,
                     keep_timing=int(math.ceil(seconds * rate)) + 16, stop_on_fault=False, record=tmp,
                     record_attrs={"command": "rig bench loop"}, realtime=realtime) as session:
            loop = session.loop
            if announce:
                print(announce, file=sys.stderr)
            loop.activate()
            reason = session.run(seconds=seconds)
    finally:
        os.unlink(tmp)
    tm = loop.timing_us()
    return {"fault_reason": loop.lc.fault_reason, "stop_reason": reason, "mounts": loop.n, "rate_hz": rate,
            "iterations": loop.iterations,
            "wake_latency_us": {k: round(v, 2) for k, v in tm["wake_latency_us"].items()},
            "compute_us": {k: round(v, 2) for k, v in tm["compute_us"].items()},
            "overruns": loop.overruns, "missed_deadline_fraction": loop.missed_deadline_fraction}


def _bench_layouts(cfg, args, rate: float, layout: str) -> int:
    """The prototype alone, or both layouts in short alternating blocks (_bench_both)."""
    from rig.commands.run import LAYOUTS
    proto = load_config(getattr(args, "config", None) or LAYOUTS["prototype"][None])
    if proto.layout.plant != "stand":
        raise RigError(f"--layout {layout}: {proto.source} is not a stand layout")
    if layout == "both":
        return _bench_both(cfg, proto, args, rate)
    out = _bench_once(proto, args, rate, args.seconds, PROTOTYPE_BENCH_MODE,
                      f"rig bench loop: prototype (1 mount) at {rate:g} Hz for {args.seconds:g} s, {PROTOTYPE_BENCH_MODE}")
    fault, reason = out.pop("fault_reason"), out.pop("stop_reason")
    _print_loop_figures(out, args.json, 0)
    code = faulted_exit({"prototype": fault})
    return interrupted_exit(reason, out["iterations"] / rate, args.seconds) or code


class BlockClock(MonotonicClock):
    """The real clock of one of several loops run in turns: stopped between the loop's blocks, so its loop time
    (and the simulated plant that keeps pace with it) runs only while the loop runs: a resumed loop sees no gap
    (no catch-up of the plant, no replayed periods).

    With align_ns, the first reading after a resume (the scheduler's, which sets the block's deadlines one
    period apart from it) waits, still stopped, until the wall clock is on a multiple of align_ns: every
    block's deadlines then sit at the same phase of the host's own periodic work (the kernel's timer tick,
    every 1 to 10 ms: about 30 us on this VM, landing in the work of every 10th or 20th period of a block
    whose start happened to line it up), so that work falls on the layouts' periods alike."""

    def __init__(self, spin_ns: int | None = None, align_ns: int = 0) -> None:
        super().__init__(spin_ns)
        self.offset_ns = 0                  # real time spent stopped so far
        self._stopped_at: int | None = None
        self.align_ns = int(align_ns)
        self._align = False

    def now_ns(self) -> int:
        if self._align:
            self._align = False
            wall = time.monotonic_ns()
            on_grid = wall + (-wall) % self.align_ns
            MonotonicClock.sleep_until(self, on_grid)
            self.offset_ns += on_grid - wall            # the wait is no loop time
            return on_grid - self.offset_ns
        return time.monotonic_ns() - self.offset_ns

    def sleep_until(self, t_ns: int) -> None:
        MonotonicClock.sleep_until(self, t_ns + self.offset_ns)

    def stop(self, at_ns: int | None = None) -> None:
        """Stopped now, or as from loop time at_ns (past: the end of the loop's last period, so the run's
        teardown after it, which may wait for the CPU on a loaded host, is no loop time either)."""
        self._stopped_at = time.monotonic_ns() if at_ns is None else min(time.monotonic_ns(), at_ns + self.offset_ns)

    def resume(self) -> None:
        if self._stopped_at is not None:
            self.offset_ns += time.monotonic_ns() - self._stopped_at
            self._stopped_at = None
            self._align = self.align_ns > 0


BLOCK_SETTLE = 10               # periods left out at the start of each block: the first replays the gap and
                                # re-activates (~5x a period's compute), the next few run on the other loop's caches
BLOCK_ALIGN_NS = 20_000_000     # blocks start on the wall clock's 20 ms grid (a multiple of any timer tick period)


def block_plan(seconds: float, rounds: int, block_s: float) -> tuple[int, float]:
    """Blocks per layout per round and their length [s]: each layout gets seconds / (2 rounds) per round, cut
    into blocks of about block_s (at least one)."""
    per = seconds / (2 * rounds)
    k = max(1, int(round(per / block_s)))
    return k, per / k


def _bench_both(cfg, proto, args, rate: float) -> int:
    """Four mounts and one, both sessions open at once, run in short alternating blocks (MPMP... in even
    rounds, PMPM... in odd ones), each block a run of its session on a BlockClock; per round, each layout's
    compute and wake-up figures pooled over its blocks (less the first BLOCK_SETTLE periods of each), so the shared
    host's noise falls on both alike."""
    from rig.runtime.session import Session
    rounds, block_s = args.rounds, args.block_s
    if not 1 <= rounds <= 100 or not 0.05 <= block_s <= 60:
        raise RigError(f"--rounds/--block-s: expected 1..100 rounds of 0.05..60 s blocks, got {rounds}, {block_s}")
    k, blk = block_plan(args.seconds, rounds, block_s)
    realtime = cfg.loop.realtime and not args.no_realtime
    spin = None if args.spin_us is None else int(round(args.spin_us * 1e3))
    names = ("machine", "prototype")
    keep = int(math.ceil((args.seconds / 2 + 1) * rate)) + 4 * rounds * k     # every period of a session
    tmp = []
    for _ in names:
        fd, path = tempfile.mkstemp(suffix=".h5", prefix="rig-bench-")
        os.close(fd)
        tmp.append(path)
    clocks = {n: BlockClock(spin, BLOCK_ALIGN_NS) for n in names}
    spans: dict = {n: [[] for _ in range(rounds)] for n in names}     # (first, last) period index per block
    faulted = {n: 0 for n in names}         # blocks left out: the loop faulted in them
    faults: dict = {}                       # per layout: the first fault's reason
    load0 = os.getloadavg()
    try:
        with contextlib.ExitStack() as stack:
            sessions = {n: stack.enter_context(Session(
                c, "sim", clock=clocks[n], rate_hz=rate, overrun_policy=args.policy, mode=mode, keep_timing=keep,
                stop_on_fault=False, rate_check=False, record=path, realtime=realtime,
                record_attrs={"command": "rig bench loop --layout both"}))
                for n, c, mode, path in zip(names, (cfg, proto), (None, PROTOTYPE_BENCH_MODE), tmp)}
            for c in clocks.values():
                c.stop()
            for sess in sessions.values():
                sess.loop.sched.measure_cpu()
            print(f"rig bench loop --layout both: 4 mounts and 1 at {rate:g} Hz, {rounds} rounds, each "
                  f"{k} block(s) of {blk:g} s per layout, alternating; "
                  f"{'real-time set-up where allowed' if realtime else 'no real-time hygiene'}; "
                  f"load average {load0[0]:.2f}", file=sys.stderr)
            settle = BLOCK_SETTLE
            for r in range(rounds):
                order = names if r % 2 == 0 else names[::-1]
                for _ in range(k):
                    for n in order:
                        span = _run_block(sessions[n], clocks[n], blk, settle)
                        if span is None:
                            faulted[n] += 1
                            faults.setdefault(n, sessions[n].loop.lc.fault_reason)
                        else:
                            spans[n][r].append(span)
                print(f"rig bench loop --layout both: round {r + 1}/{rounds} done", file=sys.stderr)
            loops = {n: s.loop for n, s in sessions.items()}
    finally:
        for path in tmp:
            os.unlink(path)
    out = _both_figures(loops, spans, rate, rounds, k, blk)
    for n in names:
        out[n]["faulted_blocks"] = faulted[n]
    out["kernel_us"] = {"machine": _kernel_us(cfg, None), "prototype": _kernel_us(proto, PROTOTYPE_BENCH_MODE)}
    out["load_average"] = [round(v, 2) for v in load0 + os.getloadavg()]
    _print_both(out, args.json)
    return faulted_exit({f"{n} ({faulted[n]} of {rounds * k} blocks)": why for n, why in faults.items()},
                        BLOCKS_LEFT_OUT)


def _run_block(session, clock, seconds: float, settle: int) -> tuple[int, int] | None:
    """One block of a session's loop, ACTIVE from its first period: the period indexes it measured (less the
    first `settle` and the last, the stop period: deactivation, its event and log line, once a block); None
    when the loop faulted in it (a stall of the shared host): its periods after the fault did less work, so
    the block is left out (and said so: faulted_exit)."""
    loop = session.loop
    clock.resume()
    end = None
    try:
        if loop.state is State.FAULT:           # a stall of the shared host tripped a rule: acknowledged
            loop.reset_fault()
        loop.stop_reason = None
        loop.activate()
        i0 = loop.iterations
        reason = session.run(seconds=seconds)
        end = loop.t_ns + loop.period_ns        # the end of its last period
    finally:
        clock.stop(end)
    stop_if_interrupted(reason)
    if loop.state is State.FAULT:
        return None
    return min(i0 + settle, loop.iterations - 1), loop.iterations - 1


def _both_figures(loops, spans, rate: float, rounds: int, k: int, blk: float) -> dict:
    """Per layout: pooled figures per round and over the run; the ratio of the p99s per round."""
    out: dict = {"rate_hz": rate, "rounds": rounds, "blocks_per_round": k, "block_s": round(blk, 4),
                 "settle_periods": BLOCK_SETTLE}
    for name, loop in loops.items():
        keep = loop.keep
        comp = np.frombuffer(loop.compute_ns, dtype=np.int64)
        wake = np.frombuffer(loop.wake_ns, dtype=np.int64)
        cpu = np.frombuffer(loop.cpu_ns, dtype=np.int64) if loop.cpu_ns is not None else None

        def pool(a, rs):
            idx = [np.arange(i0, i1) for r in rs for i0, i1 in spans[name][r]]
            return a[np.concatenate(idx) % keep] * 1e-3 if idx else np.zeros(0)
        out[name] = {"mounts": loop.n,
                     "compute_us_by_round": [_pct(pool(comp, [r])) for r in range(rounds)],
                     "wake_latency_us_by_round": [_pct(pool(wake, [r])) for r in range(rounds)],
                     "compute_us": _pct(pool(comp, range(rounds))),
                     "wake_latency_us": _pct(pool(wake, range(rounds))),
                     "iterations": loop.iterations, "overruns": loop.overruns}
        if cpu is not None:         # the loop thread's CPU time: the same periods, the host's preemption left out
            out[name]["cpu_us_by_round"] = [_pct(pool(cpu, [r])) for r in range(rounds)]
            out[name]["cpu_us"] = _pct(pool(cpu, range(rounds)))
    m, p = out["machine"]["compute_us_by_round"], out["prototype"]["compute_us_by_round"]
    out["compute_p99_ratio"] = [round(b["p99"] / a["p99"], 3) if a["n"] and b["n"] else None for a, b in zip(m, p)]
    out["rounds_prototype_p99_le_machine"] = sum(a["n"] > 0 and b["n"] > 0 and b["p99"] <= a["p99"] for a, b in zip(m, p))
    out["prototype_p99_le_machine_every_round"] = out["rounds_prototype_p99_le_machine"] == rounds
    mp, pp = out["machine"]["compute_us"], out["prototype"]["compute_us"]
    # the issue's figure: one mount's compute p99 against four mounts', each pooled over the whole run
    out["prototype_p99_le_machine_pooled"] = bool(mp["n"] and pp["n"] and pp["p99"] <= mp["p99"])
    if "cpu_us" in out["machine"] and "cpu_us" in out["prototype"]:
        mc, pc = out["machine"]["cpu_us_by_round"], out["prototype"]["cpu_us_by_round"]
        out["cpu_p99_ratio"] = [round(b["p99"] / a["p99"], 3) if a["n"] and b["n"] else None for a, b in zip(mc, pc)]
        out["rounds_prototype_cpu_p99_le_machine"] = sum(a["n"] > 0 and b["n"] > 0 and b["p99"] <= a["p99"]
                                                         for a, b in zip(mc, pc))
    return out


def _pct(a) -> dict:
    if not a.size:                          # every block of the round faulted
        return {"p50": None, "p99": None, "max": None, "n": 0}
    return {"p50": round(float(np.percentile(a, 50)), 2), "p99": round(float(np.percentile(a, 99)), 2),
            "max": round(float(a.max()), 2), "n": int(a.size)}


def _print_both(out: dict, as_json: bool) -> None:
    if as_json:
        print(json.dumps(out))
        return
    print(f"{out['rounds']} rounds at {out['rate_hz']:g} Hz; per round and layout {out['blocks_per_round']} "
          f"block(s) of {out['block_s']:g} s, alternating, starting on a {BLOCK_ALIGN_NS / 1e6:g} ms grid, each "
          f"less its first {out['settle_periods']} periods and its stop period; load average {out['load_average'][0]:.2f} before, {out['load_average'][3]:.2f} after")
    m, p = out["machine"], out["prototype"]
    for r, ratio in enumerate(out["compute_p99_ratio"]):
        a, b = m["compute_us_by_round"][r], p["compute_us_by_round"][r]
        if ratio is None:
            print(f"  round {r + 1}: every block of a layout faulted (see the warnings)")
            continue
        print(f"  round {r + 1}: compute machine (4) p50 {a['p50']:6.2f} p99 {a['p99']:6.2f} max {a['max']:8.1f} us"
              f" | prototype (1) p50 {b['p50']:6.2f} p99 {b['p99']:6.2f} max {b['max']:8.1f} us | p99 ratio "
              f"{ratio:.2f}")
    for name in ("machine", "prototype"):
        c, w = out[name]["compute_us"], out[name]["wake_latency_us"]
        if not c["n"]:
            print(f"  {name:9s} ({out[name]['mounts']}) pooled: no figures (every block faulted)")
            continue
        print(f"  {name:9s} ({out[name]['mounts']}) pooled: compute p50 {c['p50']:6.2f} p99 {c['p99']:6.2f} max "
              f"{c['max']:8.1f} us | wake p99 {w['p99']:7.1f} us | overruns {out[name]['overruns']}"
              + (f" | {out[name]['faulted_blocks']} block(s) left out (faulted)" if out[name]['faulted_blocks'] else ""))
    if "cpu_p99_ratio" in out:
        for name in ("machine", "prototype"):
            c = out[name]["cpu_us"]
            if not c["n"]:
                continue
            print(f"  {name:9s} ({out[name]['mounts']}) pooled: CPU time of the loop thread per period p50 "
                  f"{c['p50']:6.2f} p99 {c['p99']:6.2f} max {c['max']:8.1f} us")
        print("  CPU time p99 ratio by round (1 / 4 mounts): "
              + ", ".join("-" if v is None else f"{v:.2f}" for v in out["cpu_p99_ratio"]))
    kern = out["kernel_us"]
    print(f"  the compiled period alone: machine {kern['machine']:.3f} us, prototype {kern['prototype']:.3f} us "
          f"({kern['prototype'] / kern['machine']:.2f}x)")
    mp, pp = m["compute_us"], p["compute_us"]
    if mp["n"] and pp["n"]:
        print(f"one-mount compute p99 <= four-mount compute p99 over the run: "
              f"{'yes' if out['prototype_p99_le_machine_pooled'] else 'no'} "
              f"({pp['p99']:.2f} against {mp['p99']:.2f} us, ratio {pp['p99'] / mp['p99']:.2f})")
    ok = out["prototype_p99_le_machine_every_round"]
    n_ok = out["rounds_prototype_p99_le_machine"]
    print(f"one-mount compute p99 <= four-mount compute p99 in every round: {'yes' if ok else 'no'} "
          f"({n_ok} of {out['rounds']} rounds)")
    if "cpu_p99_ratio" in out:
        n_cpu = out["rounds_prototype_cpu_p99_le_machine"]
        print(f"one-mount CPU time p99 <= four-mount in every round: {'yes' if n_cpu == out['rounds'] else 'no'} "
              f"({n_cpu} of {out['rounds']} rounds)")


def _kernel_us(cfg, mode) -> float:
    """The compiled period's own cost on the layout's controllers after a short run in simulated time: the
    least of five means over 20000 back-to-back calls with the last measurement (ACTIVE, no recorder)."""
    from rig.runtime.session import Session
    from rig.runtime.clock import SimClock
    from rig.runtime.kernel import MODE_ACTIVE
    from rig.runtime.measured import MeasuredBlock
    with Session(cfg, "sim", clock=SimClock(), mode=mode) as s:
        s.run(seconds=0.1, activate_after_s=0.01)
        k, m = s.loop.kernel, s.loop.last_meas
        feed = MeasuredBlock(k.n, k.nf)                 # the last measurement as a latest value: every call steps
        feed.put(m)
        k.bind_io(feed.io)
        k.bind_ring(k.no_ring, k.no_hdr)
        args = (k.at, 0.0, 0.0, 0.0, 0.0, float(MODE_ACTIVE), 2.0, 1.0, 0.0, 0.0)
        best = math.inf
        for _ in range(5):
            t = time.perf_counter_ns()
            for _ in range(20000):
                k.call(*args)
            best = min(best, (time.perf_counter_ns() - t) / 20000 / 1e3)
    return round(best, 4)
