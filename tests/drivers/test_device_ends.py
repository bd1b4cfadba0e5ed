"""The drivers against device ends that nobody here wrote, so that a misunderstanding the drivers and the emulators
share (byte order, register offsets, PDO mapping, frame format) shows:

  - the analog module's driver against pymodbus's own server (its simulator's register store) serving the
    register map of drivers/devicemaps/adam6024_modbus.md, filled by the test from that document;
  - the valve driver against the canopen library's LocalNode serving drivers/devicemaps/valve408.eds, answering
    SYNC with its TPDO as drivers/devicemaps/valve408_canopen.md says a valve does;
  - the transducer driver against an answer script written from drivers/devicemaps/dta4_serial.md alone (its own
    framing and checksum, not drivers/protocol/dta.py).
Each driver runs in this process on an exchange block of the test's (as in its I/O process); loopback only.
"""
from __future__ import annotations

import asyncio
import os
import select
import struct
import threading
import time
import tty

import numpy as np
import pytest

from drivers import ANALOG, TRANSDUCER, VALVES, conversion
from drivers.canopen_valves import ValveIO
from drivers.modbus_io import AnalogIO
from drivers.serial_dta import TransducerIO
from rig.runtime import exchange as ex

pytestmark = pytest.mark.hil           # the real drivers against real device ends, on loopback

EDS = os.path.join(os.path.dirname(__file__), "..", "..", "drivers", "devicemaps", "valve408.eds")


def _block(n=4, nf=0):
    return ex.Block.create(ex.Layout(n, nf, devices=("valves", "accelerometer module", "transducer amplifier")))


# ---- Modbus: pymodbus's own server holding the documented map ------------------------------------------------
# adam6024_modbus.md: holding registers, address = 4xxxx - 40001; AI ch0-7 at 40001-40008, raw 0..65535 =
# -10..+10 V; 40009 conversion counter; 40010 status (bit0 watchdog); 40021 watchdog in 0.1 s; 40025-40600 the
# FIFO, newest first, 64 entries of [counter, AI ch0..ch7].
MAP_REGS = 600


def _raw(volts: float) -> int:
    return max(0, min(65535, round((volts + 10.0) * 65535 / 20.0)))


@pytest.fixture(scope="module")
def pymodbus_server():
    from pymodbus.client import ModbusTcpClient
    from pymodbus.server import ModbusTcpServer
    from pymodbus.simulator import DataType, SimData, SimDevice
    ready = threading.Event()
    holder = {}

    def serve():
        async def main():
            device = SimDevice(id=0, simdata=[SimData(0, count=MAP_REGS, values=0, datatype=DataType.REGISTERS)])
            server = ModbusTcpServer(device, address=("127.0.0.1", 0))
            await server.serve_forever(background=True)
            holder["port"] = server.transport.sockets[0].getsockname()[1]
            holder["loop"], holder["server"] = asyncio.get_running_loop(), server
            ready.set()
            while not holder.get("stop"):
                await asyncio.sleep(0.02)
            await server.shutdown()
        asyncio.run(main())
    th = threading.Thread(target=serve, daemon=True)
    th.start()
    assert ready.wait(20)
    writer = ModbusTcpClient("127.0.0.1", port=holder["port"], timeout=1.0)
    assert writer.connect()
    yield holder["port"], writer
    writer.close()
    holder["stop"] = True
    th.join(5)


def _fill(writer, newest: int, accel_V: dict[int, list[float]]) -> None:
    """The map for conversions up to `newest` (its AI volts per channel in accel_V[counter]): AI ch0-7 and the
    counter of the newest, and the FIFO, newest first (entries not converted yet: counter newest + 1)."""
    regs = [0] * MAP_REGS
    regs[0:8] = [_raw(v) for v in accel_V[newest]]
    regs[8] = newest & 0xFFFF
    for e in range(64):
        c = newest - e
        base = 24 + 9 * e
        if c in accel_V:
            regs[base:base + 9] = [c & 0xFFFF] + [_raw(v) for v in accel_V[c]]
        else:
            regs[base:base + 9] = [(newest + 1) & 0xFFFF] + [32768] * 8
    for at in range(0, MAP_REGS, 100):                       # (a write carries at most 123 registers)
        assert not writer.write_registers(at, regs[at:at + 100], device_id=1).isError()


def test_analog_driver_reads_the_documented_map_from_pymodbus(pymodbus_server):
    port, writer = pymodbus_server
    volts = {c: [0.1 * c + 0.01 * ch for ch in range(8)] for c in range(1, 11)}
    _fill(writer, 1, volts)
    block = _block(4, 4)
    k = 2.0                                                  # V per m/s^2, every channel
    spec = {"device": ANALOG, "name": "module", "host": "127.0.0.1", "port": port, "unit": 1, "timeout_s": 1.0,
            "channels": conversion.to_dict(conversion.channels(range(8), [1 / k] * 8)), "names": list("abcdefgh"),
            "watchdog_s": 0.5, "stale_s": 1.0, "period_s": 0.001, "fifo": True, "fetch_every": 1,
            "sync_device": VALVES}
    dev = AnalogIO(spec, block)
    dev.open()
    try:
        # the driver configured the watchdog (40021 = 5) and cleared the status (40010) in the server's store
        r = writer.read_holding_registers(20, count=1, device_id=1)
        assert r.registers == [5]
        assert writer.read_holding_registers(9, count=1, device_id=1).registers == [0]
        first = int(dev.count)
        _fill(writer, 10, volts)                             # nine more conversions before the next request
        assert dev.poll()
        io = block.io
        a, cap, w = block.part("accel"), int(io[ex.H_ACAP]), int(io[ex.H_AWIDTH])
        got = []
        for c in range(first + 1, int(io[a + ex.A_NEWEST]) + 1):
            s = a + ex.A_SLOTS + (c % cap) * w
            got.append(io[s + 1 + 4:s + w].tolist())          # 4 mount accelerations, then 4 floor ones
        assert len(got) == 9                                 # conversions 2..10, in order
        for c, values in zip(range(2, 11), got):
            assert values == pytest.approx([v / k for v in volts[c]], abs=20 / 65535 / k)
    finally:
        dev.close()
        block.close()


# ---- CANopen: canopen's LocalNode serving valve408.eds --------------------------------------------------------
class DocumentedValve:
    """valve408_canopen.md, on canopen's LocalNode: controlword 0x6040 bits D H M (R: fault reset) -> statusword
    0x6041 (R always set: no fault); RPDO1 the host maps by SDO; on SYNC the valve answers with its TPDO1 (the
    host's mapping, transmission type 1) after setting the sample counter 0x2000 one further."""

    def __init__(self, network, node_id: int):
        import canopen
        self.node = canopen.LocalNode(node_id, canopen.import_od(EDS, node_id))
        network.add_node(self.node)
        self.network = network
        self.counter = 0
        self.rpdo_data: list[bytes] = []
        self.node.add_write_callback(self._on_write)
        self.node.set_data(0x6041, 0, (0x0008).to_bytes(2, "little"))     # ready, no fault, disabled
        network.subscribe(0x80, self._on_sync)
        network.subscribe(0x200 + node_id, lambda cid, data, ts: self.rpdo_data.append(bytes(data)))

    def _on_write(self, index, subindex, od, data):
        if index == 0x6040:
            cw = int.from_bytes(data, "little")
            self.node.set_data(0x6041, 0, ((cw & 0x7) | 0x8).to_bytes(2, "little"))

    def _on_sync(self, can_id, data, ts):
        self.counter = (self.counter + 1) & 0xFF
        self.node.set_data(0x2000, 0, bytes([self.counter]))
        tp = self.node.tpdo
        tp.read(from_od=True)                                # the mapping the host wrote by SDO
        for var in tp[1].map:                                # the mapped objects' values from the dictionary
            var.set_data(self.node.get_data(var.index, var.subindex))
        tp[1].transmit()


def test_valve_driver_against_canopen_localnodes_serving_the_eds():
    import can
    import canopen
    channel = f"rig-device-ends-{os.getpid()}"
    net = canopen.Network()
    net.connect(interface="virtual", channel=channel, receive_own_messages=False)
    valves = [DocumentedValve(net, nid) for nid in (1, 2)]
    for v in valves:
        v.node.set_data(0x6301, 1, struct.pack("<h", 4096))        # spool actual: +25 %
    block = _block(2)
    spec = {"device": VALVES, "name": "valves", "interface": "virtual", "channel": channel, "node_ids": [1, 2],
            "names": ["a", "b"], "max_V": 10.0, "stale_s": 1.0, "period_s": 0.002, "priority": 0}
    dev = ValveIO(spec, block)
    try:
        dev.open()
        for v in valves:                                     # what the driver configured by SDO, in the EDS's OD
            od = v.node
            assert int.from_bytes(od.get_data(0x6042, 0), "little", signed=True) == 1     # setpoint from the bus
            assert int.from_bytes(od.get_data(0x6043, 0), "little", signed=True) == 2     # spool, closed loop
            v.node.rpdo.read(from_od=True)
            v.node.tpdo.read(from_od=True)
            rp, tp = v.node.rpdo[1], v.node.tpdo[1]
            assert [(m.index, m.subindex, m.length) for m in rp.map] == [(0x6040, 0, 16), (0x6300, 1, 16)]
            assert [(m.index, m.subindex, m.length) for m in tp.map] == [(0x6041, 0, 16), (0x6301, 1, 16),
                                                                         (0x2000, 0, 8)]
            assert rp.trans_type == 255 and tp.trans_type == 1
        assert dev.actual == pytest.approx([0.25, 0.25])     # TPDO1 decoded as the map says
        stop = threading.Event()
        th = threading.Thread(target=dev.run, args=(stop,), daemon=True)
        th.start()
        try:
            end = time.monotonic() + 2.0
            periods = []
            while time.monotonic() < end and not all(len(v.rpdo_data) > 20 for v in valves):
                periods.append(float(time.monotonic_ns()))
                ex.put_commands(block.io, periods[-1], np.array([2.5, -5.0]))
                time.sleep(0.002)
        finally:
            stop.set()
            th.join(2)
        # the period whose commands the last SYNC carried, beside its time (the module's hold counts from it)
        assert block.device_row(VALVES)[ex.D_PERIOD] in periods
        for v, want in zip(valves, (2.5, -5.0)):
            cw, sp = struct.unpack("<Hh", v.rpdo_data[-1])
            assert cw == 0x7 and sp == round(want / 10.0 * 16384)   # controlword ACTIVE, setpoint INT16
        assert dev.check(time.monotonic_ns()) is None
    finally:
        dev.close()
        block.close()
        net.disconnect()
    del can


# ---- serial: an answer script from dta4_serial.md ---------------------------------------------------------------
def _frame(body: str) -> bytes:
    """`$<body>*<CS>\\r\\n`, CS = two upper-case hex digits, the XOR of the body's bytes."""
    cs = 0
    for b in body.encode():
        cs ^= b
    return f"${body}*{cs:02X}\r\n".encode()


def _answer(master: int, frames: list, stop: threading.Event) -> None:
    """RD -> the next data frame of `frames` (repeating the last), ID -> identification, else error 01."""
    buf, k = b"", 0
    while not stop.is_set():
        r, _, _ = select.select([master], [], [], 0.05)
        if not r:
            continue
        buf += os.read(master, 256)
        while b"\r" in buf:
            cmd, buf = buf.split(b"\r", 1)
            if cmd.strip() == b"ID":
                os.write(master, _frame("I,DTA-4,SN7,FW9.9"))
            elif cmd.strip() == b"RD":
                os.write(master, _frame(frames[min(k, len(frames) - 1)]))
                k += 1
            else:
                os.write(master, _frame("E,01,unknown command"))


def test_transducer_driver_against_an_answer_script_from_the_device_map():
    master, slave = os.openpty()
    tty.setraw(slave)
    frames = ["D,41,OK,+0012.345,OK,-0003.100,OK,+0000.000,OK,+0101.010",
              "D,42,OK,+0013.000,OR,+2000.000,OK,+0000.001,NP,+0000.000"]
    stop = threading.Event()
    th = threading.Thread(target=_answer, args=(master, frames, stop), daemon=True)
    th.start()
    block = _block(4)
    spec = {"device": TRANSDUCER, "name": "amplifier", "port": os.ttyname(slave), "baud": 921600,
            "names": ["a", "b", "c", "d"], "channels": conversion.to_dict(conversion.channels(range(4), [1.0] * 4)),
            "stale_s": 1.0, "rate_hz": 100.0, "reply_timeout_s": 0.5}
    dev = TransducerIO(spec, block)
    try:
        dev.open()                                           # ID answered, then the first data frame (seq 41)
        assert dev.ident.fields[0] == "DTA-4"
        io = block.io
        so = block.part("stroke")

        def newest():
            sn = int(io[so + ex.S_NEWEST])
            s = so + ex.S_SLOTS + (sn % int(io[ex.H_SCAP])) * int(io[ex.H_SWIDTH])
            return sn, io[s + 2:s + 6].tolist()
        seq, x = newest()
        assert x == pytest.approx([12.345e-6, -3.1e-6, 0.0, 101.01e-6], abs=1e-12)   # micrometres -> metres
        assert dev.check(time.monotonic_ns()) is None
        assert dev.poll()                                    # seq 42: a new sample
        seq2, x2 = newest()
        assert seq2 == seq + 1 and x2[0] == pytest.approx(13.0e-6, abs=1e-12)
        assert dev.check(time.monotonic_ns()) == f"serial DTA-4 {os.ttyname(slave)} ch2 (b): over range"
        assert not dev.poll()                                # the same frame again: no new sample
    finally:
        stop.set()
        th.join(2)
        dev.close()
        block.close()
        os.close(master)
        os.close(slave)


def test_the_drivers_register_response_decodes_as_pymodbus_does():
    """The analog module's client decodes read-register replies with a response class of its own (one unpack):
    the same registers as pymodbus's own class for any reply, and one whose byte count overruns it refused alike."""
    from pymodbus.exceptions import ModbusIOException
    from pymodbus.pdu.register_message import ReadHoldingRegistersResponse
    from drivers.modbus_io import registers_response
    ours, theirs = registers_response()(), ReadHoldingRegistersResponse()
    rng = np.random.default_rng(5)
    for nbytes in (2, 3, 4, 18, 19, 36, 54, 250):
        data = bytes([nbytes]) + rng.integers(0, 256, nbytes + 1, dtype=np.uint8).tobytes()
        ours.decode(data)
        theirs.decode(data)
        assert ours.registers == theirs.registers
    for pdu in (ours, theirs):
        with pytest.raises(ModbusIOException):
            pdu.decode(bytes([10, 1, 2]))
    assert "registers" in str(ours)
