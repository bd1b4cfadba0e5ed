"""The batch's rules that need no analysis: which quantity changed beyond its confidence interval over the
recordings' dates (rig/batch/trends.py), and the recordings a batch is given and their folders
(rig/batch/inputs.py)."""
from __future__ import annotations

import numpy as np
import pytest

from rig.batch import inputs, trends
from rig.errors import RigError


def _rows(n, *, delay_to=0.003, k_q_std=None, k_q_drift=0.0, seed=0):
    rng = np.random.default_rng(seed)
    rows = []
    for i in range(n):
        d = delay_to * i / (n - 1)
        k_q = 1.94e-6 * (1 + k_q_drift * i / (n - 1) + 2e-4 * rng.standard_normal())
        rows.append({"recording": f"r{i}", "status": "ok", "date_utc": f"2026-11-{i + 1:02d}T03:00:00+00:00",
                     "effects": {"transport_delay": {"delay_s": d}} if d > 0.0005 else {},
                     "parameters": {"K_Q": k_q}, "std": {"K_Q": k_q_std} if k_q_std else {},
                     "units": {"K_Q": "m^3/s/mA"}})
    return rows


def test_a_delay_that_appears_and_grows_is_named_and_a_steady_parameter_is_not(tmp_path):
    rows = _rows(20)
    rows.insert(3, {"recording": "bad", "status": "failed", "error": "x", "date_utc": "", "effects": {},
                    "parameters": {}, "std": {}, "units": {}})
    out = trends.write(tmp_path, rows)
    assert out["changed"] == ["transport_delay.delay_s"]
    assert out["line"].startswith("trends over 20 recordings: changed beyond the confidence interval: "
                                  "transport_delay.delay_s")
    assert (tmp_path / "trends.png").stat().st_size > 5000
    assert (tmp_path / "trends.csv").read_text().splitlines()[1].startswith("transport_delay.delay_s,")


def test_a_drift_within_the_recordings_own_sigma_is_not_a_change_and_beyond_it_is():
    _, _, judged = trends.analyse(_rows(10, delay_to=0.0, k_q_drift=0.02, k_q_std=0.05 * 1.94e-6))
    assert not judged["K_Q"]["changed"]                       # 2 % drift, 5 % 1-sigma each
    _, _, judged = trends.analyse(_rows(10, delay_to=0.0, k_q_drift=0.2, k_q_std=0.01 * 1.94e-6))
    assert judged["K_Q"]["changed"] and judged["K_Q"]["last"] > judged["K_Q"]["first"]


def test_too_few_recordings_make_no_trend(tmp_path):
    assert trends.write(tmp_path, _rows(2)) == {} and not (tmp_path / "trends.png").exists()


def test_inputs_folder_glob_and_names(tmp_path):
    for sub in ("mar", "apr"):
        (tmp_path / sub).mkdir()
        (tmp_path / sub / "day1.h5").write_bytes(b"")
        (tmp_path / sub / "notes.txt.bak").write_bytes(b"")
    paths = inputs.expand([str(tmp_path / "*" / "day1.h5")])
    assert [p.parent.name for p in paths] == ["apr", "mar"]
    assert inputs.output_names(paths) == ["apr__day1", "mar__day1"]
    assert inputs.expand([tmp_path / "mar"]) == [tmp_path / "mar" / "day1.h5"]
    assert inputs.is_batch([tmp_path / "mar"]) and not inputs.is_batch([tmp_path / "mar" / "day1.h5"])
    with pytest.raises(RigError, match="no recording in the folder"):
        inputs.expand([tmp_path])
    with pytest.raises(RigError, match="nope.h5: no such file or folder"):
        inputs.expand([tmp_path / "nope.h5"])
    with pytest.raises(RigError, match="every file given is inside the output folder"):
        inputs.expand([tmp_path / "mar"], exclude=tmp_path)
