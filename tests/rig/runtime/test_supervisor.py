"""The do-no-harm supervisor (rig/runtime/supervisor.py): on conversions published into a real exchange block it
trips when isolation makes the table worse than isolation off by more than the margin (the whole table or one
mount), names the mount, and lets isolation that helps, or harms less than the margin, be; in a run (the sim
backend at the HIL design's 500 Hz, SimClock) one mount's feedback of the wrong sign is switched off within 5 s,
said once, recorded as an event and in the recording's attributes, and isolation stays off; the right design
runs through untouched; a run with no reference says so."""
from __future__ import annotations

import dataclasses
import logging
import math

import numpy as np
import pytest
import scipy.signal

from controllers.isolation import IsolationController, params_from_config
from rig.config import MOUNTS, layout_mounts, load_config
from rig.runtime.clock import SimClock
from rig.runtime.exchange import Block, Layout, put_conversion
from rig.runtime.recorder import read_recording
from rig.runtime.session import Session
from rig.runtime.supervisor import HarmSupervisor
from tests.paths import REPO

RATE = 500.0
HIL = load_config(REPO / "drivers" / "devicemaps" / "hil.toml")
SUP = HIL.supervisor
ON_AT_S = 4.0                 # isolation on (after 4 s off: the reference)


def _floor(seconds: float, seed: int = 1) -> np.ndarray:
    """Broadband floor acceleration at four mounts (white noise through 1-200 Hz), as the module converts it."""
    rng = np.random.default_rng(seed)
    sos = scipy.signal.butter(2, [1.0, 200.0], btype="bandpass", fs=RATE, output="sos")
    return scipy.signal.sosfilt(sos, rng.standard_normal((int(seconds * RATE), 4)), axis=0) * 1e-2


def _feed(gains_on, seconds: float = 10.0):
    """Table = floor (isolation off) then gains x floor (isolating from ON_AT_S), through a real block;
    the supervisor looking every tenth of a second. (trip time s or None, the supervisor)."""
    block = Block.local(Layout(4, 4))
    sup = HarmSupervisor(SUP, 4, 4, RATE, MOUNTS)
    every = sup.look_periods(block.io)
    floor = _floor(seconds)
    ts = np.zeros(4)
    for k, fl in enumerate(floor):
        t = k / RATE
        table = fl * (np.asarray(gains_on) if t >= ON_AT_S else 1.0)
        put_conversion(block.io, float(k), ts, np.concatenate([table, fl]))
        if (k + 1) % every == 0 and sup.look(block.io, t >= ON_AT_S, t):
            return t, sup
    return None, sup


@pytest.mark.parametrize("gains, mount", [((2.0,) * 4, None), ((2.5, 0.5, 0.5, 0.5), "front_left"),
                                          ((0.5, 0.5, 0.5, 2.0), "rear_right")])
def test_isolation_that_makes_the_table_worse_trips_within_5_s_naming_the_mount(gains, mount):
    t, sup = _feed(gains)
    assert t is not None and t - ON_AT_S < 5.0, sup.summary()
    assert sup.harm.startswith("do-no-harm: isolation made the table worse than isolation off (table/floor)")
    if mount:
        assert f": {mount} +" in sup.harm
    assert sup.summary()["tripped"] and sup.summary()["conversions_skipped"] == 0


@pytest.mark.parametrize("gains", [(0.3,) * 4, (1.0,) * 4, (1.2,) * 4])
def test_isolation_that_helps_or_harms_less_than_the_margin_is_let_be(gains):
    t, sup = _feed(gains)
    assert t is None and sup.harm is None
    want = 20 * math.log10(gains[0])
    assert sup.worst_db == pytest.approx(want, abs=0.3)     # it measured what the gains did


def _ctrls(trim0: float):
    def build(cfg, dt):
        return [IsolationController(dataclasses.replace(params_from_config(cfg, i), gain_trim=trim0 if i == 0 else 1.0),
                                    dt, name=m) for i, m in enumerate(layout_mounts(cfg))]
    return build


def _run(tmp_path, trim0: float, cfg=HIL, seconds: float = 10.0, isolation=False, script=((ON_AT_S, "on"),)):
    path = tmp_path / "run.h5"
    with Session(cfg, "sim", clock=SimClock(), rate_hz=RATE, controllers=_ctrls(trim0), isolation=isolation,
                 script=list(script), record=path) as s:
        reason = s.run(seconds=seconds, activate_after_s=0.05)
        lp = s.loop
    return reason, lp, path


def test_a_mount_with_feedback_of_the_wrong_sign_is_switched_off_and_recorded(tmp_path, caplog):
    caplog.set_level(logging.WARNING, logger="rig.loop")
    reason, lp, path = _run(tmp_path, -1.0, script=((ON_AT_S, "on"), (8.0, "off"), (8.5, "on")))
    assert reason == "time" and lp.lc.fault_reason is None
    harm = lp.harm
    assert harm and ": front_left +" in harm and lp.isolation is False       # switched off, and held off at 8.5 s
    said = [r.getMessage() for r in caplog.records if r.getMessage().startswith("do-no-harm")]
    assert said == [harm]                                                       # one line, once
    t_trip = float(harm.rsplit("at t = ", 1)[1].split(" s")[0])
    assert t_trip - ON_AT_S < 5.0
    rec = read_recording(path)
    events = [text for _, text in rec["events"]]
    assert harm in events and "isolation off" in events[events.index(harm):]
    assert "isolation on refused: held off by the do-no-harm supervisor" in events
    assert rec["attrs"]["harm"] == harm
    on = np.asarray(rec["isolation_on"]).ravel()
    t = np.asarray(rec["time_s"]).ravel()
    assert on[t > t_trip + 0.2].max() == 0 and on[(t > ON_AT_S + 0.1) & (t < t_trip)].min() == 1   # off from the trip


def test_the_right_design_runs_through_untouched(tmp_path):
    reason, lp, _ = _run(tmp_path, 1.0)
    sup = lp.supervisor.summary()
    assert reason == "time" and lp.harm is None and lp.isolation is True
    assert sup["reference"] == "isolation off (table/floor)" and sup["table_vs_reference_db"] < -3.0


def test_without_floor_accelerometers_or_isolation_off_it_says_it_cannot_judge(tmp_path, caplog):
    caplog.set_level(logging.WARNING, logger="rig.loop")
    cfg = HIL.replace(sensors=dataclasses.replace(HIL.sensors, floor_accel=False))
    reason, lp, _ = _run(tmp_path, 1.0, cfg=cfg, seconds=3.0, isolation=True, script=())
    said = [r.getMessage() for r in caplog.records if r.getMessage().startswith("do-no-harm: no reference")]
    assert len(said) == 1 and lp.harm is None and lp.supervisor.summary()["reference"] == "none"


def test_the_compiled_filter_is_scipys_sosfilt():
    """filter_squares against scipy.signal.sosfilt (the reference), carried across calls by its state."""
    from rig.runtime.supervisor import band_filter, filter_squares
    sos = band_filter((1.0, 100.0), RATE, 2)
    x = np.random.default_rng(3).standard_normal((700, 8))
    want = scipy.signal.sosfilt(sos, x, axis=0)
    zi, got = np.zeros((sos.shape[0], 2, 8)), np.zeros(8)
    total = np.zeros(8)
    for part in (x[:250], x[250:251], x[251:]):
        filter_squares(sos, zi, np.ascontiguousarray(part), got)
        total += got
    assert np.allclose(total, (want ** 2).sum(axis=0), rtol=1e-9, atol=0)


@pytest.mark.parametrize("floor", [True, False])
def test_the_running_window_and_the_compiled_comparison_match_the_direct_sums(floor):
    """The supervisor keeps each kind's window as running sums and compares in compiled code (its look runs in
    the loop's slack): the same dB as summing the newest window_s of looks afresh and taking the ratios."""
    from rig.runtime.supervisor import ISOLATING, PASSIVE, worse_db
    n = 4
    sup = HarmSupervisor(SUP, n, n if floor else 0, RATE, MOUNTS)
    rng = np.random.default_rng(3)
    kept = {PASSIVE: [], ISOLATING: []}
    for k in range(300):
        kind = PASSIVE if k < 150 else ISOLATING
        sq, count = rng.uniform(0.5, 2.0, sup.width), int(rng.integers(5, 40))
        if kind == ISOLATING:
            sq[:n] *= 0.1                            # the table's, not the floor's
        sup._add(kind, sq, count)
        kept[kind].append((sq, count))
        looks = kept[kind]
        while len(looks) > 1 and sum(c for _, c in looks[1:]) >= sup.window_n:   # the newest window_s
            del looks[0]
        want = sum(s for s, _ in looks) / sum(c for _, c in looks)
        if sum(c for _, c in looks) >= sup.window_n:
            assert np.allclose(sup._window(kind), want, rtol=1e-12), k
        else:
            assert sup._window(kind) is None
    on, off = sup._window(ISOLATING), sup._window(PASSIVE)
    out = np.zeros(n + 1)
    worse_db(on, off, n, floor, out)

    def ratio(ms):
        tab = ms[:n]
        return np.append(tab / ms[n:], tab.sum() / ms[n:].sum()) if floor else np.append(tab, tab.sum())
    assert np.allclose(out, 10 * np.log10(ratio(on) / ratio(off)), atol=1e-9)
    assert out[n] < -5                               # a tenth of the power: isolating helps
    if floor:                                        # no reference: against the floor itself
        worse_db(on, on[:0], n, True, out)
        assert np.allclose(out, 10 * np.log10(ratio(on)), atol=1e-9)
