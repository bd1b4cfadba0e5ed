"""Batches of recordings as a user runs them (issue 30): `rig diagnose FOLDER --out DIR` killed half-way and run
again (it resumes), its summary against one-by-one `rig diagnose`, the trend that names a delay growing over the
recordings' dates, a recording that fails as one line; `rig identify` and `rig prove` on a real Dask LocalCluster
(127.0.0.1, two worker processes) against the local pool: the same summary, the same proof. The recordings are
made by the simulated plant (short chirps, so that the batch takes a minute)."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys

import pytest

from rig.commands.bench_batch import make_recordings, what
from sim_backend.linear import IDENTIFIED
from tests.rig.support import Command

RIG = [sys.executable, "-m", "rig.cli"]
N_RECORDINGS = 4
DELAY_S = 0.003                   # the concealed delay grows from 0 to this over the recordings
DURATION_S = 12.0                 # the shortest chirp the diagnosis makes a claim on (>= 5 s of excitation)


def _rig(*args, timeout=600):
    return subprocess.run(RIG + [str(a) for a in args], capture_output=True, text=True, timeout=timeout)


@pytest.fixture(scope="module")
def recordings(tmp_path_factory):
    folder = tmp_path_factory.mktemp("batch") / "runs"
    make_recordings(folder, N_RECORDINGS, DURATION_S, delay_s=DELAY_S)
    (folder / "broken.h5").write_bytes(b"\x89HDF\r\n\x1a\n not really")       # a file cut short in the copy
    return folder


def _summary(out):
    return json.loads((out / "summary.json").read_text())["rows"]


def test_diagnose_batch_killed_resumes_and_matches_one_by_one(recordings, tmp_path):
    out = tmp_path / "out"
    first = Command("diagnose", str(recordings), "--out", str(out), "--workers", "1")
    try:
        assert first.wait_for("1/5", timeout=300), first.text      # one recording done: kill the batch
    finally:
        os.kill(first.proc.pid, signal.SIGKILL)
        first.proc.wait()
    done_before = sum(json.loads(m.read_text())["row"]["status"] == "ok" for m in out.glob("*/batch_row.json"))
    assert 1 <= done_before < N_RECORDINGS

    res = _rig("diagnose", recordings, "--out", out)             # the same command again, default workers
    assert "Traceback" not in res.stderr + res.stdout
    assert res.returncode == 1, res.stderr[-2000:]                 # the broken file failed; the batch went on
    assert res.stderr.strip().splitlines()[-1].startswith(
        f"rig diagnose: {N_RECORDINGS + 1 - done_before} done now, {done_before} done before (resumed), 1 failed")
    rows = {r["recording"]: r for r in _summary(out)}
    assert list(rows) == ["broken", *(f"day{i:03d}" for i in range(N_RECORDINGS))]     # the folder's order
    assert [r["status"] for r in rows.values()] == ["failed"] + ["ok"] * N_RECORDINGS

    broken = rows["broken"]
    assert broken["error"].startswith(str(recordings / "broken.h5")) and "\n" not in broken["error"]
    assert "| broken |" in (out / "summary.md").read_text() and "failed" in (out / "summary.md").read_text()

    # each recording its own folder, as `rig diagnose REC --out DIR` writes it
    for name in rows:
        if name != "broken":
            assert {"diagnosis.json", "fit.csv", "report.md", "frf.png"} <= {p.name for p in (out / name).iterdir()}
    # the summary's effects are diagnosis.json's, names and values exactly; the delay named where it is
    for name, r in rows.items():
        if name == "broken":
            continue
        doc = json.loads((out / name / "diagnosis.json").read_text())
        assert r["effects"] == {e["name"]: e["parameters"] for e in doc["effects"]}
        assert r["verdict"] == doc["verdict"]["status"]
    assert "transport_delay" not in rows["day000"]["effects"]
    assert rows["day003"]["effects"]["transport_delay"]["delay_s"] == pytest.approx(DELAY_S, rel=0.05)

    # one by one: the same recording alone gives the row the batch gave
    single = _rig("diagnose", recordings / "day002.h5", "--out", tmp_path / "single", "--json")
    assert single.returncode == 0, single.stderr[-2000:]
    doc = json.loads(single.stdout)
    assert rows["day002"]["effects"] == {e["name"]: e["parameters"] for e in doc["effects"]}
    assert rows["day002"]["verdict"] == doc["verdict"]["status"]

    # the trend names the delay, and only what changed
    line = [ln for ln in res.stdout.splitlines() if ln.startswith("trends over")][0]
    assert line.startswith(f"trends over {N_RECORDINGS} recordings: changed beyond the confidence interval: "
                           "transport_delay.delay_s"), line
    named = [q.strip().split(" ")[0] for q in line.split(": ", 2)[2].split(";")]
    assert named and all(q.startswith("transport_delay.") for q in named), line   # the delay, in its units
    assert (out / "trends.png").stat().st_size > 10_000

    # the same batch again: nothing left to do
    again = _rig("diagnose", recordings, "--out", out)
    assert again.stderr.strip().splitlines()[-1].startswith("rig diagnose: 1 done now, 4 done before")


def test_a_batch_with_other_options_is_refused_in_one_line(recordings, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "batch.json").write_text(json.dumps({"command": "diagnose", "options": {"seed": 0, "plant": None,
                                                                                    "config": None}}))
    res = _rig("diagnose", recordings, "--out", out, "--seed", "1")
    assert res.returncode == 2 and "Traceback" not in res.stderr
    assert res.stderr.strip() == (f"rig diagnose: error: --out {out}: holds a batch made with other options (seed "
                                  "differ): run it with the same options to resume, or give another folder (or "
                                  "--overwrite)")
    res = _rig("diagnose", recordings / "nothing*.h5", "--out", tmp_path / "o2")
    assert res.returncode == 2 and res.stderr.strip().endswith("nothing*.h5: no file matches")
    res = _rig("identify", recordings)
    assert res.returncode == 2 and "--out: a batch needs an output folder" in res.stderr
    res = _rig("identify", recordings, "--out", tmp_path / "o3", "--scheduler", "127.0.0.1:8786")
    assert res.returncode == 2 and "expected tcp://HOST:PORT" in res.stderr


def test_identify_and_prove_on_a_dask_local_cluster_equal_the_local_pool(recordings, tmp_path):
    from distributed import LocalCluster

    picked = tmp_path / "runs"
    picked.mkdir()
    for i in (0, 3):
        os.symlink(recordings / f"day{i:03d}.h5", picked / f"day{i:03d}.h5")
    local = _rig("identify", picked, "--out", tmp_path / "local", "--workers", "2", "--json")
    assert local.returncode == 0, local.stderr[-2000:]
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address=None) as cluster:
        address = cluster.scheduler_address
        assert address.startswith("tcp://127.0.0.1:")
        dask = _rig("identify", picked, "--out", tmp_path / "dask", "--scheduler", address, "--json")
        proof = _rig("prove", "--n", "1", "--duration", "12", "--seed", "3", "--scheduler", address, "--json")
    assert proof.returncode == 0, proof.stderr[-2000:]
    assert f"on the Dask cluster at {address}" in proof.stderr
    local_proof = _rig("prove", "--n", "1", "--duration", "12", "--seed", "3", "--json")
    assert local_proof.returncode == 0, local_proof.stderr[-2000:]
    graded = [[(r["case"], r["named"], r["named_parameters"], r["verdict"], r["nrmse"])
               for r in json.loads(out)["rows"]] for out in (proof.stdout, local_proof.stdout)]
    assert graded[0] == graded[1] and len(graded[0]) == 1
    assert dask.returncode == 0, dask.stderr[-2000:]
    assert f"on the Dask cluster at {address}" in dask.stderr
    a, b = json.loads(local.stdout)["rows"], json.loads(dask.stdout)["rows"]
    assert what(a) == what(b) and len(a) == 2
    assert {r["worker"] for r in b} != {r["worker"] for r in a}       # it did run elsewhere
    assert all(set(r["parameters"]) == set(IDENTIFIED) and r["std"] for r in b)
    assert (tmp_path / "dask" / "summary.csv").read_text().splitlines()[0] == \
        (tmp_path / "local" / "summary.csv").read_text().splitlines()[0]
    for name in ("day000", "day003"):
        written = {p.name for p in (tmp_path / "dask" / name).iterdir()}
        assert {"identified.md", "identify.json", "fig3_bode.png"} <= written
