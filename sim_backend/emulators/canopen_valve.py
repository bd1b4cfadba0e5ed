"""Emulated CiA 408-style valve nodes and the plant they drive, in a process of their own, behind a CAN gateway
with two doors: binary SocketCAN-layout frames on an abstract Unix socket (python-can interface `rig_stream`,
drivers/can_stream.py: HIL's default, [hil] can_transport) and socketcand's text protocol on 127.0.0.1
(python-can's `socketcand` interface, as the driver would reach a remote CAN bus through a socketcand daemon).

Why these transports: python-can's `virtual` bus connects only inside one process, there is no vcan here and
multicast is not allowed; python-can's `slcan` over a pty pair (a USB-CAN adapter's serial line) reads its
frames byte by byte and drains the line after each one (measured here: SYNC -> four TPDOs p50 448 us,
p99 1.7 ms, against 66 us / 163 us for socketcand on loopback TCP): too slow for a 2 kHz loop. socketcand
formats and parses each frame as text on both ends; rig_stream moves the same frames as bytes
(drivers/README.md: the CPU budget).

The nodes are canopen LocalNodes on a canopen Network whose frames go through the gateway (the network's own
send_message and notify, canopen's documented way to a custom interface), all in this process's one thread.
RPDO1 (event-driven, type 255) carries the setpoint; the driver sends it right before its SYNC. On each SYNC
the plant steps to the SYNC instant with the setpoints latched at the SYNC before (each command acts from
the SYNC after it was sent: a ZOH plus one period after its sample), the devices' shared state gets the
step's conversion (the Modbus module and the amplifier, processes of their own, serve it), the new setpoints
are latched, and each node answers with its synchronous TPDO (status word, spool actual value, sample
counter), the four in one TCP write. Without SYNC (the loop not started, held up, stopped) the plant keeps
pace with the wall clock on the commands it has.

Wiring faults of the valves ([hil] valve_null_V, valve_gain, valve_node_id; drivers/devicemaps/
hil_wiring_faults.md): the plant's input from valve i is gain_i x (its setpoint - null_i), and each mount's node
answers to the number it was given (two exchanged: the driver's command for one mount moves the other).
"""
from __future__ import annotations

import math
import os
import pickle
import random
import select
import socket
import struct
import sys
import time

from drivers import can_stream
from drivers.protocol import valve408 as v4
from rig.runtime.rt import raise_priority
from sim_backend.emulators import shared as sh

# per-node fault knobs
VALVE_MODES = ("ok", "silence", "garbage", "stale", "fault", "hold")
_ACTIVE_BITS = v4.BIT_D | v4.BIT_H | v4.BIT_M | v4.BIT_R      # DEVICE MODE ACTIVE (v4.state_of)


class ValveNode:
    """One valve: the 408 state machine, a first-order spool model for the actual value, and its knob."""

    def __init__(self, network, node_id: int, w_spool: float, od_path=v4.EDS_PATH):
        import canopen
        self.node = canopen.LocalNode(node_id, canopen.import_od(str(od_path), node_id))
        network.add_node(self.node)
        self.id = node_id
        self.w_spool = w_spool
        self.mode = "ok"
        self.statusword = v4.BIT_R          # powered, ready, DISABLED
        self.controlword = 0
        self.setpoint = 0                   # latched at SYNC
        self.actual = 0.0
        self.counter = 0
        self.frozen: bytes | None = None
        self._dt = None
        self._pdo_dirty = True
        self._rng = random.Random(node_id)
        self.node.add_write_callback(self._on_write)
        self.node.add_read_callback(self._on_read)

    def _on_write(self, index, subindex, od, data):
        if 0x1400 <= index <= 0x1BFF:
            self._pdo_dirty = True
        elif index == v4.CONTROLWORD:
            self._apply_controlword(int.from_bytes(data, "little"))

    def _on_read(self, index, subindex, od):
        if index == v4.STATUSWORD:
            return self.statusword
        if index == v4.ACTUAL and subindex == 1:
            return int(round(self.actual))
        return None

    def _apply_controlword(self, cw: int) -> None:
        if cw & v4.BIT_R and not self.controlword & v4.BIT_R and self.mode != "fault":
            self.statusword |= v4.BIT_R                     # rising edge of R: fault reset
        self.controlword = cw
        if not self.statusword & v4.BIT_R:
            return                                          # in FAULT: only a reset leaves it
        dhm = cw & (v4.BIT_D | v4.BIT_H | v4.BIT_M)
        if not dhm & v4.BIT_D:
            dhm = 0
        elif not dhm & v4.BIT_H:
            dhm = v4.BIT_D
        self.statusword = (self.statusword & ~0x7) | dhm

    def _reload_pdo(self) -> None:
        """The host rewrote the PDO configuration by SDO: read it back from our own object dictionary, and turn
        each mapping into a struct format and its objects for the cyclic path (RPDO1 then comes to _on_rpdo)."""
        node = self.node
        node.rpdo.read(from_od=False)
        node.tpdo.read(from_od=False)
        rp, tp = node.rpdo[1], node.tpdo[1]
        self._rp_fmt, self._rp_idx = self._layout(rp)
        self._tp_fmt, self._tp_idx = self._layout(tp)
        self._tp_cob = tp.cob_id
        net = node.network
        net.subscribers.get(rp.cob_id, []).clear()         # canopen's PDO map: the cyclic path is ours
        net.subscribe(rp.cob_id, self._on_rpdo)
        self._rx = self._rx_last = None
        self._rp_size = struct.calcsize(self._rp_fmt)
        self._standard = self._tp_idx == [v4.STATUSWORD, v4.ACTUAL, v4.SAMPLE_COUNTER]
        self._pdo_dirty = False

    @staticmethod
    def _layout(pdo_map) -> tuple[str, list[int]]:
        """The mapping as a little-endian struct format over its objects (byte-aligned, in order)."""
        import canopen
        fmt, idx, at = "<", [], 0
        for v in pdo_map.map:
            if v.offset % 8 or v.length % 8 or v.offset // 8 != at:
                raise ValueError("emulated valve: only byte-aligned, contiguous PDO mappings")
            signed = v.od.data_type in canopen.objectdictionary.SIGNED_TYPES
            fmt += {1: "b", 2: "h", 4: "i"}[v.length // 8].upper() if not signed else {1: "b", 2: "h", 4: "i"}[
                v.length // 8]
            idx.append(v.index)
            at += v.length // 8
        return fmt, idx

    def _on_rpdo(self, can_id, data, timestamp) -> None:
        self._rx = bytes(data)

    def on_sync(self, dt: float) -> None:
        """The setpoint latched at the SYNC before acts over the step that ends at this SYNC (the spool follows
        it); then the RPDO received since is taken (controlword, setpoint) for the next step."""
        if self.node.nmt.state != "OPERATIONAL":
            return
        if self._pdo_dirty:
            self._reload_pdo()
        if self.mode == "fault":
            self.statusword &= ~v4.BIT_R
        elif self.mode == "hold":
            self.statusword = (self.statusword & ~0x7) | v4.BIT_D
        applied = self.setpoint if self.statusword & _ACTIVE_BITS == _ACTIVE_BITS else 0   # else: null
        if dt != self._dt:
            self._dt, self._follow = dt, 1.0 - math.exp(-self.w_spool * dt)
        self.actual += (applied - self.actual) * self._follow
        self.counter = (self.counter + 1) & 0xFF
        data, self._rx = self._rx, None
        if data is not None and data != self._rx_last and len(data) >= self._rp_size:   # (a short one: ignored)
            self._rx_last = data
            for idx, v in zip(self._rp_idx, struct.unpack_from(self._rp_fmt, data)):
                if idx == v4.CONTROLWORD:
                    if v != self.controlword:
                        self._apply_controlword(v)
                elif idx == v4.SETPOINT:
                    self.setpoint = v

    def tpdo(self) -> tuple[int, bytes] | None:
        """The TPDO this SYNC answers with (cob id, data), or None (silent)."""
        if self.node.nmt.state != "OPERATIONAL" or self.mode == "silence":
            return None
        if self.mode == "stale" and self.frozen is not None:
            return self._tp_cob, self.frozen
        if self.mode == "garbage":
            return self._tp_cob, bytes([self._rng.getrandbits(8)])
        if self._standard:
            self.frozen = struct.pack(self._tp_fmt, self.statusword, int(round(self.actual)), self.counter)
        else:
            vals = {v4.STATUSWORD: self.statusword, v4.ACTUAL: int(round(self.actual)),
                    v4.SAMPLE_COUNTER: self.counter}
            self.frozen = struct.pack(self._tp_fmt, *(vals.get(i, 0) for i in self._tp_idx))
        return self._tp_cob, self.frozen


def _network(send):
    """A canopen Network whose frames go out through send(can_id, data) and come in through notify()."""
    import canopen

    class GatewayNetwork(canopen.Network):
        def send_message(self, can_id: int, data: bytes, remote: bool = False) -> None:
            send(can_id, bytes(data))
    return GatewayNetwork()


class Gateway:
    """The socketcand side of one TCP client (rawmode): `< send ID LEN B0 B1 .. >` in, `< frame ID T HEX >` out."""

    def __init__(self, conn: socket.socket) -> None:
        self.conn = conn
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        conn.sendall(b"< hi >")
        self.raw = False
        self.buf = b""
        self.out: list[bytes] = []
        self.now = time.time()                 # the frames' time stamp (set per batch)

    def frames(self, data: bytes):
        """(can_id, data) of each frame the client sent; the handshake answered on the way."""
        self.buf += data
        while True:
            i = self.buf.find(b"<")
            j = self.buf.find(b">", i + 1)
            if i < 0 or j < 0:
                if i < 0:
                    self.buf = b""
                return
            msg, self.buf = self.buf[i + 1:j].split(), self.buf[j + 1:]
            if not msg:
                continue
            if msg[0] == b"open":
                self.conn.sendall(b"< ok >")
            elif msg[0] == b"rawmode":
                self.raw = True
                self.conn.sendall(b"< ok >")
            elif msg[0] == b"send" and len(msg) >= 3:
                try:
                    yield int(msg[1], 16), bytes(int(b, 16) for b in msg[3:3 + int(msg[2], 16)])
                except ValueError:
                    continue

    def send(self, can_id: int, data: bytes) -> None:
        self.out.append(b"< frame %03X %.6f %s >" % (can_id, self.now, data.hex().encode()))

    def flush(self) -> None:
        if self.out:
            out, self.out = b"".join(self.out), []
            try:
                self.conn.sendall(out)
            except OSError:
                pass


class StreamGateway:
    """The other end of the valves' I/O's `rig_stream` bus (drivers/can_stream.py): binary SocketCAN-layout
    frames over a local stream socket, no handshake; the same interface as Gateway."""

    def __init__(self, conn: socket.socket) -> None:
        self.conn = conn
        self.buf = b""
        self.out: list[bytes] = []
        self.now = time.time()

    def frames(self, data: bytes):
        frames, self.buf = can_stream.unpack(self.buf + data)
        for cid, _dlc, payload in frames:
            if not cid & (can_stream.CAN_ERR_FLAG | can_stream.CAN_RTR_FLAG):
                yield cid & (can_stream.CAN_EFF_MASK if cid & can_stream.CAN_EFF_FLAG else can_stream.CAN_SFF_MASK), \
                    payload

    def send(self, can_id: int, data: bytes) -> None:
        self.out.append(can_stream.pack(can_id, data))

    flush = Gateway.flush


class PlantServer:
    """This process: the plant, the valve nodes, the gateway; the devices' shared state (sim_backend/emulators/
    shared.py) written at each step, the fault knobs and the metering read from it."""

    def __init__(self, arr, plant, dt: float, node_ids, w_spool: float, max_V: float, floor_sensors: bool,
                 trace_steps: int, valve_faults=None) -> None:
        self.arr, self.plant, self.dt = arr, plant, dt
        self.max_V = max_V
        self.floor_sensors = floor_sensors
        self.trace_steps = trace_steps
        self.gw: Gateway | None = None
        self.net = _network(self._send)
        self.nodes = [ValveNode(self.net, nid, w_spool) for nid in node_ids]
        self.net.subscribe(0x80, self._sync)
        n = len(self.nodes)
        # the valves' wiring faults ([hil] valve_null_V, valve_gain): the flow of valve i follows
        # gain_i * (setpoint - null_i), its spool centred at null_i (Eq. 1: x_v = K_v v; the flow K_Q x_v)
        null, gain = valve_faults if valve_faults is not None else ([0.0] * n, [1.0] * n)
        self.null_V, self.gain = [float(v) for v in null[:n]], [float(g) for g in gain[:n]]
        self.setpoint_V = [0.0] * n                    # what the valves were sent (latched at SYNC)
        self.cmd = [-g * v0 for v0, g in zip(self.null_V, self.gain)]   # the plant's input, the faults applied
        self.steps = 0
        self._t0: float | None = None
        # a refill of the floor and noise blocks inside a step held that SYNC's conversion up by about 160 us,
        # every 256 steps (a held period in rig hil at 2 kHz): drawn between SYNCs instead
        self._prefetch = getattr(plant, "prefetch", None) or (lambda: None)
        self._publish()

    def _send(self, can_id: int, data: bytes) -> None:
        if self.gw is not None:
            self.gw.send(can_id, data)

    def _sync(self, can_id, data, timestamp) -> None:
        for i, n in enumerate(self.nodes):
            n.mode = VALVE_MODES[int(self.arr[sh.VALVE_MODE + i])]
            n.on_sync(self.dt)
        self._advance(time.monotonic(), sync=True)          # the step ending now, on the commands held
        self.setpoint_V = [v4.setpoint_to_volts(n.setpoint if v4.state_of(n.statusword) == "ACTIVE" else 0, self.max_V)
                           for n in self.nodes]               # latched for the next step
        self.cmd = [g * (v - v0) for v, v0, g in zip(self.setpoint_V, self.null_V, self.gain)]
        self.arr[sh.SYNCS] += 1.0
        for n in self.nodes:
            t = n.tpdo()
            if t is not None:
                self._send(*t)

    def _advance(self, now: float, sync: bool) -> None:
        """The plant keeps pace with the wall clock: one step per SYNC, extra steps when it fell behind, none
        when ahead; without SYNC it catches up on the commands it has."""
        if self._t0 is None:
            self._t0 = now - self.dt
        behind = (now - self._t0) / self.dt - self.steps
        if sync:
            n = 1 if -1.5 <= behind <= 1.5 else (0 if behind < 0 else min(int(behind), 1000))
        else:
            n = min(int(behind - 1.5), 1000) if behind > 2.5 else 0
        for _ in range(n):
            self.plant.step(self.cmd)
            self.steps += 1
            self._meter()
            self._publish()                 # every step is a conversion of the devices

    def _publish(self) -> None:
        p = self.plant
        self.arr[sh.LAST_CMD:sh.LAST_CMD + len(self.cmd)] = self.setpoint_V
        sh.publish(self.arr, float(getattr(p, "t_s", 0.0)), p.accel_mps2, p.stroke_m, self.steps,
                   p.floor_accel_mps2 if self.floor_sensors else None)

    def _meter(self) -> None:
        """The true table motion (and the floor under it) into the current phase's sums and the trace."""
        arr, p = self.arr, self.plant
        x = float(p.table_m) if not isinstance(p.table_m, (list, tuple)) else math.fsum(p.table_m) / len(p.table_m)
        fm = getattr(p, "floor_m", ())
        g = math.fsum(fm) / len(fm) if fm else 0.0
        ph = int(arr[sh.PHASE])
        if 0 < ph <= sh.MAX_PHASES:
            m = sh.METER + 5 * (ph - 1)
            arr[m] += 1
            arr[m + 1] += x
            arr[m + 2] += x * x
            arr[m + 3] += g
            arr[m + 4] += g * g
        k = int(arr[sh.TRACE])
        if k < self.trace_steps:
            b = sh.SIZE + sh.TRACE_WIDTH * k
            arr[b:b + 3] = (x, g, float(ph))
            arr[sh.TRACE] = k + 1

    def handle(self, data: bytes) -> None:
        """The client's frames in `data` to the nodes (a SYNC steps the plant), their answers out; then the
        plant's next block of floor and noise is drawn, after the TPDOs, not inside a step."""
        subs = self.net.subscribers
        now = self.gw.now = time.time()
        for can_id, frame in self.gw.frames(data):     # (the network's notify, without its scanner)
            for cb in subs.get(can_id, ()):
                cb(can_id, frame, now)
        self.gw.flush()
        self._prefetch()

    def serve(self, listeners: dict, parent_gone) -> None:
        """listeners: {listening socket: its gateway class}; one client at a time (a new one replaces it)."""
        while not parent_gone():
            socks = list(listeners) + ([self.gw.conn] if self.gw is not None else [])
            r, _, _ = select.select(socks, [], [], 2 * self.dt)
            for srv in listeners:
                if srv in r:
                    conn, _ = srv.accept()
                    if self.gw is not None:
                        self.gw.conn.close()
                    self.gw = listeners[srv](conn)
            if self.gw is not None and self.gw.conn in r:
                try:
                    data = self.gw.conn.recv(65536)
                except OSError:
                    data = b""
                if not data:
                    self.gw.conn.close()
                    self.gw = None
                    continue
                self.handle(data)
            else:
                self._advance(time.monotonic(), sync=False)   # no SYNC came: the plant keeps pace


def serve(arr, announce, spec_path: str, priority: int = 0) -> None:
    """Process entry: the pickled spec (plant, dt, node ids, spool bandwidth, valve range, floor sensors, trace
    length) from spec_path, listen on 127.0.0.1 (socketcand) and on an abstract Unix socket (rig_stream),
    announce `PORT NAME`, serve until the parent goes away."""
    import logging
    logging.getLogger("canopen").setLevel(logging.WARNING)
    with open(spec_path, "rb") as f:
        spec = pickle.load(f)
    os.unlink(spec_path)
    server = PlantServer(arr, spec["plant"], spec["dt"], spec["node_ids"], spec["w_spool"], spec["max_V"],
                         spec["floor_sensors"], spec["trace_steps"], spec.get("valve_faults"))
    raise_priority(priority)                 # (after the set-up: at SCHED_FIFO it would hold the others off)
    srv = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    srv.bind(("127.0.0.1", 0))
    srv.listen(2)
    name = f"@rig-hil-can-{os.getpid()}-{srv.getsockname()[1]}"     # abstract: nothing on disk, never off the host
    local = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    local.bind(can_stream.socket_address(name))
    local.listen(2)
    announce.send(f"{srv.getsockname()[1]} {name}")
    parent = os.getppid()
    try:
        server.serve({srv: Gateway, local: StreamGateway}, lambda: os.getppid() != parent or announce.poll())
    finally:
        srv.close()
        local.close()
        sys.stdout.flush()
