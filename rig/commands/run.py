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
  `feedback` / `feedback_feedforward`  the isolation mode (with floor accelerometers, [sensors] floor_accel)
The status line on stderr shows state, isolation, loop timing, overruns, strokes and commands. With --record
the run ends with the recording's vibration-criterion classes per mode (rig report REC: the curves).
Exit code: 0 after a normal stop, 1 after a fault (the reason is printed), 2 for a user error.
"""
from __future__ import annotations

import logging
import os
import sys

from rig import cliargs, report
from rig.backends import BACKENDS
from rig.clock import MonotonicClock, SimClock
from rig.config import hil_run_config, load_config
from rig.errors import RecordingError, RigError
from rig.lifecycle import State
from rig.session import Session

log = logging.getLogger("rig.run")


def warmup_s(ctrls) -> float:
    """Time for the controllers' estimators to forget a cold start: 2 / blend_hz (about five time constants of
    the blend's slowest pole), 0.05 s for controllers without a blend."""
    blends = [c.p.blend_hz for c in ctrls if getattr(getattr(c, "p", None), "blend_hz", 0) > 0]
    return min(2.0 / min(blends), 60.0) if blends else 0.05


def add_arguments(p) -> None:
    p.add_argument("--backend", choices=tuple(BACKENDS), default=None,
                   help="backend (default: [backend] name in the config, else sim)")
    p.add_argument("--seconds", type=cliargs.seconds(), default=None, metavar="N",
                   help="run for N seconds of loop time (default: until Ctrl-C / SIGTERM / `stop`)")
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
    p.add_argument("--quiet", action="store_true", help="no status line")
    p.add_argument("--console", action="store_true",
                   help="serve the operator console (a live web page) on 127.0.0.1; its address, with a random "
                        "access token, is printed at start")
    p.add_argument("--port", type=cliargs.Number(ge=0, le=65535, integer=True), default=None, metavar="N",
                   help="console port (default: the first free one from 8765; 0: any free port)")
    p.add_argument("--read-only", action="store_true", help="console shows everything and accepts no command")


def run(args) -> int:
    if not logging.getLogger().handlers:
        # our own INFO lines (lifecycle, start/stop); libraries (canopen, pymodbus) only from WARNING
        logging.basicConfig(level=logging.WARNING, format="rig run: %(message)s", stream=sys.stderr)
        logging.getLogger("rig").setLevel(logging.INFO)
    cfg = load_config(args.config)
    backend = args.backend or cfg.backend.name
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
    if (args.port is not None or args.read_only) and not args.console:
        raise RigError("--port/--read-only: only with --console")
    clock = SimClock() if args.sim_time else MonotonicClock()

    def new_session(record=args.record) -> Session:
        # with the console a fault keeps the loop running in FAULT (valves safe, sensors read) for the operator
        return Session(cfg, backend, clock=clock, isolation=(args.isolation == "on"), overrun_policy=args.policy,
                       record=record, record_attrs={"command": "rig run", "isolation_at_start": args.isolation,
                                                    "overrun_policy": args.policy or cfg.loop.overrun_policy},
                       realtime=cfg.loop.realtime and not args.no_realtime, signals=True,
                       status=not args.quiet, control_file=args.control, stop_on_fault=not args.console,
                       feedforward=args.feedforward)

    def started(session) -> float:
        """Log the start; the settle time before activation."""
        loop = session.loop
        log.info("backend %s, %d mounts at %g Hz, isolation %s, pid %d (SIGUSR1 toggles isolation%s)",
                 backend, loop.n, loop.rate_hz, args.isolation, os.getpid(),
                 f", control file {args.control}" if args.control else "")
        settle = args.settle if args.settle is not None else (0.05 if backend == "sim" else warmup_s(loop.ctrls))
        cliargs.check_settle(settle, args.seconds, default="the default --settle")
        if settle > 1.0:
            log.info("warming up the controllers for %.1f s before activation (valves at null)", settle)
        return settle

    if args.console:
        from rig.console.runner import run_with_console
        loop, reason = run_with_console(args, cfg, backend, new_session, started)
    else:
        with new_session() as session:
            loop = session.loop
            reason = session.run(seconds=args.seconds, activate_after_s=started(session))
    tm = loop.timing_us()
    log.info("stopped (%s) after %d periods: overruns %d, missed deadlines %.4f %%, wake p99 %.1f us, "
             "compute p99 %.1f us%s", reason, loop.iterations, loop.overruns,
             100 * loop.missed_deadline_fraction, tm["wake_latency_us"]["p99"], tm["compute_us"]["p99"],
             f", recorded to {args.record}" if args.record else "")
    if args.record:
        _vc_summary(args.record)
    if loop.lc.state is State.FAULT:
        return 1                          # the reason was logged once, when it happened
    return 0


def _vc_summary(path) -> None:
    """The recording's VC classes per isolation mode, one line (rig report REC gives the curves)."""
    try:
        log.info("%s (curves: rig report %s)", report.summary(report.vc_of_recording(path)), path)
    except RecordingError as e:
        log.info("no VC report: %s", e)
