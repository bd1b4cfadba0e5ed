"""The Python API as a notebook user meets it (issue 29): docs/PYTHON_API.md's example runs as written and
returns typed results; the CLI's rules hold (a feedback-only recording refused, a session that never
activates warns); `import rig` loads nothing heavy."""
from __future__ import annotations

import dataclasses
import math
import re
import subprocess
import sys
import time
import warnings
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
DOC = REPO / "docs" / "PYTHON_API.md"


def _blocks() -> list[str]:
    return re.findall(r"```python\n(.*?)```", DOC.read_text(), re.S)


def test_the_worked_example_runs_as_written_and_returns_typed_results(tmp_path, monkeypatch):
    from rig.api import IsolationComparison
    from rig.diagnose.results import Diagnosis, NamedEffect
    from rig.identify import IdentResult
    from rig.recordings.recording import Recording
    from sim_backend.linear import ActuatorParams

    blocks = _blocks()
    assert len(blocks) == 2, "docs/PYTHON_API.md: the example's two python blocks"
    monkeypatch.chdir(tmp_path)
    ns: dict = {}
    for code in blocks:
        exec(compile(code, str(DOC), "exec"), ns)
    assert isinstance(ns["rec"], Recording) and ns["rec"].n > 100_000
    assert isinstance(ns["ident"], IdentResult) and isinstance(ns["ident"].params, ActuatorParams)
    design = ActuatorParams()
    assert ns["ident"].params.w_nv == pytest.approx(design.w_nv, rel=0.05)      # Table 1: 524 rad/s
    assert isinstance(ns["diag"], Diagnosis)
    assert all(isinstance(e, NamedEffect) for e in ns["diag"].effects)
    assert ns["diag"].verdict.status == "explained" and not ns["diag"].effects   # the model's own actuator
    iso = ns["iso"]
    assert isinstance(iso, IsolationComparison)
    assert iso.reduction_db["feedback"] > 10 and iso.reduction_db["feedback_feedforward"] > iso.reduction_db["feedback"]
    assert ns["session"].activated and ns["reason"] == "time"
    assert (tmp_path / "run.h5").is_file()
    # the example run again: the recording it made is not replaced without overwrite=True, as the CLI's rule
    import rig
    from rig.errors import RigError
    made = (tmp_path / "chirp30.h5").stat()
    with pytest.raises(RigError, match=r"chirp30\.h5: file exists \(pass overwrite=True"):
        rig.record_chirp("chirp30.h5", seconds=30)
    after = (tmp_path / "chirp30.h5").stat()
    assert (after.st_mtime_ns, after.st_size) == (made.st_mtime_ns, made.st_size)


def test_identify_refuses_a_feedback_only_recording_as_the_cli_does(tmp_path):
    import rig
    from rig.cli import main
    from rig.errors import RigError
    run = tmp_path / "run.h5"
    assert main(["run", "--sim-time", "--seconds", "1", "--quiet", "--record", str(run)]) == 0
    with pytest.raises(RigError, match="closed-loop recording"):
        rig.identify_actuator(run)


@pytest.mark.parametrize("kw, words", [
    ({"seconds": math.nan}, "seconds: expected > 0 s and <= 3600 s, got nan"),
    ({"seconds": 1e9}, "seconds: expected > 0 s and <= 3600 s, got 1000000000.0"),
    ({"seconds": 1.0, "amplitude_V": math.nan}, "--amplitude: expected 0 < V <="),
])
def test_record_chirp_refuses_what_rig_chirp_refuses(tmp_path, kw, words):
    """Found by the abuse trial: seconds=nan ended in a ValueError from the scheduler, seconds=1e9 went on building
    a billion-second chirp (`rig chirp --seconds` stops at an hour), amplitude_V=nan ran into a FAULT."""
    import rig
    from rig.errors import RigError
    t0 = time.monotonic()
    with pytest.raises(RigError, match=re.escape(words)):
        rig.record_chirp(tmp_path / "c.h5", **kw)
    assert time.monotonic() - t0 < 20 and list(tmp_path.iterdir()) == []       # refused before any run


@pytest.mark.parametrize("kw, words", [
    ({"seconds": 0}, "simulate_isolation: seconds: expected >= 0.5 s and <= 600 s, got 0"),
    ({"seconds": -1}, "simulate_isolation: seconds: expected >= 0.5 s and <= 600 s, got -1"),
    ({"seconds": math.nan}, "simulate_isolation: seconds: expected >= 0.5 s and <= 600 s, got nan"),
    ({"seconds": 1, "settle_s": -1}, "simulate_isolation: settle_s: expected >= 0 s and <= 60 s, got -1"),
])
def test_simulate_isolation_refuses_what_rig_demo_refuses(kw, words):
    """Found by the abuse trial: seconds=0 ended in a ValueError from scipy after RuntimeWarnings ("Mean of empty
    slice"), -1 in a ZeroDivisionError, nan in a ValueError: the API holds its arguments to rig demo's ranges."""
    import rig
    from rig.errors import RigError
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(RigError, match=re.escape(words)):
            rig.simulate_isolation(**kw)


def test_record_chirp_under_a_file_is_one_line(tmp_path):
    """Found by the abuse trial: a path under a file ended in a NotADirectoryError from the clean-up of the part
    file, which hid the recorder's one line."""
    import rig
    from rig.errors import RigError
    (tmp_path / "notes.txt").write_text("mine")
    with pytest.raises(RigError, match="cannot create recording") as e:
        rig.record_chirp(tmp_path / "notes.txt" / "c.h5", seconds=1)
    assert "\n" not in str(e.value) and (tmp_path / "notes.txt").read_text() == "mine"


def test_identify_warns_where_the_cli_exits_5(tmp_path):
    """A chirp buried in transducer noise: `rig identify` says "poor fit" and exits 5; the API returns the
    parameters with a SuspectFit warning naming the same reason (issue 29: the same rules as the CLI)."""
    import rig
    from rig.recordings.recording import Recording
    from sim_backend.actuator import Effects, linear_chirp, simulate_stand
    from sim_backend.linear import ActuatorParams
    t, u = linear_chirp(1000.0, 20.0, 0.1, 100.0, 2.0)
    out = simulate_stand(ActuatorParams(), u, 1000.0, Effects(position_noise_m=1e-6, accel_noise_mps2=2e-4, seed=1))
    noisy = Recording.from_arrays(t, u, out["position_m"], out["accel_mps2"], source="sim 1000 Hz")
    with pytest.warns(rig.SuspectFit, match="identify_actuator: poor fit"):
        res = rig.identify_actuator(noisy, starts=1, refine_time_domain=False)
    assert res.fit["warning"].startswith("poor fit") and set(res.change_pct()) == {"K_L", "C", "w_nv", "zeta", "K_Q", "K_C"}
    out = simulate_stand(ActuatorParams(), u, 1000.0, Effects(position_noise_m=2e-8, accel_noise_mps2=2e-4, seed=1))
    clean = Recording.from_arrays(t, u, out["position_m"], out["accel_mps2"], source="sim 1000 Hz")
    with warnings.catch_warnings():
        warnings.simplefilter("error", rig.SuspectFit)
        res = rig.identify_actuator(clean, starts=1, refine_time_domain=False)
    assert "warning" not in res.fit
    below = dataclasses.replace(res, params=dataclasses.replace(res.p0, K_Q=res.p0.K_Q * (1.0 - 1e-6)))
    assert str(below.change_pct()["K_Q"]) == "0.0"          # a change that rounds to zero is not printed -0.0


def test_a_session_that_never_activates_warns_and_one_that_does_not():
    from rig.config import load_config
    from rig.runtime.clock import SimClock
    from rig.runtime.session import NeverActivated, Session
    cfg = load_config(None)
    with Session(cfg, "sim", clock=SimClock()) as s:
        with pytest.warns(NeverActivated, match="stayed INACTIVE"):
            s.run(seconds=0.05)
    assert not s.activated
    with Session(cfg, "sim", clock=SimClock()) as s:
        with warnings.catch_warnings():
            warnings.simplefilter("error", NeverActivated)
            s.run(seconds=0.05, activate_after_s=0.01)
    assert s.activated


def test_import_rig_is_light_and_names_its_api():
    code = ("import sys, rig; print(sorted(m for m in ('numpy', 'scipy', 'h5py', 'numba') if m in sys.modules)); "
            "print(rig.__all__); print(callable(rig.identify_actuator))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=REPO)
    assert out.returncode == 0, out.stderr
    heavy, names, callable_ = out.stdout.strip().splitlines()
    assert heavy == "[]"
    for name in ("load_recording", "record_chirp", "identify_actuator", "diagnose_recording", "simulate_isolation"):
        assert name in names
    assert callable_ == "True"
