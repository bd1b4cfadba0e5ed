"""The prototype from the command line: `rig run --layout prototype` (modes, references, a script, the
figures and the plot), refusals in one line, `rig design --layout prototype`, `rig bench loop --layout`, and
`rig identify` on a track-mode recording (closed-loop data, said so)."""
from __future__ import annotations

import array
import json
import subprocess
import sys
import time

import pytest

from rig.commands.bench import BlockClock, _both_figures, block_plan
from rig.errors import EXIT_SUSPECT
from tests.hosttiming import skip_unless_on_time


def rig(*args, timeout=600):
    return subprocess.run([sys.executable, "-m", "rig.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=timeout)


def test_run_tracks_a_sine_and_prints_the_figures_and_the_plot(tmp_path):
    script = tmp_path / "s.txt"
    script.write_text("# a session\n0.3 hold 5um\n0.6 track sine:amp=10um,freq=5\n2.0 isolate\n2.6 off\n2.8 stop\n")
    out = rig("run", "--layout", "prototype", "--sim-time", "--seconds", "5", "--script", script,
              "--record", tmp_path / "r.h5", "--plot", tmp_path / "r.png")
    assert out.returncode == 0, out.stderr[-2000:]
    lines = out.stdout.strip().splitlines()
    assert len(lines) == 5 and "track sine:amp=10um,freq=5" in lines[2] and "% of 10.00 um" in lines[2]
    assert "isolate" in lines[3] and "off" in lines[4]
    assert "script at 2.8 s: stop" in out.stderr
    assert (tmp_path / "r.png").stat().st_size > 10000


def test_a_timed_run_without_record_still_says_how_well_it_tracked(tmp_path):
    """A run with --seconds and no --record prints its tracking figures (it printed none)."""
    out = rig("run", "--layout", "prototype", "--sim-time", "--seconds", "1", "--mode", "track",
              "--reference", "sine:amp=10um,freq=5")
    assert out.returncode == 0, out.stderr[-2000:]
    assert "tracking error rms" in out.stdout and "% of 10.00 um" in out.stdout
    assert "recorded to" not in out.stderr


def test_a_run_longer_than_the_temporary_recording_holds_says_where_its_figures_are(monkeypatch, capsys, caplog):
    """Over TRACK_TEMP_S without --record no temporary recording is made (it would grow large): the run says so."""
    from rig.cli import main
    from rig.commands import run
    monkeypatch.setattr(run, "TRACK_TEMP_S", 0.5)
    with caplog.at_level("INFO", logger="rig.run"):
        assert main(["run", "--layout", "prototype", "--sim-time", "--seconds", "1", "--mode", "track",
                     "--reference", "sine:amp=10um,freq=5"]) == 0
    assert "tracking error rms" not in capsys.readouterr().out
    assert "over 0.5 s they need --record FILE" in caplog.text


@pytest.mark.parametrize("args,match", [
    (["--position", "30um"], "outside what the actuator can hold: +-24.1 um"),
    (["--reference", "sine:amp=10um,freq=30"], "above the reference rate limit"),
    (["--mode", "track"], "--mode track: needs --reference"),
    (["--reference", "sine:amp=1um"], "missing freq")])
def test_run_refuses_in_one_line(tmp_path, args, match):
    out = rig("run", "--layout", "prototype", "--sim-time", "--seconds", "0.2", "--quiet", *args)
    assert out.returncode == 2 and match in out.stderr
    assert out.stderr.strip().count("\n") == 0


@pytest.mark.parametrize("args,match", [
    (["--position", "2mm"], "--position 2mm: position 2000.0 um is outside the stroke limit (+-900 um"),
    (["--reference", "sine:amp=0.5mm,freq=1,offset=-0.6mm"], "position -1100.0 um is outside the stroke limit")])
def test_a_start_beyond_the_stroke_is_refused_before_the_controllers_load(args, match):
    """The stroke rule runs on the options, before numba and python-control load (seconds on a busy host)."""
    code = ("import sys\nfrom rig.cli import main\n"
            f"code = main(['run', '--layout', 'prototype', '--sim-time', '--seconds', '0.2', *{args!r}])\n"
            "print('CODE', code, sorted(m for m in sys.modules if m.split('.')[0] in ('numba', 'control')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert "CODE 2 []" in out.stdout, (out.stdout, out.stderr[-2000:])
    assert match in out.stderr and out.stderr.strip().count("\n") == 0, out.stderr


def test_run_layout_must_agree_with_the_config(tmp_path):
    out = rig("run", "--layout", "prototype", "--config", "drivers/devicemaps/hil.toml", "--sim-time", "--seconds",
              "0.1")
    assert out.returncode == 2 and "--layout prototype" in out.stderr and "'machine'" in out.stderr


def test_design_reports_both_loops(tmp_path):
    out = rig("design", "--layout", "prototype", "--json", "--out", tmp_path)
    assert out.returncode == 0, out.stderr[-2000:]
    res = json.loads(out.stdout)
    tr, iso = res["tracking"], res["isolation"]
    assert tr["bandwidth_hz"] >= 95 and tr["gain_margin_db"] >= 6 and tr["phase_margin_deg"] >= 45
    assert tr["step_2um"]["settling_2pct_ms"] <= 20 and tr["sine_10um_5hz"]["rms_error_pct"] <= 2
    assert iso["stable"] and iso["gain_margin_db"] >= 6 and iso["isolation_db"] > 6
    assert {p.name for p in tmp_path.iterdir()} == {"prototype_fig4_tracking.png", "prototype_step.png",
                                                    "prototype_isolation.png", "prototype_design.json"}


def test_bench_loop_both_layouts_in_one_run():
    out = rig("bench", "loop", "--layout", "both", "--rate", "5000", "--seconds", "1.2", "--rounds", "2",
              "--block-s", "0.1", "--no-realtime", "--json")
    skip_unless_on_time(out)                # a stall of the shared host faults a block (exit 1, said in a warning)
    assert out.returncode == 0, out.stderr[-2000:]
    res = json.loads(out.stdout)
    assert res["machine"]["mounts"] == 4 and res["prototype"]["mounts"] == 1
    assert res["rounds"] == 2 and res["blocks_per_round"] == 3 and res["block_s"] == pytest.approx(0.1)
    for name in ("machine", "prototype"):
        by_round = res[name]["compute_us_by_round"]
        assert len(by_round) == 2 and all(0 < r["p50"] <= r["p99"] <= r["max"] for r in by_round if r["n"])
        # every block's periods less its settling ones and its stop period: 3 blocks of 500 periods, the first
        # 10 and the last of each left out; a block in which a stall of the loaded host faulted the loop is left
        # out whole
        assert all(r["n"] % 489 == 0 and r["n"] <= 3 * 489 for r in by_round)
        assert res[name]["compute_us"]["n"] == (2 * 3 - res[name]["faulted_blocks"]) * 489
        # the loop thread's CPU time over the same periods: inside the period's wall time (+ one clock read)
        cpu, wall = res[name]["cpu_us"], res[name]["compute_us"]
        assert cpu["n"] == wall["n"] and 0 < cpu["p50"] <= wall["p50"] + 5.0
    pairs = list(zip(res["machine"]["compute_us_by_round"], res["prototype"]["compute_us_by_round"]))
    assert res["compute_p99_ratio"] == [round(b["p99"] / a["p99"], 3) if a["n"] and b["n"] else None
                                        for a, b in pairs]
    assert res["prototype_p99_le_machine_every_round"] == all(a["n"] and b["n"] and b["p99"] <= a["p99"]
                                                              for a, b in pairs)
    pm, pp = res["machine"]["compute_us"], res["prototype"]["compute_us"]
    assert res["prototype_p99_le_machine_pooled"] == (pp["p99"] <= pm["p99"])
    assert set(res["kernel_us"]) == {"machine", "prototype"} and all(v > 0 for v in res["kernel_us"].values())
    assert len(res["load_average"]) == 6


def test_bench_loop_both_layouts_prints_rounds_and_verdict():
    out = rig("bench", "loop", "--layout", "both", "--seconds", "0.8", "--rounds", "2", "--block-s", "0.2",
              "--no-realtime")
    skip_unless_on_time(out)
    assert out.returncode == 0, out.stderr[-2000:]
    lines = out.stdout.splitlines()
    assert sum(line.strip().startswith("round ") and "p99 ratio" in line for line in lines) == 2
    assert lines[-3].startswith("one-mount compute p99 <= four-mount compute p99 over the run: ")
    pooled = {n: float(line.split("p99")[1].split()[0]) for line in lines for n in ("machine", "prototype")
              if line.strip().startswith(n) and "pooled: compute" in line}
    assert ("yes" if pooled["prototype"] <= pooled["machine"] else "no") == lines[-3].split(": ")[1].split()[0]
    assert lines[-2].startswith("one-mount compute p99 <= four-mount compute p99 in every round: ")
    assert lines[-1].startswith("one-mount CPU time p99 <= four-mount in every round: ")
    assert sum("CPU time of the loop thread per period" in line for line in lines) == 2
    assert "alternating" in lines[0] and "load average" in lines[0]


@pytest.mark.parametrize("as_json", [True, False], ids=["json", "text"])
def test_bench_loop_both_layouts_whose_rig_faulted_exits_as_a_fault(tmp_path, as_json):
    """Was: a faulted block was said in a `note:` and the benchmark exited 0 (and with every block faulted the
    text figures ended in a TypeError traceback). Now as every benchmark (faulted_exit): a warning line per
    layout naming the fault and how many blocks it took out, exit 1; the figures left are still printed."""
    from rig.commands.run import LAYOUTS
    cfg = tmp_path / "trip.toml"                # the stand, its accelerometer's range too small for any reading
    cfg.write_text(LAYOUTS["prototype"][None].read_text() + "\n[safety]\naccel_range_mps2 = 1e-9\n")
    out = rig("bench", "loop", "--layout", "both", "--config", cfg, "--rate", "5000", "--seconds", "0.6",
              "--rounds", "1", "--block-s", "0.1", "--no-realtime", *(["--json"] if as_json else []))
    assert out.returncode == 1, out.stderr[-2000:]
    warned = [ln for ln in out.stderr.splitlines() if ln.startswith("rig bench: warning: ")]
    assert [ln.split(":")[2].strip() for ln in warned] == ["machine (3 of 3 blocks)", "prototype (3 of 3 blocks)"]
    assert all("faulted (" in ln and "accelerometer implausible" in ln for ln in warned), out.stderr[-2000:]
    assert "note:" not in out.stderr and "Traceback" not in out.stderr
    if as_json:
        assert json.loads(out.stdout)["prototype"]["faulted_blocks"] == 3        # still only JSON on stdout
    else:
        assert "prototype (1) pooled: no figures (every block faulted)" in out.stdout


def test_block_plan_cuts_each_layouts_share_of_a_round():
    assert block_plan(18, 3, 0.2) == (15, pytest.approx(0.2))         # 3 s per layout per round
    assert block_plan(1.2, 2, 0.5) == (1, pytest.approx(0.3))        # shorter than a block: one block
    k, s = block_plan(10, 3, 0.7)
    assert k * s == pytest.approx(10 / 6) and k == 2


def test_both_figures_pool_each_layouts_blocks_per_round():
    class FakeLoop:                     # the scheduler's rings, as a loop keeps them
        def __init__(self, n, comp_us):
            self.n, self.keep, self.iterations, self.overruns = n, len(comp_us), len(comp_us), 0
            self.compute_ns = array.array("q", [int(c * 1e3) for c in comp_us])
            self.wake_ns = array.array("q", [5000] * len(comp_us))
            self.cpu_ns = None          # measure_cpu() not called
    machine = FakeLoop(4, [10.0] * 10 + [30.0] * 10 + [20.0] * 10)
    proto = FakeLoop(1, [5.0] * 10 + [40.0] * 10 + [1.0] * 10)
    spans = {"machine": [[(0, 10), (20, 25)], [(10, 20)]], "prototype": [[(0, 10)], [(10, 20)]]}
    out = _both_figures({"machine": machine, "prototype": proto}, spans, 5000.0, 2, 2, 0.2)
    m, p = out["machine"]["compute_us_by_round"], out["prototype"]["compute_us_by_round"]
    assert [r["n"] for r in m] == [15, 10] and [r["n"] for r in p] == [10, 10]
    assert m[0]["max"] == 20.0 and m[0]["p50"] == 10.0 and m[1]["p99"] == 30.0     # only the blocks' periods
    assert out["compute_p99_ratio"] == [round(5.0 / m[0]["p99"], 3), round(40.0 / 30.0, 3)]
    assert out["rounds_prototype_p99_le_machine"] == 1 and not out["prototype_p99_le_machine_every_round"]
    # pooled over the run: machine 10 x 10, 5 x 20 and 10 x 30 us; prototype 10 x 5 and 10 x 40 us
    assert out["machine"]["compute_us"]["p99"] == 30.0 and out["prototype"]["compute_us"]["p99"] == 40.0
    assert out["prototype_p99_le_machine_pooled"] is False
    spans["prototype"][1] = []                                  # every block of the round faulted: left out
    out = _both_figures({"machine": machine, "prototype": proto}, spans, 5000.0, 2, 2, 0.2)
    assert out["prototype"]["compute_us_by_round"][1]["n"] == 0 and out["compute_p99_ratio"][1] is None
    assert out["prototype"]["compute_us"]["n"] == 10


def test_block_clock_stops_loop_time_between_blocks():
    clock = BlockClock(0)
    clock.stop()
    time.sleep(0.05)
    clock.resume()
    t = clock.now_ns()
    assert clock.offset_ns >= 50e6 and abs(t - (time.monotonic_ns() - clock.offset_ns)) < 5e6
    clock.sleep_until(t + 2_000_000)                  # on its own time base: 2 ms on, not at once
    assert clock.now_ns() - t >= 2e6
    last, off = clock.now_ns(), clock.offset_ns       # stopped as from a loop time already past:
    time.sleep(0.03)
    clock.stop(last)
    clock.resume()
    assert clock.offset_ns - off >= 30e6              # the 30 ms after it are no loop time


def test_block_clock_starts_each_block_on_the_wall_grid_without_loop_time_passing():
    clock = BlockClock(0, 20_000_000)
    before = clock.now_ns()
    clock.stop()
    clock.resume()
    t = clock.now_ns()                                # the block's first reading: waits for the grid
    assert (t + clock.offset_ns) % 20_000_000 == 0 and 0 <= t - before < 5e6
    assert 0 <= clock.now_ns() - t < 5e6              # then on as before, no jump either way


@pytest.mark.slow
def test_identify_reads_a_track_chirp_as_closed_loop_data(tmp_path):
    rec = tmp_path / "chirp.h5"
    out = rig("run", "--layout", "prototype", "--sim-time", "--seconds", "9", "--quiet", "--mode", "track",
              "--reference", "chirp:amp=0.7um,f0=1,f1=100,duration=8", "--record", rec)
    assert out.returncode == 0, out.stderr[-2000:]
    out = rig("identify", rec, "--json", "--starts", "2")
    assert out.returncode == EXIT_SUSPECT, out.stderr[-2000:]     # identified, with the closed-loop warning
    assert "closed-loop data" in out.stderr
    res = json.loads(out.stdout)
    p = res["parameters"]
    assert p["w_nv"] == pytest.approx(524.0, rel=0.12) and p["zeta"] == pytest.approx(0.65, rel=0.12)


def test_design_on_the_identified_actuator(tmp_path):
    """`rig design --layout prototype --identified DIR`: the stand's loops analysed on the actuator `rig identify`
    found (here a valve 30 % stronger than Table 1's: the same PID closes a faster tracking loop)."""
    from controllers.analysis import ACTUATOR_KEYS
    from rig.commands.run import LAYOUTS
    from rig.config import load_config
    cfg = load_config(LAYOUTS["prototype"][None])
    par = {k: getattr(cfg.actuator if sec == "actuator" else cfg.valve, k) for k, sec in ACTUATOR_KEYS.items()}
    par["K_Q"] *= 1.3
    (tmp_path / "identify.json").write_text(json.dumps({"parameters": par}))
    base = json.loads(rig("design", "--layout", "prototype", "--json").stdout)
    out = rig("design", "--layout", "prototype", "--json", "--identified", tmp_path)
    assert out.returncode == 0, out.stderr[-2000:]
    res = json.loads(out.stdout)
    assert res["design_model"]["actuator"].startswith("identified") and res["design_model"]["parameters"] == par
    assert res["tracking"]["bandwidth_hz"] > base["tracking"]["bandwidth_hz"] + 5


def test_run_plot_is_never_overwritten_without_overwrite(tmp_path):
    png = tmp_path / "p.png"
    png.write_bytes(b"old")
    out = rig("run", "--layout", "prototype", "--sim-time", "--seconds", "0.2", "--quiet", "--plot", png)
    assert out.returncode == 2 and "--plot" in out.stderr and "--overwrite" in out.stderr
    assert png.read_bytes() == b"old"


def test_an_isolate_run_plots_load_and_floor_and_says_what_runs_in_words(tmp_path):
    """`rig run --layout prototype --mode isolate` (issue 29): the start line says "the actuator on its stand" (not
    "stand on the stand"), the stop line says simulated time is not timed (no `compute p99 0.0 us`), and the
    plot has no empty tracking panel but the load's and the floor's motion."""
    import matplotlib.pyplot as plt
    import numpy as np
    from rig import operated
    rec = tmp_path / "iso.h5"
    out = rig("run", "--layout", "prototype", "--sim-time", "--seconds", "3", "--mode", "isolate", "--record", rec)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "backend sim, the actuator on its stand at 5000 Hz, mode isolate" in out.stderr
    assert "stand on the stand" not in out.stderr
    assert "compute p99" not in out.stderr and "p99=" not in out.stderr       # stop line and status line
    assert "in simulated time (loop timing is not measured in simulated time" in out.stderr
    run = operated.load_operated(rec)
    figs = operated.figures(run)
    fig = operated.figure(run, figs)
    try:
        labels = [a.get_ylabel() for a in fig.axes]
        motion = fig.axes[1]
        lines = {ln.get_label().split(" ")[0]: np.asarray(ln.get_ydata()) for ln in motion.get_lines()}
        texts = [t.get_text() for t in motion.texts]
    finally:
        plt.close(fig)
    assert labels == ["position [um]", "motion 1-100 Hz [um]", "valve [V]"]     # no tracking panel
    load, floor = lines["load"], lines["floor"]
    iso = next(d for d in figs if d["mode"] == "isolate")
    # one figure (issue 29: the printed 7.618 um against the legend's 7.46): the printed rms is the drawn curve's
    # over the stretch the plot leaves unshaded, and the plot writes that very figure beside the segment
    lo, hi = iso["motion_s"]
    win = (run.t_s >= lo) & (run.t_s <= hi)
    load_um, floor_um = np.sqrt(np.mean(load[win] ** 2)), np.sqrt(np.mean(floor[win] ** 2))
    assert load_um == pytest.approx(iso["load_motion_um"], rel=1e-9)
    assert floor_um == pytest.approx(iso["floor_motion_um"], rel=1e-9)
    printed = f"load {iso['load_motion_um']:.3f} um rms in 1-100 Hz"
    assert printed in operated.figures_text(figs) and printed in out.stdout
    assert texts == [f"load {iso['load_motion_um']:.3f}\nfloor {iso['floor_motion_um']:.3f} um"], texts
    assert 1.0 < floor_um < 4.0 and load_um < floor_um / 3                     # the floor moves, the load less


def test_a_track_run_keeps_its_tracking_panel(tmp_path):
    import matplotlib.pyplot as plt
    import numpy as np
    from rig import operated
    rec = tmp_path / "track.h5"
    out = rig("run", "--layout", "prototype", "--sim-time", "--seconds", "2", "--quiet", "--reference",
              "sine:amp=5um,freq=5", "--record", rec)
    assert out.returncode == 0, out.stderr[-2000:]
    fig = operated.figure(operated.load_operated(rec))
    try:
        labels = [a.get_ylabel() for a in fig.axes]
        err = np.asarray(fig.axes[1].get_lines()[0].get_ydata())
    finally:
        plt.close(fig)
    assert labels == ["position [um]", "tracking error [um]", "motion 1-100 Hz [um]", "valve [V]"]
    assert np.isfinite(err).sum() > 1000
