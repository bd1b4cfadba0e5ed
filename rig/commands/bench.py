"""`rig bench`: benchmarks, printed as distributions (never pass/fail).

  rig bench loop --rate HZ --seconds N [--json]   the control loop, four mounts on the simulated backend,
                                                  real clock, real-time hygiene where allowed, recording on
  rig bench loop --empty ...                      the same deadlines and wait with nothing in the period:
                                                  what the machine itself allows (same JSON)
  rig bench loop --layout prototype ...           the prototype instead: one mount on its stand, tracking a
                                                  sine (the isolation filters stepped alongside)
  rig bench loop --layout both ...                four mounts and one, alternately in one run (three rounds
                                                  each of --seconds / 6): {"machine", "prototype",
                                                  "compute_p99_ratio"} (prototype / machine, per round), and
                                                  "kernel_us": the compiled period alone, per layout (the
                                                  least of 5 x 20000 back-to-back calls: the code's cost
                                                  without the shared host's noise)
  rig bench loop --feedforward [--rounds R] ...   the feedback-only loop and the loop with the floor
                                                  accelerometers and feedforward, alternating in one run
  rig bench loop --console ...                    blocks without and with the operator console and a browser
                                                  on its page, alternating (rig/console/bench.py)
  rig bench recorder [--seconds N] [--json]       the recording writer's CPU time and the recording's size per
                                                  hour, gzip against none (rig/commands/bench_recorder.py)
  rig bench sim ...                               simulation speed of the plant
  rig bench prototype [--json]                    the prototype's tracking targets on the simulated stand,
                                                  in simulated time (rig/commands/prototype_bench.py)

`loop --json` prints exactly: {"rate_hz", "iterations", "wake_latency_us": {"p50","p99","max"},
"compute_us": {"p50","p99","max"}, "overruns", "missed_deadline_fraction"}; compute is read + check +
update + limit + write + record-push within one period; missed_deadline_fraction is
(overruns + skipped periods) / (iterations + skipped periods).

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
import json
import logging
import math
import os
import sys
import tempfile
import time

import numpy as np

from rig import cliargs
from rig.clock import MonotonicClock
from rig.config import load_config
from rig.console import bench as console_bench
from rig.errors import RigError
from rig.rt import cpu_steal_ms, enter_realtime, leave_realtime
from rig.session import Session
from sim_backend.bench import bench_sim as run_bench

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
    rp = sub.add_parser("recorder", help="recording writer: CPU time and size per hour, compressed or not")
    _config_arg(rp)
    rp.add_argument("--seconds", type=cliargs.seconds(ge=1, le=600), default=10.0, metavar="N",
                    help="seconds of `rig run` (sim backend, simulated time) recorded, then replayed (default 10)")
    rp.add_argument("--rounds", type=cliargs.count(1, 100), default=3,
                    help="replays of each mode, alternating (default 3; medians are printed)")
    rp.add_argument("--json", action="store_true", help="print only the JSON figures on stdout")


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
    raise RigError("bench: expected a benchmark: loop, sim, recorder or prototype (see rig bench --help)")


# ---- rig bench sim (owner: the plant engineer) ---------------------------------------------------------
def add_sim_arguments(p) -> None:
    """Arguments of `rig bench sim`."""
    p.add_argument("--seconds", type=cliargs.seconds(le=3600), default=100.0, metavar="N",
                   help="simulated time (default 100)")
    p.add_argument("--rate", type=cliargs.rate_hz(), default=5000.0, metavar="HZ", help="loop rate (default 5000)")
    p.add_argument("--repeats", type=cliargs.count(1, 1000), default=3, help="batch runs to time (default 3)")
    p.add_argument("--json", action="store_true", help="print only the JSON figures on stdout")


def bench_sim(args) -> int:
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
    if not logging.getLogger().handlers:
        logging.basicConfig(level=logging.WARNING, format="rig bench: %(message)s", stream=sys.stderr)
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
    if args.feedforward:
        return _feedforward_ab(cfg, args, rate)
    if layout != "machine":
        return _bench_layouts(cfg, args, rate, layout)
    if args.console:
        return console_bench.bench_console(args, cfg, rate, clock)
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
            session.run(seconds=args.seconds)
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
    if loop.lc.fault_reason:
        print(f"rig bench loop: note: the simulated rig faulted during the run: {loop.lc.fault_reason}",
              file=sys.stderr)
    n = min(loop.iterations, loop.keep)
    _print_host_stalls(np.frombuffer(loop.wake_ns, dtype="<i8")[:n], loop.period_ns, steal0, steal1, cpu)
    _print_loop_figures(out, args.json, loop.skipped)
    return 0


def _feedforward_ab(cfg, args, rate: float) -> int:
    """Feedback only and feedback + feedforward, alternating runs (AB BA AB ...), recording on, each run its
    own session; pooled compute and wake-up figures per path and their difference."""
    import dataclasses
    if not 1 <= args.rounds <= 100:              # (--rounds is shared with --console: rig/console/bench.py)
        raise RigError(f"--rounds: expected 1 to 100, got {args.rounds}")
    realtime = cfg.loop.realtime and not args.no_realtime
    paths = ("feedback", "feedback_feedforward")
    comp, wake = {p: [] for p in paths}, {p: [] for p in paths}
    out = {"rate_hz": rate, "rounds": args.rounds, "seconds": args.seconds}
    per_round = {p: [] for p in paths}
    counts = {p: {"iterations": 0, "overruns": 0} for p in paths}
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
                    session.run(seconds=args.seconds)
            finally:
                os.unlink(tmp)
            n = min(loop.iterations, loop.keep)
            cu = np.frombuffer(loop.compute_ns, dtype="<i8")[:n] * 1e-3
            comp[path].append(cu)
            wake[path].append(np.frombuffer(loop.wake_ns, dtype="<i8")[:n] * 1e-3)
            per_round[path].append(round(float(np.percentile(cu, 99)), 2))
            counts[path]["iterations"] += loop.iterations
            counts[path]["overruns"] += loop.overruns
            if loop.lc.fault_reason:
                print(f"rig bench loop: note: {path}: the simulated rig faulted: {loop.lc.fault_reason}",
                      file=sys.stderr)
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
        return 0
    print(f"{args.rounds} rounds of {args.seconds:g} s per path at {rate:g} Hz, alternating (AB BA ...)")
    for p in paths:
        c, w = out[p]["compute_us"], out[p]["wake_latency_us"]
        print(f"  {p:21s} compute p50 {c['p50']:6.2f} us  p99 {c['p99']:6.2f} us  max {c['max']:8.1f} us | "
              f"wake p99 {w['p99']:6.1f} us | p99 by round {out[p]['compute_p99_us_by_round']} | "
              f"overruns {out[p]['overruns']}")
    print(f"  feedforward - feedback: compute p50 {out['compute_p50_difference_us']:+.2f} us, "
          f"p99 {out['compute_p99_difference_us']:+.2f} us (pooled); p99 paired by round (median) "
          f"{out['compute_p99_paired_difference_us']:+.2f} us")
    return 0


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


def _bench_once(cfg, args, rate: float, seconds: float, mode=None) -> dict:
    """One timed run on the simulated backend (cfg's layout; mode: the stand's operating mode), recording to a
    temporary file: the loop figures."""
    fd, tmp = tempfile.mkstemp(suffix=".h5", prefix="rig-bench-")
    os.close(fd)
    realtime = cfg.loop.realtime and not args.no_realtime
    clock = MonotonicClock(None if args.spin_us is None else int(round(args.spin_us * 1e3)))
    try:
        with Session(cfg, "sim", clock=clock, rate_hz=rate, overrun_policy=args.policy, mode=mode,
                     keep_timing=int(math.ceil(seconds * rate)) + 16, stop_on_fault=False, record=tmp,
                     record_attrs={"command": "rig bench loop"}, realtime=realtime) as session:
            loop = session.loop
            loop.activate()
            session.run(seconds=seconds)
    finally:
        os.unlink(tmp)
    tm = loop.timing_us()
    return {"mounts": loop.n, "rate_hz": rate, "iterations": loop.iterations,
            "wake_latency_us": {k: round(v, 2) for k, v in tm["wake_latency_us"].items()},
            "compute_us": {k: round(v, 2) for k, v in tm["compute_us"].items()},
            "overruns": loop.overruns, "missed_deadline_fraction": loop.missed_deadline_fraction}


def _bench_layouts(cfg, args, rate: float, layout: str) -> int:
    """The prototype alone, or both layouts alternately (machine, prototype, machine, prototype) in one run."""
    from rig.commands.run import LAYOUTS
    proto = load_config(getattr(args, "config", None) or LAYOUTS["prototype"][None])
    if proto.layout.plant != "stand":
        raise RigError(f"--layout {layout}: {proto.source} is not a stand layout")
    order = [("prototype", proto)] if layout == "prototype" else [("machine", cfg), ("prototype", proto)] * 3
    seconds = args.seconds if layout == "prototype" else args.seconds / 6
    runs: dict = {}
    for name, c in order:
        print(f"rig bench loop: {name} ({len(c.layout.mounts) or 4} mount(s)) at {rate:g} Hz for {seconds:g} s"
              f"{', ' + PROTOTYPE_BENCH_MODE if name == 'prototype' else ''}", file=sys.stderr)
        runs.setdefault(name, []).append(_bench_once(c, args, rate, seconds,
                                                     PROTOTYPE_BENCH_MODE if name == "prototype" else None))
    if layout == "prototype":
        _print_loop_figures(runs["prototype"][0], args.json, 0)
        return 0
    ratios = [p["compute_us"]["p99"] / m["compute_us"]["p99"] for m, p in zip(runs["machine"], runs["prototype"])]
    kern = {"machine": _kernel_us(cfg, None), "prototype": _kernel_us(proto, PROTOTYPE_BENCH_MODE)}
    out = {"machine": runs["machine"], "prototype": runs["prototype"], "compute_p99_ratio": [round(r, 3) for r in ratios],
           "kernel_us": kern}
    if args.json:
        print(json.dumps(out))
        return 0
    for name in ("machine", "prototype"):
        for r in runs[name]:
            c, w = r["compute_us"], r["wake_latency_us"]
            print(f"{name:9s} {r['mounts']} mount(s): compute p50 {c['p50']:6.2f} p99 {c['p99']:6.2f} max {c['max']:8.1f} us"
                  f" | wake p99 {w['p99']:7.1f} us | overruns {r['overruns']}")
    print(f"compute p99, prototype / machine, per round: {', '.join(f'{r:.2f}' for r in ratios)}")
    print(f"the compiled period alone: machine {kern['machine']:.3f} us, prototype {kern['prototype']:.3f} us "
          f"({kern['prototype'] / kern['machine']:.2f}x)")
    return 0


def _kernel_us(cfg, mode) -> float:
    """The compiled period's own cost on the layout's controllers after a short run in simulated time: the
    least of five means over 20000 back-to-back calls with the last measurement (ACTIVE, no recorder)."""
    from rig.clock import SimClock
    from rig.kernel import MODE_ACTIVE
    with Session(cfg, "sim", clock=SimClock(), mode=mode) as s:
        s.run(seconds=0.1, activate_after_s=0.01)
        k, m = s.loop.kernel, s.loop.last_meas
        args = [0, 0.0, 0.0, 0.0, MODE_ACTIVE, 0, 0, True, *m.accel_mps2, *m.stroke_m, *m.sample_t_ns]
        best = math.inf
        for _ in range(5):
            t = time.perf_counter_ns()
            for _ in range(20000):
                k.call(k.mem, k.no_ring, -1, *args)
            best = min(best, (time.perf_counter_ns() - t) / 20000 / 1e3)
    return round(best, 4)
