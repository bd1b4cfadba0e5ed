"""python-can interface `rig_stream`: a CAN bus carried over a local stream socket, each frame in the 16 bytes of
Linux's `struct can_frame` (can_id with the EFF/RTR/ERR flags, dlc, 3 pad bytes, 8 data bytes). It is the HIL's
CAN between the valves' I/O process and the emulated valve nodes (sim_backend/emulators/canopen_valve.py), used
through canopen by the unchanged valve driver (drivers/canopen_valves.py); the real rig opens its own interface
([drivers] can_interface: socketcan).

Why: python-can's `virtual` bus connects only inside one process, there is no vcan here, multicast is not
allowed, and python-can's `socketcand` interface formats and parses every frame as text (drivers/README.md,
the CPU budget: the valves' I/O process spent most of its time per SYNC there and in TCP).

channel: the bus's name (as socketcand's `can0`); address: the socket's, a Unix socket path or `@name` for
Linux's abstract namespace (nothing on disk, never off the host); default the channel. `burst()`: the frames sent inside it leave in one write (the RPDOs and the SYNC of one
period: the other end wakes once).
"""
from __future__ import annotations

import contextlib
import select
import socket
import struct
import time
from collections import deque

import can

FRAME = struct.Struct("=IB3x8s")        # struct can_frame, host byte order (as SocketCAN's raw sockets)
CAN_EFF_FLAG, CAN_RTR_FLAG, CAN_ERR_FLAG = 0x80000000, 0x40000000, 0x20000000
CAN_EFF_MASK, CAN_SFF_MASK = 0x1FFFFFFF, 0x7FF


def socket_address(name: str) -> str:
    """`@name` -> the abstract socket `\\0name`; a path as it is."""
    return "\0" + name[1:] if name.startswith("@") else name


_address = socket_address


def pack(can_id: int, data: bytes, extended: bool = False, remote: bool = False) -> bytes:
    """One frame's 16 bytes."""
    cid = (can_id & CAN_EFF_MASK) | CAN_EFF_FLAG if extended else can_id & CAN_SFF_MASK
    if remote:
        cid |= CAN_RTR_FLAG
    return FRAME.pack(cid, len(data), bytes(data))


def unpack(buf: bytes) -> tuple[list[tuple[int, int, bytes]], bytes]:
    """The whole frames in buf as (can_id with flags, dlc, data), and the bytes left over (a frame split)."""
    n = len(buf) // FRAME.size * FRAME.size
    out = [(cid, dlc, data[:dlc]) for cid, dlc, data in FRAME.iter_unpack(buf[:n])]
    return out, buf[n:]


class StreamBus(can.BusABC):
    """A python-can bus over a stream socket to the other end (the emulated nodes' gateway)."""

    def __init__(self, channel: str, address: str | None = None, can_filters=None, connect_timeout_s: float = 10.0,
                 **kwargs) -> None:
        where = address or channel
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        end = time.monotonic() + connect_timeout_s
        while True:
            try:
                self._sock.connect(_address(where))
                break
            except OSError as e:
                if time.monotonic() > end:
                    self._sock.close()
                    raise can.CanInitializationError(f"rig_stream {where}: cannot connect ({e})") from None
                time.sleep(0.01)
        self._rx: deque[can.Message] = deque()
        self._buf = b""
        self._out: list[bytes] | None = None
        self.channel = channel
        self.channel_info = f"rig_stream {channel}"
        super().__init__(channel=channel, can_filters=can_filters, **kwargs)

    def fileno(self) -> int:
        return self._sock.fileno()

    def _recv_internal(self, timeout):
        if self._rx:
            return self._rx.popleft(), False
        if timeout is None or timeout > 0:
            try:
                ready, _, _ = select.select([self._sock], [], [], timeout)
            except OSError as e:
                raise can.CanOperationError(f"rig_stream {self.channel}: {e}") from None
            if not ready:
                return None, False
        try:
            data = self._sock.recv(65536, socket.MSG_DONTWAIT)
        except BlockingIOError:
            return None, False
        except OSError as e:
            raise can.CanOperationError(f"rig_stream {self.channel}: {e}") from None
        if not data:
            raise can.CanOperationError(f"rig_stream {self.channel}: the other end closed the connection")
        frames, self._buf = unpack(self._buf + data)
        now, ch = time.time(), self.channel
        for cid, dlc, payload in frames:
            self._rx.append(can.Message(
                timestamp=now, arbitration_id=cid & (CAN_EFF_MASK if cid & CAN_EFF_FLAG else CAN_SFF_MASK),
                is_extended_id=bool(cid & CAN_EFF_FLAG), is_remote_frame=bool(cid & CAN_RTR_FLAG),
                is_error_frame=bool(cid & CAN_ERR_FLAG), dlc=dlc, data=payload, channel=ch, check=False))
        return (self._rx.popleft() if self._rx else None), False

    def send(self, msg: can.Message, timeout=None) -> None:
        frame = pack(msg.arbitration_id, bytes(msg.data[:msg.dlc]), msg.is_extended_id, msg.is_remote_frame)
        if self._out is not None:
            self._out.append(frame)
            return
        try:
            self._sock.sendall(frame)
        except OSError as e:
            raise can.CanOperationError(f"rig_stream {self.channel}: {e}") from None

    @contextlib.contextmanager
    def burst(self):
        """The frames sent inside leave together, in one write, when it ends."""
        self._out = []
        try:
            yield
        finally:
            out, self._out = b"".join(self._out), None
            if out:
                try:
                    self._sock.sendall(out)
                except OSError as e:
                    raise can.CanOperationError(f"rig_stream {self.channel}: {e}") from None

    def shutdown(self) -> None:
        super().shutdown()
        self._sock.close()
