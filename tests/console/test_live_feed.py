"""The console's pure parts: the live ring (shared memory between the loop's process and the web server), the
feed that turns rows into what the page draws, and the command check."""
from __future__ import annotations

import json
import math
import os

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rig.runtime import ring as rr
from rig.console import feed as feed_mod
from rig.console.feed import Feed
from rig.console.live import LiveReader, LiveRing
from rig.console.protocol import COMMANDS, check_command
from rig.console.server import ConsoleState
from rig.runtime.layout import loop_channels
from rig.runtime.lifecycle import State

MOUNTS = ("front_left", "front_right", "rear_left", "rear_right")


def _reader(ring: LiveRing) -> LiveReader:
    return LiveReader(os.dup(ring.fd))


def test_rows_the_kernel_commits_reach_the_reader_in_order():
    ring = LiveRing(3, 16)
    rd = _reader(ring)
    hdr = ring.ring_header()
    rows = []
    for k in range(10):                         # what the compiled period does (rig/runtime/ring.py): publish, claim
        rr.publish(hdr)
        ring.ring_rows()[rr.claim(hdr, ring.capacity)] = (k, 2 * k, 3 * k)
        new = rd.read()
        assert len(new) == (1 if k else 0)                             # the row before, published
        rows.extend(new.tolist())
    rr.publish(hdr)                                                    # the run ends: the last row too
    rows = np.array(rows + rd.read().tolist())
    assert rows[:, 0].tolist() == list(range(10)) and rows[:, 2].tolist() == [3 * k for k in range(10)]
    assert len(rd.read()) == 0                                        # nothing new
    ring.push_row(np.array([10.0, 20.0, 30.0]))
    assert rd.read().tolist() == [[10.0, 20.0, 30.0]] and rd.skipped_rows == 0


def test_the_ring_overwrites_and_a_reader_behind_skips_ahead_and_counts():
    ring = LiveRing(1, 32)
    rd = _reader(ring)
    ring.append(np.arange(100.0)[:, None])                            # more than the capacity at once
    rows = rd.read()[:, 0]
    assert rows[-1] == 99 and np.all(np.diff(rows) == 1)              # the newest, contiguous
    assert rd.skipped_rows == 100 - len(rows) and len(rows) <= 32
    ring.append(np.arange(100.0, 120.0)[:, None])                     # wraps around the end
    assert rd.read()[:, 0].tolist() == list(range(100, 120))


def test_a_reader_of_the_wrong_size_is_refused():
    ring = LiveRing(4, 8)
    os.ftruncate(ring.fd, 64 + 8 * 4 * 8 + 8)
    with pytest.raises(ValueError, match="do not hold"):
        _reader(ring)


@settings(max_examples=60, deadline=None)
@given(chunks=st.lists(st.integers(1, 90), min_size=1, max_size=20), cap=st.integers(8, 64))
def test_any_chunking_reads_the_same_rows_back(chunks, cap):
    """Whatever the writer's chunks and the reader's timing, the reader gets the newest rows in order."""
    ring = LiveRing(2, cap)
    rd = _reader(ring)
    got, k = [], 0
    for n in chunks:
        ring.append(np.column_stack([np.arange(k, k + n), -np.arange(k, k + n)]).astype(float))
        k += n
        got.extend(rd.read()[:, 0].tolist())
    assert got == sorted(set(got)) and got[-1] == k - 1
    assert len(got) + rd.skipped_rows == k


# ---- the feed ------------------------------------------------------------------------------------------------
def _layout(rate_hz=1000.0):
    chans = loop_channels(MOUNTS, ("front_left.x",))
    return {"channels": [{"name": c.name, "width": c.width} for c in chans], "rate_hz": rate_hz,
            "mounts": list(MOUNTS), "limits": {"valve_limit_V": 10.0, "stroke_limit_m": 9e-4,
                                               "accel_range_mps2": 50.0}}


def _rows(f: Feed, t_s, *, state=State.ACTIVE, iso=1.0, accel=None, cmd=None):
    n = len(t_s)
    r = np.zeros((n, f.ncols))
    c = f.col
    r[:, c["time_s"]] = t_s
    r[:, c["lifecycle_state"]] = float(state)
    r[:, c["isolation_on"]] = iso
    if accel is not None:
        r[:, c["accel_mps2"]:c["accel_mps2"] + 4] = np.asarray(accel).reshape(n, -1)
    if cmd is not None:
        r[:, c["valve_cmd_V"]:c["valve_cmd_V"] + 4] = np.asarray(cmd).reshape(n, -1)
    r[:, c["wake_latency_us"]] = 5.0
    r[:, c["compute_prev_us"]] = np.linspace(10, 20, n)
    return r


def test_the_envelope_keeps_every_spike_and_the_order_of_extremes():
    f = Feed(_layout(1000.0))                                    # buckets of 10 rows
    t = np.arange(1000) / 1000
    cmd = np.zeros((1000, 4))
    cmd[333, 2] = 9.9                                            # one period at the clamp, mount 3
    cmd[700, 0] = -4.0
    f.add(_rows(f, t, cmd=cmd))
    d = f.take_delta()
    v = np.array(d["traces"]["v"])
    assert len(d["traces"]["t"]) == 200 and v.shape == (12, 200)
    assert v[8 + 2].max() == 9.9 and v[8].min() == -4.0          # command traces keep the spike
    assert "traces" not in f.take_delta()                        # nothing new
    full = f.full()
    assert len(full["traces"]["t"]) == 200 and full["trace_names"][8] == "valve_cmd_V.front_left"


def test_a_partial_bucket_waits_for_its_rows():
    f = Feed(_layout(1000.0))
    f.add(_rows(f, np.arange(15) / 1000))
    assert len(f.take_delta()["traces"]["t"]) == 2                # one bucket; five rows pending
    f.add(_rows(f, np.arange(15, 20) / 1000))
    t = f.take_delta()["traces"]["t"]
    assert t == [0.01, 0.015]


def test_the_newest_row_is_the_state_and_a_switch_is_no_second_event():
    """The rows give the state; an isolation switch is the loop's own log record (the gate logs it where it
    applies it), so the feed adds no event of its own: the page shows each switch once."""
    f = Feed(_layout())
    iso = np.r_[np.ones(50), np.zeros(50), np.ones(20)]
    rows = _rows(f, np.arange(120) / 1000)
    rows[:, f.col["isolation_on"]] = iso
    f.add(rows)
    d = f.take_delta()
    assert "events" not in d
    assert d["now"]["state"] == "ACTIVE" and d["now"]["isolation"] is True
    assert d["timing"]["compute_us"]["max"] == 20.0 and d["timing"]["wake_latency_us"]["p99"] == 5.0


@pytest.mark.parametrize("fs", [1000.0, 5000.0])          # rows kept as they come / as 1 ms block means
def test_the_spectrum_sorts_by_isolation_and_skips_the_settling(monkeypatch, fs):
    monkeypatch.setattr(feed_mod, "SPECTRUM_EVERY_S", 0.0)
    f = Feed(_layout(fs))
    t = np.arange(int(8 * fs)) / fs
    off = np.sin(2 * np.pi * 10 * t)[:, None] * np.ones(4)          # 1 m/s^2 at 10 Hz, isolation off
    on = 0.1 * np.sin(2 * np.pi * 10 * t)[:, None] * np.ones(4)     # ten times less with it on
    for k in range(0, len(t), 333):                                  # in the server's uneven chunks
        f.add(_rows(f, t[k:k + 333], iso=0.0, accel=off[k:k + 333]))
    for k in range(0, len(t), 333):
        f.add(_rows(f, t[k:k + 333] + 8, iso=1.0, accel=on[k:k + 333]))
    sp = f.take_delta()["spectrum"]
    assert sp["classes"]["off"]["seconds"] == pytest.approx(8 - feed_mod.SETTLE_S)
    assert sp["classes"]["on"]["seconds"] == pytest.approx(8 - feed_mod.SETTLE_S)
    freqs = np.array(sp["f_hz"])
    k = int(np.argmin(abs(freqs - 10)))
    ratio = sp["classes"]["off"]["asd"][k] / sp["classes"]["on"]["asd"][k]
    assert ratio == pytest.approx(10, rel=0.02)
    assert sp["rms_mps2"]["off"] == pytest.approx(1 / math.sqrt(2), rel=0.05)     # no glitch between chunks
    # a unit sine's power 1/2 over the Hann window's noise bandwidth, 1.5 bins of 1/SEGMENT_S Hz
    assert sp["classes"]["off"]["asd"][k] == pytest.approx(math.sqrt(0.5 / (1.5 / feed_mod.SEGMENT_S)), rel=0.02)
    assert freqs[0] >= feed_mod.F_MIN_HZ and freqs[-1] <= feed_mod.F_MAX_HZ
    vc = f.vc                                   # 1 m/s^2 at 10 Hz: 11.3 mm/s rms velocity in the 10 Hz band
    band = vc["band_hz"].index(10.0)
    assert vc["velocity_um_s"]["off"][band] == pytest.approx(1e6 / (2 * math.pi * 10) / math.sqrt(2), rel=0.05)
    assert vc["velocity_um_s"]["on"][band] == pytest.approx(0.1 * vc["velocity_um_s"]["off"][band], rel=0.02)
    assert vc["vc_class"]["off"] == "above workshop (ISO)" and vc["criteria"]["VC-A"][band] == 50.0


def test_a_fault_period_is_in_neither_spectrum(monkeypatch):
    monkeypatch.setattr(feed_mod, "SPECTRUM_EVERY_S", 0.0)
    f = Feed(_layout())
    f.add(_rows(f, np.arange(3000) / 1000, state=State.FAULT))
    sp = f.take_delta()["spectrum"]
    assert sp["classes"]["on"]["seconds"] == 0 and sp["classes"]["off"]["seconds"] == 0


# ---- the command check -------------------------------------------------------------------------------------
def test_every_command_has_a_handler_and_well_formed_ones_pass():
    from rig.console.link import Console
    assert all(hasattr(Console, f"_cmd_{name}") for name in COMMANDS)
    assert check_command({"cmd": "isolation", "args": {"on": True}}) == ("isolation", {"on": True})
    assert check_command({"cmd": "chirp", "args": {"amplitude_V": 1, "f0_hz": 0.5, "f1_hz": 50, "duration_s": 10,
                                                   "mount": "rear_left"}})[1]["amplitude_V"] == 1.0


@given(st.one_of(st.none(), st.integers(), st.text(), st.lists(st.integers()),
                 st.dictionaries(st.text(max_size=5), st.one_of(st.none(), st.booleans(), st.floats(), st.text()))))
def test_anything_else_is_one_line_never_an_exception(msg):
    r = check_command(msg)
    assert isinstance(r, str) and "\n" not in r or isinstance(r, tuple)


def test_event_numbers_let_a_page_skip_what_a_full_state_already_gave():
    """The server numbers its events: the delta after a snapshot repeats the pending ones with the same
    numbers (the page skips numbers it has shown)."""
    st = ConsoleState(control=None)
    sent = []
    st.clients.add(type("Page", (), {"put": lambda self, text: sent.append(text)})())
    st.add_events([{"t_s": None, "wall": 1.0, "text": "lifecycle: configure -> INACTIVE", "level": "INFO"}])
    snap = st.snapshot()
    st.tick()
    st.add_events([{"t_s": None, "wall": 2.0, "text": "lifecycle: activate -> ACTIVE", "level": "INFO"}])
    st.tick()
    deltas = [json.loads(x) for x in sent]
    shown = [e["seq"] for e in snap["events"]]
    later = [e["seq"] for d in deltas for e in d.get("events", ())]
    assert shown == [1] and later == [1, 2]
    new = [n for n in later if n > max(shown)]
    assert new == [2]
