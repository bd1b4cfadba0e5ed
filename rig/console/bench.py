"""`rig bench loop --console`: what the console costs the loop, with a real browser on the page.

One loop run (four mounts on the simulated backend, real clock, the real-time set-up and recording of
`rig bench loop`; with --no-record no recording, so the console's live ring is the ring the period writes),
cut into blocks that alternate between conditions:
  none     no console: isolation toggled every TOGGLE_S through the session's request, as the page would;
  process  the console with its web server in a process of its own (the default of rig run --console), a
           headless chromium showing the page and clicking "isolation on" / "isolation off" every TOGGLE_S;
  thread   the same with the web server as a thread of the loop's process (the comparison behind the
           choice of a process).
The browser is driven from a process of its own (`python -m rig.console.bench --drive`), as an operator's
browser is another program: nothing of Playwright runs in the loop's process. Each console block starts the
console, lets the page connect and settle, then measures; the loop's compute and wake-up times come from the
scheduler's per-period record over exactly the block's periods. Also measured in the browser: the page's
update rate (renders with new data) and the time from the click on an isolation button to the new state shown
on the page (the frame after the state arrived).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request

import numpy as np

from rig.console import browser
from rig.errors import EXIT_STOPPED_BY, RigError
from rig.runtime.lifecycle import State

TOGGLE_S = 0.5
SETTLE_S = 1.0                  # after the page has connected, before the block's periods count
RESET_TRIES = 3                 # resets in a row before a block is given up: a fault back at once is no stall


def add_arguments(p) -> None:
    """The options of `rig bench loop` that belong to --console."""
    p.add_argument("--console", action="store_true",
                   help="alternate blocks without and with the operator console and a browser on its page")
    p.add_argument("--serve", choices=("process", "thread", "both"), default="both",
                   help="--console: where the web server runs in the console blocks (default both, alternating)")
    p.add_argument("--block-s", type=float, default=None, metavar="S",
                   help="--console: block length (default 6); --layout both: about this long per block (default 0.2)")
    p.add_argument("--rounds", type=int, default=None,
                   help="--console: rounds of all conditions; --feedforward: rounds of both runs (default 4); "
                        "--layout both: rounds (default 3)")
    p.add_argument("--no-record", action="store_true",
                   help="--console: no recording: the console's live ring is then the ring the period writes "
                        "(its whole cost on the loop's path), against none at all")


def bench_console(args, cfg, rate: float, clock) -> tuple[dict, dict, str | None]:
    """The benchmark: (its figures, for print_figures; its faulted blocks, {what: the first fault's reason}, for
    rig.commands.bench.faulted_exit: a block the loop faulted in, or could not start ACTIVE in, is left out of
    the figures; the run's stop reason, a signal's name when it was interrupted)."""
    from rig.runtime.session import Session      # lazy: `rig bench --help` loads no numba
    why = browser.missing()
    if why:
        raise RigError(f"--console: a browser is needed: {why}")
    if not 1 <= args.rounds <= 100 or not 1 <= args.block_s <= 600:
        raise RigError(f"--rounds/--block-s: expected 1..100 rounds of 1..600 s, got {args.rounds}, {args.block_s}")
    conditions = ["none"] + (["process", "thread"] if args.serve == "both" else [args.serve])
    est_s = args.rounds * len(conditions) * (args.block_s + 8) + 10
    tmp = None
    if not args.no_record:
        fd, tmp = tempfile.mkstemp(suffix=".h5", prefix="rig-bench-")
        os.close(fd)
    realtime = cfg.loop.realtime and not args.no_realtime
    # a stall of the shared machine must not leave the loop in FAULT (less work per period) for the rest of a
    # block: the watchdog is relaxed here; the stall still shows in the wake-up figures
    cfg = cfg.replace(safety=dataclasses.replace(cfg.safety, watchdog_s=max(cfg.safety.watchdog_s, 1.0)))
    session = Session(cfg, "sim", clock=clock, rate_hz=rate, overrun_policy=args.policy,
                      keep_timing=int(math.ceil(2 * est_s * rate)), stop_on_fault=False, record=tmp,
                      record_attrs={"command": "rig bench loop --console"}, realtime=realtime)
    blocks: list[dict] = []
    failure: list[BaseException] = []
    say = (lambda m: print(f"rig bench loop --console: {m}", file=sys.stderr, flush=True))
    try:
        with session:
            loop = session.loop
            loop.activate()
            say(f"{loop.n} mounts at {rate:g} Hz, {args.rounds} rounds of {conditions} in {args.block_s:g} s "
                f"blocks, recording {'off' if args.no_record else 'on'}; "
                f"{'real-time set-up where allowed' if realtime else 'no real-time hygiene'}")

            def drive():
                try:
                    _drive(session, cfg, conditions, args, blocks, say)
                except BaseException as e:      # noqa: BLE001 - reported after the loop has stopped
                    failure.append(e)
                finally:
                    session.safe_stop("bench done")

            t = threading.Thread(target=drive, name="rig-bench-driver", daemon=True)
            t.start()
            reason = session.run()
            t.join()
    finally:
        if tmp:
            os.unlink(tmp)
    if failure and reason not in EXIT_STOPPED_BY:      # after Ctrl-C (it reaches the web server too): the interrupt
        raise RigError(f"--console: {failure[0].__class__.__name__}: {failure[0]}")
    out = _figures(loop, conditions, blocks, rate)
    out["recording"] = not args.no_record
    faults: dict = {}
    for cond in conditions:
        why = [b["fault"] for b in blocks if b["cond"] == cond and b["fault"]]
        if why:
            faults[f"{cond} ({len(why)} of {args.rounds} blocks)"] = why[0]
    return out, faults, reason


def _drive(session, cfg, conditions, args, blocks, say) -> None:
    loop = session.loop
    while loop.t0_ns is None:
        time.sleep(0.01)
    time.sleep(1.0)
    drv = _Driver()
    try:
        for r in range(args.rounds):
            for cond in conditions:
                if loop.stop_reason is not None:        # the run has ended: no block can be measured
                    return
                fault = _active_again(session)
                if fault:
                    blocks.append({"cond": cond, "round": r, "fault": fault})
                    say(f"round {r + 1}/{args.rounds}: {cond} not run: the rig faulted again at once after "
                        f"{RESET_TRIES} resets ({fault})")
                    continue
                b = _block_none(session, args.block_s) if cond == "none" else \
                    _block_console(session, cfg, cond, args.block_s, drv)
                b.update(cond=cond, round=r, fault=loop.lc.fault_reason)
                blocks.append(b)
                say(f"round {r + 1}/{args.rounds}: {cond} done ({b['i1'] - b['i0']} periods"
                    f"{', FAULT: ' + b['fault'] if b['fault'] else ''})")
    finally:
        drv.close()


def _active_again(session) -> str | None:
    """Every block starts ACTIVE: a fault of the last one (a stall of the shared machine tripping the
    watchdog) is reset, as an operator would. None once ACTIVE; else the fault's reason, after RESET_TRIES
    resets in a row (a fault that comes straight back is the set-up's: waiting for ACTIVE would never end)."""
    loop = session.loop
    for _ in range(RESET_TRIES):
        if loop.state is State.FAULT:
            session.reset_fault()
            _applied(loop)
        if loop.state is State.INACTIVE:
            session.request_active(True)
            _applied(loop)
        if loop.state is State.ACTIVE:
            return None
    return loop.lc.fault_reason or f"the loop stayed {loop.state.name}"


def _applied(loop) -> None:
    """Until a request made now has been applied (and its period's checks run): two period boundaries on, or
    the run's end. Not the state itself: a reset's INACTIVE can turn FAULT again within the same period."""
    i = loop.iterations
    while loop.iterations < i + 2 and loop.stop_reason is None:
        time.sleep(0.002)


def _block_none(session, block_s: float) -> dict:
    loop = session.loop
    i0, on = loop.iterations, True
    end = time.monotonic() + block_s
    while time.monotonic() < end:
        on = not on
        session.request_isolation(on)
        time.sleep(TOGGLE_S)
    session.request_isolation(True)
    return {"i0": i0, "i1": loop.iterations}


def _block_console(session, cfg, serve: str, block_s: float, drv: "_Driver") -> dict:
    loop = session.loop
    from rig.console.link import Console         # lazy: `rig bench --help` loads no numba
    with Console(cfg, "sim", port=0, serve=serve, log_level=None) as console:
        console.attach(session)
        try:
            drv.ask({"open": console.url})
            time.sleep(SETTLE_S)
            drv.ask({"reset": True})
            i0, on = loop.iterations, True
            end = time.monotonic() + block_s
            while time.monotonic() < end:
                on = not on
                drv.ask({"click": "#iso-on" if on else "#iso-off"})
                time.sleep(TOGGLE_S)
            i1 = loop.iterations
            page = drv.ask({"stats": True})
            page["server"] = _server_stats(console)
            drv.ask({"click": "#iso-on"})
            time.sleep(0.2)
            drv.ask({"blank": True})
        finally:
            console.detach()
    return {"i0": i0, "i1": i1, "page": page}


def _server_stats(console) -> dict:
    """The web server's own work per update (its /api/state)."""
    with urllib.request.urlopen(f"http://127.0.0.1:{console.port}/api/state?token={console.token}", timeout=10) as r:
        return json.loads(r.read())["server"]


def _pct(a) -> dict:
    a = np.asarray(a, dtype=float)
    if len(a) == 0:
        return {"p50": None, "p99": None, "max": None, "n": 0}
    return {"p50": round(float(np.percentile(a, 50)), 2), "p99": round(float(np.percentile(a, 99)), 2),
            "max": round(float(a.max()), 2), "n": int(len(a))}


def _figures(loop, conditions, blocks, rate) -> dict:
    wake = np.frombuffer(loop.wake_ns, dtype=np.int64)
    comp = np.frombuffer(loop.compute_ns, dtype=np.int64)
    keep = len(wake)
    out = {"rate_hz": rate, "conditions": {}, "block_s": None}
    for cond in conditions:
        bs = [b for b in blocks if b["cond"] == cond and not b["fault"]]     # faulted blocks left out
        idx = np.concatenate([np.arange(b["i0"], b["i1"]) % keep for b in bs]) if bs else np.array([], int)
        c, w = comp[idx] * 1e-3, wake[idx] * 1e-3
        per_block = [float(np.percentile(comp[np.arange(b["i0"], b["i1"]) % keep] * 1e-3, 99)) for b in bs]
        per_block_w = [float(np.percentile(wake[np.arange(b["i0"], b["i1"]) % keep] * 1e-3, 99)) for b in bs]
        period_ns = 1e9 / rate
        d = {"blocks": len(bs), "periods": int(len(idx)),
             "faults": sum(1 for b in blocks if b["cond"] == cond and b["fault"]),
             "compute_us": _pct(c), "wake_latency_us": _pct(w),
             "compute_p99_by_block_us": [round(x, 2) for x in per_block],
             "wake_p99_by_block_us": [round(x, 2) for x in per_block_w],
             "compute_p99_median_of_blocks_us": round(float(np.median(per_block)), 2) if bs else None,
             "wake_p99_median_of_blocks_us": round(float(np.median(per_block_w)), 2) if bs else None,
             "late_periods": int(np.sum(w * 1e3 + c * 1e3 > period_ns))}
        pages = [b["page"] for b in bs if "page" in b]
        if pages:
            iv = np.concatenate([np.diff(p["renders_ms"]) for p in pages if len(p["renders_ms"]) > 1])
            span = sum((p["renders_ms"][-1] - p["renders_ms"][0]) for p in pages if len(p["renders_ms"]) > 1)
            d["page_update_interval_ms"] = _pct(iv)
            d["page_updates_per_s"] = round(1e3 * len(iv) / span, 2) if span > 0 else None
            d["click_to_shown_ms"] = _pct(np.concatenate([p["iso_latency_ms"] for p in pages]))
            d["page_render_work_ms"] = _pct(np.concatenate([p["render_work_ms"] for p in pages]))
            d["server_tick_ms_p99_by_block"] = [p["server"]["tick_ms"]["p99"] for p in pages]
        out["conditions"][cond] = d
    base = out["conditions"]["none"]
    for cond, d in out["conditions"].items():
        if cond != "none":
            d["compute_p99_minus_none_us"] = _minus(d["compute_us"]["p99"], base["compute_us"]["p99"])
            d["compute_p99_median_of_blocks_minus_none_us"] = _minus(d["compute_p99_median_of_blocks_us"],
                                                                     base["compute_p99_median_of_blocks_us"])
            d["wake_p99_minus_none_us"] = _minus(d["wake_latency_us"]["p99"], base["wake_latency_us"]["p99"])
    return out


def _minus(a, b):
    """a - b, None when a condition has no block measured (each faulted)."""
    return None if a is None or b is None else round(a - b, 2)


def _num(v, spec: str) -> str:
    """v formatted, or "-" in the spec's width for a figure no block measured."""
    return format(v, spec) if v is not None else "-".rjust(int(spec.split(".")[0].lstrip("+") or 0))


def print_figures(out: dict, as_json: bool) -> None:
    if as_json:
        print(json.dumps(out))
        return
    print(f"loop at {out['rate_hz']:g} Hz, periods pooled over the blocks of each condition:")
    print(f"  {'condition':10s} {'blocks':>6s} {'compute p50/p99/max us':>26s} {'wake p50/p99/max us':>26s}"
          f" {'compute p99 vs none':>20s}")
    for cond, d in out["conditions"].items():
        c, w = d["compute_us"], d["wake_latency_us"]
        diff = "" if cond == "none" else f"{_num(d['compute_p99_minus_none_us'], '+.2f')} us"
        print(f"  {cond:10s} {d['blocks']:6d} {_num(c['p50'], '8.1f')} {_num(c['p99'], '8.1f')} "
              f"{_num(c['max'], '8.0f')} {_num(w['p50'], '8.1f')} {_num(w['p99'], '8.1f')} "
              f"{_num(w['max'], '8.0f')} {diff:>20s}")
    print("  compute p99, median of the blocks' p99: " + ", ".join(
        f"{cond} {_num(d['compute_p99_median_of_blocks_us'], '.2f')} us" +
        ("" if cond == "none" else f" ({_num(d['compute_p99_median_of_blocks_minus_none_us'], '+.2f')})")
        for cond, d in out["conditions"].items()))
    for cond, d in out["conditions"].items():
        print(f"  {cond:10s} compute p99 by block: {d['compute_p99_by_block_us']} us; wake p99 by block: "
              f"{d['wake_p99_by_block_us']} us; blocks left out (faulted): {d['faults']}")
        if "page_updates_per_s" in d:
            iv, cl = d["page_update_interval_ms"], d["click_to_shown_ms"]
            print(f"  {cond:10s} page: {d['page_updates_per_s']} updates/s (interval p50 {iv['p50']} ms, p99 "
                  f"{iv['p99']} ms, max {iv['max']} ms); click isolation -> shown: n={cl['n']}, p50 {cl['p50']} ms, "
                  f"p99 {cl['p99']} ms, max {cl['max']} ms")
            rw = d["page_render_work_ms"]
            print(f"  {cond:10s} the page's drawing per update p50 {rw['p50']} ms, p99 {rw['p99']} ms; the server's "
                  f"work per update, p99 by block: {d['server_tick_ms_p99_by_block']} ms")


# ---- the browser, in a process of its own ---------------------------------------------------------------------
class _Driver:
    """The browser process: one JSON request a line on its stdin, one JSON answer a line on its stdout."""

    def __init__(self) -> None:
        self.proc = None                # started by the first console block: none if every block faulted

    def ask(self, req: dict) -> dict:
        if self.proc is None:
            # a session of its own: a Ctrl-C at the terminal stops the bench, which then closes the browser
            self.proc = subprocess.Popen([sys.executable, "-m", "rig.console.bench", "--drive"],
                                         stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, bufsize=1,
                                         start_new_session=True)
        self.proc.stdin.write(json.dumps(req) + "\n")
        self.proc.stdin.flush()
        line = self.proc.stdout.readline()
        if not line:
            raise RigError("the browser process has gone")
        ans = json.loads(line)
        if "error" in ans:
            raise RigError(f"browser: {ans['error']}")
        return ans

    def close(self) -> None:
        if self.proc is None:
            return
        try:
            self.proc.stdin.close()
            self.proc.wait(timeout=20)
        except (OSError, subprocess.TimeoutExpired):
            self.proc.kill()
            self.proc.wait()


def _drive_main() -> int:
    from playwright.sync_api import sync_playwright
    with sync_playwright() as pw:
        b = browser.launch(pw)
        page = b.new_page(viewport={"width": 1400, "height": 1300})
        for line in sys.stdin:
            req = json.loads(line)
            try:
                if "open" in req:
                    page.goto(req["open"])
                    browser.wait_for(page, "window.rigStats && rigStats.deltas > 10 && rigStats.renders > 5", 30)
                    ans = {"ok": True}
                elif "reset" in req:
                    page.evaluate("rigStats.renderTimes = []; rigStats.isoLatencyMs = []; rigStats.renderMs = []")
                    ans = {"ok": True}
                elif "click" in req:
                    page.click(req["click"])
                    ans = {"ok": True}
                elif "stats" in req:
                    ans = page.evaluate("({renders_ms: rigStats.renderTimes, iso_latency_ms: rigStats.isoLatencyMs, "
                                        "render_work_ms: rigStats.renderMs})")
                elif "blank" in req:
                    page.goto("about:blank")
                    ans = {"ok": True}
                else:
                    ans = {"error": f"unknown request {req}"}
            except Exception as e:      # noqa: BLE001 - one line back to the bench
                ans = {"error": f"{e.__class__.__name__}: {e}".splitlines()[0]}
            print(json.dumps(ans), flush=True)
        b.close()
    return 0


if __name__ == "__main__":
    ap = argparse.ArgumentParser(prog="python -m rig.console.bench")
    ap.add_argument("--drive", action="store_true", help="the browser process of the benchmark")
    if ap.parse_args().drive:
        sys.exit(_drive_main())
