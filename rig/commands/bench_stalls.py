"""`rig bench stalls`: where a stall of tens of milliseconds comes from, measured side by side in one run.

  rig bench stalls [--seconds N] [--rate HZ] [--json]

Four probes run at once, each a process of its own, for --seconds:
  loop (SCHED_FIFO)    an empty loop on absolute deadlines at --rate and the loop's priority ([loop] rt_priority):
                       what the host lets a real-time loop do (a stall here is the host's: the hypervisor, or the
                       kernel's real-time throttling when real-time tasks take more than 95 % of a CPU)
  loop (normal)        the same at normal priority: the machine's other load
  pty echo             a byte echoed through a pty pair between two SCHED_FIFO processes (the emulated amplifier's
                       line, at the devices' priorities), every 2 ms
  socket echo          the same through a socket pair (the Modbus and CAN gateways' loopback TCP takes this path)
Per probe: the gap or echo time p50/p99/max, and how many exceeded 20 ms; for the loops also the share of
wake-ups more than a period late (what `rig hil` counts as a late period). A pty moves its bytes through the
kernel's tty flip buffer, pushed by a worker thread at normal priority: under the machine's other load that
worker waits, and the echo stalls while both ends run at SCHED_FIFO and the real-time loop does not (a serial
port's driver uses the same buffer).

Then the CPUs kept busy, --seconds / 2 (at most 10 s) each: a busy loop pinned to one CPU alone, then one pinned
to every CPU at once. What such a loop loses in gaps over 0.5 ms was taken from it: by the machine's other
processes (the load says whether there are any) or, on an otherwise idle machine, by the kernel or the
hypervisor. A host that takes far more when every CPU is busy cannot hold a loop whose processes need more than
one CPU to a period (drivers/README.md, the same code on a noisier host). --json prints {"seconds", "rate_hz", "load", "probes": {name: {...}}, "busy": {"one CPU", "every CPU":
{"seconds", "cpus", "load", "lost_pct", "gaps_over_5_ms", "longest_ms"}}}.
"""
from __future__ import annotations

import json
import multiprocessing as mp
import os
import select
import socket
import sys
import time
import tty

import numpy as np

from rig import cliargs
from rig.config import load_config
from rig.runtime.empty_loop import EmptyLoop
from rig.runtime.rt import raise_priority

OVER_MS = 20.0
GAP_NS = 500_000            # a busy loop's gap longer than this was the CPU taken from it
BUSY_MAX_S = 10.0


def add_arguments(p) -> None:
    p.add_argument("--seconds", type=cliargs.seconds(ge=1, le=3600), default=20.0, metavar="N",
                   help="duration (default 20)")
    p.add_argument("--rate", type=cliargs.rate_hz(le=20000), default=1000.0, metavar="HZ",
                   help="the empty loops' rate (default 1000)")
    p.add_argument("--json", action="store_true", help="print only the JSON figures on stdout")


def _echo(conn, kind: str, priority: int, seconds: float) -> None:
    """One end asks, the other (a forked child at priority + 5) echoes: the round trip, every 2 ms."""
    if kind == "pty":
        a, b = os.openpty()
        tty.setraw(b)
        near, far = b, a
    else:
        s1, s2 = socket.socketpair()
        near, far = s1.detach(), s2.detach()
    pid = os.fork()
    if pid == 0:
        raise_priority(priority + 5)
        while True:
            r, _, _ = select.select([far], [], [], 1.0)
            if r:
                d = os.read(far, 64)
                if not d or d == b"q":
                    os._exit(0)
                os.write(far, d)
    raise_priority(priority)
    out = []
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        t0 = time.monotonic_ns()
        os.write(near, b"x")
        r, _, _ = select.select([near], [], [], 1.0)
        if r:
            os.read(near, 64)
        out.append(time.monotonic_ns() - t0)
        time.sleep(0.002)
    os.write(near, b"q")
    os.waitpid(pid, 0)
    conn.send(np.asarray(out, dtype=np.float64) * 1e-3)


def _figures(a: np.ndarray) -> dict:
    """A probe's gaps or echo times (us): p50, p99, max, how many over OVER_MS."""
    if not a.size:
        return {"n": 0}
    return {"p50_us": round(float(np.percentile(a, 50)), 1), "p99_us": round(float(np.percentile(a, 99)), 1),
            "max_ms": round(float(a.max()) * 1e-3, 2), f"over_{OVER_MS:g}_ms": int((a > OVER_MS * 1e3).sum()),
            "n": int(a.size)}


def _spin(conn, cpu: int, seconds: float) -> None:
    """Busy on one CPU for `seconds`: the gaps over GAP_NS between two readings of the clock (us)."""
    os.sched_setaffinity(0, {cpu})
    now_ns = time.monotonic_ns
    last = now_ns()
    end = last + int(seconds * 1e9)
    gaps = []
    while last < end:
        now = now_ns()
        if now - last > GAP_NS:
            gaps.append(now - last)
        last = now
    conn.send(np.asarray(gaps, dtype=np.float64) * 1e-3)


def busy(seconds: float) -> dict:
    """A busy loop on one CPU alone, then on every CPU at once: per phase the share of its time each lost in
    gaps (the mean over the CPUs), the gaps over 5 ms and the longest."""
    ctx = mp.get_context("fork")
    cpus = sorted(os.sched_getaffinity(0))
    out = {}
    for phase, on in (("one CPU", cpus[-1:]), ("every CPU", cpus)):
        running = []
        for cpu in on:
            here, there = ctx.Pipe()
            p = ctx.Process(target=_spin, args=(there, cpu, seconds), daemon=True)
            p.start()
            running.append((p, here))
        gaps = []
        for p, here in running:
            gaps.append(here.recv() if here.poll(seconds + 30) else np.zeros(0))
            p.join(5)
        out[phase] = {"seconds": seconds, "cpus": len(on), "load": round(os.getloadavg()[0], 2),
                      "lost_pct": round(100 * float(np.mean([g.sum() * 1e-6 / seconds for g in gaps])), 2),
                      "gaps_over_5_ms": int(sum((g > 5e3).sum() for g in gaps)),
                      "longest_ms": round(max((float(g.max()) for g in gaps if g.size), default=0.0) * 1e-3, 2)}
    return out


def measure(cfg, seconds: float, rate: float) -> dict:
    ctx = mp.get_context("fork")
    prio, dev = cfg.loop.rt_priority, cfg.hil.device_priority
    loops = {"loop (SCHED_FIFO)": EmptyLoop(rate, seconds, prio), "loop (normal)": EmptyLoop(rate, seconds, 0)}
    echoes = {"pty echo": ("pty", dev - 5, seconds), "socket echo": ("socket", dev - 5, seconds)}
    running = {}
    for name, args in echoes.items():
        here, there = ctx.Pipe()
        p = ctx.Process(target=_echo, args=(there, *args), daemon=True)
        p.start()
        running[name] = (p, here)
    load0 = os.getloadavg()[0]
    echoed = {}
    with loops["loop (SCHED_FIFO)"], loops["loop (normal)"]:
        for name, (p, here) in running.items():
            echoed[name] = _figures(here.recv() if here.poll(seconds + 30) else np.zeros(0))
            p.join(5)
    out = {}
    for name, el in loops.items():
        late = el.late_us()
        gaps = el.period_ns * 1e-3 + np.diff(late)          # between two wake-ups (us)
        out[name] = dict(_figures(gaps), late_over_period_pct=round(100 * float((late > el.period_ns * 1e-3).mean()), 2)
                         if late.size else None)
    load = round((load0 + os.getloadavg()[0]) / 2, 2)
    return {"seconds": seconds, "rate_hz": rate, "load": load, "probes": {**out, **echoed},
            "busy": busy(min(seconds / 2, BUSY_MAX_S))}


def run(args) -> int:
    cfg = load_config(getattr(args, "config", None))
    print(f"rig bench stalls: {args.seconds:g} s of the four probes side by side, then the CPUs kept busy "
          f"(2 x {min(args.seconds / 2, BUSY_MAX_S):g} s)", file=sys.stderr)
    res = measure(cfg, args.seconds, args.rate)
    if args.json:
        print(json.dumps(res))
        return 0
    print(f"{res['seconds']:g} s side by side, load average {res['load']:g} on {os.cpu_count()} CPUs:")
    for name, d in res["probes"].items():
        if not d.get("n"):
            print(f"  {name:18s} no samples")
            continue
        late = (f"  late > a period: {d['late_over_period_pct']:.2f} %" if d.get("late_over_period_pct") is not None
                else "")
        print(f"  {name:18s} p50 {d['p50_us']:8.1f} us  p99 {d['p99_us']:8.1f} us  max {d['max_ms']:7.2f} ms  "
              f"over {OVER_MS:g} ms: {d[f'over_{OVER_MS:g}_ms']}{late}", file=sys.stdout)
    print(f"CPUs kept busy, {res['busy']['one CPU']['seconds']:g} s each (time the host took from a busy loop):")
    for phase, d in res["busy"].items():
        print(f"  {phase:18s} lost {d['lost_pct']:5.2f} %  gaps over 5 ms: {d['gaps_over_5_ms']}  longest "
              f"{d['longest_ms']:.1f} ms  (load average {d['load']:g})")
    return 0
