"""`rig hil --bench`: the loop through the drivers on the emulated rig with no control compute (every mount's
controller off: the period is the loop's own work, the exchange block read and written, the row recorded),
at the HIL rate, printed as distributions:

  loop        the period's work (wake-up to the end of the period; no controller), the wake-up latency, the
              missed deadlines
  transports  each transport's round trip as its I/O process measures it: SYNC -> the first valve's TPDO,
              one Modbus read of the module's counter and FIFO, RD -> a data frame on the serial line
  devices     each device's configured rate and latency beside what it did: SYNCs, conversions and frames a
              second, their misses (SYNCs with the period before's commands, conversions lost from the FIFO,
              requests without a new frame), the age of the conversion and of the transducer sample when the
              loop used them (p50/p99/max)
  cpu         each process's CPU time per loop period (all its threads, from /proc/PID/task/*/schedstat): the
              loop's, each I/O process's, each emulated device's; their sum as CPUs kept busy, against the
              CPUs there are. Above about two thirds of them the processes of one period wait for each other.

--json prints {"rate_hz", "seconds", "loop": {...}, "round_trip_us": {...}, "devices": {...}, "cpu": {...}} only.
"""
from __future__ import annotations

import json
import math
import sys

import numpy as np

from rig.config import channel_delays, layout_mounts
from rig.runtime.session import Session

SECONDS = 10.0


class _Off:
    """A mount's controller that computes nothing (the kernel's kind 0): the period is the loop's own work."""
    kind = 0
    state_names: tuple = ()

    def __init__(self, dt: float) -> None:
        self.dt = dt

    def coefficients(self):
        return np.zeros(0)

    def initial_state(self) -> list:
        return []

    def set_enabled(self, state, on: bool):
        return state


def pct(a) -> dict:
    a = np.asarray(a, dtype=float)
    if a.size == 0:
        return {"p50": math.nan, "p99": math.nan, "max": math.nan, "n": 0}
    return {"p50": round(float(np.percentile(a, 50)), 1), "p99": round(float(np.percentile(a, 99)), 1),
            "max": round(float(a.max()), 1), "n": int(a.size)}


def cpu_ns(pid: int) -> int | None:
    """CPU time of a process so far (ns, all its threads), or None where the kernel does not say."""
    import glob
    total, seen = 0, False
    for f in glob.glob(f"/proc/{pid}/task/*/schedstat"):
        try:
            with open(f) as fh:
                total += int(fh.read().split()[0])
            seen = True
        except (OSError, ValueError, IndexError):
            pass
    return total if seen else None


def _processes(port) -> dict[str, int]:
    """The run's processes by name: the loop's, the I/O processes, the emulated devices."""
    import os
    out = {"loop's process": os.getpid()}
    out.update({f"I/O: {k}": v for k, v in port.pids.items()})
    rig = getattr(port, "rig", None)
    for what in ("plant", "modbus", "serial"):
        try:
            out[f"emulated {what}"] = rig.device_pid(what)
        except (AttributeError, StopIteration):
            pass
    return out


def cpu_figures(before: dict, after: dict, periods: int, wall_s: float) -> dict:
    """Per process: us of CPU per loop period and the share of one CPU; their sum as CPUs busy."""
    import os
    per = {}
    for name, (pid, c0) in before.items():
        c1 = after.get(name)
        if c0 is None or c1 is None or periods <= 0 or wall_s <= 0:
            continue
        per[name] = {"us_per_period": round((c1 - c0) * 1e-3 / periods, 1),
                     "cpu_share": round((c1 - c0) * 1e-9 / wall_s, 3)}
    return {"processes": per, "cpus_busy": round(sum(v["cpu_share"] for v in per.values()), 2),
            "cpus": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()}


def measure(cfg, seconds: float, realtime: bool = True) -> dict:
    """The figures of one run (see the module doc)."""
    rate = cfg.loop.rate_hz
    with Session(cfg, "hil", controllers=lambda c, dt: [_Off(dt) for _ in layout_mounts(c)],
                 keep_timing=int(seconds * rate) + 16, realtime=realtime, rate_check=False) as s:
        port, loop = s.port, s.loop
        procs = _processes(port)
        cpu0 = {k: (pid, cpu_ns(pid)) for k, pid in procs.items()}
        c0, t0, i0 = port.counts(), s.clock.now_ns(), loop.iterations
        s.run(seconds=seconds, activate_after_s=min(0.05, seconds / 10))
        wall = (s.clock.now_ns() - t0) * 1e-9
        cpu = cpu_figures(cpu0, {k: cpu_ns(pid) for k, pid in procs.items()}, loop.iterations - i0, wall)
        counts = {k: (v[0] - c0[k][0], v[1] - c0[k][1]) for k, v in port.counts().items()}
        n = min(loop.iterations, loop.keep)
        work = np.frombuffer(loop.compute_ns, dtype=np.int64)[:n] * 1e-3
        wake = np.frombuffer(loop.wake_ns, dtype=np.int64)[:n] * 1e-3
        ages = port.sample_ages_us()[-n:]
        rtt = {k: pct(v) for k, v in port.round_trips_us().items()}
        fault = loop.lc.fault_reason
    d = cfg.drivers
    delays = channel_delays(cfg, rate)
    return {"rate_hz": rate, "seconds": seconds, "fault": fault, "cpu": cpu,
            "loop": {"work_us": pct(work), "wake_latency_us": pct(wake), "periods": int(n),
                     "missed_deadline_fraction": round(loop.missed_deadline_fraction, 5)},
            "round_trip_us": rtt,
            "devices": {
                "valves": {"rate_hz": rate, "measured_hz": round(counts["valves"][0] / wall, 1),
                           "sync_offset_us": d.sync_offset_s * 1e6, "late_commands": counts["valves"][1]},
                "accelerometer module": {"rate_hz": rate / d.accel_fetch_every,
                                         "conversions_hz": round(counts["accelerometer module"][0] / wall, 1),
                                         "fetch_delay_us": d.accel_fetch_delay_s * 1e6,
                                         "delay_periods": delays[0], "lost": counts["accelerometer module"][1],
                                         "age_at_use_us": pct(ages[:, 0])},
                "transducer amplifier": {"rate_hz": min(d.serial_rate_hz, rate),
                                         "frames_hz": round(counts["transducer amplifier"][0] / wall, 1),
                                         "latency_us": d.serial_latency_s * 1e6, "delay_periods": delays[1],
                                         "no_frame": counts["transducer amplifier"][1],
                                         "age_at_use_us": pct(ages[:, 1])}}}


def run(cfg, seconds: float, as_json: bool) -> int:
    res = measure(cfg, seconds, realtime=cfg.loop.realtime)
    if as_json:
        print(json.dumps({k: res[k] for k in ("rate_hz", "seconds", "loop", "round_trip_us", "devices", "cpu")}))
        return 1 if res["fault"] else 0
    lp = res["loop"]

    def dist(d):
        return f"p50 {d['p50']} p99 {d['p99']} max {d['max']}"
    print(f"loop at {res['rate_hz']:g} Hz for {res['seconds']:g} s, no control compute: {lp['periods']} periods, "
          f"missed deadlines {100 * lp['missed_deadline_fraction']:.3f} %")
    print(f"  period's work (us)      {dist(lp['work_us'])}")
    print(f"  wake-up latency (us)    {dist(lp['wake_latency_us'])}")
    print("round trips (us), as each I/O process measures them:")
    for k, v in res["round_trip_us"].items():
        print(f"  {k:22s}  {dist(v)}")
    print("devices:")
    for name, v in res["devices"].items():
        print(f"  {name}: " + ", ".join(f"{k} {dist(x) if isinstance(x, dict) else x}" for k, x in v.items()))
    cpu = res["cpu"]
    print(f"CPU per loop period (us) and share of one CPU: {cpu['cpus_busy']:g} of {cpu['cpus']} CPUs busy")
    for name, v in sorted(cpu["processes"].items(), key=lambda kv: -kv[1]["us_per_period"]):
        print(f"  {name:28s}  {v['us_per_period']:8.1f} us  {100 * v['cpu_share']:5.1f} %")
    if res["fault"]:
        print(f"rig hil --bench: FAULT: {res['fault']}", file=sys.stderr)
    return 1 if res["fault"] else 0
