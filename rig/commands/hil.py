"""`rig hil`: the control loop through the real drivers (CANopen valves, Modbus TCP accelerometers, serial
displacement transducers) against the emulated rig under broadband floor vibration; isolation off, then
feedback, then (with floor accelerometers, [sensors] floor_accel) feedback + floor feedforward, switched live.

  rig hil [--config F] [--seconds N] [--rate HZ] [--record FILE] [--json]
  rig hil --bench [--seconds N] [--json]        driver round trips, p50/p99/max (us): in the loop's pattern
                                                (null commands, no controller), then each transport alone

Without --config the run uses drivers/devicemaps/hil.toml (the HIL rate and the isolation controller re-tuned
for it, see controllers/tune_hil.py); a config of your own should carry a [controller] section
tuned for [hil] rate_hz. The run uses [hil] rate_hz (Modbus request/response limits the rate) and [hil]
stale_s as the staleness limit of the drivers and of the loop's sensor check. The run is split evenly into the
modes, switched live through the loop's mode request (bumpless): off, feedback, and feedback_feedforward when
the floor accelerometers are fitted (hil.toml fits them: the module's AI ch4-7); [hil] settle_s at the start of
each mode and at the end of the run is not metered. isolation_reduction_db = 20 log10(rms table motion off / feedback),
feedforward_reduction_db the same for feedback + feedforward (null without floor accelerometers): the true table
motion of the emulated plant. The modes see successive stretches of the floor motion (one real-time run), so
the figures also carry the floor's own variation; "transmissibility_db" (table rms over floor rms per mode)
takes the floor's level out.
"late_periods" gives per mode the share of its metered periods that were late: the loop woke more than a period
after its deadline, or the accelerometer module's new conversion had not arrived (a late Modbus reply); the valves
hold their last command meanwhile, so a loaded machine shows here first (the feedforward's figure suffers first).
"empty_loop_late" gives per mode the share of its periods in which an empty loop beside the run (one pinned to each
CPU, above the loop's priority, at a tenth of its rate, nothing in its period but a timed fixed piece of
arithmetic: rig/runtime/empty_loop.py) was held more than a period: the host took a CPU from the run; "host_slowed"
the share in 50 ms stretches in which every CPU ran slowed (the empty loops' fixed compiled work took 1.25 times
its median or longer: the host slowed the CPUs without taking them); "host_noisy" the share of the empty loops'
wake-ups whose fixed work took 1.25 times its fastest or longer (the host taking the CPUs often for short
pieces; about 3 % on a quiet host). The closing warning says from the first two whether the late periods were the
host's or the drivers' chain's, and gives the third.
--json prints only {"transports", "faults", "overruns", "iterations", "samples_recorded", "isolation_reduction_db",
"feedforward_reduction_db", "transmissibility_db", "late_periods", "empty_loop_late", "host_slowed", "host_noisy",
"recording", "pre_steps", "end_steps"} on stdout (pre_steps: the emulated plant's steps before the loop's first
period, which stretch of the seeded floor the run met, its lockstep twin takes them first; end_steps: its steps
before the loop's last period, where the metered trace ends); progress goes to stderr. Exit 1 after a fault;
stopped early (Ctrl-C, SIGTERM) it says so, gives no isolation figure and exits 130 (SIGTERM: 143).
Fault rehearsal: --inject KIND:MOUNT:SIGNAL@T drives the emulated devices' knobs (rig/runtime/inject.py), e.g.
  rig hil --seconds 4 --inject silence:*:accel@2

  rig hil --layout prototype [--seconds N] ...  the prototype on its stand (drivers/devicemaps/prototype_hil.toml
                                                without --config) in three thirds: hold, track a 10 um 5 Hz
                                                sine, isolate; the tracking error (rms, % of the amplitude)
                                                and the load's true motion isolating against holding
                                                (isolation_reduction_db); --json adds "tracking"
"""
from __future__ import annotations

import argparse
import contextlib
import json
import logging
import math
import os
import sys
import threading
import time

import numpy as np

from rig import cliargs
from rig.runtime import inject
from rig.backends import default_config
from rig.commands.run import layout_config
from rig.config import hil_run_config, load_config
from rig.errors import EXIT_FAULT, EXIT_HARM, EXIT_STOPPED_BY, EXIT_SUSPECT, RecordingError, RigError
from rig.runtime.empty_loop import PROBE_PRIORITY, QUIET_NOISY, EmptyLoop, late_share, noisy_share, slowed_share
from rig.runtime.gate import ISOLATION_MODES
from rig.runtime.recorder import read_recording

log = logging.getLogger("rig.hil")
# without --config: the HIL rate, staleness limit and the isolation controller tuned for that rate
HIL_DEFAULT_CONFIG = default_config("hil")
JSON_KEYS = ("transports", "harm", "supervisor", "faults", "overruns", "iterations", "samples_recorded", "isolation_reduction_db",
             "feedforward_reduction_db", "lockstep_reduction_db", "transmissibility_db", "late_periods",
             "empty_loop_late", "host_slowed", "host_noisy", "recording", "pre_steps", "end_steps")
BESIDE_DIVIDER = 10         # the empty loops beside the run wake at a tenth of its rate: at its own, the two cost
#                             the run a fifth of a CPU and tripled its late periods on the 2-core machine
TRACE_MARGIN_S = 120.0      # the emulated plant's trace: the run and its set-up (the plant steps from its start)
CONFIG_HELP = "TOML configuration (default: the HIL design, drivers/devicemaps/hil.toml; not Table 1)"


def add_arguments(p) -> None:
    p.add_argument("--seconds", type=cliargs.seconds(le=3600), default=None, metavar="N",
                   help="the WHOLE run's length, split evenly into the modes: off, feedback (and feedback + "
                        "feedforward with floor accelerometers), so 15 gives 5 s each (default [hil] seconds)")
    p.add_argument("--rate", type=cliargs.rate_hz(le=5000), default=None, metavar="HZ",
                   help="loop rate (default [hil] rate_hz)")
    cliargs.output_arg(p, "--record", metavar="FILE", default=None,
                       help="HDF5 recording of the run (default hil-<date>-<time>.h5 in the current directory)")
    p.add_argument("--bench", action="store_true", help="driver round-trip benchmark only")
    p.add_argument("--no-realtime", action="store_true", help="do not try SCHED_FIFO/affinity/mlockall")
    p.add_argument("--json", action="store_true", help="print only the JSON result on stdout")
    p.add_argument("--force", action="store_true",
                   help="run isolation controllers that `rig design` calls unstable at the HIL rate")
    p.add_argument("--inject", metavar="KIND:MOUNT:SIGNAL@T", action="append", default=[],
                   help="fault rehearsal on the emulated devices at loop time T s, e.g. silence:*:accel@2 "
                        "(repeatable; see rig run --help)")
    p.add_argument("--layout", choices=("machine", "prototype"), default=None,
                   help="prototype: the actuator on its stand (hold, track a sine, isolate)")


def hil_config(cfg, rate_hz: float | None = None):
    """The config of a HIL run: [hil] rate, staleness limit and watchdog applied to the loop and the safety
    checks (rig.config.hil_run_config), with the rate checked."""
    rate = cfg.hil.rate_hz if rate_hz is None else rate_hz
    if not 0 < rate <= 5000:
        raise RigError(f"--rate: expected 0 < HZ <= 5000 for HIL, got {rate}")
    return hil_run_config(cfg, rate)


def _pct(xs: list[float]) -> dict:
    if not xs:
        return {"p50": math.nan, "p99": math.nan, "max": math.nan, "n": 0}
    a = np.asarray(xs)
    return {"p50": round(float(np.percentile(a, 50)), 1), "p99": round(float(np.percentile(a, 99)), 1),
            "max": round(float(a.max()), 1), "n": int(a.size)}


class _Progress(threading.Thread):
    """One progress line a second on stderr (the loop's time, state and isolation mode)."""

    def __init__(self, loop, quiet: bool) -> None:
        super().__init__(name="hil-progress", daemon=True)
        self.loop, self.quiet = loop, quiet
        self._halt = threading.Event()

    def run(self) -> None:
        lp = self.loop
        while not self._halt.wait(1.0):
            if not self.quiet and lp.t0_ns is not None and lp.t_ns:
                print(f"rig hil: t={(lp.t_ns - lp.t0_ns) * 1e-9:5.1f} s {lp.state.name} isolation mode "
                      f"{lp.isolation_mode} overruns {lp.overruns}", file=sys.stderr)

    def stop(self) -> None:
        self._halt.set()
        self.join(1.0)


def schedule_modes(loop, rig, seconds: float, settle_s: float, modes) -> dict:
    """The modes in turn, an equal share of the run each, switched at those loop times (the gate's schedule: the
    period boundary at or after them, as the lockstep run switches); each metered from settle_s into its share
    (the emulated plant's phase, per plant step) to its end, the last one to settle_s before the run's end
    (as hil_lockstep meters: no window at the band filter's edge). Returns the plant's steps taken before the
    loop's first period ("first") and before its last one ("last"), filled as the loop reaches them: the stretch
    of the trace the run itself drove (the plant steps from the moment it starts, and after the loop's last
    period the valves go to null)."""
    from rig.commands.hil_lockstep import windows
    share = seconds / len(modes)
    for k, (mode, (t0, t1)) in enumerate(zip(modes, windows(seconds, modes, settle_s))):
        if k:
            loop.gate.schedule(k * share, lambda m=mode: loop.request_isolation_mode(m))
        loop.gate.schedule(t0, lambda m=mode: rig.phase(m))
        loop.gate.schedule(t1 - 0.5 * loop.dt, lambda: rig.phase(None))
    steps = {}
    loop.gate.schedule(0.0, lambda: steps.setdefault("first", rig.steps))
    loop.gate.schedule(seconds - 1.5 * loop.dt, lambda: steps.setdefault("last", rig.steps))
    return steps


def run(args) -> int:
    cliargs.log_to_stderr("hil")
    logging.getLogger("canopen").setLevel(logging.WARNING)
    if args.layout == "prototype" or (args.config and load_config(args.config).layout.plant == "stand"):
        cfg = hil_config(layout_config(argparse.Namespace(config=args.config, layout="prototype"), "hil"), args.rate)
    else:
        cfg = hil_config(load_config(args.config if args.config else HIL_DEFAULT_CONFIG), args.rate)
    seconds = args.seconds if args.seconds is not None else cfg.hil.seconds
    if not 0 < seconds <= 3600:
        raise RigError(f"--seconds: expected 0 < N <= 3600, got {seconds}")
    injections = [inject.parse(x) for x in getattr(args, "inject", [])]
    for inj in injections:
        inject.check(inj, "hil", seconds)
    if args.bench:
        from rig.commands import hil_bench
        cliargs.check_periods(seconds if args.seconds is not None else hil_bench.SECONDS, cfg.loop.rate_hz)
        return hil_bench.run(cfg, seconds if args.seconds is not None else hil_bench.SECONDS, args.json)
    cliargs.check_rate(cfg, cfg.loop.rate_hz, "HIL", sections=("controller",))
    if not args.json:
        print(f"rig hil: config {cfg.source}", file=sys.stderr)
    if cfg.layout.plant == "stand":
        return _prototype(cfg, seconds, args)
    res = run_hil(cfg, seconds, record=args.record, realtime=cfg.loop.realtime and not args.no_realtime,
                  quiet=args.json, injections=injections, stability_check=not getattr(args, "force", False))
    out = {k: res[k] for k in JSON_KEYS if k in res}
    if res["stop_reason"] in ("SIGINT", "SIGTERM"):
        print(f"rig hil: interrupted ({res['stop_reason']}) at t = {res['t_s']:.1f} s of {seconds:g} s: the run "
              f"did not finish, no isolation figure; {out['samples_recorded']} samples recorded to "
              f"{out['recording']}", file=sys.stderr)
        if args.json:
            print(json.dumps(dict(out, isolation_reduction_db=None, feedforward_reduction_db=None)))
        return EXIT_STOPPED_BY[res["stop_reason"]]
    rt = res["round_trip_us"]
    print("rig hil: driver round trips (us): " + "; ".join(f"{k} p50 {v['p50']} p99 {v['p99']} max {v['max']}"
                                                           for k, v in rt.items()), file=sys.stderr)
    print(f"rig hil: accelerometer conversions interpolated (left the module's FIFO unfetched): "
          f"{res['lost_conversions']}; SYNCs sent with the period before's commands (the loop late): "
          f"{res['late_commands']}", file=sys.stderr)
    if res["lost_conversions"]:
        print("rig hil: warning: with conversions lost, isolation was suspended and the floor feedforward held off "
              "from then on (the events above): the figures after it are not the design's", file=sys.stderr)
    if args.json:
        print(json.dumps(out))
    else:
        print(f"transports {', '.join(out['transports'])}: {out['iterations']} periods at "
              f"{cfg.loop.rate_hz:g} Hz, {out['faults']} faults, {out['overruns']} overruns, "
              f"{out['samples_recorded']} samples recorded to {out['recording']}")
        _print_modes(res, out)
    return _exit_code(res)


def _print_modes(res: dict, out: dict) -> None:
    """The modes side by side: the table's rms through the drivers with each reduction, the same design in
    lockstep (gap: drivers minus lockstep), the transmissibility and the late periods."""
    from rig.commands.hil_lockstep import BAND_HZ
    from rig.compare import LABELS, mode_row
    modes = [m for m in LABELS if m in res["table_rms_m"]]
    red = {"feedback": out.get("isolation_reduction_db"), "feedback_feedforward": out.get("feedforward_reduction_db")}
    ls = res.get("lockstep_reduction_db", {})

    def db(x, fmt=".1f"):
        return "n/a" if x is None else f"{x:{fmt}} dB"
    print(mode_row("", [LABELS[m] for m in modes]))
    print(mode_row(f"table Y rms ({BAND_HZ[0]:g}-{BAND_HZ[1]:g} Hz)", [
        "n/a" if math.isnan(res['table_rms_m'][m]) else
        f"{res['table_rms_m'][m] * 1e6:.3f} um" + ("" if m == "off" else f" ({db(red.get(m))})") for m in modes]))
    print(mode_row("in lockstep (gap)", ["" if m == "off" else db(ls.get(m)) + (
        "" if red.get(m) is None or ls.get(m) is None else f" ({red[m] - ls[m]:+.1f})") for m in modes]))
    print(mode_row("table/floor", [db(out["transmissibility_db"].get(m), ".2f") for m in modes]))
    for label, late in (("late periods", out["late_periods"]),
                        ("an empty loop beside, late", out.get("empty_loop_late")),
                        ("the CPUs slowed beside", out.get("host_slowed")),
                        ("wake-ups slowed beside", out.get("host_noisy"))):
        if late:
            print(mode_row(label, ["n/a" if late.get(m) is None else f"{100 * late[m]:.1f} %" for m in modes]))


LATE_WARN = 0.01        # issue 24: at most 1 % of a mode's periods late; beyond, the run says its figures suffer


def _exit_code(res) -> int:
    """EXIT_FAULT after a fault; EXIT_HARM when the do-no-harm supervisor switched isolation off or a mode made
    the table worse than isolation off (below the supervisor's margin); EXIT_SUSPECT when the host let more than
    LATE_WARN of a mode's periods come late. Each is said in one line."""
    worse = {m: -res[k] for k, m in (("isolation_reduction_db", "feedback"),
                                     ("feedforward_reduction_db", "feedback_feedforward"))
             if res.get(k) is not None and res[k] < 0}
    for mode, d in worse.items():
        print(f"rig hil: warning: {mode.replace('_', ' + ')} made the table {d:.1f} dB worse than isolation off",
              file=sys.stderr)
    late = {m: v for m, v in (res.get("late_periods") or {}).items() if v is not None and v > LATE_WARN}
    if late:
        host = {m: v + ((res.get("host_slowed") or {}).get(m) or 0.0)
                for m, v in (res.get("empty_loop_late") or {}).items() if m in late and v is not None}
        noisy = {m: v for m, v in (res.get("host_noisy") or {}).items() if m in late and v is not None}
        _say_late(late, host, res.get("load"), noisy)
    short = res.get("unmetered") or []
    if short:
        _say_unmetered(short, res["seconds_to_meter"])
    if res["faults"]:
        return EXIT_FAULT
    if res.get("harm"):
        print(f"rig hil: {res['harm']}", file=sys.stderr)
        return EXIT_HARM
    return EXIT_HARM if worse else EXIT_SUSPECT if late or short else 0


def _say_late(late: dict, beside: dict, load: float | None = None, noisy: dict | None = None) -> None:
    """The one warning line for modes with more than LATE_WARN of their periods late, and whose they were: the
    host's when the empty loops beside the run were held or their CPUs ran slowed (`beside`: the two shares added)
    at least half as often in each such mode (or were not measured), else the drivers' chain's (held by the
    machine's other load or by its own work). Either way it gives the share of the empty loops' wake-ups whose
    work ran slowed (`noisy`), which a reader can hold against a quiet host's; it decides nothing (no bound
    separated the runs: drivers/README.md, a noisy host)."""
    def shares(d):
        return ", ".join(f"{m.replace('_', ' + ')} {100 * v:.1f} %" for m, v in d.items())
    work = (f"; the empty loops' fixed work slowed in {shares(noisy)} of their wake-ups (a quiet host: about "
            f"{100 * QUIET_NOISY:g} %)") if noisy else ""
    if beside and any(2 * beside.get(m, 1.0) < v for m, v in late.items()):
        held = f"; load average {load:.1f}" if load is not None else ""
        print(f"rig hil: warning: the drivers' chain fell behind ({shares(late)} of the periods late, more than "
              f"{100 * LATE_WARN:g} %) while the empty loops beside the run kept better time and speed "
              f"({shares(beside)}{work}): the SYNC, the plant, the module and the loop were held by the machine's "
              f"other load or their own work{held}; isolation through the drivers falls with that (drivers/README.md, "
              "the rates)", file=sys.stderr)
        return
    host = (f"; the empty loops beside the run held or slowed: {shares(beside)}" if beside else "") + work
    print(f"rig hil: warning: the host did not keep time ({shares(late)} of the periods late, more than "
          f"{100 * LATE_WARN:g} %{host}): isolation through the drivers falls with that, so these figures are below "
          "what this rig does on a host that keeps time (docs/OPERATING.md, real-time set-up)", file=sys.stderr)


def _say_unmetered(modes, seconds_needed: float) -> None:
    """The one warning line for modes metered too briefly to give an isolation figure."""
    from rig.commands.hil_lockstep import BAND_HZ, MIN_WINDOW_S
    print(f"rig hil: warning: {', '.join(m.replace('_', ' + ') for m in modes)}: metered for less than "
          f"{MIN_WINDOW_S:g} s after [hil] settle_s (the {BAND_HZ[0]:g}-{BAND_HZ[1]:g} Hz band needs it): no "
          f"isolation figure; give --seconds {seconds_needed:g} or more", file=sys.stderr)


def run_hil(cfg, seconds: float, *, record: str | None = None, realtime: bool = True, quiet: bool = False,
            port_options: dict | None = None, injections=(), stability_check: bool = True,
            compare: bool = True) -> dict:
    """One HIL run with the runtime's loop; `cfg` as from hil_config. Returns the figures (and more); compare:
    also the same run in lockstep simulated time (rig/commands/hil_lockstep.py)."""
    from rig.commands.hil_lockstep import lockstep, phase_rms, reductions, seconds_to_meter, unmetered
    from rig.runtime.session import Session
    rate = cfg.loop.rate_hz
    if record is None:
        record = time.strftime("hil-%Y%m%d-%H%M%S.h5")
    if not quiet:
        print(f"rig hil: starting the emulated rig (CANopen valves, Modbus TCP module, serial amplifier) and the "
              f"drivers' I/O processes at {rate:g} Hz", file=sys.stderr)
    modes = ISOLATION_MODES if cfg.sensors.floor_accel else ISOLATION_MODES[:2]
    settle = cfg.hil.settle_s          # of each mode's share, not metered (hil_lockstep.windows: a third at most)
    activate = min(0.05, seconds / 10)
    opts = {"trace_s": seconds + TRACE_MARGIN_S, **(port_options or {})}
    session = Session(cfg, "hil", rate_hz=rate, port_options=opts, isolation=False,
                      keep_timing=int(seconds * rate) + 16, record=record,
                      record_attrs={"command": "rig hil", "transports": "canopen,modbus_tcp,serial",
                                    "modes": ",".join(modes)},
                      realtime=realtime, signals=True, stability_check=stability_check)
    progress = beside = None
    reason = None
    with session:
        port, loop = session.port, session.loop
        rig = port.rig
        try:
            time.sleep(0.2)          # the I/O processes refresh their samples after the set-up pause
            steps = schedule_modes(loop, rig, seconds, settle, modes)
            progress = _Progress(loop, quiet)
            progress.start()
            before = rig.steps
            with contextlib.ExitStack() as stack:
                beside = [stack.enter_context(EmptyLoop(rate / BESIDE_DIVIDER, seconds + 1.0,
                                                        PROBE_PRIORITY if realtime else 0, cpu, speed=True))
                          for cpu in range(os.cpu_count() or 1)]
                stack.enter_context(inject.Armed(session, injections))
                reason = session.run(seconds=seconds, activate_after_s=activate)
            pre_steps = steps.get("first", before)          # the trace the loop drove (schedule_modes)
            end_steps = steps.get("last", rig.steps)
        finally:
            if progress is not None:
                progress.stop()
            rig.phase(None)
            rtt = {k: _pct(v) for k, v in port.round_trips_us().items()}
            counts = port.counts()
    rec = session.recorder
    late = late_periods(record, modes, seconds, settle, rate)
    host_late, host_slowed, host_noisy = (empty_loop_late(beside, loop.t0_ns, loop.period_ns, modes, seconds, settle,
                                                          share) for share in (late_share, slowed_share, noisy_share))
    table, floor, codes = rig.trace()
    short = unmetered(seconds, modes, settle)          # too short a window: no figure (said by _exit_code)
    band_rms = phase_rms(table, codes, rate, {m: rig.phase_code(m) for m in modes if m in rig.meter}, end=end_steps)
    band_rms = {m: math.nan if m in short else v for m, v in band_rms.items()}
    total = {m: rig.table_rms_m(m) if m in rig.meter and m not in short else math.nan for m in modes}
    tr = {m: 20 * math.log10(total[m] / rig.floor_rms_m(m)) if m in rig.meter and total[m] > 0 else math.nan
          for m in modes}
    red = reductions(band_rms)
    out = {"transports": ["canopen", "modbus_tcp", "serial"],
           "faults": 1 if loop.lc.fault_reason else 0, "overruns": loop.overruns, "iterations": loop.iterations,
           "samples_recorded": rec.rows_written if rec is not None else 0,
           "isolation_reduction_db": red["feedback"], "feedforward_reduction_db": red[ISOLATION_MODES[2]],
           "transmissibility_db": {m: None if math.isnan(v) else round(v, 2) for m, v in tr.items()},
           "late_periods": late, "empty_loop_late": host_late, "host_slowed": host_slowed, "host_noisy": host_noisy,
           "load": round(os.getloadavg()[0], 2),
           "recording": str(record), "fault_reason": loop.lc.fault_reason, "table_rms_m": band_rms,
           "round_trip_us": rtt, "skipped": loop.skipped, "timing_us": loop.timing_us(),
           "lost_conversions": counts["accelerometer module"][1], "late_commands": counts["valves"][1],
           "stop_reason": reason, "pre_steps": pre_steps, "end_steps": end_steps, "harm": loop.harm,
           "supervisor": loop.supervisor.summary() if loop.supervisor is not None else None,
           "t_s": (loop.t_ns - loop.t0_ns) * 1e-9 if loop.t0_ns is not None else 0.0,
           "unmetered": short, "seconds_to_meter": seconds_to_meter(modes, settle)}
    if compare and reason not in ("SIGINT", "SIGTERM") and not out["faults"] and "off" not in short:
        if not quiet:
            print("rig hil: the same design and floor in lockstep simulated time", file=sys.stderr)
        ls = lockstep(cfg, seconds, modes, settle, activate, pre_steps)
        out["lockstep_table_rms_m"] = {m: math.nan if m in short else v for m, v in ls["table_rms_m"].items()}
        out["lockstep_reduction_db"] = reductions(out["lockstep_table_rms_m"])
    return out


def empty_loop_late(beside, t0_ns: int | None, period_ns: int, modes, seconds: float, settle_s: float,
                    share=late_share) -> dict:
    """Per mode, over the same metered window as late_periods: the share of its periods in a stretch where an
    empty loop beside the run (one per CPU above the loop's priority: rig/runtime/empty_loop.py) was held more than a
    period, i.e. the host took a CPU from the run; with share=slowed_share, where every CPU ran slowed; with
    noisy_share, the share of their wake-ups whose fixed work ran slowed. {} without empty loops."""
    from rig.commands.hil_lockstep import windows
    if t0_ns is None or not beside:
        return {}
    out = {}
    for mode, (t0, t1) in zip(modes, windows(seconds, modes, settle_s)):
        v = share(beside, t0_ns + int(t0 * 1e9), t0_ns + int(t1 * 1e9), period_ns)
        out[mode] = None if v is None else round(v, 4)
    return out


def late_periods(record, modes, seconds: float, settle_s: float, rate_hz: float) -> dict:
    """Per mode (its window of the run's seconds, hil_lockstep.windows, as schedule_modes meters): the share of its
    periods that were late, from the recording: the loop woke more than a period after the deadline, or the
    accelerometers read as in the period before (the module's new conversion had not arrived: the controllers
    held). {} when the recording cannot be read."""
    try:
        rec = read_recording(record)
        t, wake, acc = rec["time_s"], rec["wake_latency_us"], rec["accel_mps2"]
    except (RecordingError, KeyError):
        return {}
    held = np.r_[False, np.all(acc[1:] == acc[:-1], axis=1)]
    late = (wake > 1e6 / rate_hz) | held
    out = {}
    from rig.commands.hil_lockstep import windows
    for mode, (t0, t1) in zip(modes, windows(seconds, modes, settle_s)):
        m = (t >= t0) & (t < t1)
        out[mode] = round(float(late[m].mean()), 4) if m.any() else None
    return out


PROTOTYPE_SINE = "sine:amp=10um,freq=5"


def run_hil_prototype(cfg, seconds: float, *, record: str | None = None, realtime: bool = True,
                      quiet: bool = False) -> dict:
    """The prototype through the drivers on the emulated stand: hold, track PROTOTYPE_SINE, isolate (a third
    each, [hil] settle_s of each not metered). Returns the figures (tracking per segment, true load motion)."""
    from rig import operated
    from rig.runtime.session import Session
    if record is None:
        record = time.strftime("hil-prototype-%Y%m%d-%H%M%S.h5")
    q = seconds / 3
    settle = min(cfg.hil.settle_s, q / 3)
    holder = {}

    def phase(name):
        return lambda: holder["rig"].phase(name)
    script = [(settle, phase("hold")), (q, phase(None)), (q, f"track {PROTOTYPE_SINE}"), (2 * q, "isolate"),
              (2 * q + settle, phase("isolate"))]
    session = Session(cfg, "hil", isolation=False, keep_timing=int(seconds * cfg.loop.rate_hz) + 16, record=record,
                      record_attrs={"command": "rig hil --layout prototype", "transports": "canopen,modbus_tcp,serial"},
                      realtime=realtime, signals=True, script=[(t, w) for t, w in script if isinstance(w, str)])
    if not quiet:
        print(f"rig hil: the prototype on its emulated stand at {cfg.loop.rate_hz:g} Hz: hold, track {PROTOTYPE_SINE}"
              f", isolate ({q:.1f} s each)", file=sys.stderr)
    with session:
        port, loop = session.port, session.loop
        holder["rig"] = port.rig
        for t, action in script:
            if not isinstance(action, str):
                loop.gate.schedule(t, action)
        time.sleep(0.2)              # driver threads refresh their samples after the set-up pause
        session.run(seconds=seconds, activate_after_s=min(0.05, seconds / 10))
        port.rig.phase(None)
        rtt = {k: _pct(v) for k, v in port.round_trips_us().items()}
    rig = port.rig
    from rig.commands.hil_lockstep import MIN_WINDOW_S
    short = q - settle < MIN_WINDOW_S - 1e-9        # hold and isolate each metered from settle to the third's end
    hold, iso = (rig.table_rms_m(k) if k in rig.meter and not short else math.nan for k in ("hold", "isolate"))
    red = 20 * math.log10(hold / iso) if hold > 0 and iso > 0 else math.nan
    figs = operated.figures(operated.load_operated(record))
    track = next((d for d in figs if d["mode"] == "track"), {})
    return {"transports": ["canopen", "modbus_tcp", "serial"], "faults": 1 if loop.lc.fault_reason else 0,
            "overruns": loop.overruns, "iterations": loop.iterations,
            "samples_recorded": session.recorder.rows_written if session.recorder is not None else 0,
            "tracking": {k: track.get(k) for k in ("request", "rms_error_um", "rms_error_pct", "max_error_um",
                                                   "peak_command_V")},
            "isolation_reduction_db": None if math.isnan(red) else round(red, 2), "load_rms_hold_um": hold * 1e6,
            "load_rms_isolate_um": iso * 1e6, "recording": str(record), "fault_reason": loop.lc.fault_reason,
            "round_trip_us": rtt, "segments": figs, "harm": loop.harm,
            "unmetered": ["hold", "isolate"] if short else [],
            "seconds_to_meter": 3 * (MIN_WINDOW_S + min(cfg.hil.settle_s, MIN_WINDOW_S / 2))}


def _prototype(cfg, seconds: float, args) -> int:
    res = run_hil_prototype(cfg, seconds, record=args.record, realtime=cfg.loop.realtime and not args.no_realtime,
                            quiet=args.json)
    if res["fault_reason"]:
        print(f"rig hil: FAULT: {res['fault_reason']}", file=sys.stderr)
    out = {k: res[k] for k in ("transports", "harm", "faults", "overruns", "iterations", "samples_recorded",
                               "tracking", "isolation_reduction_db", "recording")}
    red = res["isolation_reduction_db"]
    worse = red is not None and red < 0
    code = EXIT_FAULT if res["faults"] else EXIT_HARM if res["harm"] or worse else EXIT_SUSPECT if res["unmetered"] else 0
    if res["unmetered"]:
        _say_unmetered(res["unmetered"], res["seconds_to_meter"])
    if res["harm"]:
        print(f"rig hil: {res['harm']}", file=sys.stderr)
    elif worse:
        print(f"rig hil: warning: isolating made the load {-red:.1f} dB worse than holding", file=sys.stderr)
    if args.json:
        print(json.dumps(out))
        return code
    from rig import operated
    print(operated.figures_text(res["segments"]))
    tr = res["tracking"]
    print(f"transports {', '.join(out['transports'])}: {out['iterations']} periods at {cfg.loop.rate_hz:g} Hz, "
          f"{out['faults']} faults, {out['overruns']} overruns, recorded to {out['recording']}")
    if tr.get("rms_error_um") is not None:
        print(f"tracking {tr['request']}: rms error {tr['rms_error_um']:.3f} um = {tr['rms_error_pct']:.2f} % of the "
              f"amplitude (max {tr['max_error_um']:.3f} um)")
    if res["unmetered"]:
        print("isolation: n/a (not metered: the run is too short)")
    else:
        print(f"isolation: load motion rms {res['load_rms_hold_um']:.3f} um holding -> {res['load_rms_isolate_um']:.3f} "
              f"um isolating ({'n/a' if red is None else f'{red:.1f} dB'})")
    return code
