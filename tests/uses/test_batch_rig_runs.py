"""A batch of the rig's own runs as a user runs it: `rig run --sim-time --record` twice on the simulated four-mount
rig (one clean, one hiding a valve delay at front_left) and a chirp of one actuator in the same folder, then
`rig diagnose FOLDER --out DIR` on a real Dask LocalCluster (127.0.0.1, two worker processes). Each run gets the
machine's diagnosis (the route `rig diagnose RUN.h5` takes for one file), the chirp its plant's."""
from __future__ import annotations

import json
import subprocess
import sys

import pytest

from rig.commands.bench_batch import make_recordings

pytestmark = pytest.mark.slow

RIG = [sys.executable, "-m", "rig.cli"]
SECONDS = 15                      # the shortest run tests/rig/diagnose/machine/test_diagnose_cli.py names a delay on
DELAY_S = 3.5e-4


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    d = tmp_path_factory.mktemp("rigbatch")
    runs = d / "runs"
    runs.mkdir()
    (d / "delay.toml").write_text(f"[rig_error]\nvalve_delay_s = [{DELAY_S}, 0.0, 0.0, 0.0]\n")
    procs = [subprocess.Popen(RIG + ["run", *cfg, "--sim-time", "--seconds", str(SECONDS), "--record",
                                     str(runs / f"{name}.h5"), "--quiet"], stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True)
             for name, cfg in (("clean", []), ("delay", ["--config", str(d / "delay.toml")]))]
    make_recordings(runs, 1, 12.0)                                  # day000.h5: a chirp of Table 1's actuator
    for p in procs:
        _, err = p.communicate(timeout=900)
        assert p.returncode == 0, err[-2000:]
    return d


def test_a_batch_gives_each_run_of_the_rig_the_machines_diagnosis(folder):
    from distributed import LocalCluster

    out = folder / "out"
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address=None) as cluster:
        res = subprocess.run(RIG + ["diagnose", str(folder / "runs"), "--out", str(out), "--scheduler",
                                    cluster.scheduler_address, "--json"], capture_output=True, text=True, timeout=1800)
    assert res.returncode == 0, res.stderr[-3000:]
    assert "Traceback" not in res.stderr
    rows = {r["recording"]: r for r in json.loads(res.stdout)["rows"]}
    assert set(rows) == {"clean", "delay", "day000"} and all(r["status"] == "ok" for r in rows.values())

    for name in ("clean", "delay"):                     # the machine's diagnosis, its files, as for one file
        doc = json.loads((out / name / "diagnosis.json").read_text())
        assert {"transmissibility", "margins", "floor_measured"} <= set(doc), name
        assert [m["mount"] for m in doc["margins"]] == ["front_left", "front_right", "rear_left", "rear_right"]
        assert "## rig design on the diagnosed rig" in (out / name / "report.md").read_text()
        assert (out / name / "replay.csv").is_file() and not (out / name / "fit.csv").exists()
        r = rows[name]
        assert r["verdict"] == doc["verdict"]
        assert r["effects"] == {f"{e['name']}[{e['location']}]": e["parameters"] for e in doc["effects"]}
        assert r["parameters"] == {k: pytest.approx(v, rel=1e-12) for k, v in doc["refit"].items()}
    assert rows["clean"]["effects"] == {}
    assert list(rows["delay"]["effects"]) == ["transport_delay[front_left]"]
    assert rows["delay"]["effects"]["transport_delay[front_left]"]["delay_s"] == pytest.approx(DELAY_S, rel=0.15)
    fit = rows["delay"]["figures"]
    assert fit["worst_mount_residual_diagnosed"] < fit["worst_mount_residual_model"]

    chirp = json.loads((out / "day000" / "diagnosis.json").read_text())      # the plant's diagnosis
    assert (out / "day000" / "fit.csv").is_file() and "transmissibility" not in chirp
    assert rows["day000"]["verdict"] == chirp["verdict"]["status"]

    table = (out / "summary.md").read_text()
    assert "| delay |" in table and "transport_delay[front_left]" in table
