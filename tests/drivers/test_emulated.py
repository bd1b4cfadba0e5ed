"""The three drivers against the emulated devices over real stacks (python-can virtual bus + canopen, pymodbus
TCP on 127.0.0.1, a pty): PDO mapping and scaling, register scaling and exceptions, serial frames, and every
fault knob ending in a one-line device fault. The plant is the deterministic stand-in (protocol level)."""
from __future__ import annotations

import multiprocessing as mp
import os
import signal
import threading
import time

import pytest

from drivers.protocol import dta as proto
from drivers import modbus_io
from drivers.protocol import valve408 as v4
from rig.backends import make_hil_port
from rig.config import Config
from rig.port import Commands
from sim_backend.emulators import shared as sh
from tests.sim_backend.standin import StandInPlant

pytestmark = pytest.mark.hil           # the real drivers against the emulated devices, on loopback

DT = 1e-3
PACE = 2e-3          # the tests' own read/write pacing (lighter than a 1 kHz loop on a shared machine)
STALE_S = 0.1         # as [hil] stale_s: above the shared VM's whole-machine stalls (45-51 ms seen)


def drive(port, seconds, cmd=(0.0, 0.0, 0.0, 0.0), until=None, write=True):
    """Read (and write cmd) every PACE for `seconds`, or until until(m) is true. Returns the last reading."""
    end = time.monotonic() + seconds
    m = None
    while time.monotonic() < end:
        t = time.monotonic_ns()
        m = port.read(t)
        if until is not None and until(m):
            return m
        if write:
            port.write(t, Commands(list(cmd)))
        time.sleep(PACE)
    return m


@pytest.fixture(scope="module")
def port():
    p = make_hil_port(Config(), StandInPlant(DT), dt=DT, stale_s=STALE_S)
    try:
        p.open()
        yield p
    finally:
        p.close()
    assert not p.rig.alive and p.rig.valves is None


def recover(port):
    port.rig.set_modbus("ok")
    port.rig.set_serial("ok")
    for ch in range(4):
        port.rig.set_serial_channel(ch, None)
    for i in range(4):
        port.rig.set_valve(i, "ok")
    port.reset_faults()
    m = drive(port, 5.0, until=lambda m: m.device_fault is None)
    assert m.device_fault is None, m.device_fault


# ---- CANopen ------------------------------------------------------------------------------------------------
def test_pdo_mapping_was_configured_by_sdo(port):
    for node in port.rig.valves.nodes:
        ln = node.node
        rp, tp = ln.rpdo[1], ln.tpdo[1]
        assert [(v.index, v.subindex, v.length) for v in rp.map] == [(0x6040, 0, 16), (0x6300, 1, 16)]
        assert [(v.index, v.subindex, v.length) for v in tp.map] == [(0x6041, 0, 16), (0x6301, 1, 16),
                                                                     (0x2000, 0, 8)]
        assert rp.trans_type == 255 and tp.trans_type == 1     # setpoint applied on receipt, TPDO on SYNC
        assert rp.cob_id == 0x200 + node.id and tp.cob_id == 0x180 + node.id
        assert int.from_bytes(ln.get_data(v4.DEVICE_MODE, 0), "little", signed=True) == v4.DEVICE_MODE_BUS
        assert int.from_bytes(ln.get_data(v4.CONTROL_MODE, 0), "little", signed=True) == v4.CONTROL_MODE_SPOOL_CL
        assert v4.state_of(node.statusword) == "ACTIVE"


def test_setpoint_and_actual_scaling_through_pdos(port):
    cmd = (2.5, -5.0, 0.0, 10.0)
    m = drive(port, 0.3, cmd)
    drive(port, 0.01, cmd)
    assert [n.setpoint for n in port.rig.valves.nodes] == [4096, -8192, 0, 16384]
    assert port.rig.last_cmd_V == pytest.approx(list(cmd))
    # the valve's first-order spool (524 rad/s) has settled: TPDO actual = setpoint / 16384
    assert m.spool_actual == pytest.approx([0.25, -0.5, 0.0, 1.0], abs=2e-3)
    # the stand-in actuator extends with + command (2.68 um/V DC)
    assert m.stroke_m[0] > 3e-6 and m.stroke_m[1] < -6e-6
    drive(port, 0.2)


def test_safe_state_nulls_every_valve_at_once(port):
    drive(port, 0.1, (3.0, 3.0, 3.0, 3.0))
    port.safe_state()                                          # no write after this: the SYNC applies it
    end = time.monotonic() + 2.0
    while port.rig.last_cmd_V != [0.0] * 4 and time.monotonic() < end:
        time.sleep(0.001)
    assert port.rig.last_cmd_V == [0.0, 0.0, 0.0, 0.0]
    assert [n.setpoint for n in port.rig.valves.nodes] == [0, 0, 0, 0]


# ---- Modbus (the module's server alone, known values) --------------------------------------------------------
# The device entry points run in a thread here (same code as the device process, no spawn cost): the
# tests control the shared values exactly.
def start_device(target, *args):
    here, there = mp.Pipe()
    th = threading.Thread(target=target, args=(args[0], there, *args[1:]), daemon=True)
    th.start()
    assert here.poll(30)
    return here.recv(), here, th


def stop_device(here, th):
    here.send("stop")
    th.join(5)
    assert not th.is_alive()


@pytest.fixture(scope="module")
def modbus_module():
    from pymodbus.client import ModbusTcpClient
    from sim_backend.emulators import modbus_server
    arr = sh.new_shared()
    port, here, th = start_device(modbus_server.serve, arr, 2.0)
    client = ModbusTcpClient("127.0.0.1", port=port, timeout=0.5, retries=0)
    assert client.connect()
    yield arr, client
    client.close()
    stop_device(here, th)


@pytest.fixture
def modbus_alone(modbus_module):
    arr, client = modbus_module
    arr[sh.MODBUS_MODE] = sh.OK
    arr[sh.COUNT] = 0
    sh.publish(arr, 0.0, [1.0, -2.0, 0.5, 4.9], [0.0] * 4)
    return arr, client


def test_register_scaling_and_counter(modbus_alone):
    arr, c = modbus_alone
    r = c.read_holding_registers(0, count=10, device_id=1)
    assert not r.isError()
    expect = [modbus_io.volts_to_raw(a * 2.0) for a in (1.0, -2.0, 0.5, 4.9)] + [32768] * 4   # no floor: 0 V
    assert r.registers[:8] == expect
    assert r.registers[8] == 1                                 # one conversion published
    assert [modbus_io.raw_to_volts(x) / 2.0 for x in r.registers[:4]] == pytest.approx(
        [1.0, -2.0, 0.5, 4.9], abs=20 / 65535)
    sh.publish(arr, 0.001, [6.0, 0, 0, 0], [0.0] * 4)         # 12 V: beyond the rail
    r = c.read_holding_registers(0, count=10, device_id=1)
    assert r.registers[0] == 65535 and r.registers[8] == 2


def test_exception_knob_gives_exception_response(modbus_alone):
    arr, c = modbus_alone
    arr[sh.MODBUS_MODE] = sh.EXCEPTION
    r = c.read_holding_registers(0, count=10, device_id=1)
    assert r.isError() and r.exception_code == 4
    arr[sh.MODBUS_MODE] = sh.OK
    assert not c.read_holding_registers(0, count=10, device_id=1).isError()


def test_illegal_address_is_an_exception(modbus_alone):
    _arr, c = modbus_alone
    r = c.read_holding_registers(596, count=10, device_id=1)        # the map ends at 40600
    assert r.isError() and r.exception_code == 2


def test_conversion_fifo_serves_the_last_64_conversions_newest_first(modbus_alone):
    arr, c = modbus_alone
    for k in range(2, 71):                                          # conversions 2..70 (1 is the fixture's)
        sh.publish(arr, k * 1e-3, [0.01 * k, -0.01 * k, 0.0, 0.5], [0.0] * 4)
    r = c.read_holding_registers(0, count=modbus_io.N_READ_FIFO, device_id=1)
    assert not r.isError() and r.registers[8] == 70
    regs = r.registers[modbus_io.REG_FIFO:]
    for chunk in range(modbus_io.FIFO_FIRST, modbus_io.FIFO_DEPTH, modbus_io.FIFO_CHUNK):
        n = min(modbus_io.FIFO_CHUNK, modbus_io.FIFO_DEPTH - chunk)
        w = modbus_io.FIFO_WIDTH
        r = c.read_holding_registers(modbus_io.REG_FIFO + w * chunk, count=w * n, device_id=1)
        assert not r.isError()
        regs += r.registers
    w = modbus_io.FIFO_WIDTH
    counters = [regs[w * e] for e in range(modbus_io.FIFO_DEPTH)]
    assert counters == list(range(70, 6, -1))                       # the newest 64, newest first
    for e, k in enumerate(counters):
        acc = [modbus_io.raw_to_volts(x) / 2.0 for x in regs[w * e + 1:w * e + w]]
        assert acc == pytest.approx([0.01 * k, -0.01 * k, 0.0, 0.5] + [0.0] * 4, abs=20 / 65535)


def _fifo_driver(port):
    return modbus_io.ModbusAnalogIO(host="127.0.0.1", port=port, unit=1, channels=[0, 1, 2, 3],
                                    names=["a", "b", "c", "d"], V_per_mps2=2.0, timeout_s=0.5, watchdog_s=0.0,
                                    stale_s=1.0, poll_s=0.01, fifo=True)


def test_driver_hands_over_every_conversion_in_order(modbus_alone, modbus_module):
    """Late polls lose nothing: the conversions made between two polls come back exactly, oldest first (the
    driver reads further back into the FIFO after a stall); more than the FIFO holds are interpolated, so
    their count (the integration's time base) stays exact."""
    arr, client = modbus_alone
    drv = _fifo_driver(client.comm_params.port)
    requests = []

    class Counting:                                                 # the module fixture's connection, counted
        def read_holding_registers(self, *a, **kw):
            requests.append(a)
            return client.read_holding_registers(*a, **kw)
    drv.client = Counting()
    assert drv._poll_once()
    n, last, acc, older = drv.conversions_since(-1)
    assert (n, last, older) == (1, 1, [])

    def publish(ks):
        for k in ks:
            sh.publish(arr, k * 1e-3, [0.01 * k] * 4, [0.0] * 4)
    publish(range(2, 7))                                            # five conversions before the next poll
    requests.clear()
    assert drv._poll_once()
    assert len(requests) == 1                                       # the newest entries cover them: one request
    n, last, acc, older = drv.conversions_since(1)
    assert n == 5 and last == 6
    assert [o[0] for o in older] == pytest.approx([0.02, 0.03, 0.04, 0.05], abs=1e-4)
    assert acc[0] == pytest.approx(0.06, abs=1e-4)
    assert drv.conversions_since(6)[0] == 0                         # nothing new: the loop holds
    publish(range(7, 57))                                           # fifty: beyond the first 16 entries
    requests.clear()
    assert drv._poll_once()
    assert len(requests) == 1 + -(-(50 - modbus_io.FIFO_FIRST) // modbus_io.FIFO_CHUNK)   # and chunks further back
    n, last, acc, older = drv.conversions_since(6)
    assert n == 50 and last == 56 and len(older) == 49
    assert [o[0] for o in older] == pytest.approx([0.01 * k for k in range(7, 56)], abs=1e-4)
    assert drv.lost_conversions == 0
    publish(range(57, 127))                                         # seventy: six fall out of the FIFO
    assert drv._poll_once()
    n, last, acc, older = drv.conversions_since(56)
    assert n == 70 and last == 126 and len(older) == 69
    assert [o[0] for o in older] == pytest.approx([0.01 * k for k in range(57, 126)], abs=1e-4)
    assert drv.lost_conversions == 6


def test_conversion_counter_wraps():
    drv = _fifo_driver(1)
    drv.conversions = {65534: (1.0,), 65535: (2.0,), 0: (3.0,), 1: (4.0,)}
    drv.newest = 1
    n, last, acc, older = drv.conversions_since(65534)
    assert (n, last, acc, older) == (3, 1, (4.0,), [(2.0,), (3.0,)])


def test_host_watchdog_sets_ao_safe_values(modbus_alone):
    _arr, c = modbus_alone
    assert not c.write_registers(10, [40000, 41000, 32768, 30000], device_id=1).isError()   # AO, AO safe
    assert not c.write_register(20, 1, device_id=1).isError()                             # 0.1 s
    r = c.read_holding_registers(9, count=5, device_id=1)
    assert r.registers[0] & 1 == 0 and r.registers[1:3] == [40000, 41000]
    time.sleep(0.3)                                                                      # host silent
    r = c.read_holding_registers(9, count=5, device_id=1)
    assert r.registers[0] & 1 == 1 and r.registers[1:3] == [32768, 30000]


# ---- serial amplifier alone --------------------------------------------------------------------------------
@pytest.fixture
def serial_alone():
    import serial
    from sim_backend.emulators import serial_device
    arr = sh.new_shared()
    sh.publish(arr, 0.0, [0.0] * 4, [1e-6, -2.5e-6, 123.456e-6, 0.0])
    path, here, th = start_device(serial_device.serve, arr)
    ser = serial.Serial(path, 921600, timeout=0.5)
    yield arr, ser
    ser.close()
    stop_device(here, th)


def ask(ser, cmd):
    p = proto.FrameParser()
    ser.write(cmd)
    end = time.monotonic() + 2
    while time.monotonic() < end:
        frames = p.feed(ser.read(ser.in_waiting or 1))
        if frames:
            return frames[0]
    return None


def test_serial_frames_over_pty(serial_alone):
    arr, ser = serial_alone
    f = ask(ser, b"RD\r")
    assert f.status == ("OK",) * 4
    assert f.position_m == pytest.approx((1e-6, -2.5e-6, 123.456e-6, 0.0), abs=1e-12)
    assert ask(ser, b"RD\r").seq == f.seq                      # no new conversion: same seq
    sh.publish(arr, 0.001, [0.0] * 4, [2.5e-3, -3e-3, 0.0, 0.0])
    g = ask(ser, b"RD\r")
    assert g.seq == f.seq + 1 and g.status == ("OR", "UR", "OK", "OK")
    assert g.position_m[:2] == pytest.approx((2e-3, -2e-3))    # clamped to the span
    assert ask(ser, b"ID\r").fields[0] == "DTA-4"
    e = ask(ser, b"XYZ\r")
    assert e.kind == "E" and e.fields[0] == "01"
    arr[sh.SERIAL_CH + 2] = 3
    assert ask(ser, b"RD\r").status[2] == "NP"


# ---- fault knobs through the whole port -------------------------------------------------------------------------
KNOBS = [
    ("modbus", "silence", r"modbus_tcp 127.0.0.1:\d+ unit 1: no new sample .*no valid response within"),
    ("modbus", "exception", r"modbus_tcp 127.0.0.1:\d+ unit 1: no new sample .*exception response 4"),
    ("modbus", "garbage", r"modbus_tcp 127.0.0.1:\d+ unit 1: no new sample"),
    ("modbus", "stale", r"modbus_tcp 127.0.0.1:\d+ unit 1: no new sample .*values not updating"),
    ("serial", "silence", r"serial DTA-4 /dev/pts/\d+: no new sample .*no reply"),
    ("serial", "exception", r"serial DTA-4 /dev/pts/\d+: amplifier reports error 10,adc fault"),
    ("serial", "garbage", r"serial DTA-4 /dev/pts/\d+: no new sample .*garbled frames"),
    ("serial", "stale", r"serial DTA-4 /dev/pts/\d+: no new sample .*sequence number not advancing"),
    ("serial_ch", "NP", r"serial DTA-4 /dev/pts/\d+ ch3 \(rear_left\): no probe"),
    ("serial_ch", "OR", r"serial DTA-4 /dev/pts/\d+ ch3 \(rear_left\): over range"),
    ("valve", "silence", r"canopen virtual:rig-hil-\S+ valve front_right \(node 2\): no new TPDO"),
    ("valve", "garbage", r"valve front_right \(node 2\): garbled TPDO: TPDO of 1 bytes"),
    ("valve", "stale", r"valve front_right \(node 2\): no new TPDO"),
    ("valve", "fault", r"valve front_right \(node 2\): valve in FAULT \(statusword 0x0007\)"),
    ("valve", "hold", r"valve front_right \(node 2\): valve in HOLD \(statusword 0x0009\)"),
]


@pytest.mark.parametrize("dev,mode,pattern", KNOBS, ids=[f"{d}-{m}" for d, m, _ in KNOBS])
def test_fault_knob_ends_in_one_line_device_fault(port, dev, mode, pattern):
    import re
    assert drive(port, 0.05).device_fault is None
    rig = port.rig
    t0 = time.monotonic()
    if dev == "modbus":
        rig.set_modbus(mode)
    elif dev == "serial":
        rig.set_serial(mode)
    elif dev == "serial_ch":
        rig.set_serial_channel(2, mode)
    else:
        rig.set_valve(1, mode)
    # wait for this device's fault (an unrelated transient on a loaded machine must not confuse the test)
    m = drive(port, 5.0, until=lambda m: m.device_fault is not None and re.search(pattern, m.device_fault))
    took = time.monotonic() - t0
    try:
        assert m.device_fault is not None, f"{dev} {mode}: no fault after 5 s"
        assert "\n" not in m.device_fault
        assert re.search(pattern, m.device_fault), m.device_fault
        print(f"{dev}/{mode}: FAULT after {took * 1e3:.1f} ms: {m.device_fault}")
    finally:
        recover(port)


def test_fragmented_replies_are_not_a_fault(port):
    bad0, n0 = port.stroke.parser.bad_frames, port.stroke.n_latency
    port.rig.set_serial("fragment")
    try:
        m = drive(port, 0.3, until=lambda m: m.device_fault is not None)
        assert m.device_fault is None
        assert port.stroke.parser.bad_frames == bad0          # every split reply was reassembled
        assert port.stroke.n_latency > n0 + 20                # and delivered as data frames
    finally:
        recover(port)


def test_killed_device_process_ends_in_fault_naming_it(port):
    """Last test of the module (it kills the shared port's Modbus device; the fixture still cleans up)."""
    assert drive(port, 0.05).device_fault is None
    os.kill(port.rig.device_pid("modbus"), signal.SIGKILL)
    m = drive(port, 5.0, until=lambda m: m.device_fault is not None and "modbus" in m.device_fault)
    assert m.device_fault is not None and m.device_fault.startswith("modbus_tcp 127.0.0.1:")
    assert not port.rig.alive


def test_module_watchdog_trip_is_a_fault():
    """The driver configures the module's host watchdog; a poller that stops asking trips it -> FAULT."""
    p = make_hil_port(Config(), StandInPlant(DT), dt=DT, stale_s=5.0)    # staleness out of the way
    try:
        p.open()
        assert drive(p, 0.05).device_fault is None
        p.accel.watchdog_s = 0.1
        p.accel.client.write_register(20, 1, device_id=1)               # 0.1 s
        p.accel._stop.set()                                             # the poller stops asking
        p.accel._thread.join(2)
        time.sleep(0.3)
        p.accel._poll_once()                                            # the next request sees the trip
        m = drive(p, 0.05)
        assert m.device_fault is not None and "host watchdog tripped" in m.device_fault
    finally:
        p.close()


def test_floor_accelerometers_on_ch4_7_in_registers_fifo_and_driver(modbus_alone, modbus_module):
    """The floor accelerometers ([sensors] floor_accel) on AI ch4-7: in the live registers and in every FIFO
    entry, with the same conversion counter as the mount accelerometers; the driver reads them with their own
    sensitivity after the mount values, in the newest sample and in every older conversion."""
    arr, client = modbus_alone
    floor = [0.03, -0.07, 0.11, -0.22]
    for k in range(2, 6):
        sh.publish(arr, k * 1e-3, [0.01 * k] * 4, [0.0] * 4, floor_mps2=[g * k for g in floor])
    r = client.read_holding_registers(0, count=modbus_io.N_READ_FIFO, device_id=1)
    assert not r.isError() and r.registers[8] == 5
    got = [modbus_io.raw_to_volts(x) / 2.0 for x in r.registers[4:8]]
    assert got == pytest.approx([g * 5 for g in floor], abs=20 / 65535)
    entry = r.registers[modbus_io.REG_FIFO + modbus_io.FIFO_WIDTH:modbus_io.REG_FIFO + 2 * modbus_io.FIFO_WIDTH]
    assert entry[0] == 4 and [modbus_io.raw_to_volts(x) / 2.0 for x in entry[5:9]] == pytest.approx(
        [g * 4 for g in floor], abs=20 / 65535)
    drv = modbus_io.ModbusAnalogIO(host="127.0.0.1", port=client.comm_params.port, unit=1,
                                   channels=[0, 1, 2, 3, 4, 5, 6, 7], names=list("abcdefgh"),
                                   V_per_mps2=[2.0] * 4 + [2.0] * 4, timeout_s=0.5, watchdog_s=0.0, stale_s=1.0,
                                   poll_s=0.01, fifo=True)
    drv.client = client
    assert drv._poll_once()
    assert drv.sample[0][4:] == pytest.approx([g * 5 for g in floor], abs=1e-4)
    n, last, acc, older = drv.conversions_since(2)
    assert (n, last) == (3, 5) and len(older) == 2
    for k, o in zip((3, 4), older):
        assert o == pytest.approx([0.01 * k] * 4 + [g * k for g in floor], abs=1e-4)
