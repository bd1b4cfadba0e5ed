"""`rig prove` end to end: a small blind set from a seed, and grading a folder of recordings with answers."""
from __future__ import annotations

import json
import subprocess
import sys

import pytest

from rig.diagnose import grading, prove
from rig.recordings.rigformat import save_recording_csv

RIG = [sys.executable, "-m", "rig.cli"]


def _rig(*args):
    return subprocess.run(RIG + [str(a) for a in args], capture_output=True, text=True, timeout=600)


@pytest.mark.slow
def test_prove_small_blind_set(tmp_path):
    out = tmp_path / "proof"
    res = _rig("prove", "--n", 3, "--seed", 7, "--duration", 10, "--workers", 2, "--out", out, "--json")
    assert res.returncode == 0, res.stderr
    doc = json.loads(res.stdout)                                   # only JSON on stdout
    assert "[3/3] diagnosed" in res.stderr                          # progress on stderr
    rows, cases = doc["rows"], doc["cases"]
    # the same seed draws the same cases, in order
    assert [c["effects"] for c in cases] == [c.effects for c in prove.draw_cases(3, 7, duration_s=10.0)]
    assert [r["case"] for r in rows] == [c["name"] for c in cases]
    assert sorted(len(c["effects"]) for c in cases) == [0, 1, 2]
    for r, c in zip(rows, cases):
        assert r["truth"] == sorted(c["effects"])
        assert r["right"] == (set(r["truth"]) == set(r["named"]))
        assert r["nrmse"]["nominal"] > 0 and r["nrmse"]["augmented"] <= r["nrmse"]["refit"] + 1e-9
    s = doc["score"]
    assert s["cases"] == 3 and s["right"] == sum(r["right"] for r in rows) and s["clean_cases"] == 1
    assert sum(sum(v.values()) for v in doc["confusion"].values()) >= 3
    assert (out / "proof.md").is_file() and json.loads((out / "proof.json").read_text())["score"] == s
    assert "| case | habits | truth | named |" in (out / "proof.md").read_text()


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    """Two 10 s recordings like ../shared/recordings: a moved-parameter nominal one and a 1.5 ms delay."""
    d = tmp_path_factory.mktemp("cases")
    answers = {}
    for name, effects, lin in (("q01_nominal.csv.gz", {}, {"K_L": 7.4e8, "zeta": 0.7}),
                               ("q02_delay.csv", {"transport_delay": {"delay_s": 0.0015}},
                                {"K_Q": 1.75e-6, "C": 2100.0})):
        case = prove.Case(name=name, effects=effects, linear=lin, duration_s=10.0, seed=len(answers) + 3)
        save_recording_csv(prove.simulate_case(case), d / name)
        answers[name] = {"sample_rate_hz": 1000, "duration_s": 10, "amplitude_V": 2.0, "effects": effects,
                         "true_linear_parameters": lin, "position_noise_m_rms": 2e-8}
    (d / "answers.json").write_text(json.dumps(answers))
    return d


def test_prove_grades_folder(folder, tmp_path):
    res = _rig("prove", "--cases", folder, "--workers", 1, "--out", tmp_path / "o")
    assert res.returncode == 0, res.stderr
    text = res.stdout
    assert "| q01_nominal.csv.gz | - | none | none | yes |" in text
    assert "| q02_delay.csv | - | transport_delay | transport_delay | yes | delay.delay" in text
    assert "confusion matrix" in text and "score: 2/2 named right" in text
    doc = json.loads((tmp_path / "o" / "proof.json").read_text())
    err = doc["rows"][1]["parameter_errors"]["transport_delay.delay_s"]
    assert err < grading.TARGETS["delay_s"]
    assert doc["score"]["delays"]["within"] == 1 and doc["score"]["invented_on_clean"] == 0


def test_prove_cases_folder_errors(tmp_path):
    res = _rig("prove", "--cases", tmp_path)                         # no answers.json
    assert res.returncode == 2 and "answers.json" in res.stderr and "Traceback" not in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1
    (tmp_path / "answers.json").write_text(json.dumps({"missing.csv": {"effects": {}}}))
    res = _rig("prove", "--cases", tmp_path)
    assert res.returncode == 2 and "'missing.csv'" in res.stderr and "not found" in res.stderr
    (tmp_path / "answers.json").write_text(json.dumps({"x.csv": {"effects": {"gremlins": {}}}}))
    res = _rig("prove", "--cases", tmp_path)
    assert res.returncode == 2 and "gremlins" in res.stderr


@pytest.mark.parametrize("argv, words", [
    (["--kinds", "accel_sign"], "--kinds: expected with --single"),
    (["--all-mounts"], "--all-mounts: expected with --single"),
    (["--repeats", "3"], "--repeats: expected with --single"),
    (["--clean", "5"], "--clean: expected with --commission"),
    (["--retries", "1"], "--retries: expected with --commission"),
    (["--keep", "kept"], "--keep: expected with --rig"),
])
def test_an_option_of_another_mode_is_refused_not_ignored(tmp_path, capsys, monkeypatch, argv, words):
    """Found by the abuse trial: `rig prove --kinds foo` ignored --kinds and ran the default 30 blind chirp cases
    (minutes); an option that belongs to another mode is one line, exit 2."""
    from rig.cli import main
    monkeypatch.chdir(tmp_path)
    assert main(["prove", "--n", "1", "--duration", "5", *argv]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0] == f"rig prove: error: {words} (see rig prove --help)", err
