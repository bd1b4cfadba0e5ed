"""The console page in a real browser (Debian's chromium through Playwright): live traces that move, isolation
switched from the page and seen on the page and in the recording, a sensor fault injected in the simulated
backend and its reason on the page, nothing without the token, read-only refusing, two browsers alike."""
from __future__ import annotations

import numpy as np
import pytest

from rig.console.browser import wait_for
from rig.runtime.lifecycle import State
from rig.runtime.recorder import read_recording
from tests.console.support import base, live_run, open_page

pytestmark = pytest.mark.browser


def test_live_traces_move(chromium):
    with live_run() as (s, console):
        page = open_page(chromium, console)
        chart = page.locator("#chart-front_left-0")       # acceleration of the first mount
        t0 = wait_for(page, "rigStats.lastNow && rigStats.lastNow.t_s")
        shot0 = chart.screenshot()
        wait_for(page, f"rigStats.lastNow.t_s > {t0} + 1.0")
        shot1 = chart.screenshot()
        n = page.evaluate("document.querySelectorAll('#mounts canvas').length")
        text = page.text_content("#state")
        stats = page.evaluate("({d: rigStats.deltas, r: rigStats.renders})")
        assert page.errors == []
    assert n == 12 and text == "ACTIVE"
    assert shot0 != shot1                                  # the plotted trace changed
    assert stats["r"] > 5


def test_isolation_on_from_the_page_is_shown_and_recorded(chromium, tmp_path):
    rec_path = tmp_path / "switch.h5"
    with live_run(isolation=False, record_dir=tmp_path) as (s, console):
        page = open_page(chromium, console)
        assert page.text_content("#isolation") == "off"
        page.fill("#rec-path", str(rec_path))
        page.click("#rec-start")
        wait_for(page, "document.getElementById('rec-file').textContent.endsWith('switch.h5')")
        wait_for(page, "+document.getElementById('rec-rows').textContent > 200")
        page.click("#iso-on")
        wait_for(page, "document.getElementById('isolation').textContent === 'on'")
        latency = wait_for(page, "rigStats.isoLatencyMs.length && rigStats.isoLatencyMs")
        wait_for(page, "+document.getElementById('rec-rows').textContent > 600")
        page.click("#rec-stop")
        wait_for(page, "document.getElementById('rec-file').textContent.endsWith('(closed)')")
        events = page.text_content("#events")
        assert page.errors == []
    assert s.loop.isolation
    assert 0 < latency[0] < 5000
    assert "isolation on" in events and "recording closed" in events
    r = read_recording(rec_path)
    iso = r["isolation_on"]
    assert iso[0] == 0 and iso[-1] == 1 and np.count_nonzero(np.diff(iso)) == 1       # the one switch
    assert any(text == "isolation on" for _, text in r["events"])
    assert r["attrs"]["started_by"] == "console"


def test_an_injected_sensor_fault_shows_its_reason_and_is_reset_from_the_page(chromium):
    with live_run() as (s, console):
        page = open_page(chromium, console)
        assert page.is_hidden("#fault")
        t_s = (s.loop.t_ns - s.loop.t0_ns) * 1e-9
        s.port.inject("nan", mount=1, sensor="accel", at_s=t_s + 0.2)     # the simulated backend's knob
        wait_for(page, "document.getElementById('state').textContent === 'FAULT'")
        banner = wait_for(page, "!document.getElementById('fault').hidden && "
                                "!document.getElementById('fault').textContent.includes('follows') && "
                                "document.getElementById('fault').textContent")
        assert s.loop.state is State.FAULT and s.loop.lc.fault_reason in banner
        assert "front_right" in banner
        assert s.loop.isolation             # chosen on, not isolating: never shown as plain "on" in green
        assert page.text_content("#isolation") == "on (held: FAULT)"
        assert "held" in page.get_attribute("#isolation", "class")
        s.port.clear_faults()
        page.click("#reset-fault")
        wait_for(page, "document.getElementById('state').textContent === 'INACTIVE'")
        assert page.is_hidden("#fault")
        page.click("#activate")
        wait_for(page, "document.getElementById('state').textContent === 'ACTIVE'")
        # the events list comes in its own message, which can follow the state's: waited for, not read at once
        events = wait_for(page, "document.getElementById('events').textContent.includes('fault reset requested') "
                                "&& document.getElementById('events').textContent")
        assert page.errors == []
    assert "FAULT" in events and "fault reset requested" in events


def test_no_page_and_no_data_without_the_token(chromium):
    with live_run() as (s, console):
        page = chromium.new_page()
        resp = page.goto(base(console) + "/")
        assert resp.status == 403 and "forbidden" in page.content()
        assert page.locator("#state").count() == 0
        # a page of the console's origin without the cookie: its websocket is refused
        page.goto(base(console) + "/static/console.js")             # 403 too: same origin, no token
        closed = page.evaluate("""() => new Promise((done) => {
            const ws = new WebSocket(`ws://${location.host}/ws`);
            ws.onmessage = () => done("data");
            ws.onclose = () => done("closed");
        })""")
        assert closed == "closed"


def test_read_only_shows_everything_and_refuses_commands(chromium):
    with live_run(read_only=True) as (s, console):
        page = open_page(chromium, console)
        assert page.is_visible("#readonly")
        wait_for(page, "rigStats.lastNow && rigStats.lastNow.state === 'ACTIVE'")
        disabled = page.evaluate("[...document.querySelectorAll('button')].every((b) => b.disabled)")
        assert disabled
        page.evaluate("""() => { const ws = new WebSocket(`ws://${location.host}/ws`);
            ws.onopen = () => ws.send(JSON.stringify({id: 99, cmd: "isolation", args: {on: false}}));
            ws.onmessage = (ev) => { const m = JSON.parse(ev.data); if (m.type === "reply") window.refused = m; }; }""")
        reply = wait_for(page, "window.refused")
        page.wait_for_timeout(300)
        assert reply["ok"] is False and "read-only" in reply["text"]
        assert s.loop.isolation and page.text_content("#isolation") == "on"


def test_a_second_browser_sees_the_same_state(chromium):
    with live_run() as (s, console):
        a = open_page(chromium, console)
        ctx = chromium.new_context(viewport={"width": 1400, "height": 1300})      # another browser profile
        b = ctx.new_page()
        b.goto(console.url)
        wait_for(b, "window.rigStats && rigStats.deltas > 5")
        a.click("#iso-off")
        wait_for(b, "document.getElementById('isolation').textContent === 'off'")
        wait_for(a, "document.getElementById('isolation').textContent === 'off'")
        wait_for(b, "document.getElementById('events').textContent.includes('isolation off requested')")
        ctx.close()
    assert s.loop.isolation is False
