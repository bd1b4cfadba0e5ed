"""`rig chirp`: the identification run through rig.runtime.loop on the simulated stand (simulated time), its recording,
and identification from it."""
from __future__ import annotations

import gzip
import json
import math

import numpy as np
import pytest

from controllers.playback import SignalPlayback
from rig.chirp import chirp_samples, run_chirp
from rig.config import Config
from rig.identify import identify, simulate_linear
from rig.recordings.rigformat import load_recording
from sim_backend.actuator import linear_chirp
from sim_backend.linear import ActuatorParams

DESIGN = ActuatorParams()
PROTO = DESIGN.with_(w_nv=DESIGN.w_nv * 1.1, zeta=DESIGN.zeta * 0.9, K_Q=DESIGN.K_Q * 0.93, K_L=DESIGN.K_L * 1.1)


def test_chirp_playback_is_the_papers_linear_chirp():
    fs, T = 1000.0, 3.0
    _, u = linear_chirp(fs, T, 0.1, 100.0, 2.0)
    c = SignalPlayback(chirp_samples(2.0, 0.1, 100.0, T, 1.0 / fs), 1.0 / fs)
    s = c.initial_state()
    for _ in range(7):                                     # disabled (INACTIVE): null, does not advance
        v, s = c.step(s, (0.0, 0.0), 1.0 / fs)
        assert v == 0.0
    s = c.set_enabled(s, True)                             # activation starts the chirp
    out = []
    for _ in range(len(u) + 5):
        v, s = c.step(s, (0.0, 0.0), 1.0 / fs)
        out.append(v)
    np.testing.assert_allclose(out[:len(u)], u, atol=1e-9)
    assert out[len(u):] == [0.0] * 5                        # null after the chirp


@pytest.fixture(scope="module")
def sim_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("chirp") / "run.h5"
    summary = run_chirp(Config(), backend="sim", amplitude_V=2.0, f0_hz=0.2, f1_hz=100.0, duration_s=12.0,
                        rate_hz=1000.0, out=out, settle_s=0.05, seed=4, stand_params=PROTO)
    return summary, load_recording(out)


def test_sim_chirp_through_the_loop_records_the_plant(sim_run):
    summary, rec = sim_run
    assert summary["simulated_time"] and summary["overruns"] == 0 and summary["dropped_rows"] == 0
    assert rec.fs_hz == pytest.approx(1000.0) and rec.n == summary["rows_written"] == summary["periods"]
    assert rec.n == round((0.05 + 12.0 + 0.05) * 1000)
    # null while INACTIVE, then the chirp from its first sample
    k0 = int(np.argmax(rec.valve_cmd_V != 0.0))
    assert np.all(rec.valve_cmd_V[:k0] == 0.0) and k0 == pytest.approx(50, abs=2)
    _, u = linear_chirp(1000.0, 12.0, 0.2, 100.0, 2.0)
    np.testing.assert_allclose(rec.valve_cmd_V[k0 - 1:k0 - 1 + len(u)], u, atol=1e-9)
    # position is sampled before the command of the same period acts (ZOH): the linear model driven by the
    # recorded command reproduces it to the 2e-8 m sensor noise
    resid = rec.position_m - simulate_linear(PROTO, rec.valve_cmd_V, rec.fs_hz)
    assert np.std(resid) == pytest.approx(2e-8, rel=0.1)
    # and a one-sample misalignment would be 5x worse
    late = np.concatenate([[0.0], simulate_linear(PROTO, rec.valve_cmd_V, rec.fs_hz)[:-1]])
    assert np.std(rec.position_m - late) > 5 * np.std(resid)


def test_identify_from_the_loop_chirp(sim_run):
    _, rec = sim_run
    res = identify(rec, DESIGN, starts=4)
    p = res.params
    assert abs(p.w_nv / PROTO.w_nv - 1) < 0.01 and abs(p.zeta / PROTO.zeta - 1) < 0.01
    assert abs(p.K_Q / PROTO.K_Q - 1) < 0.02
    assert abs(p.K_C * p.K_L / (PROTO.K_C * PROTO.K_L) - 1) < 0.02


def test_cli_csv_output_is_the_shared_format(tmp_path, capsys):
    from rig.cli import main
    out = tmp_path / "c.csv.gz"
    assert main(["chirp", "--duration", "0.5", "--f0", "1", "--f1", "20", "--rate", "1000", "--csv",
                 "--record", str(out)]) == 0
    with gzip.open(out, "rt") as f:
        assert f.readline().strip() == "time_s,valve_cmd_V,position_m,accel_mps2"
    rec = load_recording(out)
    assert rec.n == 600 and math.isclose(rec.fs_hz, 1000.0)
    assert not (tmp_path / "c.csv.gz.part.h5").exists()
    got = capsys.readouterr()                 # docs/CLI.md: the result on stdout, progress and hints on stderr
    assert got.out.splitlines() == [f"chirp 1->20 Hz, 2 V, 0.5 s on the sim backend at 1000 Hz: 600 samples -> {out} "
                                    f"(csv); {got.out.split('; ')[1].split(' s wall')[0]} s wall, overruns 0, "
                                    f"dropped rows 0"], got
    assert "samples ->" not in got.err and got.err.strip().splitlines()[-1] == f"next: rig identify {out}"


def test_cli_json_is_only_the_result_on_stdout(tmp_path, capsys):
    from rig.cli import main
    out = tmp_path / "c.h5"
    assert main(["chirp", "--duration", "0.5", "--f0", "1", "--f1", "20", "--rate", "1000", "--json",
                 "--record", str(out)]) == 0
    got = capsys.readouterr()
    res = json.loads(got.out)                 # only JSON on stdout
    assert res["recording"] == str(out) and res["rows_written"] == load_recording(out).n == 600
    assert res["signal"] == "chirp" and res["f1_hz"] == 20 and res["dropped_rows"] == 0
    assert got.err.strip().splitlines()[-1] == f"next: rig identify {out}"


@pytest.mark.parametrize("argv, expect", [
    (["--amplitude", "50"], "--amplitude: expected 0 < V <= safety.valve_limit_V"),
    (["--f1", "800", "--rate", "1000"], "--f0/--f1: expected 0 <= f0 < f1 < rate/2"),
    (["--duration", "0"], "--duration/--seconds: expected > 0 s"),
])
def test_cli_bad_arguments_are_one_line(tmp_path, capsys, argv, expect):
    from rig.cli import main
    assert main(["chirp", "--record", str(tmp_path / "x.h5"), *argv]) == 2
    err = capsys.readouterr().err
    assert err.startswith("rig chirp: error: ") and err.count("\n") == 1 and expect in err   # (no empty bar line)


@pytest.mark.parametrize("name, argv, expect", [
    ("x.h5", ["--csv"], "--csv writes CSV: expected a name ending in .csv or .csv.gz"),
    ("x.csv", [], "expected --csv for a .csv name (without it the recording is HDF5), or a .h5 name"),
])
def test_a_record_name_of_the_other_format_is_refused(tmp_path, capsys, name, argv, expect):
    """Found by the abuse trial: `rig chirp --record x.h5 --csv` wrote CSV into x.h5, and the `next: rig identify
    x.h5` it printed then failed ("not an HDF5 file"); `--record x.csv` without --csv wrote HDF5 into x.csv."""
    from rig.cli import main
    out = tmp_path / name
    assert main(["chirp", "--record", str(out), "--duration", "0.5", *argv]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"rig chirp: error: --record {out}: {expect}"] and not out.exists()


def test_stand_effects_from_the_config_reach_the_recording(tmp_path):
    # a 2 ms transport delay in [stand]: the linear refit hides it by lowering w_nv (PHYSICS_NOTES)
    from rig.cli import main
    cfg = tmp_path / "delay.toml"
    cfg.write_text("[stand]\ndelay_s = 0.002\n")
    out = tmp_path / "d.h5"
    assert main(["chirp", "--config", str(cfg), "--duration", "12", "--f0", "0.2", "--rate", "1000",
                 "--record", str(out)]) == 0
    res = identify(load_recording(out), DESIGN, starts=3)
    assert res.params.w_nv < 0.8 * DESIGN.w_nv
    assert res.fit["residual_rms_m"] > 3 * 2e-8            # and the fit no longer reaches the noise floor
