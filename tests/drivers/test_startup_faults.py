"""Devices that are missing at start-up or die while running (issue 17, items 1 and 7): one line naming the
device, no traceback, no recording replaced, and the FAULT line printed once. Real stacks on loopback only:
Modbus TCP on 127.0.0.1, python-can's virtual bus (inside one I/O process: no valve answers there) and its
socketcand interface to the emulated valves' gateway, pty serial ports (the emulated rig)."""
from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from drivers import build_driver_port
from rig.backends import make_hil_port
from rig.runtime.clock import MonotonicClock
from rig.config import Config, HilConfig, VibrationConfig, config_from_dict, hil_run_config
from rig.errors import DeviceError
from rig.runtime.lifecycle import State
from rig.runtime.loop import Loop
from sim_backend.emulators.rig import EmulatedRig
from tests.paths import REPO
from tests.rig.support import CentringP
from tests.sim_backend.standin import StandInPlant

pytestmark = pytest.mark.hil           # the real drivers against closed ports and emulated devices, loopback
RIG = [sys.executable, "-m", "rig.cli"]


def _closed_port() -> int:
    """A loopback TCP port nothing listens on (bound, then released)."""
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


def _hardware_config(tmp_path: Path) -> Path:
    """The hardware backend pointed at loopback: a closed Modbus port, a serial device that does not exist and
    a virtual CAN bus (nothing here reaches a real address)."""
    cfg = tmp_path / "hw.toml"
    cfg.write_text(f'[backend]\nname = "hardware"\n[drivers]\ncan_interface = "virtual"\ncan_channel = '
                   f'"rig-test-{os.getpid()}"\nmodbus_host = "127.0.0.1"\nmodbus_port = {_closed_port()}\n'
                   f'modbus_timeout_s = 0.05\nserial_port = "{tmp_path / "no-such-tty"}"\n')
    return cfg


def test_drivers_close_safely_without_open():
    """Closing the port that never started: no process to stop, its exchange block gone from /dev/shm."""
    cfg = Config()
    port = build_driver_port(cfg, "hardware", can_interface="virtual", can_channel="never",
                             modbus_host="127.0.0.1", modbus_port=_closed_port(), serial_port="/nonexistent/tty",
                             stale_s=0.1)
    path = port.exchange.path
    assert os.path.exists(path)
    port.close()
    port.close()
    assert not os.path.exists(path) and not port.pids


def test_missing_device_at_start_up_is_one_line_naming_it_and_keeps_the_recording(tmp_path):
    """Item 1: `rig run` on the hardware backend with the Modbus module absent. Was: `RuntimeError: cannot join
    thread before it is started`, exit 1, and the --record file replaced by an empty one."""
    cfg = _hardware_config(tmp_path)
    rec = tmp_path / "precious.h5"
    rec.write_bytes(b"sixteen megabytes of yesterday's run")
    out = subprocess.run(RIG + ["run", "--config", str(cfg), "--seconds", "1", "--record", str(rec), "--overwrite",
                                "--no-realtime", "--quiet", "--uncommissioned"], capture_output=True, text=True, timeout=120,
                         cwd=tmp_path)
    assert out.returncode == 2, out.stderr
    lines = out.stderr.strip().splitlines()
    assert "Traceback" not in out.stderr
    assert len(lines) == 1 and lines[0].startswith("rig run: error: modbus_tcp 127.0.0.1:"), out.stderr
    assert "not answering" in lines[0]
    assert rec.read_bytes() == b"sixteen megabytes of yesterday's run"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["hw.toml", "precious.h5"]      # no partial file left


def test_missing_device_without_a_recording_leaves_no_empty_file(tmp_path):
    cfg = _hardware_config(tmp_path)
    rec = tmp_path / "new.h5"
    out = subprocess.run(RIG + ["chirp", "--config", str(cfg), "--duration", "1", "--record", str(rec),
                                "--uncommissioned"],
                         capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert out.stderr.strip().splitlines()[-1].startswith("rig chirp: error: modbus_tcp 127.0.0.1:")
    assert not rec.exists()


def test_missing_valves_with_the_other_devices_present_name_the_valve():
    """The Modbus module and the serial amplifier answer (emulated), the valves at the configured node ids do
    not: the DeviceError names the valve node, and the I/O processes already started are stopped again."""
    cfg = Config()
    emu = EmulatedRig(StandInPlant(1e-3), 1e-3, node_ids=[1, 2, 3, 4], priority=0).start()
    try:
        port = build_driver_port(cfg.replace(drivers=config_from_dict(
            {"drivers": {"valve_node_id_base": 20}}).drivers), "hil", can_interface="socketcand",
            can_channel="can0", can_options={"host": "127.0.0.1", "port": emu.can_port},
            modbus_host="127.0.0.1", modbus_port=emu.modbus_port, serial_port=emu.serial_path, stale_s=0.1,
            priority=0, period_s=1e-3)
        with pytest.raises(DeviceError, match=r"canopen socketcand:can0 valve front_left \(node 20\): SDO"):
            port.open()
        assert not port.pids                                    # every I/O process stopped
        port.close()
    finally:
        emu.stop()


def test_dead_modbus_module_is_named_in_the_loop_fault():
    """Item 7: a Modbus module that dies while the loop runs ends in FAULT naming the module (host:port, unit),
    not the first mount's stale sample. Was: `front_left: stale sample: 101 ms old`."""
    cfg = hil_run_config(Config().replace(hil=HilConfig(rate_hz=500.0), vibration=VibrationConfig(rms_m=0.0)))
    # the serial amplifier's staleness limit out of the way (a loaded machine's stalls are not this test's)
    port = make_hil_port(cfg, StandInPlant(2e-3), dt=2e-3, priority=0, serial_stale_s=5.0)
    try:
        loop = Loop(cfg, port, [CentringP(1e4, dt=2e-3) for _ in range(4)], clock=MonotonicClock(), rate_hz=500.0)
        loop.configure()
        pid = port.rig.device_pid("modbus")
        threading.Timer(0.3, lambda: os.kill(pid, signal.SIGKILL)).start()
        loop.run(seconds=5.0, activate_after_s=0.05)
        assert loop.lc.state is State.FAULT
        assert loop.lc.fault_reason.startswith("device fault: modbus_tcp 127.0.0.1:"), loop.lc.fault_reason
        assert "unit 1: no new sample" in loop.lc.fault_reason
    finally:
        port.close()


def test_hil_fault_line_is_printed_once(tmp_path):
    """Item 7: every FAULT line was printed twice in `rig hil` (the lifecycle's log line and the command's own)."""
    text = (REPO / "drivers" / "devicemaps" / "hil.toml").read_text().replace("\nstale_s = 0.1\n", "\nstale_s = 0.001\n")
    cfg = tmp_path / "tight.toml"
    cfg.write_text(text)
    out = subprocess.run(RIG + ["hil", "--config", str(cfg), "--seconds", "1", "--no-realtime", "--record",
                                str(tmp_path / "r.h5")], capture_output=True, text=True, timeout=180, cwd=tmp_path)
    assert out.returncode == 1, out.stderr
    assert out.stderr.count("FAULT:") == 1, out.stderr
