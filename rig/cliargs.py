"""Argument types and checks of the `rig` command line.

A bad value ends in one line naming the option and what was expected, exit status 2, before anything is
opened, started or written: numbers are finite and inside a stated range with their unit, and output files
and folders are never overwritten without `--overwrite` (`check_outputs`, the one place of that rule).
Units: a number may carry its option's unit (`--f1 100Hz`, `--duration 100s`, `--amplitude 2V`); a bare
number is in that unit, which the help names. A length needs its unit (`--position 5um`, `0.5mm`): a bare
5 would be 5 m, so it is refused (`length`, with controllers/reference.py's rule).
Checks that need the loaded configuration (a rate against the configured frequencies, --settle against
--seconds) are functions here, called in one line by the commands.
"""
from __future__ import annotations

import argparse
import logging
import math
import sys
from pathlib import Path

from rig.errors import RigError

MAX_RATE_HZ = 100000.0        # the loop's own ceiling ([loop] rate_hz): 10 us a period
MAX_RUN_S = 86400.0           # one day of loop time per run
MAX_CHIRP_S = 3600.0          # one hour of chirp (the paper's identification chirp is 100 s)
MAX_SEED = 2 ** 32 - 1        # numpy seeds are unsigned; 32 bits are plenty


class _CommandLines(logging.Formatter):
    """A command's log lines: `rig COMMAND: warning: ...` for a warning, as every command says one (docs/CLI.md);
    `rig COMMAND: ...` for the others (a fault is its own `FAULT: ...` line)."""

    def __init__(self, command: str) -> None:
        super().__init__("%(message)s")
        self.prefix = f"rig {command}: "

    def format(self, record: logging.LogRecord) -> str:
        said = "warning: " if record.levelno == logging.WARNING else ""
        return self.prefix + said + super().format(record)


def log_to_stderr(command: str, level: int = logging.WARNING) -> None:
    """The command's log lines on stderr from level on; once (a caller that set up logging keeps its own)."""
    if not logging.getLogger().handlers:
        handler = logging.StreamHandler(sys.stderr)
        handler.setFormatter(_CommandLines(command))
        logging.basicConfig(level=level, handlers=[handler])


class ArgumentParser(argparse.ArgumentParser):
    """argparse with a one-line error (the usage text is what --help is for)."""

    def error(self, message: str):
        if message.startswith("argument "):          # "argument --rate: expected ..." -> "--rate: expected ..."
            message = message[len("argument "):]
        else:
            message += f" (see {self.prog} --help)"
        self.exit(2, f"{self.prog}: error: {message}\n")


def _fmt(x: float) -> str:
    return f"{x:g}"


class Number:
    """A finite float (or int) with optional bounds: `Number(gt=0, le=100000, unit="Hz")`."""

    def __init__(self, *, gt=None, ge=None, lt=None, le=None, unit: str = "", integer: bool = False) -> None:
        self.gt, self.ge, self.lt, self.le, self.unit, self.integer = gt, ge, lt, le, unit, integer

    def expected(self) -> str:
        unit = f" {self.unit}" if self.unit else ""
        fmt = (lambda b: str(int(b))) if self.integer else _fmt          # a seed's bound in full, not 4.29497e+09
        parts = [f"{op} {fmt(b)}{unit}" for op, b in ((">", self.gt), (">=", self.ge), ("<", self.lt),
                                                      ("<=", self.le)) if b is not None]
        if self.integer:
            return "an integer" + (" " + " and ".join(parts) if parts else "")
        return " and ".join(parts) if parts else f"a finite number{unit}"

    def __call__(self, text: str):
        t = text.strip() if isinstance(text, str) else text
        if self.unit and isinstance(t, str) and t.lower().endswith(self.unit.lower()) and len(t) > len(self.unit):
            t = t[:-len(self.unit)].rstrip()                      # `100Hz`, `2 V`: the option's own unit
        try:
            v = int(t, 10) if self.integer else float(t)
        except (TypeError, ValueError):
            raise argparse.ArgumentTypeError(f"expected {self.expected()}, got {text!r}") from None
        ok = math.isfinite(v) and (self.gt is None or v > self.gt) and (self.ge is None or v >= self.ge) and \
            (self.lt is None or v < self.lt) and (self.le is None or v <= self.le)
        if not ok:
            raise argparse.ArgumentTypeError(f"expected {self.expected()}, got {text!r}")
        return v

    def __repr__(self) -> str:              # argparse names the type in some messages
        return self.expected()


def length(text: str) -> str:
    """A length with its unit (argparse type): `5um`, `0.5mm`, `-250nm`, `0`; the text as given (the mode request
    reads it), refused when the unit is missing or it is not a number."""
    try:
        from controllers.reference import parse_length    # lazy: `rig --help` loads cliargs, not numpy
        parse_length(text, "length", "length")
    except RigError as e:
        why = " (a bare number would be metres)" if "no unit" in str(e) else ""
        raise argparse.ArgumentTypeError(f"expected a length with its unit, e.g. 5um or 0.5mm{why}, "
                                         f"got {text!r}") from None
    return text.strip()


def seconds(*, gt=0.0, ge=None, le=MAX_RUN_S) -> Number:
    """A duration in seconds (> 0 unless ge is given)."""
    return Number(gt=None if ge is not None else gt, ge=ge, le=le, unit="s")


def rate_hz(le: float = MAX_RATE_HZ) -> Number:
    """A loop rate: > 0 and at most le Hz (0 is refused, not read as 'the default')."""
    return Number(gt=0.0, le=le, unit="Hz")


def count(ge: int = 1, le: int = 1_000_000) -> Number:
    return Number(ge=ge, le=le, integer=True)


def seed() -> Number:
    return Number(ge=0, le=MAX_SEED, integer=True)


# ---- output files and folders --------------------------------------------------------------------------
class _Output(argparse.Action):
    """Stores the path and registers it (option, path, kind) for check_outputs."""

    def __init__(self, option_strings, dest, kind: str = "file", suffix: str = "", suffixes=(), **kw):
        super().__init__(option_strings, dest, **kw)
        self.kind, self.suffix, self.suffixes = kind, suffix, tuple(suffixes)

    def __call__(self, parser, namespace, value, option_string=None):
        p = Path(value)
        if self.kind == "file":
            if not p.name or value.endswith(("/", "\\")) or p.is_dir():
                parser.error(f"argument {self.option_strings[0]}: expected a file name, got {value!r}"
                             f"{' (a folder)' if p.is_dir() else ''}")
            if self.suffix and not p.suffix:
                p = p.with_name(p.name + self.suffix)       # what is written is what is said
            elif self.suffixes and p.suffix.lower() not in self.suffixes:
                parser.error(f"argument {self.option_strings[0]}: expected a file name ending in "
                             f"{', '.join(self.suffixes)}, got {value!r}")
        setattr(namespace, self.dest, p)
        outs = [o for o in getattr(namespace, "_outputs", []) if o[0] != self.option_strings[0]]
        namespace._outputs = outs + [(option_string or self.option_strings[0], p, self.kind)]


PLOT_SUFFIXES = (".png", ".pdf", ".svg")       # a --plot FILE's formats


def output_arg(p: argparse.ArgumentParser, *flags: str, kind: str = "file", suffix: str = "",
               suffixes=(), **kw) -> None:
    """An option naming a file (kind "file") or folder ("folder") the command writes, and --overwrite once.
    suffix: added to a file name without one (matplotlib would add it silently); suffixes: the ones allowed
    (a --plot: PLOT_SUFFIXES, checked before any work rather than by matplotlib after it)."""
    if "--plot" in flags and not suffixes:
        suffixes = PLOT_SUFFIXES
    p.add_argument(*flags, action=_Output, kind=kind, suffix=suffix, suffixes=suffixes, **kw)
    if not any("--overwrite" in a.option_strings for a in p._actions):
        p.add_argument("--overwrite", action="store_true",
                       help="replace existing output files (default: refuse, naming the file)")


def check_outputs(args) -> None:
    """The rule: an output file that exists, or an output folder that is not empty, is refused without
    --overwrite (but a batch's own folder, given to the same batch again: rig/batch/command.py `resumes`); a file
    name that is a folder (or a folder name that is a file, or a path under a file) always. RigError, one line.
    Then the folder of each output file is made if missing."""
    overwrite = bool(getattr(args, "overwrite", False))
    for option, path, kind in getattr(args, "_outputs", []):
        above = next((a for a in path.parents if a.exists()), None)     # the nearest part of the path there
        if above is not None and not above.is_dir():
            raise RigError(f"{option} {path}: {above} is a file, not a folder")
        if kind == "file":
            if path.is_dir():
                raise RigError(f"{option} {path}: is a folder, expected a file name")
            if path.exists() and not overwrite:
                raise RigError(f"{option} {path}: file exists (add --overwrite to replace it)")
        else:
            if path.exists() and not path.is_dir():
                raise RigError(f"{option} {path}: exists and is not a folder")
            resumes = getattr(args, "resumes", None)      # a batch's folder, run again into: it resumes
            if path.is_dir() and not overwrite and any(path.iterdir()) and not (resumes and resumes(args, path)):
                raise RigError(f"{option} {path}: folder is not empty (add --overwrite to write into it)")
    for option, path, kind in getattr(args, "_outputs", []):    # all accepted: a file's folder is made if
        if kind == "file":                                       # missing, as --out DIR is
            make_out_dir(path.parent, option)


# ---- checks that need the configuration or more than one option -----------------------------------------
def make_out_dir(path, flag: str = "--out"):
    """Create an output folder (and its parents); one line naming the option when it cannot be made."""
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise RigError(f"{flag} {path}: cannot create directory ({e})") from None
    return path


def check_settle(settle_s: float, seconds_s: float | None, *, default: str = "") -> None:
    """INACTIVE for settle_s, then ACTIVE: a run shorter than its settle time would never activate."""
    if seconds_s is not None and settle_s >= seconds_s:
        what = f"--settle {settle_s:g} s" if not default else f"the settle time ({default}: {settle_s:.3g} s)"
        raise RigError(f"--seconds {seconds_s:g}: expected longer than {what}, or the run would end before "
                       f"activation (give a longer --seconds or a shorter --settle)")


def check_within_run(at_s: float, seconds_s: float | None, where: str) -> None:
    """A loop time at or after the run's end never comes (an --inject T, a --script line): refused before the run
    starts, never left to pass silently. where: what names the time (`--inject SPEC: T`, `--script FILE: line N`)."""
    if seconds_s is not None and at_s >= seconds_s:
        raise RigError(f"{where}: expected a loop time within the run (< --seconds {seconds_s:g}), got {at_s:g} s")


def check_periods(seconds_s: float, rate_hz: float, at_least: int = 10, option: str = "--seconds") -> None:
    """A benchmark of fewer than at_least periods measures nothing (and an empty one has no percentiles)."""
    if seconds_s * rate_hz < at_least:
        raise RigError(f"{option} {seconds_s:g}: expected at least {at_least} periods at {rate_hz:g} Hz "
                       f"(>= {at_least / rate_hz:g} s)")


def check_rate(cfg, rate_hz: float, where: str = "", *, sections=("controller", "vibration")) -> None:
    """Frequencies of the configuration against the Nyquist frequency of the rate the command will run at
    (where: the option or key that set it, for the message)."""
    from rig.config import check_nyquist                 # lazy: as parse_length above
    check_nyquist(cfg, rate_hz, sections=sections,
                  rate_source=f"the loop at {rate_hz:g} Hz" + (f", {where}" if where else ""))
