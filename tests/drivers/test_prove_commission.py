"""`rig prove --commission` (issue 27): the draws of wiring faults, and one blind case end to end."""
from __future__ import annotations

import json
import random
import subprocess
import sys

import pytest
from hypothesis import given, settings, strategies as st

from rig.commands.prove_commission import (FAULTS, FLOOR_AI, REFUSED, Wiring, _figures, _floor_fitted, case_config,
                                          draw, fault_kinds, parse_kinds, per_fault, place, run_single, single_cases,
                                          single_markdown, single_summary, single_wirings)
from rig.config import MOUNTS
from rig.errors import RigError
from tests.paths import REPO


@settings(max_examples=200, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.sampled_from([2, 3]), floor=st.booleans())
def test_a_draw_puts_each_fault_on_mounts_of_its_own(seed, n, floor):
    """Two or three faults, on distinct mounts (a swap takes two), each named by one (channel, kind) per mount it
    takes; the wiring differs from a rig wired right exactly on those mounts, on the channels of the fault's kind:
    a floor accelerometer's fault on AI ch4-7 only (and only with floor accelerometers fitted), a table
    accelerometer's on AI ch0-3 only."""
    w, said, expected = draw(random.Random(seed), n, floor)
    assert len(said) == n
    mounts = [c.split(":")[1] for c, _ in expected]
    assert len(mounts) == len(set(mounts)) <= len(MOUNTS)
    right = Wiring()
    changed = set()
    for key, vals in vars(w).items():
        for i, (a, b) in enumerate(zip(vals, getattr(right, key))):
            if a != b:
                kind = ("floor" if i >= FLOOR_AI else "accel") if key.startswith("ai_") else \
                    "stroke" if key.startswith("dt_") else "valve"
                changed.add((kind, MOUNTS[i % len(MOUNTS)]))
    assert changed == {tuple(c.split(":")) for c, _ in expected}, (said, vars(w))
    assert floor or not any(c.startswith("floor:") for c, _ in expected), said


def test_floor_faults_are_drawn_only_where_floor_accelerometers_are_fitted(tmp_path):
    """Without floor accelerometers ([sensors] floor_accel = false) no floor fault is drawn and the draws are the
    ones of the table without them (a seed gives the cases it gave before the floor's faults existed); with them,
    every floor fault comes up. The proof reads the flag as the rig loads the configuration."""
    table = [k for k in FAULTS if FAULTS[k][2] != "floor"]
    assert fault_kinds(False) == table and fault_kinds(True) == list(FAULTS)
    assert {k for k in FAULTS if FAULTS[k][2] == "floor"} == {"floor_swap", "floor_sign", "floor_g_range",
                                                              "floor_offset", "floor_dead", "floor_noisy"}
    seen = {True: set(), False: set()}
    for floor in (True, False):
        rng = random.Random(5)
        for _ in range(400):
            seen[floor] |= {s.split("(")[0] for s in draw(rng, 3, floor)[1]}
    assert seen == {True: set(FAULTS), False: set(table)}
    # the same seed, the same draws as a table that never had the floor's faults
    rng_a, rng_b = random.Random(1), random.Random(1)
    kinds = sorted(table)
    for i in range(40):
        n = 2 + i % 2
        w, said, _ = draw(rng_a, n, False)
        while True:
            names = [rng_b.choice(kinds) for _ in range(n)]
            if sum(FAULTS[k][0] for k in names) <= len(MOUNTS):
                break
        free = list(range(len(MOUNTS)))
        rng_b.shuffle(free)
        expect = []
        for k in names:
            ms, free = sorted(free[:FAULTS[k][0]]), free[FAULTS[k][0]:]
            expect.append(place(Wiring(), k, ms, rng_b, set()))
        assert said == expect
    hil = (REPO / "drivers" / "devicemaps" / "hil.toml").read_text()
    assert "floor_accel = true" in hil and _floor_fitted(tmp_path, hil)
    assert not _floor_fitted(tmp_path, hil.replace("floor_accel = true", "floor_accel = false"))
    # --single with a floor fault on a rig without floor accelerometers: one line, before anything runs
    cfg = tmp_path / "nofloor.toml"
    cfg.write_text(hil.replace("floor_accel = true", "floor_accel = false"))
    args = type("A", (), dict(kinds="accel_sign,floor_sign", config=str(cfg), out=tmp_path / "out", seed=1))()
    with pytest.raises(RigError, match="--kinds: floor_sign: the configuration has no floor accelerometers"):
        run_single(args)


def test_a_floor_fault_is_wired_on_its_floor_channel_and_named_there():
    """Each floor fault of the table on AI ch4-7 of its mount(s), with the sizes the wiring doc gives (inverted,
    a g range, an offset, dead (at a constant, or with the module's own noise), noisy, a swap of two floor
    channels), and named on the floor channel: floor:<mount>."""
    doc = (REPO / "drivers" / "devicemaps" / "hil_wiring_faults.md").read_text()
    assert "AI ch4-7" in doc and "`[0, 1, 2, 3, 4, 5, 7, 6]`" in doc
    for seed in range(20):
        for k in [k for k in FAULTS if FAULTS[k][2] == "floor"]:
            ms = [2, 3] if FAULTS[k][0] == 2 else [1]
            w, exp = Wiring(), set()
            place(w, k, ms, random.Random(seed), exp)
            assert exp == {(f"floor:{MOUNTS[m]}", FAULTS[k][3]) for m in ms}
            assert w.ai_source[:4] == [0, 1, 2, 3] and w.ai_factor[:4] == [1.0] * 4
            assert w.ai_offset_mps2[:4] == [0.0] * 4 and w.ai_noise_mps2[:4] == [0.0] * 4
            ch = FLOOR_AI + ms[0]
            if k == "floor_swap":
                assert w.ai_source == [0, 1, 2, 3, 4, 5, 7, 6]
            elif k == "floor_sign":
                assert w.ai_factor[ch] == -1.0
            elif k == "floor_g_range":
                assert w.ai_factor[ch] == pytest.approx(0.10197, abs=1e-5)
            elif k == "floor_offset":
                assert w.ai_offset_mps2[ch] in (-0.5, 0.3, 0.8)
            elif k == "floor_dead":
                assert w.ai_factor[ch] == 0.0 and w.ai_noise_mps2[ch] in (0.0, 0.002)
            else:
                assert w.ai_noise_mps2[ch] in (0.02, 0.05)


def test_the_proof_counts_each_fault_of_the_table():
    """per_fault: for each fault drawn in a judged case, whether its own channels were named with its kind, and
    whether the whole case was right (an invented name elsewhere spoils the case, not the fault)."""
    rows = [{"faults": ["floor_swap(rear_left, rear_right)", "accel_sign(front_left)"], "right": False,
             "named": [["accel:front_left", "sign"], ["floor:rear_left", "swap"], ["floor:rear_right", "swap"],
                       ["stroke:front_right", "scale"]]},
            {"faults": ["floor_swap(front_left, front_right)", "valve_null(rear_left)"], "right": False,
             "named": [["floor:front_left", "swap"], ["valve:rear_left", "null"]]}]
    assert per_fault(rows) == {"accel_sign": {"drawn": 1, "named": 1, "case_right": 0},
                               "valve_null": {"drawn": 1, "named": 1, "case_right": 0},
                               "floor_swap": {"drawn": 2, "named": 1, "case_right": 0}}


def test_every_documented_fault_can_be_drawn():
    """Every fault kind of the table comes up in a few hundred draws, and its keys are in the wiring doc."""
    seen = set()
    rng = random.Random(1)
    for _ in range(400):
        seen |= {s.split("(")[0] for s in draw(rng, 3)[1]}
    assert seen == set(FAULTS)
    doc = (REPO / "drivers" / "devicemaps" / "hil_wiring_faults.md").read_text()
    assert all(f"`{k}`" in doc for k in vars(Wiring())), [k for k in vars(Wiring()) if f"`{k}`" not in doc]


@pytest.mark.hil
@pytest.mark.slow
def test_prove_commission_runs_as_a_user_runs_it(tmp_path):
    """`rig prove --commission --n 1 --clean 1`: two commissionings of the emulated rig, graded; the summary
    counts both, and the clean rig is not flagged."""
    out = tmp_path / "proof"
    r = subprocess.run([sys.executable, "-m", "rig.cli", "prove", "--commission", "--n", "1", "--clean", "1",
                        "--seed", "3", "--out", str(out), "--json"], capture_output=True, text=True, timeout=900,
                       cwd=REPO)
    assert r.returncode == 0, r.stderr[-3000:]
    s = json.loads(r.stdout)
    assert s["combinations"] == 1 and s["clean"] == 1 and s["clean_flagged"] == 0, (s, r.stderr[-3000:])
    rows = json.loads((out / "proof.json").read_text())["rows"]
    assert [x["what"] for x in rows] == ["clean", "faults"] and rows[1]["expected"]
    assert s["peak_stroke_pct_of_limit_max"] < 50.0
    assert "| case | faults drawn |" in (out / "proof.md").read_text()


def test_the_single_faults_take_every_kind_of_the_table_and_every_mount():
    """`--single`'s cases: every fault of the table once, the mounts turning so that each comes up (a swap on its
    mount and the next); --all-mounts every fault on every mount; --kinds a subset; each case wires exactly its
    fault, and the channels it should be named on are its mounts'."""
    doc = (REPO / "drivers" / "devicemaps" / "hil_wiring_faults.md").read_text()
    kinds_named = {FAULTS[k][3] for k in FAULTS}
    assert kinds_named == {"swap", "sign", "scale", "offset", "dead", "noisy", "null", "gain"}
    cases = single_cases()
    assert [k for k, _ in cases] == list(FAULTS)
    assert {MOUNTS[m] for _, ms in cases for m in ms} == set(MOUNTS)
    for k, ms in cases:
        assert len(ms) == FAULTS[k][0] and len(set(ms)) == len(ms)
        w, exp = Wiring(), set()
        said = place(w, k, ms, random.Random(0), exp)
        assert exp == {(f"{FAULTS[k][2]}:{MOUNTS[m]}", FAULTS[k][3]) for m in ms}, said
        changed = {key for key, v in vars(w).items() if v != getattr(Wiring(), key)}
        assert changed and all(f"`{key}`" in doc for key in changed), (k, changed)
    every = single_cases(all_mounts=True)
    assert len(every) == 4 * len(FAULTS)
    assert all({tuple(ms) for k2, ms in every if k2 == k} and
               {m for k2, ms in every if k2 == k for m in ms} == set(range(4)) for k in FAULTS)
    assert single_cases(["valve_null", "accel_sign"]) == [("accel_sign", [1]), ("valve_null", [0])]
    whole = single_wirings(random.Random(1))
    some = single_wirings(random.Random(1), ["accel_offset", "stroke_range"])
    assert [(k, ms, vars(w), said) for k, ms, w, said, _ in some] == \
        [(k, ms, vars(w), said) for k, ms, w, said, _ in whole if k in ("accel_offset", "stroke_range")]
    assert parse_kinds(None) is None and parse_kinds("accel_sign, valve_gain") == ["accel_sign", "valve_gain"]
    with pytest.raises(RigError, match="--kinds: expected fault names of .*got accel_upside_down"):
        parse_kinds("accel_sign,accel_upside_down")
    assert {k for k in FAULTS if FAULTS[k][3] in REFUSED} == {"accel_dead", "accel_noisy", "stroke_dead",
                                                               "stroke_noisy", "floor_dead", "floor_noisy"}


def test_a_case_config_carries_its_wiring_and_its_calibration(tmp_path):
    """The faulty rig's configuration (hil.toml with the case's [hil] keys) loads as the rig loads it; with its
    calibration, [drivers] calibration names that commissioning.toml, added to a [drivers] section or made."""
    from rig.config import load_config
    base = (REPO / "drivers" / "devicemaps" / "hil.toml").read_text()
    w, exp = Wiring(), set()
    place(w, "valve_nodes_swapped", [1, 2], random.Random(0), exp)
    cal = tmp_path / "case" / "commissioning.toml"
    for text in (base, base + "\n[drivers]\nstale_s = 0.1\n"):
        plain, calibrated = tmp_path / "plain.toml", tmp_path / "cal.toml"
        plain.write_text(case_config(text, w))
        calibrated.write_text(case_config(text, w, cal))
        assert load_config(plain).hil.valve_node_id == (1, 3, 2, 4)
        assert load_config(plain).drivers.calibration == ""
        assert load_config(calibrated).drivers.calibration == str(cal.resolve())


def test_the_single_summary_measures_the_clean_rigs_spread():
    """The summary's figures come from the rows: each case's difference calibrated - wired right, the clean runs'
    spread over the run and between a case's two clean runs; a run that did not finish clean is left out."""
    def row(case, cal, clean, err=""):
        runs = [dict(rig="calibrated", feedback_db=x, feedforward_db=x + 5, error="") for x in cal] + \
               [dict(rig="clean", feedback_db=x, feedforward_db=x + 5, error=err if j else "")
                for j, x in enumerate(clean)]
        for r in runs:
            r["feedback_vs_lockstep_db"] = r["feedback_db"] - 8.0
        fb, ff = _figures(runs, "feedback_db"), _figures(runs, "feedforward_db")
        return {"case": case, "named_right": True, "verdict_right": True, "verdict_expected": "corrected",
                "error": "", "commission_stopped": [], "hil_stopped": [], "hil": runs, "feedback_db": fb,
                "feedforward_db": ff,
                "feedback_vs_lockstep_db": _figures(runs, "feedback_vs_lockstep_db")}
    rows = [row(0, [8.0, 8.4], [8.5, 8.1]), row(1, [6.0, 6.2], [8.0, 7.0], err="exit 1")]
    assert rows[0]["feedback_db"]["difference"] == -0.1 and rows[1]["feedback_db"]["clean"] == [8.0]
    s = single_summary(rows, (1, 2, 3), (4, 5, 6))
    assert s["feedback_db"]["within_1db"] == 1 and s["feedback_db"]["judged"] == 2
    assert s["feedback_db"]["clean_runs"]["n"] == 3 and s["feedback_db"]["clean_runs"]["max"] == 8.5
    assert s["feedback_db"]["clean_pair_abs_difference"] == {"n": 1, "min": 0.4, "max": 0.4, "mean": 0.4,
                                                             "sd": None}
    assert s["feedforward_db"]["difference"]["min"] == -1.9
    assert s["feedback_db"]["clean_successive_abs_difference"] == {"n": 2, "min": 0.1, "max": 0.4, "mean": 0.25,
                                                                   "sd": 0.21}
    assert s["feedback_vs_lockstep_db"]["difference"]["max"] == -0.1
    # judged on the same floor: the calibrated runs against their twins (0.0, 0.4 and -2.0, -1.8 dB)
    assert s["feedback_vs_lockstep_db"]["same_floor"]["within_1db"] == 1
    assert s["feedback_vs_lockstep_db"]["same_floor"]["calibrated_vs_twin"]["min"] == -1.9
    assert "on the same stretch of floor** (the calibrated run through the drivers against its lockstep twin, the " \
           "rig wired right in simulated time), feedback: 1 of 2 (-1.9 to 0.2 dB" in single_markdown({"summary": s, "rows": [], "command": "c", "seed": 0, "date_utc": "d",
                                        "repeats": 2, "hil_seconds": None})


@pytest.mark.hil
@pytest.mark.slow
def test_prove_commission_single_runs_as_a_user_runs_it(tmp_path):
    """`rig prove --commission --single --kinds accel_sign --repeats 1 --retries 2` (a loaded host may stall a
    run): the front-right accelerometer inverted is named on its channel and corrected; `rig hil` runs with the
    calibration it wrote and on the rig wired right, and both figures and their difference are reported (the 1 dB
    is a measurement: docs/COMMISSIONING.md)."""
    out = tmp_path / "proof"
    r = subprocess.run([sys.executable, "-m", "rig.cli", "prove", "--commission", "--single", "--kinds", "accel_sign",
                        "--repeats", "1", "--hil-seconds", "6", "--retries", "2", "--out", str(out), "--json"],
                       capture_output=True, text=True, timeout=1800, cwd=REPO)
    assert r.returncode == 0, r.stderr[-3000:]
    proof = json.loads(r.stdout)
    assert proof == json.loads((out / "proof.json").read_text())
    (row,) = proof["rows"]
    assert row["fault"] == "accel_sign" and row["mounts"] == ["front_right"]
    assert row["hil_keys"] == {"ai_factor": [1.0, -1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0]}
    assert row["named"] == [["accel:front_right", "sign"]] and row["named_right"], (row, r.stderr[-3000:])
    assert row["verdicts"] == {"accel:front_right": "corrected"} and row["verdict_right"]
    assert sorted(h["rig"] for h in row["hil"]) == ["calibrated", "clean"]
    cal_cfg = (out / "case000-calibrated.toml").read_text()
    assert str((out / "case000" / "commissioning.toml").resolve()) in cal_cfg
    for who in ("calibrated", "clean"):
        assert (out / "case000" / f"hil-{who}-1.h5").exists()
    fb = row["feedback_db"]
    assert isinstance(fb["calibrated_mean"], float) and isinstance(fb["clean_mean"], float), (row["hil"],
                                                                                              r.stderr[-3000:])
    assert fb["difference"] == round(fb["calibrated_mean"] - fb["clean_mean"], 2)
    assert all(isinstance(h["feedback_vs_lockstep_db"], float) for h in row["hil"])
    assert row["within_1db"] in (True, False)
    assert "| fault (mounts) |" in (out / "proof.md").read_text() and "[1/1] accel_sign(front_right)" in r.stderr


def test_the_lockstep_twin_is_the_rig_wired_right_whatever_the_wiring_and_its_calibration(tmp_path):
    """The proof judges a calibrated rig against its run's lockstep twin as the rig wired right on the same stretch
    of floor: the simulated backend carries neither the [hil] wiring faults nor the calibration, so the twin of a
    miswired calibrated configuration is the twin of the rig wired right, to the last bit; and a different stretch
    of floor (the plant's steps before the loop) gives another figure (what made two `rig hil` runs differ)."""
    from rig.commands.hil import hil_config
    from rig.commands.hil_lockstep import lockstep
    from rig.config import load_config
    from rig.runtime.gate import ISOLATION_MODES
    text = (REPO / "drivers" / "devicemaps" / "hil.toml").read_text()
    w = Wiring()
    place(w, "valve_nodes_swapped", [2, 3], random.Random(0), set())
    cal = tmp_path / "commissioning.toml"
    cal.write_text('[valve.rear_left]\nmount = "rear_right"\n\n[valve.rear_right]\nmount = "rear_left"\n')
    (tmp_path / "clean.toml").write_text(case_config(text, Wiring()))
    (tmp_path / "cal.toml").write_text(case_config(text, w, cal))
    modes = ISOLATION_MODES[:2]
    twin = {k: [lockstep(hil_config(load_config(tmp_path / f"{k}.toml")), 1.0, modes, 0.1, 0.05, pre)["table_rms_m"]
                for pre in (0, 400)] for k in ("clean", "cal")}
    assert load_config(tmp_path / "cal.toml").hil.valve_node_id == (1, 2, 4, 3)
    assert twin["cal"] == twin["clean"]
    assert twin["clean"][0]["feedback"] != twin["clean"][1]["feedback"]
