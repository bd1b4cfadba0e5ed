"""Emulated CiA 408-style valve nodes: canopen LocalNodes on a python-can virtual bus (in-process).

The nodes are served by the emulator network's notifier thread. RPDO1 (event-driven, type 255) carries the
setpoint; on each SYNC the plant advances to the SYNC instant with the setpoints received since the previous
SYNC held over the step, and each node answers with its synchronous TPDO (status word, spool actual value,
sample counter).
"""
from __future__ import annotations

import math
import random

from drivers.protocol import valve408 as v4
from rig.runtime.rt import raise_priority

# per-node fault knobs
VALVE_MODES = ("ok", "silence", "garbage", "stale", "fault", "hold")


class ValveNode:
    """One valve: the 408 state machine, a first-order spool model for the actual value, and its knobs."""

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

    @property
    def operational(self) -> bool:
        return self.node.nmt.state == "OPERATIONAL"

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
        """The host rewrote the PDO configuration by SDO: read it back from our own object dictionary, and
        turn each mapping into (index, byte offset, bytes, signed) fields for the cyclic path."""
        self.node.rpdo.read(from_od=False)
        self.node.tpdo.read(from_od=False)
        self._rp_fields = self._fields(self.node.rpdo[1])
        self._tp_fields = self._fields(self.node.tpdo[1])
        self._tp_len = sum(n for _, _, n, _ in self._tp_fields)
        self._pdo_dirty = False

    @staticmethod
    def _fields(pdo_map):
        import canopen
        out = []
        for v in pdo_map.map:
            if v.offset % 8 or v.length % 8:
                raise ValueError("emulated valve: only byte-aligned PDO mappings")
            out.append((v.index, v.offset // 8, v.length // 8, v.od.data_type in canopen.objectdictionary.SIGNED_TYPES))
        return out

    def _values(self) -> dict:
        return {v4.STATUSWORD: self.statusword, v4.ACTUAL: int(round(self.actual)),
                v4.SAMPLE_COUNTER: self.counter}

    def on_sync(self, dt: float) -> float:
        """Apply the received setpoint; returns the valve command in volts-equivalent for the plant."""
        if not self.operational:
            return 0.0
        if self._pdo_dirty:
            self._reload_pdo()
        rp = self.node.rpdo[1]
        if rp.is_received:
            data = bytes(rp.data)
            got = {idx: int.from_bytes(data[o:o + n], "little", signed=sg) for idx, o, n, sg in self._rp_fields
                   if o + n <= len(data)}
            if v4.CONTROLWORD in got:
                self._apply_controlword(got[v4.CONTROLWORD])
            if v4.SETPOINT in got:               # a short or odd RPDO keeps the last setpoint
                self.setpoint = got[v4.SETPOINT]
        if self.mode == "fault":
            self.statusword &= ~v4.BIT_R
        elif self.mode == "hold":
            self.statusword = (self.statusword & ~0x7) | v4.BIT_D
        active = v4.state_of(self.statusword) == "ACTIVE"
        target = self.setpoint if active else 0            # HOLD/FAULT/DISABLED: spool to null
        self.actual += (target - self.actual) * (1.0 - math.exp(-self.w_spool * dt))
        self.counter = (self.counter + 1) & 0xFF
        return target

    def transmit(self) -> None:
        if not self.operational or self.mode == "silence":
            return
        tp = self.node.tpdo[1]
        if self.mode == "stale" and self.frozen is not None:
            tp.pdo_node.network.send_message(tp.cob_id, self.frozen)
            return
        if self.mode == "garbage":
            tp.pdo_node.network.send_message(tp.cob_id, bytes([self._rng.getrandbits(8)]))
            return
        vals = self._values()
        data = bytearray(self._tp_len)
        for idx, o, n, sg in self._tp_fields:
            data[o:o + n] = int(vals.get(idx, 0)).to_bytes(n, "little", signed=sg)
        self.frozen = bytes(data)
        tp.pdo_node.network.send_message(tp.cob_id, self.frozen)


class ValveBus:
    """Valve nodes on a virtual CAN channel. On SYNC: `rig.apply_sync(volts)` with the commands they apply
    (the plant advances), then the TPDOs go out."""

    def __init__(self, channel: str, node_ids: list[int], w_spool: float, max_V: float, rig, priority: int = 0):
        import canopen
        self.network = canopen.Network()
        self.network.connect(interface="virtual", channel=channel, receive_own_messages=False)
        self.nodes = [ValveNode(self.network, nid, w_spool) for nid in node_ids]
        self.max_V = max_V
        self.rig = rig
        self.syncs = 0
        self.priority = priority
        self.network.subscribe(0x80, self._sync)

    def _sync(self, can_id, data, timestamp):
        if not self.syncs:                         # runs in the emulator's notifier thread: raise it once
            raise_priority(self.priority)
        self.syncs += 1
        dt = self.rig.dt
        cmds = [v4.setpoint_to_volts(n.on_sync(dt), self.max_V) for n in self.nodes]
        self.rig.apply_sync(cmds)
        for n in self.nodes:
            n.transmit()

    def close(self) -> None:
        try:
            self.network.unsubscribe(0x80)
        except KeyError:
            pass
        self.network.disconnect()
