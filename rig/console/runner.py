"""`rig run --console`: the run with its operator console, and the chirp identification the page can ask for.

The console (rig/console/link.py) lives as long as the command; the run is a session as without it
(rig/commands/run.py builds it), with one difference: a fault keeps the loop running in FAULT (valves safe,
sensors read and shown) until the operator resets it or stops the run.

A chirp identification needs other controllers on the valves (a chirp played open loop), so it is a run of
its own, as `rig chirp` makes it: the page's request stops the isolation run safely (the gate's stop, valves
to null), the chirp runs through `rig.chirp.run_chirp` with its progress on the page, then the
isolation run resumes as it was (ACTIVE again after its settle time, unless the chirp faulted) while
`rig identify` works on the recording in a process of its own; its result appears on the page beside Table 1.
"""
from __future__ import annotations

import logging
import sys
import time

from rig.chirp import run_chirp
from rig.console.link import Console
from rig.errors import RigError

log = logging.getLogger("rig.console")


def run_with_console(args, cfg, backend: str, new_session, started):
    """Run sessions (new_session(record) -> Session; started(session) -> settle seconds) with the console
    until the run ends. Returns (the last isolation run's loop, its stop reason)."""
    loop, reason = None, "stopped"
    remaining = args.seconds
    record = args.record
    settle_next: bool = True
    with Console(cfg, backend, port=args.port, read_only=args.read_only, config_path=args.config) as console:
        print(f"rig run: operator console at {console.url}" + (" (read-only)" if args.read_only else ""),
              file=sys.stderr, flush=True)
        while True:
            with new_session(record) as session:
                record = None                      # --record is the first run's; later ones from the page
                loop = session.loop
                settle = started(session)
                console.attach(session)
                try:
                    reason = session.run(seconds=remaining, activate_after_s=settle if settle_next else None)
                finally:
                    console.detach()
            if remaining is not None:
                remaining -= loop.iterations / loop.rate_hz
            job = console.take_job()
            if job is None or console.stop_requested or (remaining is not None and remaining <= 0):
                break
            settle_next = _chirp(console, job, cfg, backend, args) and job.resume_active
            if console.stop_requested:
                reason = "console: safe stop"
                break
        console.finish(reason)
    return loop, reason


def _chirp(console: Console, job, cfg, backend: str, args) -> bool:
    """The chirp run and the start of its identification; False if it did not complete."""
    out = console.record_dir / f"chirp_{time.strftime('%Y%m%d_%H%M%S')}.h5"
    job.recording = str(out)
    console.job_progress("chirp", 0.0, f"chirp {job.f0_hz:g}->{job.f1_hz:g} Hz, {job.amplitude_V:g} V, "
                                       f"{job.duration_s:g} s")

    def progress(t_s: float, total_s: float) -> None:
        console.job_progress("chirp", t_s / total_s, f"chirp {t_s:.1f} / {total_s:.1f} s")

    log.info("console: chirp identification: %g->%g Hz, %g V, %g s%s -> %s", job.f0_hz, job.f1_hz,
             job.amplitude_V, job.duration_s, "" if backend == "sim" else f" on {job.mount}", out)
    try:
        s = run_chirp(cfg, backend=backend, amplitude_V=job.amplitude_V, f0_hz=job.f0_hz, f1_hz=job.f1_hz,
                      duration_s=job.duration_s, out=out, mount=job.mount, sim_time=bool(args.sim_time),
                      progress=progress, on_session=console.attach_chirp)
    except RigError as e:
        console.job_failed(f"chirp: {e}")
        log.error("console: chirp: %s", e)
        return False
    finally:
        console.attach_chirp(None)
    console.start_identify(out)
    return True
