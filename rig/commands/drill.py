"""`rig drill`: the fault drill. Each fault the rig guards against, rehearsed on a fresh run: what the rig did
(the one line it printed), whether it nulled the valves, and the time from the fault to FAULT.

  rig drill [--backend sim|hil|both] [--only NAME ...] [--json] [--no-realtime]

Sensor and device faults are driven through the backends' knobs (rig/runtime/inject.py: the simulated backend's
`inject`, the emulated devices' knobs behind the real drivers); the loop's own faults (a stall, a loop
falling behind, a limit cycle of an unstable controller, a rate it cannot hold) and the recorder's death
through the same injections or a configuration that provokes them. Every run records (HDF5, a temporary
folder): the drill reads the FAULT row, the valve commands recorded in it and after, and counts the rows
against the loop's periods (a controlled stop loses none; a killed writer loses what it had not flushed).

Times are loop time: `to FAULT` is from the knob acting (or the first command swing beyond the oscillation
level, or the loop's lag crossing lag_limit_s) to the period that faulted. Real clock, so the figures vary
with the machine's load; the table in README is one run of `rig drill --backend both`.
"""
from __future__ import annotations

import dataclasses
import json
import logging
import math
import re
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from rig.runtime import inject
from rig.backends import default_config
from rig.runtime.clock import MonotonicClock
from rig.config import hil_run_config, load_config
from rig.errors import ConfigError, RigError
from rig.runtime.recorder import read_recording

T_SIM = 0.5          # knob time on the simulated backend (activation at 0.05 s)
T_HIL = 1.0          # on the emulated devices (activation at 0.05 s, drivers settled)


@dataclasses.dataclass(frozen=True)
class Case:
    name: str
    rule: str                       # what should catch it
    spec: str = ""                  # KIND:MOUNT:SIGNAL (the time is added)
    tweak: str = ""                 # a configuration that provokes it: kp10 (unstable gain), skip, rate
    seconds: float = 1.5            # run length after the knob time


def _loop_cases() -> list[Case]:
    """The loop's own faults, drilled on every backend."""
    return [Case("loop stalls (three watchdog limits in one period)", "watchdog", "stall:*:-"),
            Case("loop falls behind (1.2 periods extra per period)", "lag rule", "overrun:*:-"),
            Case("recording writer killed", "recorder watch", "recorder:*:-"),
            Case("limit cycle (kp x10, --force)", "oscillation rule", tweak="kp10")]


SIM_CASES = [
    Case("accelerometer NaN", "sensor check: implausible", "nan:front_left:accel"),
    Case("stroke out of range", "sensor check: implausible", "range:front_right:stroke"),
    Case("stale accelerometer samples", "sensor check: stale", "stale:rear_left:accel"),
    Case("stroke samples no longer refreshed", "sensor check: stale", "drop:rear_right:stroke"),
    Case("accelerometer stuck", "sensor check: stuck", "stuck:front_left:accel"),
    Case("device reports a fault", "device fault", "device:front_right:-"),
    *_loop_cases(),
    Case("loop misses deadlines (skip policy)", "missed-deadline rule", "overrun:*:-", tweak="skip", seconds=2.0),
    Case("unstable controller (kp x10)", "start-up: stability check", tweak="kp10-check"),
    Case("rate the loop cannot hold (100 kHz)", "start-up: rate check", tweak="rate"),
]
HIL_CASES = [
    Case("Modbus module silent", "stale sample / device", "silence:*:accel"),
    Case("Modbus module answers with exceptions", "device fault", "exception:*:accel"),
    Case("Modbus registers frozen", "stale sample", "stale:*:accel"),
    Case("serial amplifier silent", "device fault", "silence:*:stroke"),
    Case("serial amplifier sends garbage", "device fault", "garbage:*:stroke"),
    Case("stroke channel over range", "device fault", "range:front_left:stroke"),
    Case("stroke transducer not present", "device fault", "nan:front_left:stroke"),
    Case("valve node silent", "device fault", "silence:front_left:valve"),
    Case("valve node in fault", "device fault", "fault:front_right:valve"),
    *_loop_cases(),
]


def add_arguments(p) -> None:
    p.add_argument("--backend", choices=("sim", "hil", "both"), default="sim",
                   help="where to drill (default sim; hil: the real drivers against the emulated devices)")
    p.add_argument("--only", nargs="+", metavar="WORD", default=None,
                   help="only the cases whose name contains one of these words")
    p.add_argument("--no-realtime", action="store_true", help="do not try SCHED_FIFO/affinity/mlockall")
    p.add_argument("--json", action="store_true", help="print only the JSON results on stdout")


def _config(backend: str, given: str | None, tweak: str):
    cfg = load_config(given if given else default_config(backend))
    if backend == "hil":
        cfg = hil_run_config(cfg)
    if tweak.startswith("kp10"):
        cfg = cfg.replace(controller=dataclasses.replace(cfg.controller, kp_V_per_m=10 * cfg.controller.kp_V_per_m))
    elif tweak == "skip":
        cfg = cfg.replace(loop=dataclasses.replace(cfg.loop, overrun_policy="skip"))
    elif tweak == "rate":
        cfg = cfg.replace(loop=dataclasses.replace(cfg.loop, rate_hz=100000.0))
    return cfg


def _switch_on_at(case: Case, backend: str, cfg) -> float | None:
    """When the case switches isolation on (loop time), or None. The unstable gain in hil is switched on after
    the warm-up of 2 / blend_hz, as an operator would: switched on cold, its first burst could leave the
    estimate a velocity error that holds the output at one clamp (the saturation recovery's case, not a limit
    cycle)."""
    return T_HIL + 2.0 / cfg.controller.blend_hz if case.tweak == "kp10" and backend == "hil" else None


def drill_case(case: Case, backend: str, *, config: str | None = None, realtime: bool = True,
               folder: Path) -> dict:
    """One case on a fresh session; the figures of what happened."""
    from controllers.isolation import make_isolation_controllers
    from rig.runtime.session import Session, check_stable
    cfg = _config(backend, config, case.tweak)
    on_at = _switch_on_at(case, backend, cfg)
    at = on_at if on_at is not None else T_SIM if backend == "sim" else T_HIL
    spec = f"{case.spec}@{at:g}" if case.spec else ""
    injections = [inject.parse(spec)] if spec else []
    rec = folder / f"{backend}-{len(list(folder.iterdir()))}.h5"
    out = {"backend": backend, "case": case.name, "expected": case.rule, "inject": spec or case.tweak,
           "faulted": False, "line": "", "to_fault_ms": None, "valves_null": None, "rows_lost": None}
    if case.tweak == "kp10-check":            # the start-up check alone, timed
        ctrls = make_isolation_controllers(cfg, 1.0 / cfg.loop.rate_hz)
        t0 = time.perf_counter()
        try:
            check_stable(cfg, ctrls, 1.0 / cfg.loop.rate_hz)
        except ConfigError as e:
            out.update(faulted=True, line=f"refused: {e}", valves_null=True,
                       to_fault_ms=round((time.perf_counter() - t0) * 1e3, 1), measured_from="the check's start")
        return out
    session = None
    try:
        # isolation on in sim; in hil off (its controllers need a warm-up first), or switched on by the case
        session = Session(cfg, backend, clock=MonotonicClock(), isolation=backend == "sim",
                          script=None if on_at is None else [(on_at, "on")],
                          record=rec, record_attrs={"command": "rig drill", "case": case.name},
                          realtime=realtime and cfg.loop.realtime)
        with session:
            loop = session.loop
            with inject.Armed(session, injections) as armed:
                session.run(seconds=at + case.seconds, activate_after_s=0.05)
            applied = armed.applied.get(spec)
            armed_rows = armed.rows_at_kill
            held = _valves_at_null(session, backend)
    except ConfigError as e:                  # refused at start-up (the rate): after how much loop time
        lp = session.loop if session is not None else None
        t = (lp.t_ns - lp.t0_ns) * 1e-3 if lp is not None and lp.t0_ns is not None else None
        out.update(faulted=True, line=f"refused: {e}", valves_null=lp is None or all(v == 0.0 for v in lp.cmd),
                   to_fault_ms=None if t is None else round(t / 1e3, 1), measured_from="the first period")
        return out
    reason = loop.lc.fault_reason
    out["line"] = reason or f"no fault (stopped: {loop.stop_reason})"
    if reason is None:
        return out
    out["faulted"] = True
    t_fault = (loop.fault_t_ns - loop.t0_ns) * 1e-9
    d = read_recording(rec)
    fault_rows = np.flatnonzero(d["fault"] > 0.5)
    k = int(fault_rows[0]) if fault_rows.size else None
    out["valves_null"] = held and (k is None or bool(np.all(d["valve_cmd_V"][k:] == 0.0)))
    out["rows_lost"] = int(loop.iterations - len(d["time_s"]))
    if armed_rows is not None:             # the writer killed: rows committed before the kill, not in the file
        out["rows_lost_at_kill"] = max(0, int(armed_rows - len(d["time_s"])))
        out["ms_lost_at_kill"] = round(out["rows_lost_at_kill"] / loop.rate_hz * 1e3, 1)
    start, what = applied, "the knob acting"
    if case.tweak == "kp10":                  # from the first swing beyond the oscillation level
        level = cfg.safety.oscillation_level * cfg.safety.valve_limit_V
        big = np.flatnonzero(np.any(np.abs(d["valve_cmd_V"]) >= level, axis=1))
        if big.size:
            start, what = float(d["time_s"][big[0]]), "the first command beyond +-level"
    elif case.spec.startswith("stall"):         # held up inside one period: the watchdog thread's real time
        silent = re.search(r"silent for ([0-9.]+) ms", reason) or re.search(r"([0-9.]+) ms between periods", reason)
        if silent:
            out["to_fault_ms"] = float(silent.group(1))
            out["measured_from"] = "the stall's start (real time)"
            return out
    elif case.spec.startswith("overrun") and k is not None and case.tweak != "skip":
        lag = d["wake_latency_us"] * 1e-6
        below = np.flatnonzero(lag[:k] <= cfg.safety.lag_limit_s)
        if below.size:                        # the last wake-up still within the limit
            j = int(below[-1])
            out["after_limit_crossed_ms"] = round((d["time_s"][k] + lag[k] - d["time_s"][j] - lag[j]) * 1e3, 2)
        out["knob_to_fault_ms"] = round((t_fault - applied) * 1e3, 1) if applied is not None else None
    if start is not None:
        out["to_fault_ms"] = round((t_fault - start) * 1e3, 2)
        out["measured_from"] = what
    return out


def _valves_at_null(session, backend: str, wait_s: float = 0.5) -> bool:
    """What the valves got last is null: the simulated backend's last write; the emulated valves' applied
    commands (the driver's null takes effect at the SYNC it sends after it, handled in the emulator's thread:
    polled for up to wait_s)."""
    if backend == "sim":
        return all(v == 0.0 for v in session.port.last_written)
    emu = session.port.rig
    end = time.monotonic() + wait_s
    while not all(v == 0.0 for v in emu.last_cmd_V):
        if time.monotonic() > end:
            return False
        time.sleep(0.005)
    return True


def run(args) -> int:
    if not logging.getLogger().handlers:
        logging.basicConfig(level=logging.CRITICAL, stream=sys.stderr)     # the drill prints the lines itself
    backends = ("sim", "hil") if args.backend == "both" else (args.backend,)
    if args.only and not all(w.strip() for w in args.only):
        raise RigError("--only: an empty word would match every case; give words of the case names")
    chosen = {b: [c for c in (SIM_CASES if b == "sim" else HIL_CASES)
                  if not args.only or any(w.lower() in c.name.lower() for w in args.only)] for b in backends}
    if not any(chosen.values()):
        raise RigError("--only: no drill case matches " + ", ".join(map(repr, args.only)))
    results = []
    with tempfile.TemporaryDirectory(prefix="rig-drill-") as tmp:
        for backend in backends:
            for c in chosen[backend]:
                print(f"rig drill: {backend}: {c.name} ...", file=sys.stderr, flush=True)
                r = drill_case(c, backend, config=args.config, realtime=not args.no_realtime, folder=Path(tmp))
                results.append(r)
                print(f"rig drill:   {_row(r)}", file=sys.stderr, flush=True)
    if args.json:
        print(json.dumps(results, indent=1))
    else:
        print(table(results))
    missed = [r for r in results if not r["faulted"] or r["valves_null"] is False]
    return 1 if missed else 0


def _ms(v) -> str:
    return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:g} ms"


def _row(r: dict) -> str:
    null = {True: "valves null", False: "VALVES NOT NULL", None: "-"}[r["valves_null"]]
    return f"{'FAULT' if r['faulted'] else 'NO FAULT'} in {_ms(r['to_fault_ms'])}, {null}: {r['line']}"


def table(results: list[dict]) -> str:
    """Markdown: backend, case, injection, what the rig did, time to FAULT (and from what), valves, rows."""
    lines = ["| backend | fault | injected | the rig's line | to FAULT | valves null | rows lost |",
             "|---|---|---|---|---|---|---|"]
    for r in results:
        t = _ms(r["to_fault_ms"])
        if r.get("measured_from") and r["measured_from"] != "the knob acting":
            t += f" from {r['measured_from']}"
        if r.get("after_limit_crossed_ms") is not None:
            t += f" ({r['after_limit_crossed_ms']:g} ms after the lag crossed the limit)"
        line = r["line"].replace("|", "/")
        null = {True: "yes", False: "NO", None: "-"}[r["valves_null"]]
        lost = "-" if r["rows_lost"] is None else str(r["rows_lost"])
        if r.get("rows_lost_at_kill") is not None:
            lost = (f"{r['rows_lost_at_kill']} committed before the kill ({r['ms_lost_at_kill']:g} ms), "
                    f"{r['rows_lost']} in all")
        lines.append(f"| {r['backend']} | {r['case']} | `{r['inject']}` | {line} | {t} | {null} | {lost} |")
    return "\n".join(lines)
