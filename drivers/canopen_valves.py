"""CANopen proportional valves (CiA 408 style), one node per mount, on python-can + canopen, in an I/O process
of their own (drivers/process.py).

open():  SDO only here: PDO mapping (RPDO1 = controlword + setpoint, event-driven type 255; TPDO1 = statusword
         + actual + sample counter, synchronous type 1), device mode, control mode, NMT start, DEVICE MODE ACTIVE.
cycle:   the SYNC producer at the loop's rate. Each SYNC goes out `sync_offset_s` after the loop's period
         starts, right after the period's commands (the exchange block, written by the loop's kernel): one RPDO1
         per valve, then SYNC. If the period's commands are not there yet, the process waits for them (a futex
         the loop's commit wakes) up to `sync_wait_s` after the period's start, then sends the ones it has (a
         late command, counted). The valves apply the setpoint, sample and answer by TPDO (decoded in canopen's
         notifier thread); the SYNC's time goes to the block, and the accelerometer module's I/O is woken (the
         module converts on the same SYNC). Without the loop (before it starts, after it stops) SYNC keeps the
         rate on this process's own clock, with the commands last written (null until the loop writes).
faults:  a valve reporting FAULT or HOLD, a garbled TPDO stream, or a SYNC not answered within stale_s: the
         device's line in the block; the port's safe state (the block's safe count): null to every valve.
Device map: drivers/devicemaps/valve408_canopen.md, object dictionary drivers/devicemaps/valve408.eds.
"""
from __future__ import annotations

import struct
import time

import numpy as np

from drivers import conversion
from drivers.process import IODevice
from drivers.protocol import valve408 as v4
from rig.errors import DeviceError
from rig.runtime import exchange as ex
from rig.runtime.rt import raise_priority

SYNC_COB = 0x80


def _no_delay(bus):
    """A socketcand gateway's TCP socket without Nagle's delay (None for other buses). python-can sets it only
    with tcp_tune, which also re-arms TCP_QUICKACK with a system call after every send and receive: that doubled
    this process's CPU time per SYNC (104 -> 196 us for the SYNC, four RPDOs and four TPDOs, measured here)."""
    import socket
    sock = getattr(bus, "_SocketCanDaemonBus__socket", None)
    if not isinstance(sock, socket.socket):
        return None
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    return sock


class _Burst:
    """The RPDOs and the SYNC of one period leave together: a bus that offers `burst()` (the HIL's rig_stream,
    drivers/can_stream.py) writes them at once; a socketcand gateway's socket sends them in one TCP segment
    (TCP_CORK while python-can writes them, one frame each). The gateway wakes once per SYNC, not once per
    frame. On a CAN bus (socketcan) the frames go out one by one as always: nothing to do."""

    def __init__(self, sock, bus=None) -> None:
        import socket
        self.sock, self.cork = sock, getattr(socket, "TCP_CORK", None)
        self.ip = socket.IPPROTO_TCP
        self.burst = getattr(bus, "burst", None)
        self._ctx = None

    def __enter__(self):
        if self.burst is not None:
            self._ctx = self.burst()
            self._ctx.__enter__()
        elif self.sock is not None and self.cork is not None:
            self.sock.setsockopt(self.ip, self.cork, 1)

    def __exit__(self, *exc):
        if self._ctx is not None:
            ctx, self._ctx = self._ctx, None
            ctx.__exit__(*exc)
        elif self.sock is not None and self.cork is not None:
            self.sock.setsockopt(self.ip, self.cork, 0)       # uncorked: the segment goes now


class ValveIO(IODevice):
    """spec: interface, channel (python-can), bus (extra python-can keyword arguments, e.g. a socketcand host and
    port), bitrate, node_ids, names, max_V, stale_s, period_s (the loop's), sync_offset_s, sync_wait_s,
    channels (conversion rows: command V -> setpoint, per valve), priority."""

    def __init__(self, spec: dict, block: ex.Block) -> None:
        super().__init__(spec, block)
        self.interface, self.channel = spec["interface"], spec["channel"]
        self.bus_kw = dict(spec.get("bus", {}))
        self.bitrate = spec.get("bitrate")
        self.node_ids = list(spec["node_ids"])
        self.names = list(spec["names"])
        self.max_V = float(spec["max_V"])
        self.stale_ns = int(spec["stale_s"] * 1e9)
        self.period_ns = int(round(spec["period_s"] * 1e9))
        self.offset_ns = int(round(spec.get("sync_offset_s", 0.3 * spec["period_s"]) * 1e9))
        self.wait_ns = int(round(spec.get("sync_wait_s", 0.6 * spec["period_s"]) * 1e9))
        self.sdo_timeout_s = float(spec.get("sdo_timeout_s", 0.5))
        self.priority = int(spec.get("priority", 0))
        self.chs = conversion.from_dict(spec["channels"]) if "channels" in spec else \
            conversion.channels(range(len(self.node_ids)), [1.0] * len(self.node_ids))
        self.where = f"canopen {self.interface}:{self.channel}"
        n = len(self.node_ids)
        self.network = None
        self.nodes = []
        self.statusword = [0] * n
        self.actual = [0.0] * n               # spool actual, -1..1
        self.counter = [-1] * n
        self.bad = [""] * n                   # a garbled TPDO: the reason
        self.pending_ns = [0] * n             # first SYNC not yet answered by a new TPDO (0 = none)
        self._sync_t = 0
        self._raised = False
        self._cmd = np.zeros(n)
        self._T = 0.0                         # the deadline of the loop's period whose commands went out last
        self._requests = self.requests()
        self._seq_at = block.part("cmd") + ex.C_SEQ

    def label(self, i: int) -> str:
        return f"{self.where} valve {self.names[i]} (node {self.node_ids[i]})"

    # ---- configuration (SDO allowed) -----------------------------------------------------------------
    def open(self) -> None:
        import logging

        import can
        import canopen
        logging.getLogger("canopen").setLevel(logging.CRITICAL)    # our own one-line faults say it
        logging.getLogger("can.interfaces.socketcand").setLevel(logging.ERROR)   # a frame split by TCP: normal
        net = canopen.Network()
        net.NOTIFIER_CYCLE = 0.01              # the notifier (set-up only) stops within 10 ms when run() begins
        kw = {"interface": self.interface, "channel": self.channel, **self.bus_kw}
        if self.bitrate and self.interface not in ("virtual", "socketcand", "rig_stream"):
            kw["bitrate"] = self.bitrate
        if self.interface == "virtual":
            kw["receive_own_messages"] = False
        try:
            net.connect(**kw)
        except (can.CanError, OSError, ValueError, ImportError, TimeoutError) as e:
            raise DeviceError(f"{self.where}: cannot open the CAN bus ({e.__class__.__name__}: {e})") from None
        self.network = net
        self._burst = _Burst(_no_delay(net.bus), net.bus)
        self._bus = net.bus
        self._rpdo = [can.Message(arbitration_id=0x200 + nid, data=bytearray(4), is_extended_id=False)
                      for nid in self.node_ids]
        self._sync_msg = can.Message(arbitration_id=SYNC_COB, data=b"", is_extended_id=False)
        try:
            for i, nid in enumerate(self.node_ids):
                node = canopen.RemoteNode(nid, canopen.import_od(str(v4.EDS_PATH), nid))
                node.sdo.RESPONSE_TIMEOUT = self.sdo_timeout_s
                net.add_node(node)
                self.nodes.append(node)
                self._configure(i, node)
            self._tpdo_cob = {0x180 + nid: i for i, nid in enumerate(self.node_ids)}
            for cob in self._tpdo_cob:             # the TPDOs to us only (canopen's PDO maps need not decode them)
                net.subscribers.get(cob, []).clear()
                net.subscribe(cob, self._on_tpdo)
            for node in self.nodes:
                node.nmt.state = "OPERATIONAL"
            for i, node in enumerate(self.nodes):
                self._sdo(i, lambda: setattr(node.sdo[v4.CONTROLWORD], "raw", v4.CW_ACTIVE), "controlword")
            self._send(null=True)
            deadline = time.monotonic() + max(0.2, 10 * self.stale_ns * 1e-9)
            while time.monotonic() < deadline and min(self.counter) < 0:
                time.sleep(0.001)
            for i in range(len(self.nodes)):
                if self.counter[i] < 0:
                    raise DeviceError(f"{self.label(i)}: no TPDO after SYNC during start-up")
                st = v4.state_of(self.statusword[i])
                if st != "ACTIVE":
                    raise DeviceError(f"{self.label(i)}: valve did not reach DEVICE MODE ACTIVE "
                                      f"(state {st}, statusword 0x{self.statusword[i]:04X})")
        except BaseException:
            self.close()
            raise

    def _sdo(self, i: int, fn, what: str):
        import canopen
        try:
            return fn()
        except (canopen.SdoCommunicationError, canopen.SdoAbortedError) as e:
            raise DeviceError(f"{self.label(i)}: SDO {what} failed ({e})") from None

    def _configure(self, i: int, node) -> None:
        """PDO mapping, device and control mode: all by SDO, before the loop starts."""
        def pdo():
            node.rpdo.read()
            rp = node.rpdo[1]
            rp.clear()
            rp.add_variable(v4.CONTROLWORD)
            rp.add_variable(v4.SETPOINT, 1)
            rp.trans_type = 255                    # event-driven: the valve applies the setpoint on receipt
            rp.enabled = True
            rp.save()
            node.tpdo.read()
            tp = node.tpdo[1]
            tp.clear()
            tp.add_variable(v4.STATUSWORD)
            tp.add_variable(v4.ACTUAL, 1)
            tp.add_variable(v4.SAMPLE_COUNTER)
            tp.trans_type = 1                      # synchronous: sent after every SYNC
            tp.enabled = True
            tp.save()
        self._sdo(i, pdo, "PDO mapping")
        self._sdo(i, lambda: setattr(node.sdo[v4.DEVICE_MODE], "raw", v4.DEVICE_MODE_BUS), "device mode 0x6042")
        self._sdo(i, lambda: setattr(node.sdo[v4.CONTROL_MODE], "raw", v4.CONTROL_MODE_SPOOL_CL),
                  "control mode 0x6043")
        self._sdo(i, lambda: setattr(node.sdo[v4.CONTROLWORD], "raw", v4.CW_RESET_FAULT), "fault reset")
        got = self._sdo(i, lambda: node.sdo[v4.DEVICE_MODE].raw, "device mode read-back")
        if got != v4.DEVICE_MODE_BUS:
            raise DeviceError(f"{self.label(i)}: device mode 0x6042 reads {got}, expected {v4.DEVICE_MODE_BUS}")

    # ---- cyclic ------------------------------------------------------------------------------------------
    def _on_tpdo(self, can_id: int, data, timestamp) -> None:
        """TPDO1: statusword UNSIGNED16, actual INT16, sample counter UNSIGNED8 (little endian); canopen's
        notifier thread."""
        if not self._raised:                       # raise the notifier thread once
            self._raised = True
            raise_priority(self.priority)
        i = self._tpdo_cob[can_id]
        if len(data) != 5:
            self.bad[i] = f"TPDO of {len(data)} bytes (expected 5)"
            return
        sw, act, cnt = struct.unpack("<HhB", bytes(data))
        self.statusword[i] = sw
        self.actual[i] = act / v4.FULL_SCALE
        self.bad[i] = ""
        if cnt != self.counter[i]:
            self.counter[i] = cnt
            self.pending_ns[i] = 0
            if i == 0 and self._sync_t:
                self.stat((time.monotonic_ns() - self._sync_t) * 1e-3)
                self._sync_t = 0

    def _send(self, null: bool = False, cw: int = v4.CW_ACTIVE) -> None:
        """One RPDO1 per valve (the commands held, or null), then SYNC; the SYNC's time to the block and the
        module's I/O woken."""
        send = self._bus.send
        mx = self.max_V
        cmd = self._cmd.tolist()                   # Python floats: numpy scalars cost more per operation
        with self._burst:
            for i, (c, msg) in enumerate(zip(self.chs, self._rpdo)):
                v = c.offset if null else c.gain * cmd[c.source] + c.offset   # null: the valve's own (calibrated)
                struct.pack_into("<Hh", msg.data, 0, cw, v4.volts_to_setpoint(v, mx))
                send(msg)
            now = time.monotonic_ns()
            pend = self.pending_ns
            for i in range(len(pend)):
                if not pend[i]:
                    pend[i] = now
            self._sync_t = now
            send(self._sync_msg)
        self._row[ex.D_PERIOD] = float(self._T)        # before the SYNC's time: the module reads them in turn
        self._row[ex.D_SAMPLE] = float(now)
        self.block.wake(ex.FUTEX_SYNC)

    def _take(self, due: int) -> tuple[bool, bool]:
        """The loop's commands for the SYNC at `due` into self._cmd: (null: the port's safe state or no
        commands yet, late: the loop runs but its period's commands were not there in time)."""
        io = self.io
        seq, T, null = ex.get_commands(io, self._cmd)
        P = self.period_ns
        running = T > 0 and due - T < 4 * P
        if not running or T >= self._T + P // 2 or seq < 0:
            self._T = max(T, self._T)
            return null or T == 0, False
        # the loop runs and this period's commands are not in yet: wait for them (the loop's commit wakes us)
        until = self._T + P + self.wait_ns
        while time.monotonic_ns() < until:
            seen = int(self.block.futex[ex.FUTEX_CMD])
            s2 = ex.ask_wake(io)
            if s2 != seq:
                break
            self.block.wait(ex.FUTEX_CMD, seen, (until - time.monotonic_ns()) * 1e-9)
            if io[self._seq_at] != seq:
                break
        seq, T, null = ex.get_commands(io, self._cmd)
        late = T < self._T + P // 2
        self._T = max(T, self._T)
        return null, late

    def run(self, stop) -> None:
        """SYNC after SYNC; the TPDOs taken in this thread (canopen's notifier stopped after the set-up: one
        thread, no hand-over of the interpreter per frame), each through the network's notify."""
        net = self.network
        if net.notifier is not None:
            net.notifier.stop()
            net.notifier = None
        raise_priority(self.priority)
        self._raised = True
        P = self.period_ns
        due = time.monotonic_ns() + P
        while not stop.is_set():
            self.sleep_until(due)
            null, late = self._take(due)
            self.counted(1, late)
            req = self.requests()
            if req != self._requests:              # the port asked for a fault reset: the R edge, then on
                self._requests = req
                self._send(null=True, cw=v4.CW_ACTIVE | v4.CW_RESET_FAULT)
                self.bad = [""] * len(self.bad)
            self._send(null=null)
            T = self._T
            due = T + P + self.offset_ns if time.monotonic_ns() - T < 2 * P and not late else due + P
            self._receive(due - P // 4)
            now = time.monotonic_ns()
            self.report(self.check(now))
            self.beat()
            if due < now - 2 * P:                  # this process was held up: on from now
                due = now + P // 2

    def _receive(self, until_ns: int) -> None:
        """The frames that came, through the network's notify (the TPDOs to _on_tpdo), until every valve
        answered this SYNC or until_ns."""
        recv, notify, pend = self._bus.recv, self.network.notify, self.pending_ns
        tpdo, on_tpdo = self._tpdo_cob, self._on_tpdo
        while True:
            left = 0.0 if not any(pend) else (until_ns - time.monotonic_ns()) * 1e-9   # answered: what is in
            msg = recv(max(left, 0.0))
            if msg is None:
                return
            if msg.arbitration_id in tpdo:         # (the one subscriber of a TPDO: straight to it)
                on_tpdo(msg.arbitration_id, msg.data, msg.timestamp)
            else:
                notify(msg.arbitration_id, msg.data, msg.timestamp)

    def check(self, now_ns: int) -> str | None:
        """A one-line fault naming the valve, or None."""
        for i in range(len(self.node_ids)):
            if self.bad[i]:
                return f"{self.label(i)}: garbled TPDO: {self.bad[i]}"
            st = v4.state_of(self.statusword[i])
            if st != "ACTIVE":
                return f"{self.label(i)}: valve in {st} (statusword 0x{self.statusword[i]:04X})"
            # a SYNC unanswered (no TPDO with a new counter) for longer than the limit: not answering
            p = self.pending_ns[i]
            if p and now_ns - p > self.stale_ns:
                return (f"{self.label(i)}: no new TPDO for {(now_ns - p) / 1e6:.1f} ms after SYNC "
                        f"(limit {self.stale_ns / 1e6:g} ms): not answering")
        return None

    def close(self) -> None:
        net = self.network
        if net is None:
            return
        try:
            for node in self.nodes:
                try:
                    net.send_message(0x200 + node.id, struct.pack("<Hh", v4.CW_DISABLE, 0))
                except Exception:          # noqa: BLE001 - closing: best effort
                    pass
            try:
                net.send_message(SYNC_COB, b"")
            except Exception:              # noqa: BLE001
                pass
        finally:
            self.network = None
            self.nodes = []
            try:
                net.disconnect()
            except Exception:              # noqa: BLE001 - the bus may be gone already
                pass
