"""The recorder on its own: generic channels (a chirp layout), units as attributes, events, a full ring
drops rows instead of blocking, a bad path is one clear error; and the real-time set-up carries on when a
step is not allowed."""
from __future__ import annotations

import numpy as np
import pytest

from rig.errors import RecordingError
from rig.runtime.recorder import Channel, Recorder, read_recording


def test_chirp_layout_round_trip(tmp_path):
    chans = [Channel("time_s", "s"), Channel("valve_cmd_V", "V"), Channel("position_m", "m"),
             Channel("accel_mps2", "m/s^2")]
    fs = 2000.0
    rec = Recorder(tmp_path / "chirp.h5", chans, rate_hz=fs, chunk_rows=256,
                   attrs={"command": "rig chirp", "f0_hz": 0.1}).start()
    t = np.arange(3000) / fs
    u = 2.0 * np.sin(2 * np.pi * (0.1 * t + 0.5 * 50 * t ** 2))
    for k in range(len(t)):
        assert rec.push(t[k], u[k], 2.68e-6 * u[k], -1e-3 * u[k])
    rec.event(0.5, "halfway")
    rec.close(stop_reason="done")
    d = read_recording(tmp_path / "chirp.h5")
    assert d["units"] == {"time_s": "s", "valve_cmd_V": "V", "position_m": "m", "accel_mps2": "m/s^2"}
    np.testing.assert_array_equal(d["time_s"], t)
    np.testing.assert_array_equal(d["valve_cmd_V"], u)
    np.testing.assert_array_equal(d["position_m"], 2.68e-6 * u)
    assert d["attrs"]["complete"] in (True, 1) and d["attrs"]["stop_reason"] == "done"
    assert d["attrs"]["f0_hz"] == 0.1 and d["attrs"]["rate_hz"] == fs
    assert d["events"] == [(0.5, "halfway")]


def test_per_mount_channels_have_labels(tmp_path):
    mounts = ("front_left", "front_right", "rear_left", "rear_right")
    rec = Recorder(tmp_path / "m.h5", [Channel("time_s", "s"), Channel("stroke_m", "m", 4, mounts)],
                   rate_hz=1000.0).start()
    for k in range(10):
        rec.push(k * 1e-3, 1.0 * k, 2.0 * k, 3.0 * k, 4.0 * k)
    rec.close()
    import h5py
    with h5py.File(tmp_path / "m.h5") as f:
        assert f["stroke_m"].shape == (10, 4) and f["stroke_m"].attrs["unit"] == "m"
        assert [x.decode() if isinstance(x, bytes) else x for x in f["stroke_m"].attrs["labels"]] == list(mounts)
        assert f["stroke_m"].chunks is not None and f["stroke_m"].maxshape == (None, 4)
        np.testing.assert_array_equal(f["stroke_m"][:, 2], 3.0 * np.arange(10))


def test_full_ring_drops_and_counts_instead_of_blocking(tmp_path):
    rec = Recorder(tmp_path / "r.h5", [Channel("x", "")], rate_hz=10.0, ring_s=1.0, chunk_rows=1,
                   flush_s=0.1).start()
    cap = rec._cap
    rec._proc.send_signal(__import__("signal").SIGSTOP)          # the writer is stalled
    try:
        ok = [rec.push(float(k)) for k in range(cap + 25)]
    finally:
        rec._proc.send_signal(__import__("signal").SIGCONT)
    assert sum(ok) == cap and rec.dropped_rows == 25
    rec.close()
    d = read_recording(tmp_path / "r.h5")
    np.testing.assert_array_equal(d["x"], np.arange(cap, dtype=float))
    assert d["attrs"]["dropped_rows"] == 25


def test_bad_path_is_one_clear_error(tmp_path):
    (tmp_path / "file").write_text("x")
    with pytest.raises(RecordingError, match="cannot create recording"):
        Recorder(tmp_path / "file" / "sub.h5", [Channel("x", "")], rate_hz=10.0).start()


def test_realtime_not_allowed_gives_one_note_and_carries_on(caplog):
    import threading

    from rig.runtime.rt import enter_realtime, leave_realtime
    out = {}

    def body():   # in a thread of its own: affinity and policy are per thread
        st = enter_realtime(priority=200, cpu=10_000, lock_memory=False, freeze_gc=False)
        out["st"] = st
        leave_realtime(st)

    t = threading.Thread(target=body)
    t.start()
    t.join()
    st = out["st"]
    assert not st.fifo and st.cpu is None
    assert len(st.notes) == 2 and any("SCHED_FIFO" in n for n in st.notes) and any("affinity" in n for n in st.notes)
    assert sum("carrying on" in r.getMessage() for r in caplog.records) == 2


def test_cpu_latency_request_is_held_for_the_run_and_dropped_after(tmp_path):
    """The PM QoS request writes the latency as a 32-bit integer and holds the file open until
    leave_realtime (closing it is what ends a request); a device that cannot be opened is one note."""
    import os
    import struct

    import rig.runtime.rt as rt
    dev = tmp_path / "cpu_dma_latency"
    dev.write_bytes(b"")                                  # a plain file stands in for the device
    st = rt.RtState()
    rt.request_cpu_latency(st, 7, device=str(dev))
    assert st.cpu_latency_us == 7 and "cpu_dma_latency=7us" in st.summary()
    fd = st._qos_fd
    os.fstat(fd)                                          # open while the run lasts
    assert struct.unpack("i", dev.read_bytes()) == (7,)
    rt.leave_realtime(st)
    assert st._qos_fd is None
    with pytest.raises(OSError):
        os.fstat(fd)                                      # closed: the request ends
    missing = rt.RtState()
    rt.request_cpu_latency(missing, 0, device=str(tmp_path / "absent"))
    assert missing.cpu_latency_us is None and len(missing.notes) == 1 and "absent" in missing.notes[0]
