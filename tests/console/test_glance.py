"""The console read at a glance (issue 29), in a real browser: every plot has scaled axes named with their
units, the event log keeps one clock and shows each event once, the mode field is there only where operating
modes exist (the stand layout), and a chirp asked for on the page is shown live while it runs."""
from __future__ import annotations

import re
import time

import pytest

from rig.config import load_config
from rig.console.browser import wait_for
from tests.console import support
from tests.console.support import ask_for_chirp, live_run, open_page, open_when_active, rig_run_console
from tests.paths import REPO

pytestmark = pytest.mark.browser

CLOCK = re.compile(r"^\d\d:\d\d:\d\d\.\d\d\d$")       # the event log's one clock: time of day, ms


def _numbers(ticks: list[str]) -> list[float]:
    return [float(t) for t in ticks]


def _check_linear_axis(name: str, axis: dict, unit: str) -> None:
    vals = _numbers(axis["ticks"])
    assert len(set(vals)) >= 3, f"{name}: ticks {axis['ticks']} (at least three values make a scale)"
    steps = {round(b - a, 12) for a, b in zip(vals, vals[1:])}
    assert len(steps) == 1 and min(steps) > 0, f"{name}: ticks {axis['ticks']} are not evenly spaced"
    assert f"[{unit}]" in axis["label"], f"{name}: axis label {axis['label']!r} names no unit {unit}"


def test_every_panel_has_scaled_axes_with_units_and_the_log_one_clock(chromium):
    with live_run(isolation=False) as (s, console):
        page = open_page(chromium, console)
        t0 = time.time()
        page.click("#iso-on")                 # the command's log line and the gate's, where it applied it
        wait_for(page, "[...document.querySelectorAll('#events li')].some((e) => "
                       "e.lastChild.textContent === 'isolation on')")
        # the spectra need a few seconds of each class
        wait_for(page, "rigStats.axes.spectrum && rigStats.axes.spectrum.y.ticks.length > 1 && "
                       "rigStats.axes.vc && rigStats.axes.vc.y.ticks.length > 1", 60)
        axes = page.evaluate("rigStats.axes")
        times = page.eval_on_selector_all("#events time", "(els) => els.map((e) => e.textContent)")
        texts = page.eval_on_selector_all("#events li", "(els) => els.map((e) => e.textContent)")
        mode_hidden = page.is_hidden("#mode-text") and page.is_hidden("#mode-set")
        assert page.errors == []
    mounts = ("front_left", "front_right", "rear_left", "rear_right")
    units = {0: "m/s²", 1: "µm", 2: "V"}
    for m in mounts:
        for q, unit in units.items():
            name = f"chart-{m}-{q}"
            assert name in axes, f"no axes recorded for {name}: {sorted(axes)}"
            _check_linear_axis(name + " y", axes[name]["y"], unit)
            _check_linear_axis(name + " x", axes[name]["x"], "s")
    for name, unit in (("spectrum", "m/s²/√Hz"), ("vc", "µm/s")):
        assert f"[{unit}]" in axes[name]["y"]["label"] and "[Hz]" in axes[name]["x"]["label"]
        assert len(axes[name]["y"]["ticks"]) >= 2 and len(axes[name]["x"]["ticks"]) >= 2
    # one clock: every event stamped with the time of day, around now (no loop times among them)
    assert times and all(CLOCK.match(t) for t in times), times
    assert any("isolation on requested" in x for x in texts)
    shown = [x[len("00:00:00.000"):] for x in texts]                        # the events' texts without time
    assert shown.count("isolation on") == 1, texts                         # one switch, one line
    for t in times:
        h, m, sec = t.split(":")
        lt = time.localtime(t0)
        day_s = int(h) * 3600 + int(m) * 60 + float(sec)
        assert abs(day_s - (lt.tm_hour * 3600 + lt.tm_min * 60 + lt.tm_sec)) < 120, (t, times)
    assert len(shown) == len(set(shown)), f"events shown twice: {texts}"      # one run: nothing repeats
    assert mode_hidden                       # the machine refuses every mode: no mode field


def test_the_mode_field_is_there_on_the_stand(chromium):
    proto = load_config(REPO / "drivers" / "devicemaps" / "prototype.toml")
    cfg = proto.replace(safety=support.test_config().safety)
    with live_run(cfg=cfg) as (s, console):
        page = open_page(chromium, console)
        assert page.is_visible("#mode-text") and page.is_visible("#mode-set")
        page.fill("#mode-text", "hold 2um")
        page.click("#mode-set")
        reply = wait_for(page, "rigStats.replies.length && rigStats.replies[rigStats.replies.length - 1]")
        assert page.errors == []
    assert reply["ok"] and "hold" in reply["text"], reply


@pytest.mark.slow
def test_a_chirp_from_the_page_is_shown_live(chromium, tmp_path):
    """A short chirp asked for on the page: while the header says (chirp), the traces follow the chirp run
    (its loop time advances, its mount shown), then the isolation run resumes on its four mounts."""
    with rig_run_console("--seconds", "600", cwd=tmp_path) as (proc, url, lines):
        page = open_when_active(chromium, url)
        ask_for_chirp(page, 1.0, 1.0, 20.0, 6.0)
        seen = []
        end = time.monotonic() + 120
        while time.monotonic() < end:
            st = page.evaluate("({state: document.getElementById('state').textContent, "
                               "t: rigStats.lastNow && rigStats.lastNow.t_s, "
                               "mounts: [...document.querySelectorAll('.mount-name')].map((e) => e.textContent)})")
            if st["state"].endswith("(chirp)"):
                seen.append(st)
            elif seen and st["state"] == "ACTIVE" and len(st["mounts"]) == 4:
                break
            time.sleep(0.2)
        assert seen, "the header never said (chirp)\n" + "".join(lines)
        wait_for(page, "rigStats.lastNow && rigStats.lastNow.state === 'ACTIVE'", 60)
        texts = page.eval_on_selector_all("#events li", "(els) => els.map((e) => e.textContent)")
        page.click("#safe-stop")
        assert proc.wait(60) == 0
    chirp_t = [x["t"] for x in seen if x["t"] is not None and x["mounts"] == ["stand"]]
    assert chirp_t and max(chirp_t) - min(chirp_t) > 2.0, f"the traces did not follow the chirp: {seen[::10]}"
    assert len(texts) == len(set(texts)), f"events shown twice: {texts}"
