"""Session: builds a run from a config and a backend name and tears it all down; a configuration the kernel
cannot run is refused at construction; the requests and the published state work from another thread."""
from __future__ import annotations

import threading
import time

import h5py
import pytest

from rig.runtime.clock import SimClock
from rig.config import Config
from rig.errors import ConfigError
from rig.runtime.lifecycle import State
from rig.runtime.recorder import read_recording
from rig.runtime.session import Session
from rig.runtime.signals import Terminated


def test_session_builds_runs_records_and_tears_down(tmp_path):
    path = tmp_path / "run.h5"
    with Session(Config(), "sim", clock=SimClock(), record=path, record_attrs={"command": "test"}) as s:
        port, loop = s.port, s.loop
        assert port.opened and loop.state is State.INACTIVE
        reason = s.run(iterations=500, activate_after_s=0.01)
        snap = s.snapshot()
    assert reason == "iterations" and not port.opened                   # the port was closed on exit
    assert snap["state"] == "INACTIVE" and snap["iterations"] == 500 and len(snap["valve_cmd_V"]) == 4
    r = read_recording(path)
    assert len(r["time_s"]) == 500 and r["attrs"]["complete"] and r["attrs"]["stop_reason"] == "iterations"
    assert r["attrs"]["backend"] == "sim" and r["attrs"]["command"] == "test"
    with h5py.File(path) as f:                                          # state columns named by the controllers
        labels = [str(x) for x in f["controller_state"].attrs["labels"]]
    assert labels[0] == "front_left.h_acc0_z1" and "rear_right.suspended" in labels


@pytest.mark.parametrize("signame, raised", [("SIGTERM", Terminated), ("SIGINT", KeyboardInterrupt)])
def test_a_stop_signal_before_the_first_period_is_an_interrupt_and_records_nothing(tmp_path, signame, raised):
    """Was: a SIGTERM after the loop was built and before its first period ended `rig run` with exit 0, a raw
    NeverActivated warning and `recorded to FILE`: no file was written (with --overwrite the old one stayed,
    and its VC summary was printed as this run's)."""
    path = tmp_path / "run.h5"
    with Session(Config(), "sim", clock=SimClock(), record=path) as s:
        s.loop.stop(signame)                     # what the session's handler does when the signal comes
        with pytest.raises(raised):
            s.run(seconds=0.1, activate_after_s=0.01)
    assert s.loop.iterations == 0 and not path.exists()


def test_a_controller_the_kernel_cannot_run_is_refused_and_nothing_is_left_open():
    built = {}

    class NotAKind:
        def __init__(self):
            built["n"] = built.get("n", 0) + 1

    with pytest.raises(ConfigError, match="not a controller kind"):
        with Session(Config(), "sim", clock=SimClock(), controllers=lambda cfg, dt: [NotAKind()] * 4):
            pass
    assert built["n"] == 1


def test_requests_and_recording_from_another_thread(tmp_path):
    """A console's view: the loop runs in its thread; requests and a recording started and stopped meanwhile."""
    with Session(Config(), "sim", clock=SimClock()) as s:
        done = threading.Event()
        th = threading.Thread(target=lambda: (s.run(activate_after_s=0.01), done.set()))
        th.start()
        try:
            deadline = time.monotonic() + 60
            while s.snapshot()["state"] != "ACTIVE" and time.monotonic() < deadline:
                time.sleep(0.01)
            s.request_isolation(False)
            rec = s.start_recording(tmp_path / "part.h5", command="console")
            time.sleep(0.3)
            s.stop_recording(rec)
            while s.snapshot()["isolation"] and time.monotonic() < deadline:
                time.sleep(0.01)
            snap = s.snapshot()
        finally:
            s.safe_stop("console: stop")
            th.join(60)
    assert done.is_set() and s.loop.stop_reason == "console: stop"
    assert snap["state"] == "ACTIVE" and snap["isolation"] is False and snap["fault_reason"] is None
    r = read_recording(tmp_path / "part.h5")
    assert len(r["time_s"]) > 10 and r["attrs"]["command"] == "console"
    assert (r["time_s"][1:] - r["time_s"][:-1]).max() < 2.1 / s.rate_hz          # consecutive periods


@pytest.mark.parametrize("compression, filter_", [("gzip", "gzip"), ("none", None)])
def test_the_recording_is_compressed_as_the_config_says(tmp_path, compression, filter_):
    """[recording] compression: gzip (the default) or none, for a loop that shares few CPUs with its devices."""
    import dataclasses
    cfg = Config()
    cfg = cfg.replace(recording=dataclasses.replace(cfg.recording, compression=compression))
    path = tmp_path / "run.h5"
    with Session(cfg, "sim", clock=SimClock(), record=path) as s:
        s.run(iterations=300, activate_after_s=0.01)
    with h5py.File(path) as f:
        assert f["accel_mps2"].compression == filter_ and f["accel_mps2"].shape[0] == 300
    assert Config().recording.compression == "gzip"
