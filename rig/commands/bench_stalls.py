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
Per probe: the gap or echo time p50/p99/max, and how many exceeded 20 ms. A pty moves its bytes through the
kernel's tty flip buffer, pushed by a worker thread at normal priority: under the machine's other load that
worker waits, and the echo stalls while both ends run at SCHED_FIFO and the real-time loop does not (a serial
port's driver uses the same buffer). --json prints {"seconds", "rate_hz", "load", "probes": {name: {...}}}.
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
from rig.runtime.clock import MonotonicClock
from rig.runtime.rt import raise_priority

OVER_MS = 20.0


def add_arguments(p) -> None:
    p.add_argument("--seconds", type=cliargs.seconds(ge=1, le=3600), default=20.0, metavar="N",
                   help="duration (default 20)")
    p.add_argument("--rate", type=cliargs.rate_hz(le=20000), default=1000.0, metavar="HZ",
                   help="the empty loops' rate (default 1000)")
    p.add_argument("--json", action="store_true", help="print only the JSON figures on stdout")


def _loop(conn, priority: int, rate: float, seconds: float) -> None:
    raise_priority(priority)
    clock, period = MonotonicClock(0), int(round(1e9 / rate))
    t = time.monotonic_ns() + period
    end = t + int(seconds * 1e9)
    gaps, last = [], None
    while t < end:
        clock.sleep_until(t)
        now = time.monotonic_ns()
        if last is not None:
            gaps.append(now - last)
        last = now
        t += period
    conn.send(np.asarray(gaps, dtype=np.float64) * 1e-3)


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


def measure(cfg, seconds: float, rate: float) -> dict:
    ctx = mp.get_context("fork")
    prio, dev = cfg.loop.rt_priority, cfg.hil.device_priority
    probes = {"loop (SCHED_FIFO)": (_loop, (prio, rate, seconds)), "loop (normal)": (_loop, (0, rate, seconds)),
              "pty echo": (_echo, ("pty", dev - 5, seconds)), "socket echo": (_echo, ("socket", dev - 5, seconds))}
    running = {}
    for name, (fn, args) in probes.items():
        here, there = ctx.Pipe()
        p = ctx.Process(target=fn, args=(there, *args), daemon=True)
        p.start()
        running[name] = (p, here)
    load0 = os.getloadavg()[0]
    out = {}
    for name, (p, here) in running.items():
        a = here.recv() if here.poll(seconds + 30) else np.zeros(0)
        p.join(5)
        out[name] = ({"p50_us": round(float(np.percentile(a, 50)), 1), "p99_us": round(float(np.percentile(a, 99)), 1),
                      "max_ms": round(float(a.max()) * 1e-3, 2), f"over_{OVER_MS:g}_ms": int((a > OVER_MS * 1e3).sum()),
                      "n": int(a.size)} if a.size else {"n": 0})
    return {"seconds": seconds, "rate_hz": rate, "load": round((load0 + os.getloadavg()[0]) / 2, 2), "probes": out}


def run(args) -> int:
    cfg = load_config(getattr(args, "config", None))
    res = measure(cfg, args.seconds, args.rate)
    if args.json:
        print(json.dumps(res))
        return 0
    print(f"{res['seconds']:g} s side by side, load average {res['load']:g} on {os.cpu_count()} CPUs:")
    for name, d in res["probes"].items():
        if not d.get("n"):
            print(f"  {name:18s} no samples")
            continue
        print(f"  {name:18s} p50 {d['p50_us']:8.1f} us  p99 {d['p99_us']:8.1f} us  max {d['max_ms']:7.2f} ms  "
              f"over {OVER_MS:g} ms: {d[f'over_{OVER_MS:g}_ms']}", file=sys.stdout)
    return 0
