"""`rig run`: operate the rig on demand (sim, hil or hardware backend).

Start-up: configure (open the port) -> INACTIVE for --settle seconds (reading and checking, valve at null,
controllers stepped so their filters warm up) -> ACTIVE. On the hil and hardware backends the floor is already
moving when the loop starts, and the isolation controllers' double integration of acceleration needs a few
time constants of its blend to forget its cold start (2 / blend_hz); activating earlier with isolation on
can put the valves at the clamp. So --settle
defaults to that warm-up there, and to 0.05 s on the sim backend (the simulated plant starts at rest with
the loop). Stop: --seconds elapsed, Ctrl-C (SIGINT) or SIGTERM -> safe stop (valve to null), recording closed.

Switching isolation while running (bumpless; stroke centring stays on):
  kill -USR1 <pid>                 toggles isolation on/off
  --control FILE                   the file is polled every 0.1 s; write one word into it:
                                   `on` / `off` (isolation), `stop` (safe stop)
Only changes of the control file after the start count; its folder must exist.
  `feedback` / `feedback_feedforward`  the isolation mode (with floor accelerometers, [sensors] floor_accel)
The status line on stderr shows state, isolation (SUSPENDED and the mounts while the saturation recovery
holds it off), loop timing, overruns, strokes and commands. With --record the machine's run ends with the
recording's vibration-criterion classes per isolation mode (rig report REC: the curves).

Without --config the sim and hardware backends run the Table 1 defaults and the hil backend its own design
(drivers/devicemaps/hil.toml: the HIL rate and the controller tuned for it). At start-up `rig run` refuses
isolation controllers that `rig design` calls unstable on the configured plant (--force runs them), and a
rate the loop cannot hold on this machine (measured over the first periods). While running, the loop faults
when it falls lag_limit_s behind real time, misses more than missed_limit of its deadlines over
missed_window_s, when a valve command limit-cycles ([safety] oscillation_*), or when the recording's writer
dies.
Fault rehearsal: --inject KIND:MOUNT:SIGNAL@T (repeatable; rig/runtime/inject.py lists the knobs), e.g.
  rig run --seconds 3 --inject nan:front_left:accel@1.5
One process per rig: a second one driving the same devices is refused, naming the first (rig/runtime/lock.py).

The prototype (`--layout prototype`: drivers/devicemaps/prototype.toml, or prototype_hil.toml on the hil
backend; any config with [layout] plant = "stand"): the actuator alone on its stand, operated in modes
(controllers/modes.py), switchable while live and bumpless:
  --mode off|hold|track|isolate    the mode at activation (default hold: the piston held where it is)
  --position POS                   hold there, with its unit (e.g. 5um; a bare 5 would be metres: refused)
  --reference REF                  track it: setpoint:x=5um, step:amp=2um, sine:amp=10um,freq=5,
                                   chirp:amp=1um,f0=1,f1=100,duration=20, csv:profile.csv (time_s,position_m)
  --control FILE                   write `hold 5um`, `track sine:amp=10um,freq=5`, `isolate`, `off`, `stop`
  --script FILE                    timed control words, one per line: `<loop time s> <word>` (< --seconds)
  kill -USR1 / -USR2 <pid>         isolate <-> hold / off <-> hold
A reference the actuator cannot follow (outside the stroke limit or the static range of about +-24 um that
leakage leaves at 90 % of the valve clamp, faster than the rate limit, more volts than the clamp allows) is
refused with one line, never clamped. After a run with --seconds or --record: the tracking figures per segment;
--plot PNG draws reference, position and error.
Do no harm: while isolation is on the loop compares the table's vibration with isolation off (or the floor's);
isolation that makes it worse by more than [supervisor] margin_db is said in one line, recorded as an event and
switched off, bumpless, for the rest of the run (rig/runtime/supervisor.py).
No uncommissioned hardware: --backend hardware needs [drivers] calibration, a commissioning.toml newer than the
configuration (`rig commission`; --uncommissioned runs without it).
Exit code: 0 after a normal stop, 1 after a fault (the reason is printed), 2 for a user error, 3 when the
do-no-harm supervisor switched isolation off, 130 after Ctrl-C during the start-up or the closing figures
(SIGTERM: 143).
"""
from __future__ import annotations

import dataclasses
import importlib.util
import logging
import os
import sys
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING

from rig import cliargs
from rig.runtime import inject
from rig.backends import BACKENDS, default_config
from rig.runtime.clock import MonotonicClock, SimClock
from rig.config import hil_run_config, load_config
from rig.errors import EXIT_HARM, RecordingError, RigError
from rig.textfile import read_text

if TYPE_CHECKING:
    from rig.runtime.session import Session

TRACK_TEMP_S = 600.0        # the longest timed stand run kept in a temporary recording for its figures
# the package's folder, found without importing it (its drivers load numba: `rig run --help` stays quick)
DEVICEMAPS = Path(importlib.util.find_spec("drivers").submodule_search_locations[0]) / "devicemaps"
LAYOUTS = {"prototype": {"hil": DEVICEMAPS / "prototype_hil.toml", None: DEVICEMAPS / "prototype.toml"}}

log = logging.getLogger("rig.run")
CONFIG_HELP = ("TOML configuration (default: the paper's Table 1 values; with --backend hil the HIL design, "
               "drivers/devicemaps/hil.toml)")


def warmup_s(ctrls) -> float:
    """Time for the controllers' estimators to forget a cold start: 2 / blend_hz (about five time constants of
    the blend's slowest pole), 0.05 s for controllers without a blend."""
    blends = [c.p.blend_hz for c in ctrls if getattr(getattr(c, "p", None), "blend_hz", 0) > 0]
    return min(2.0 / min(blends), 60.0) if blends else 0.05


def add_arguments(p) -> None:
    p.add_argument("--backend", choices=tuple(BACKENDS), default=None,
                   help="backend (default: [backend] name in the config, else sim)")
    p.add_argument("--seconds", type=cliargs.seconds(), default=None, metavar="N",
                   help="the whole run's length: N seconds of loop time, --settle included (default: until Ctrl-C / "
                        "SIGTERM / `stop`)")
    p.add_argument("--isolation", choices=("on", "off"), default="on",
                   help="isolation at start (toggle while running: SIGUSR1 or --control FILE)")
    p.add_argument("--feedforward", action="store_true",
                   help="floor feedforward on from the start (needs [sensors] floor_accel = true; switch it while "
                        "running with the control file's feedback / feedback_feedforward)")
    cliargs.output_arg(p, "--record", metavar="FILE", default=None, help="record the run to this HDF5 file")
    p.add_argument("--control", metavar="FILE", default=None,
                   help="control file polled every 0.1 s: write `on`, `off` or `stop` into it")
    p.add_argument("--settle", type=cliargs.seconds(ge=0, le=3600), default=None, metavar="S",
                   help="seconds INACTIVE (reading, checking, valve null, filters warming) before activation "
                        "(default: sim 0.05, hil/hardware the controllers' warm-up, 2 / blend_hz)")
    p.add_argument("--policy", choices=("skip", "catch_up"), default=None,
                   help="overrun policy (default [loop] overrun_policy)")
    p.add_argument("--no-realtime", action="store_true", help="do not try SCHED_FIFO/affinity/mlockall")
    p.add_argument("--sim-time", action="store_true",
                   help="sim backend only: run in simulated time (as fast as possible, lockstep)")
    p.add_argument("--quiet", action="store_true",
                   help="only warnings, errors and the result (on stdout): no live status line, no start, "
                        "lifecycle or stop lines (the console's address still prints, and its page logs them all)")
    p.add_argument("--force", action="store_true",
                   help="run isolation controllers that `rig design` calls unstable (the oscillation rule still "
                        "faults a limit cycle)")
    p.add_argument("--uncommissioned", action="store_true",
                   help="hardware backend: run without a calibration from `rig commission` newer than the "
                        "configuration ([drivers] calibration)")
    p.add_argument("--inject", metavar="KIND:MOUNT:SIGNAL@T", action="append", default=[],
                   help="fault rehearsal: drive a fault knob at loop time T s, e.g. nan:front_left:accel@2 "
                        "(repeatable; kinds: sim nan, range, stuck, stale, drop, device; hil silence, exception, "
                        "garbage, stale, fragment, range, nan, fault, hold; both overrun, stall, recorder)")
    p.add_argument("--console", action="store_true",
                   help="serve the operator console (a live web page) on 127.0.0.1; its address, with a random "
                        "access token, is printed at start")
    p.add_argument("--port", type=cliargs.Number(ge=0, le=65535, integer=True), default=None, metavar="N",
                   help="console port (default: the first free one from 8765; 0: any free port)")
    p.add_argument("--read-only", action="store_true", help="console shows everything and accepts no command")
    p.add_argument("--layout", choices=("machine", "prototype"), default=None,
                   help="machine: the config's (default); prototype: the actuator on its stand "
                        "(drivers/devicemaps/prototype.toml, prototype_hil.toml on hil) unless --config names one")
    p.add_argument("--mode", choices=("off", "hold", "track", "isolate"), default=None,
                   help="stand layout: the mode at activation (default hold)")
    p.add_argument("--position", type=cliargs.length, default=None, metavar="POS",
                   help="hold mode: the position with its unit, e.g. 5um or 0.005mm (a bare number is refused)")
    p.add_argument("--reference", default=None, metavar="REF",
                   help="track mode: setpoint:x=POS, step:amp=DX, sine:amp=A,freq=F[,offset=POS][,seconds=S], "
                        "chirp:amp=A,f0=F0,f1=F1,duration=T, csv:FILE")
    p.add_argument("--script", metavar="FILE", default=None,
                   help="timed control words, one per line: `<loop time s> <word>` (# comments)")
    cliargs.output_arg(p, "--plot", metavar="FILE", default=None, suffix=".png",
                       help="after the run, a PNG: the stand layout's reference, position and tracking error; the "
                            "machine's VC curves per isolation mode (as rig report --plot)")


def layout_config(args, backend: str | None = None):
    """The config of --config / --layout: --layout prototype without --config is the bundled prototype file
    (the HIL one on the hil backend), no --config at all the backend's default (rig.backends.default_config);
    with --config and --layout the file must describe that layout."""
    layout = getattr(args, "layout", None)
    if layout == "prototype" and not args.config:
        files = LAYOUTS["prototype"]
        return load_config(files.get(backend, files[None]))
    cfg = load_config(args.config)
    if args.config is None and default_config(backend or cfg.backend.name) is not None:
        cfg = load_config(default_config(backend or cfg.backend.name))   # hil: its own design, not Table 1's
    if layout is not None and (cfg.layout.plant == "stand") != (layout == "prototype"):
        raise RigError(f"--layout {layout}: {cfg.source} has [layout] plant = {cfg.layout.plant!r}")
    return cfg


def start_request(args) -> str | None:
    """The start mode's text from --mode / --position / --reference (None: the layout's default)."""
    mode, pos, ref = args.mode, args.position, args.reference
    if pos is not None and ref is not None:
        raise RigError("--position and --reference: give one (hold a position, or track a reference)")
    if mode is None:
        mode = "track" if ref is not None else ("hold" if pos is not None else None)
    if mode is None:
        return None
    if mode == "track" and ref is None:
        raise RigError("--mode track: needs --reference (e.g. sine:amp=10um,freq=5)")
    if mode != "track" and ref is not None:
        raise RigError(f"--reference: only with --mode track (got --mode {mode})")
    if pos is not None and mode != "hold":
        raise RigError(f"--position: only with --mode hold (got --mode {mode})")
    return {"track": f"track {ref}", "hold": f"hold {pos}" if pos is not None else "hold"}.get(mode, mode)


def check_start_stroke(args, cfg) -> None:
    """A --position or --reference beyond the stroke limit, refused before the controllers are built (their
    libraries take seconds to load); the rule is the tracking controller's own (controllers/reference.py)."""
    text = args.reference if args.reference is not None else (
        f"hold:{args.position}" if args.position is not None else None)
    if text is None:
        return
    from controllers.reference import check_stroke, parse_reference
    where = f"--reference {args.reference}" if args.reference is not None else f"--position {args.position}"
    ref = parse_reference(text, 1.0 / cfg.loop.rate_hz, max_s=cfg.controller.track_profile_s, where=where)
    check_stroke(ref, cfg.safety.stroke_limit_m, name=where)


def read_script(path, seconds: float | None = None) -> list[tuple[float, str]]:
    """`<loop time s> <control word>` per line; RigError naming the file and line (a time at or after the run's
    `seconds` too: its word would never act)."""
    p = Path(path)
    lines = read_text(p, "--script file").splitlines()
    out = []
    for i, ln in enumerate(lines, 1):
        ln = ln.split("#", 1)[0].strip()
        if not ln:
            continue
        t, _, word = ln.partition(" ")
        try:
            at = float(t)
        except ValueError:
            raise RigError(f"--script {p}: line {i}: expected `<loop time s> <word>`, got {ln[:60]!r}") from None
        if not 0 <= at < float("inf") or not word.strip():      # nan and inf too: a word that never comes
            raise RigError(f"--script {p}: line {i}: expected a time >= 0 and a control word, got {ln[:60]!r}")
        cliargs.check_within_run(at, seconds, f"--script {p}: line {i}")
        out.append((at, word.strip()))
    return out


def run(args) -> int:
    """`rig run`: plan from the options, run (alone or under the console), report; the exit code."""
    _log_to_stderr(quiet=args.quiet)
    plan = _RunPlan(args)
    if args.console:
        from rig.console.runner import run_with_console
        loop, reason = run_with_console(args, plan.cfg, plan.backend, plan.new_session, plan.started)
    else:
        loop, reason = plan.run_alone()
    return plan.finish(loop, reason)


def _log_to_stderr(quiet: bool = False) -> None:
    """Our own INFO lines (lifecycle, start/stop) on stderr, libraries' (canopen, pymodbus) from WARNING;
    quiet: warnings and errors only. The rig's loggers stay at INFO either way (the console's page logs every
    line): --quiet silences the terminal only."""
    if not logging.getLogger().handlers:
        cliargs.log_to_stderr("run")
        logging.getLogger("rig").setLevel(logging.INFO)
    if quiet:
        for h in logging.getLogger().handlers:
            if getattr(h, "stream", None) is sys.stderr:
                h.setLevel(logging.WARNING)


def check_commissioned(cfg) -> None:
    """No uncommissioned hardware: [drivers] calibration names a file `rig commission` wrote after the
    configuration (its device maps) last changed; else one line (--uncommissioned runs anyway)."""
    import drivers                  # the hardware backend's own package: loaded when a hardware run is checked
    cal = drivers.calibration_path(cfg) if cfg.drivers.calibration else None
    src = Path(cfg.source)
    why = ("no calibration ([drivers] calibration is not set)" if cal is None else
           f"its calibration {cal} does not exist" if not cal.is_file() else
           f"its calibration {cal} is older than {src}" if src.is_file() and cal.stat().st_mtime < src.stat().st_mtime
           else None)
    if why:
        raise RigError(f"{cfg.source}: the rig is not commissioned: {why}; run `rig commission --backend hardware "
                       f"--out DIR` and set [drivers] calibration, or give --uncommissioned")


def _run_config(args, cfg, backend: str, injections):
    """The options checked against each other and the backend (one line naming the option otherwise); the
    config the run uses (hil: its own rate, staleness limit and watchdog)."""
    if args.seconds is not None and args.seconds <= 0:
        raise RigError(f"--seconds: expected > 0, got {args.seconds}")
    if args.settle is not None and not 0 <= args.settle <= 3600:
        raise RigError(f"--settle: expected 0 <= S <= 3600, got {args.settle}")
    if args.sim_time and backend != "sim":
        raise RigError("--sim-time: only with --backend sim")
    if args.settle is not None:
        cliargs.check_settle(args.settle, args.seconds)
    if backend == "hil":
        # HIL runs at the [hil] rate with its staleness limit and watchdog (Modbus and the shared machine)
        cfg = hil_run_config(cfg)
        cliargs.check_rate(cfg, cfg.loop.rate_hz, "[hil] rate_hz", sections=("controller",))
    if backend == "hardware" and not args.uncommissioned:
        check_commissioned(cfg)
    if (args.port is not None or args.read_only) and not args.console:
        raise RigError("--port/--read-only: only with --console")
    if injections and args.console:
        raise RigError("--inject: not with --console (rehearse faults on a run without it)")
    return cfg


class _RunPlan:
    """What `rig run`'s options ask for, checked before anything starts: config, backend, clock, the start
    mode on stands, the recording (a temporary one when only --plot wants it) and its attributes, the script
    and the injections. Builds the sessions, logs their start and reports after the run."""

    def __init__(self, args) -> None:
        self.args = args
        cfg = layout_config(args, args.backend)
        self.backend = backend = args.backend or cfg.backend.name
        self.injections = [inject.parse(x) for x in args.inject]
        for inj in self.injections:
            inject.check(inj, backend, args.seconds)
        self.cfg = cfg = _run_config(args, cfg, backend, self.injections)
        self.clock = SimClock() if args.sim_time else MonotonicClock()
        self.stand = stand = cfg.layout.plant == "stand"
        self.start = start = start_request(args)
        if start is not None and not stand:
            raise RigError("--mode/--position/--reference: operating modes are for the stand layout "
                           "(--layout prototype)")
        if stand:
            check_start_stroke(args, cfg)
        self.record, self.tmp = args.record, None
        # the stand's tracking figures need the run's samples: a timed run keeps them in a temporary recording
        # (up to TRACK_TEMP_S: a longer run without --record says where its figures are)
        timed = stand and args.seconds is not None
        if self.record is None and timed and args.seconds > TRACK_TEMP_S and not args.plot:
            log.info("no tracking figures after this run: over %g s they need --record FILE (a temporary recording "
                     "of it would grow large)", TRACK_TEMP_S)
        elif self.record is None and (args.plot or timed):
            fd, self.tmp = tempfile.mkstemp(suffix=".h5", prefix="rig-run-")
            os.close(fd)
            self.record = self.tmp
        self.attrs = {"command": "rig run", "isolation_at_start": args.isolation,
                      "overrun_policy": args.policy or cfg.loop.overrun_policy, "layout": cfg.layout.plant}
        if stand:
            self.attrs["mode_at_start"] = start or "hold"
        self.script = read_script(args.script, args.seconds) if args.script else None

    def new_session(self, record) -> Session:
        from rig.runtime.session import Session
        # with the console a fault keeps the loop running in FAULT (valves safe, sensors read) for the operator
        args = self.args
        return Session(self.cfg, self.backend, clock=self.clock, isolation=(args.isolation == "on"),
                       overrun_policy=args.policy, record=record, record_attrs=self.attrs,
                       realtime=self.cfg.loop.realtime and not args.no_realtime, signals=True, status=not args.quiet,
                       control_file=args.control, mode=self.start, script=self.script,
                       stop_on_fault=not args.console, stability_check=not args.force, feedforward=args.feedforward)

    def started(self, session) -> float:
        """Log the start; the settle time before activation."""
        args, backend, cfg, loop = self.args, self.backend, self.cfg, session.loop
        if self.stand:
            log.info("backend %s, %s at %g Hz, mode %s, config %s, pid %d (SIGUSR1 isolate <-> hold, "
                     "SIGUSR2 off <-> hold%s)", backend, _on_stands(loop.names), loop.rate_hz, self.start or "hold",
                     cfg.source, os.getpid(), f", control file {args.control}" if args.control else "")
        else:
            log.info("backend %s, %d mounts at %g Hz, isolation %s, config %s, pid %d (SIGUSR1 toggles "
                     "isolation%s)", backend, loop.n, loop.rate_hz,
                     f"{args.isolation}, then as {args.script} says" if args.script else args.isolation, cfg.source,
                     os.getpid(),
                     f", control file {args.control}" if args.control else "")
        settle = args.settle if args.settle is not None else (0.05 if backend == "sim" else warmup_s(loop.ctrls))
        cliargs.check_settle(settle, args.seconds, default="the default --settle")
        if settle > 1.0:
            log.info("warming up the controllers for %.1f s before activation (valves at null)", settle)
        return settle

    def run_alone(self):
        """One session without the console, with the fault rehearsal armed; (its loop, the stop reason)."""
        with self.new_session(self.record) as session:
            loop = session.loop
            settle = self.started(session)
            with inject.Armed(session, self.injections) as armed:
                reason = session.run(seconds=self.args.seconds, activate_after_s=settle)
            for spec, t in armed.applied.items():
                log.info("injected %s at t = %.3f s", spec, t)
            for inj in self.injections:
                if inj.spec not in armed.applied:
                    log.info("not injected %s: the run stopped first (%s)", inj.spec, reason)
        return loop, reason

    def finish(self, loop, reason: str) -> int:
        """The stop line, the stand's tracking figures or the machine's VC summary; the exit code."""
        args, record = self.args, self.record
        from rig.runtime.lifecycle import State
        recorded = f", recorded to {args.record}" if args.record else ""
        if loop.lc.state is State.FAULT:     # what the fault left the valves at, from the last command written
            recorded = (", valves at null" if all(v == 0.0 for v in loop.cmd) else
                        ", VALVE COMMANDS NOT AT NULL: make the rig safe by hand") + recorded
        if not loop.clock.is_real:           # no deadlines to meet: nothing to time
            log.info("stopped (%s) after %d periods in simulated time (loop timing is not measured in simulated "
                     "time: run on the real clock for it)%s", reason, loop.iterations, recorded)
        else:
            tm = loop.timing_us()
            behind = loop.overruns or loop.missed_deadline_fraction      # fell behind: said even with --quiet
            log.log(logging.WARNING if behind else logging.INFO,
                    "stopped (%s) after %d periods: overruns %d, missed deadlines %.4f %%, wake p99 %.1f us, "
                    "compute p99 %.1f us%s", reason, loop.iterations, loop.overruns,
                    100 * loop.missed_deadline_fraction, tm["wake_latency_us"]["p99"], tm["compute_us"]["p99"],
                    recorded)
        if self.stand and record is not None:
            try:
                _report(record, args.plot, loop.names, title=None if self.tmp is None else "rig run")
            finally:
                if self.tmp:
                    os.unlink(self.tmp)
        elif record is not None:
            try:
                _vc_summary(record, args.plot, "the run" if self.tmp else str(record))
            finally:
                if self.tmp:
                    os.unlink(self.tmp)
        if loop.lc.state is State.FAULT:
            return 1                          # the reason was logged once, when it happened
        if loop.harm:                         # logged when it happened; said again beside the stop line
            log.warning("%s", loop.harm)
            return EXIT_HARM
        return 0


def _on_stands(names) -> str:
    """What runs on the stand layout, in words: `the actuator on its stand`, `2 actuators on their stands (a, b)`
    (a mount named after the stand is not named twice)."""
    if len(names) == 1:
        return "the actuator on its stand" + ("" if names[0] == "stand" else f" ({names[0]})")
    return f"{len(names)} actuators on their stands ({', '.join(names)})"


def _vc_summary(path, png=None, name: str | None = None) -> None:
    """The recording's VC classes per isolation mode, one line, and with png their curves (rig report REC)."""
    from rig import report
    try:
        rep = report.vc_of_recording(path)
    except RecordingError as e:         # a plot asked for and not drawn is a warning, else a note
        (log.warning if png else log.info)("no VC report%s: %s", f" (no {png})" if png else "",
                                           str(e).replace(str(path), name or str(path)))
        return
    print(f"rig run: {report.summary(rep)}" + ("" if png else f" (curves: rig report {path} --plot FILE)"))  # a figure
    if png:
        report.plot(png, rep)
        log.info("plot: %s", png)


def _report(record, png, names, title: str | None = None) -> None:
    """The operated run's figures per segment on stdout, per mount (and the first mount's plot, titled with
    the recording's name, or `title` for a recording of its own that is not kept)."""
    from rig import operated
    for i, name in enumerate(names):
        run = operated.load_operated(record, name)
        if title:
            run = dataclasses.replace(run, source=title)
        figs = operated.figures(run)
        print(f"{name}:\n{operated.figures_text(figs)}" if len(names) > 1 else operated.figures_text(figs))
        if png and i == 0:
            operated.plot(run, png, figs)
            log.info("plot: %s", png)
