"""The HIL's CAN transport (drivers/can_stream.py, python-can interface rig_stream) against a plain socket end
written here from Linux's `struct can_frame` layout: the bytes of each frame, a burst in one write, frames split
across writes, extended and remote frames, a closed connection named; and that python-can finds the interface."""
from __future__ import annotations

import os
import socket
import struct

import can
import pytest

from drivers import can_stream

EFF, RTR = 0x80000000, 0x40000000


@pytest.fixture()
def ends():
    """(bus, the other end's connected socket) on an abstract Unix socket of this test's own."""
    name = f"@rig-test-can-{os.getpid()}-{id(object())}"
    srv = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    srv.bind("\0" + name[1:])
    srv.listen(1)
    bus = can.Bus(interface="rig_stream", channel="can0", address=name)
    conn, _ = srv.accept()
    conn.settimeout(2.0)
    try:
        yield bus, conn
    finally:
        bus.shutdown()
        conn.close()
        srv.close()


def _recv_exactly(conn, n: int) -> bytes:
    out = b""
    while len(out) < n:
        chunk = conn.recv(n - len(out))
        assert chunk, "the bus closed the connection"
        out += chunk
    return out


def test_python_can_finds_the_interface(ends):
    bus, _ = ends
    assert isinstance(bus, can_stream.StreamBus)
    assert bus.channel_info.startswith("rig_stream")


def test_frames_leave_in_socketcan_layout_and_a_burst_in_one_write(ends):
    bus, conn = ends
    with bus.burst():
        bus.send(can.Message(arbitration_id=0x201, data=[0x0F, 0x00, 0x34, 0x12], is_extended_id=False))
        bus.send(can.Message(arbitration_id=0x80, data=b"", is_extended_id=False))
        conn.setblocking(False)
        with pytest.raises(BlockingIOError):        # nothing left before the burst ended
            conn.recv(64)
        conn.settimeout(2.0)
    data = _recv_exactly(conn, 32)
    # struct can_frame: u32 can_id (host order), u8 dlc, 3 pad bytes, 8 data bytes (unused ones zero)
    assert data[:16] == struct.pack("=I", 0x201) + bytes([4, 0, 0, 0]) + bytes([0x0F, 0x00, 0x34, 0x12, 0, 0, 0, 0])
    assert data[16:] == struct.pack("=I", 0x80) + bytes(12)
    bus.send(can.Message(arbitration_id=0x1ABCDEF0, data=[1], is_extended_id=True))   # outside a burst: at once
    assert _recv_exactly(conn, 16) == struct.pack("=I", 0x1ABCDEF0 | EFF) + bytes([1, 0, 0, 0, 1]) + bytes(7)


def test_frames_come_in_whole_also_split_across_writes(ends):
    bus, conn = ends
    tpdo = struct.pack("=I", 0x182) + bytes([5, 0, 0, 0]) + bytes([0x37, 0x02, 0xFF, 0x7F, 9, 0, 0, 0])
    ext = struct.pack("=I", 0x123 | EFF) + bytes([2, 0, 0, 0]) + bytes([0xAA, 0xBB]) + bytes(6)
    rtr = struct.pack("=I", 0x701 | RTR) + bytes(12)
    stream = tpdo + ext + rtr
    conn.sendall(stream[:7])
    assert bus.recv(0.05) is None                    # part of a frame: nothing yet
    conn.sendall(stream[7:40])
    got = [bus.recv(1.0)]
    conn.sendall(stream[40:])
    got += [bus.recv(1.0), bus.recv(1.0)]
    assert [(m.arbitration_id, m.is_extended_id, m.is_remote_frame, bytes(m.data)) for m in got] == [
        (0x182, False, False, bytes([0x37, 0x02, 0xFF, 0x7F, 9])),
        (0x123, True, False, bytes([0xAA, 0xBB])),
        (0x701, False, True, b"")]
    assert bus.recv(0.0) is None


def test_a_closed_connection_is_named(ends):
    bus, conn = ends
    conn.close()
    with pytest.raises(can.CanOperationError, match="rig_stream .*closed"):
        bus.recv(1.0)


def test_no_other_end_is_named():
    with pytest.raises(can.CanInitializationError, match=r"rig_stream @rig-test-nobody-\d+: cannot connect"):
        can.Bus(interface="rig_stream", channel="can0", address=f"@rig-test-nobody-{os.getpid()}",
                connect_timeout_s=0.05)
