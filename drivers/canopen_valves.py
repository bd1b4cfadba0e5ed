"""CANopen proportional valves (CiA 408 style), one node per mount, on python-can + canopen.

open():  SDO only here: PDO mapping (RPDO1 = controlword + setpoint, event-driven type 255; TPDO1 = statusword
         + actual + sample counter, synchronous type 1), device mode, control mode, NMT start, DEVICE MODE ACTIVE.
period:  sync() sends SYNC (the valves sample and answer by TPDO); write() sends one RPDO per valve, applied
         on receipt. No SDO and no waiting inside the period.
faults:  a valve reporting FAULT or HOLD, a garbled TPDO stream, or a SYNC not answered within stale_s.
Device map: drivers/devicemaps/valve408_canopen.md, object dictionary drivers/devicemaps/valve408.eds.
"""
from __future__ import annotations

import struct
import time

from drivers.protocol import valve408 as v4
from rig.runtime.rt import raise_priority
from rig.errors import DeviceError

SYNC_COB = 0x80


class CanopenValves:
    def __init__(self, *, interface: str, channel: str, node_ids: list[int], names: list[str], max_V: float,
                 stale_s: float, bitrate: int | None = None, sdo_timeout_s: float = 0.5, priority: int = 0):
        self.interface = interface
        self.channel = channel
        self.bitrate = bitrate
        self.node_ids = list(node_ids)
        self.names = list(names)
        self.max_V = max_V
        self.stale_ns = int(stale_s * 1e9)
        self.sdo_timeout_s = sdo_timeout_s
        self.priority = priority
        self._raised = False
        self.network = None
        self.nodes = []
        n = len(node_ids)
        self.statusword = [0] * n
        self.actual = [0.0] * n               # spool actual, -1..1
        self.counter = [-1] * n
        self.rx_ns = [0] * n                  # when the last TPDO with a new counter arrived
        self.bad = [""] * n                   # a garbled TPDO: the reason
        self.pending_ns = [0] * n             # first SYNC not yet answered by a new TPDO (0 = none)
        self._sync_t = 0
        self.latency_ns = [0] * (1 << 16)     # SYNC -> first valve's TPDO, for the benchmark
        self.n_latency = 0
        self._setpoints = [0] * n
        self._rpdo_cob = [0x200 + nid for nid in node_ids]
        self._tpdo_cob = {0x180 + nid: i for i, nid in enumerate(node_ids)}
        self.where = f"canopen {interface}:{channel}"

    def label(self, i: int) -> str:
        return f"{self.where} valve {self.names[i]} (node {self.node_ids[i]})"

    # ---- configuration (SDO allowed) -----------------------------------------------------------------
    def open(self) -> None:
        import logging

        import can
        import canopen
        logging.getLogger("canopen").setLevel(logging.WARNING)     # its INFO lines narrate every SDO
        net = canopen.Network()
        kw = {"interface": self.interface, "channel": self.channel}
        if self.bitrate and self.interface != "virtual":
            kw["bitrate"] = self.bitrate
        if self.interface == "virtual":
            kw["receive_own_messages"] = False
        try:
            net.connect(**kw)
        except (can.CanError, OSError, ValueError, ImportError) as e:
            raise DeviceError(f"{self.where}: cannot open the CAN bus ({e.__class__.__name__}: {e})") from None
        self.network = net
        try:
            for i, nid in enumerate(self.node_ids):
                node = canopen.RemoteNode(nid, canopen.import_od(str(v4.EDS_PATH), nid))
                node.sdo.RESPONSE_TIMEOUT = self.sdo_timeout_s
                net.add_node(node)
                self.nodes.append(node)
                self._configure(i, node)
            for cob in self._tpdo_cob:
                net.subscribe(cob, self._on_tpdo)
            for node in self.nodes:
                node.nmt.state = "OPERATIONAL"
            for i, node in enumerate(self.nodes):
                self._sdo(i, lambda: setattr(node.sdo[v4.CONTROLWORD], "raw", v4.CW_ACTIVE), "controlword")
            self.sync()
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

    # ---- cyclic (no SDO, no waiting) ---------------------------------------------------------------------
    def _on_tpdo(self, can_id: int, data, timestamp) -> None:
        """TPDO1: statusword UNSIGNED16, actual INT16, sample counter UNSIGNED8 (little endian)."""
        if not self._raised:                       # runs in the bus notifier thread: raise it once
            self._raised = True
            raise_priority(self.priority)
        i = self._tpdo_cob[can_id]
        if len(data) != 5:
            self.bad[i] = f"TPDO of {len(data)} bytes (expected 5)"
            return
        sw, act, cnt = struct.unpack("<HhB", bytes(data))
        now = time.monotonic_ns()
        self.statusword[i] = sw
        self.actual[i] = act / v4.FULL_SCALE
        self.bad[i] = ""
        if cnt != self.counter[i]:
            self.counter[i] = cnt
            self.rx_ns[i] = now
            self.pending_ns[i] = 0
            if i == 0 and self._sync_t:
                self.latency_ns[self.n_latency % len(self.latency_ns)] = now - self._sync_t
                self.n_latency += 1
                self._sync_t = 0

    def sync(self) -> None:
        now = time.monotonic_ns()
        pend = self.pending_ns
        for i in range(len(pend)):
            if not pend[i]:
                pend[i] = now
        self._sync_t = now
        self.network.send_message(SYNC_COB, b"")

    def write(self, valve_cmd_V) -> None:
        send = self.network.send_message
        mx = self.max_V
        for i, v in enumerate(valve_cmd_V):
            sp = v4.volts_to_setpoint(v, mx)
            self._setpoints[i] = sp
            send(self._rpdo_cob[i], struct.pack("<Hh", v4.CW_ACTIVE, sp))

    def null(self) -> None:
        """Setpoint 0 on every valve, then a SYNC so it takes effect and is reported at once: the actuators are
        then passive and stiff."""
        if self.network is None:
            return
        self.write([0.0] * len(self.node_ids))
        self.sync()

    def reset_fault(self) -> None:
        """Rising edge of controlword bit R on every valve (by RPDO, with a SYNC), then the normal controlword."""
        send = self.network.send_message
        for i in range(len(self.node_ids)):
            send(self._rpdo_cob[i], struct.pack("<Hh", v4.CW_ACTIVE | v4.CW_RESET_FAULT, 0))
        self.sync()
        self.write([0.0] * len(self.node_ids))
        self.bad = [""] * len(self.node_ids)

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

    def latencies_us(self) -> list[float]:
        n = min(self.n_latency, len(self.latency_ns))
        return [x * 1e-3 for x in self.latency_ns[:n]]

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
            net.send_message(SYNC_COB, b"")
        finally:
            self.network = None
            self.nodes = []
            net.disconnect()
