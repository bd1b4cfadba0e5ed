"""`rig` command line: one sub-command per module in rig/commands, imported only when used."""
from __future__ import annotations

import argparse
import importlib
import sys

from rig.cliargs import ArgumentParser, check_outputs
from rig.errors import EXIT_FAULT, EXIT_INPUT, EXIT_INTERRUPTED, EXIT_TERMINATED, FaultError, RigError
from rig.runtime.signals import Terminated, hold_early

# name -> (module, one-line help). Each module has add_arguments(parser) and run(args) -> int.
COMMANDS = {
    "model": ("rig.commands.model", "the paper's linear model figures (Eqs. 1-10) and Bode plot"),
    "demo": ("rig.commands.demo", "four-mount rig on the simulated plant under floor vibration"),
    "design": ("rig.commands.design", "controller analysis: margins, Nyquist, transmissibilities"),
    "run": ("rig.commands.run", "operate the rig on demand (sim, hil or hardware backend)"),
    "bench": ("rig.commands.bench", "benchmarks: simulation speed, loop timing"),
    "hil": ("rig.commands.hil", "hardware-in-the-loop run through the real drivers and emulated devices"),
    "commission": ("rig.commands.commission", "check the wiring, polarity and scale of every channel before any "
                   "loop closes"),
    "chirp": ("rig.commands.chirp", "run a valve chirp on the actuator and record it"),
    "identify": ("rig.commands.identify", "identify the six actuator parameters from a chirp recording"),
    "diagnose": ("rig.commands.diagnose", "find and model the physics a recording shows but the model lacks"),
    "prove": ("rig.commands.prove", "blind proof of diagnosis on simulated or given recordings"),
    "report": ("rig.commands.report", "vibration-criterion (VC) report of a run recording, per isolation mode"),
    "export": ("rig.commands.export", "a recording for MATLAB (.mat) or a spreadsheet (.csv), with its units and "
                                      "metadata"),
    "drill": ("rig.commands.drill", "fault drill: each fault rehearsed, what the rig does, time to FAULT"),
}


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    parser = ArgumentParser(prog="rig", description="Controller runtime for the electro-hydraulic "
                                     "vibration-isolation rig (Law et al., CIRP 2015).")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (module, help_) in COMMANDS.items():
        p = sub.add_parser(name, help=help_, description=help_)
        mod = importlib.import_module(module) if only == name else None      # `rig --help` imports none
        p.add_argument("--config", metavar="FILE", default=None,
                       help=getattr(mod, "CONFIG_HELP", "TOML configuration (default: the paper's Table 1 values)"))
        if mod is not None:
            mod.add_arguments(p)
    return parser


def unrecognized(parser: argparse.ArgumentParser, command: str | None, extra: list[str]) -> str:
    """One line for arguments no option takes, named by the command they were given to, with the nearest
    option where one is close."""
    import difflib
    prog = f"rig {command}" if command else "rig"
    sub = next((a.choices[command] for a in parser._actions
                if isinstance(a, argparse._SubParsersAction) and command in a.choices), parser) if command else parser
    options = [o for a in sub._actions for o in a.option_strings]
    near = next((difflib.get_close_matches(x.split("=")[0], options, n=1, cutoff=0.7) for x in extra
                 if x.startswith("-")), [])
    hint = f"; did you mean {near[0]}?" if near else ""
    shown = " ".join(x if x.isprintable() else repr(x) for x in extra)     # a CR or newline keeps it one line
    return f"{prog}: error: unrecognized arguments: {shown}{hint} (see {prog} --help)"


def main(argv: list[str] | None = None) -> int:
    hold_early()                 # a SIGUSR1 during the imports and set-up is held, not fatal; a SIGTERM unwinds as
                                 # Ctrl-C does (rig/runtime/signals.py)
    argv = sys.argv[1:] if argv is None else argv
    # Import only the module of the command asked for (hardware libraries stay unloaded otherwise).
    only = next((a for a in argv if a in COMMANDS), None)
    said = [only]                # the command, as parsed once it is
    try:
        return _command(argv, only, said)
    except KeyboardInterrupt:    # at any point outside a run that stops on it safely: the imports, the set-up,
        print(f"{_prog(said[0])}: interrupted", file=sys.stderr)          # the closing figures
        return EXIT_INTERRUPTED
    except Terminated:
        print(f"{_prog(said[0])}: interrupted (SIGTERM)", file=sys.stderr)
        return EXIT_TERMINATED


def _prog(command: str | None) -> str:
    return f"rig {command}" if command else "rig"


def _command(argv: list[str], only: str | None, said: list) -> int:
    parser = build_parser(only)
    try:
        args, extra = parser.parse_known_args(argv)
    except SystemExit as e:                  # a bad argument (one line printed) or --help: the exit status
        return e.code if isinstance(e.code, int) else 2
    said[0] = args.command
    if extra:
        print(unrecognized(parser, args.command, extra), file=sys.stderr)
        return 2
    if not args.command:
        parser.print_help()
        return 2
    try:
        check_outputs(args)                 # before anything is opened, started or truncated
        return int(importlib.import_module(COMMANDS[args.command][0]).run(args) or 0)
    except FaultError as e:
        print(f"rig {args.command}: error: {e}", file=sys.stderr)
        return EXIT_FAULT
    except RigError as e:
        print(f"rig {args.command}: error: {e}", file=sys.stderr)
        return EXIT_INPUT


if __name__ == "__main__":
    sys.exit(main())
