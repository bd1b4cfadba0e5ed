"""When a real-clock run is judged: only when the host kept the loop's time. The safety rules stop a run the host
held off the CPU and say so in one FAULT line; a run can also finish with most periods late. Either way the
figures say nothing about the code, and the test is reported as a skip that quotes the host's figures.

Why a SCHED_FIFO loop is held off at all: Linux 6.12+ (the machine here runs 6.18) gives normal-priority work up
to 50 ms of a CPU per second over real-time tasks (its fair server), and a pty's bytes wait for a
normal-priority kernel worker (`rig bench stalls`)."""
from __future__ import annotations

import json
import re

import pytest

from rig.errors import EXIT_SUSPECT

HOST_TIMING = ("the loop cannot hold", "stale sample:", "between periods (limit watchdog_s",
               "accelerometer conversions came in one period", "RateRefused",
               "the amplifier's frames stopped")      # the emulated amplifier's pty held off (rig bench stalls)
LOOP_LAG = "behind real time (limit lag_limit_s"     # a real-clock run woken too late (rig/runtime/scheduler.py);
# judged apart from HOST_TIMING, whose lines turn any failing test into a skip: the drill's lag tests must fail
LATE_BOUND = 0.25            # more of the metered periods late than this: the host, not the drivers, is measured


def host_line(text: str) -> str | None:
    """The line of text that shows the host did not keep the loop's time, or None."""
    for ln in text.splitlines():
        if any(s in ln for s in HOST_TIMING):
            return ln.strip()
    return None


def ran_to_the_end(out) -> bool:
    """A real-clock command that ran to its end without a fault or harm: exit 0, or EXIT_SUSPECT with `rig hil`'s
    line saying more than 1 % of a mode's periods came late (the host's, or the drivers' chain's on this host)."""
    return out.returncode == 0 or (out.returncode == EXIT_SUSPECT and any(
        s in out.stderr for s in ("the host did not keep time", "the drivers' chain fell behind")))


def _command(out) -> str:
    """The rig command a subprocess ran (its words after `rig.cli`), so a CI log's skip names its test's run."""
    if isinstance(out.args, str):
        return out.args
    words = [str(a) for a in out.args]
    return "rig " + " ".join(words[words.index("rig.cli") + 1:] if "rig.cli" in words else words[1:])


def skip_unless_on_time(out) -> None:
    """Skip (quoting the host's figures) when a `rig hil`/`rig run` subprocess was stopped by the host's timing,
    or when its JSON says more than LATE_BOUND of a mode's periods were late."""
    line = host_line(out.stderr or "")
    if out.returncode != 0 and line:
        pytest.skip(f"host timing, not judged: {_command(out)}: {line[:400]}")
    try:
        late = json.loads(out.stdout).get("late_periods") or {}
    except (ValueError, AttributeError):
        return
    worst = max((v for v in late.values() if v is not None), default=0.0)
    if worst > LATE_BOUND:
        pytest.skip(f"host timing, not judged: {_command(out)}: {100 * worst:.0f} % of a mode's periods late (bound "
                    f"{100 * LATE_BOUND:.0f} %)")


def skip_unless_text_on_time(text: str) -> None:
    """The same judgement from what a real-clock command printed: its FAULT line, the late periods `rig hil`
    meters, or the missed deadlines of `rig run`'s stop line."""
    line = host_line(text) or next((ln.strip() for ln in text.splitlines() if LOOP_LAG in ln), None)
    if line:
        pytest.skip(f"host timing, not judged: {line[:400]}")
    for ln in text.splitlines():
        if ln.startswith("late periods") or "missed deadlines" in ln:
            pcts = [float(x) for x in re.findall(r"([0-9.]+) %", ln)]
            bound = 100 * LATE_BOUND if ln.startswith("late periods") else 10 * LATE_BOUND
            if pcts and max(pcts) > bound:
                pytest.skip(f"host timing, not judged: {ln.strip()[:400]}")


def skip_unless_commissioned_on_time(run) -> None:
    """skip_unless_on_time for a `rig commission` subprocess, which also stops when a device went stale while the
    host held the emulated devices' processes off the CPU ("the run faulted ... no new sample for")."""
    skip_unless_on_time(run)
    if "the run faulted" in run.stderr and "no new sample for" in run.stderr:
        pytest.skip(f"host timing, not judged: {run.stderr.strip().splitlines()[-1][:400]}")


HELD_HOST = 0.05     # a channel whose samples at null repeat more than this: the host held the emulated devices off
                     # (1-2 % on a host that kept time; 6.7 % when a stand's accelerometer read 4 x its noise)


def skip_if_noisy_from_the_host(res: dict) -> None:
    """Skip when `rig commission`'s only findings are channels refused as noisy while their quiet stretch's
    samples repeated more than HELD_HOST: the emulated module converted on a host that did not keep time, and its
    sampling jitter is what reads as noise at the top of the band."""
    noisy = [f for f in res.get("findings", []) if ": noisy," in f]
    if not noisy or len(noisy) != len(res.get("findings", [])):
        return
    words = {"accel": "accelerometer", "stroke": "transducer", "floor": "floor"}      # how a finding names a kind
    held = [row.get("held_share", 0.0) for kind, rows in res.get("channels", {}).items() for row in rows.values()
            if any(words.get(kind, kind) in f for f in noisy)]
    if held and max(held) > HELD_HOST:
        pytest.skip(f"host timing, not judged: {noisy[0][:200]} with {100 * max(held):.1f} % of its samples held")

