"""The three drivers against the emulated devices over real stacks (python-can's rig_stream interface, drivers/
can_stream.py, + canopen to the emulated nodes' gateway, socketcand's in test_startup_faults.py; Modbus TCP on
127.0.0.1, a pty), each driver in its I/O process and each device in its own: setpoint scaling and the safe state
through the PDOs, every fault knob ending in a one-line device fault, a killed device or I/O process named; and
each device end alone (its entry point in a thread here: the test sets its values exactly) with the driver's
conversion handling in this process: register scaling, exceptions, the conversion FIFO and every conversion
handed over in order, the serial frames. The plant is the deterministic stand-in (protocol level)."""
from __future__ import annotations

import dataclasses
import multiprocessing as mp
import os
import re
import signal
import threading
import time

import numpy as np
import pytest

from drivers import VALVES, conversion
from drivers.modbus_io import AnalogIO
from drivers.protocol import dta as proto
from drivers.protocol import modbus_map as mm
from rig.backends import make_hil_port
from rig.config import Config
from rig.port import Commands
from rig.runtime import exchange as ex
from sim_backend.emulators import shared as sh
from tests.sim_backend.standin import StandInPlant

pytestmark = pytest.mark.hil           # the real drivers against the emulated devices, on loopback

DT = 1e-3
PACE = 2e-3          # the tests' own read/write pacing
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
    p = make_hil_port(Config(), StandInPlant(DT), dt=DT, stale_s=STALE_S, priority=0)
    try:
        p.open()
        yield p
    finally:
        p.close()
    assert not p.rig.alive and not p.pids


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


# ---- CANopen through the I/O process and the gateway ------------------------------------------------------------
def test_setpoints_reach_the_valves_scaled_and_move_the_actuators(port):
    cmd = (2.5, -5.0, 0.0, 10.0)
    m = drive(port, 0.3, cmd)
    assert port.rig.last_cmd_V == pytest.approx(list(cmd), abs=1e-3)      # INT16 setpoints, 16384 = max_V
    # the stand-in actuator extends with + command (2.68 um/V DC)
    assert m.stroke_m[0] > 3e-6 and m.stroke_m[1] < -6e-6
    assert m.device_fault is None
    drive(port, 0.2)


def test_safe_state_nulls_every_valve_until_the_next_write(port):
    drive(port, 0.1, (3.0, 3.0, 3.0, 3.0))
    port.safe_state()                                          # no write after this: the next SYNCs apply it
    end = time.monotonic() + 2.0
    while port.rig.last_cmd_V != [0.0] * 4 and time.monotonic() < end:
        time.sleep(0.001)
    assert port.rig.last_cmd_V == [0.0, 0.0, 0.0, 0.0]
    drive(port, 0.1, (1.0, 1.0, 1.0, 1.0))                     # a write after it takes over again
    assert port.rig.last_cmd_V == pytest.approx([1.0] * 4, abs=1e-3)
    drive(port, 0.1)


def test_every_conversion_once_in_order(port):
    """The module converts at each plant step (each SYNC); the port hands every one over once, in order."""
    drive(port, 0.05)
    steps0 = port.rig.steps
    seen = 0
    end = time.monotonic() + 0.5
    while time.monotonic() < end:
        m = port.read(time.monotonic_ns())
        seen += m.new_samples
        assert len(m.accel_older) == max(0, m.new_samples - 1)
        time.sleep(0.01)
    # the module's fetch has conversions in flight (its block period, more on a busy host): keep reading until
    # every conversion made by now has arrived. None lost: seen reaches it; none twice: never past the plant
    target = port.rig.steps - steps0
    end = time.monotonic() + 2.0
    while seen < target and time.monotonic() < end:
        seen += port.read(time.monotonic_ns()).new_samples
        # (the plant's step count is published after its conversion: a block in flight at the start counts too)
        assert seen <= port.rig.steps - steps0 + 16, (seen, port.rig.steps - steps0)
        time.sleep(0.002)
    assert seen >= target, (seen, target)


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
    ("valve", "silence", r"canopen rig_stream:can0 valve front_right \(node 2\): no new TPDO"),
    ("valve", "garbage", r"valve front_right \(node 2\): garbled TPDO: TPDO of 1 bytes"),
    ("valve", "stale", r"valve front_right \(node 2\): no new TPDO"),
    ("valve", "fault", r"valve front_right \(node 2\): valve in FAULT \(statusword 0x0007\)"),
    ("valve", "hold", r"valve front_right \(node 2\): valve in HOLD \(statusword 0x0009\)"),
]


@pytest.mark.parametrize("dev,mode,pattern", KNOBS, ids=[f"{d}-{m}" for d, m, _ in KNOBS])
def test_fault_knob_ends_in_one_line_device_fault(port, dev, mode, pattern):
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
    frames0, missed0 = port.counts()["transducer amplifier"]
    port.rig.set_serial("fragment")
    try:
        m = drive(port, 0.3, until=lambda m: m.device_fault is not None)
        assert m.device_fault is None
        frames, missed = port.counts()["transducer amplifier"]
        assert frames > frames0 + 20 and missed - missed0 < 5   # every split reply reassembled and delivered
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
    """The driver configures the module's host watchdog; an I/O process held off its requests (SIGSTOP) for
    longer than the watchdog trips it, and its next status read says so -> one-line fault."""
    cfg = Config().replace(drivers=dataclasses.replace(Config().drivers, modbus_watchdog_s=0.1))
    p = make_hil_port(cfg, StandInPlant(DT), dt=DT, stale_s=5.0, priority=0)    # staleness out of the way
    try:
        p.open()
        assert drive(p, 0.05).device_fault is None
        pid = p.pids[p.specs[1]["name"]]
        os.kill(pid, signal.SIGSTOP)
        time.sleep(0.3)
        os.kill(pid, signal.SIGCONT)
        m = drive(p, 2.0, until=lambda m: m.device_fault is not None)
        assert m.device_fault is not None and "host watchdog tripped" in m.device_fault, m.device_fault
    finally:
        p.close()


# ---- the Modbus module alone, and the driver's conversions -----------------------------------------------------
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
    yield arr, client, port
    client.close()
    stop_device(here, th)


@pytest.fixture
def modbus_alone(modbus_module):
    arr, client, port = modbus_module
    arr[sh.MODBUS_MODE] = sh.OK
    arr[sh.COUNT] = 0
    sh.publish(arr, 0.0, [1.0, -2.0, 0.5, 4.9], [0.0] * 4)
    return arr, client, port


def test_register_scaling_and_counter(modbus_alone):
    arr, c, _ = modbus_alone
    r = c.read_holding_registers(0, count=10, device_id=1)
    assert not r.isError()
    expect = [mm.volts_to_raw(a * 2.0) for a in (1.0, -2.0, 0.5, 4.9)] + [32768] * 4   # no floor: 0 V
    assert r.registers[:8] == expect
    assert r.registers[8] == 1                                 # one conversion published
    assert [mm.raw_to_volts(x) / 2.0 for x in r.registers[:4]] == pytest.approx([1.0, -2.0, 0.5, 4.9],
                                                                                 abs=20 / 65535)
    sh.publish(arr, 0.001, [6.0, 0, 0, 0], [0.0] * 4)         # 12 V: beyond the rail
    r = c.read_holding_registers(0, count=10, device_id=1)
    assert r.registers[0] == 65535 and r.registers[8] == 2


def test_exception_knob_gives_exception_response(modbus_alone):
    arr, c, _ = modbus_alone
    arr[sh.MODBUS_MODE] = sh.EXCEPTION
    r = c.read_holding_registers(0, count=10, device_id=1)
    assert r.isError() and r.exception_code == 4
    arr[sh.MODBUS_MODE] = sh.OK
    assert not c.read_holding_registers(0, count=10, device_id=1).isError()


def test_illegal_address_is_an_exception(modbus_alone):
    _arr, c, _ = modbus_alone
    r = c.read_holding_registers(596, count=10, device_id=1)        # the map ends at 40600
    assert r.isError() and r.exception_code == 2


def test_conversion_fifo_serves_the_last_64_conversions_newest_first(modbus_alone):
    arr, c, _ = modbus_alone
    for k in range(2, 71):                                          # conversions 2..70 (1 is the fixture's)
        sh.publish(arr, k * 1e-3, [0.01 * k, -0.01 * k, 0.0, 0.5], [0.0] * 4)
    w = mm.FIFO_WIDTH
    regs = []
    for first in range(0, mm.FIFO_DEPTH, 13):
        n = min(13, mm.FIFO_DEPTH - first)
        r = c.read_holding_registers(mm.REG_FIFO + w * first, count=w * n, device_id=1)
        assert not r.isError()
        regs += r.registers
    counters = [regs[w * e] for e in range(mm.FIFO_DEPTH)]
    assert counters == list(range(70, 6, -1))                       # the newest 64, newest first
    for e, k in enumerate(counters):
        acc = [mm.raw_to_volts(x) / 2.0 for x in regs[w * e + 1:w * e + w]]
        assert acc == pytest.approx([0.01 * k, -0.01 * k, 0.0, 0.5] + [0.0] * 4, abs=20 / 65535)


def test_a_conversions_registers_are_made_once_and_anew_for_the_next_in_its_slot(modbus_alone):
    """The emulated module makes a conversion's registers once (noise drawn once: the same however often it is
    read) and makes them anew for the conversion that takes its FIFO slot 64 conversions later."""
    from sim_backend.emulators.modbus_server import Module
    arr, _c, _ = modbus_alone
    m = Module(arr, 2.0, faults=(tuple(range(8)), (1.0,) * 8, (0.0,) * 8, (0.05,) + (0.0,) * 7))
    sh.publish(arr, 1e-3, [0.1, 0.2, 0.0, 0.0], [0.0] * 4)
    w = mm.FIFO_WIDTH
    first = m.read(mm.REG_FIFO, 2 * w)
    assert m.read(mm.REG_FIFO, 2 * w) == first
    assert m.read(mm.REG_AI, mm.N_AI) == first[1:w]                  # the newest, as AI ch0-7 and as entry 0
    for k in range(sh.FIFO_SLOTS):
        sh.publish(arr, (2 + k) * 1e-3, [0.3, -0.3, 0.0, 0.0], [0.0] * 4)
    later = m.read(mm.REG_FIFO, w)
    assert later[0] == (first[0] + sh.FIFO_SLOTS) & 0xFFFF
    assert mm.raw_to_volts(later[2]) / 2.0 == pytest.approx(-0.3, abs=20 / 65535)
    assert later[1] != first[1]
    arr[sh.COUNT] = later[0] - 1                                    # a plant started again: the same counter anew
    sh.publish(arr, 1.0, [0.7, 0.0, 0.0, 0.0], [0.0] * 4)
    again = m.read(mm.REG_FIFO, w)
    assert again[0] == later[0] and mm.raw_to_volts(again[2]) / 2.0 == pytest.approx(0.0, abs=20 / 65535)


def test_host_watchdog_sets_ao_safe_values(modbus_alone):
    _arr, c, _ = modbus_alone
    assert not c.write_registers(10, [40000, 41000, 32768, 30000], device_id=1).isError()   # AO, AO safe
    assert not c.write_register(20, 1, device_id=1).isError()                             # 0.1 s
    r = c.read_holding_registers(9, count=5, device_id=1)
    assert r.registers[0] & 1 == 0 and r.registers[1:3] == [40000, 41000]
    time.sleep(0.3)                                                                      # host silent
    r = c.read_holding_registers(9, count=5, device_id=1)
    assert r.registers[0] & 1 == 1 and r.registers[1:3] == [32768, 30000]
    assert not c.write_register(20, 0, device_id=1).isError() and not c.write_register(9, 0, device_id=1).isError()


def _analog(port: int, channels=(0, 1, 2, 3), k=(2.0,) * 4, fetch_every=1):
    """The driver's analog module in this process, over a block of its own (n = 4 mounts, floor channels after)."""
    n = 4
    block = ex.Block.local(ex.Layout(n, len(channels) - n, devices=("valves", "accelerometer module")))
    spec = {"device": 1, "name": "module", "host": "127.0.0.1", "port": port, "unit": 1, "timeout_s": 0.5,
            "channels": conversion.to_dict(conversion.channels(channels, [1.0 / x for x in k])),
            "names": list("abcdefgh")[:len(channels)], "watchdog_s": 0.0, "stale_s": 1.0, "period_s": 0.001,
            "fifo": True, "fetch_every": fetch_every, "sync_device": VALVES}
    dev = AnalogIO(spec, block)
    dev.open()
    return dev, block


def _conversions(block, since: int) -> list:
    """(counter, values) of the conversions in the block after counter `since`, oldest first."""
    io = block.io
    a = block.part("accel")
    cap, w, n = int(io[ex.H_ACAP]), int(io[ex.H_AWIDTH]), block.n
    newest = int(io[a + ex.A_NEWEST])
    out = []
    for c in range(since + 1, newest + 1):
        s = a + ex.A_SLOTS + (c % cap) * w
        assert int(io[s]) == c
        out.append((c, io[s + 1 + n:s + w].tolist()))
    return out


def test_driver_hands_over_every_conversion_in_order(modbus_alone):
    """Late polls lose nothing: the conversions made between two polls come back exactly, oldest first (the
    driver reads further back into the FIFO after a stall); more than the FIFO holds are interpolated, so
    their count (the integration's time base) stays exact, and marked as lost (the feedforward restarts)."""
    arr, _c, port = modbus_alone
    dev, block = _analog(port)
    try:
        first = int(dev.count)
        assert _conversions(block, first - 1)[0][1][0] == pytest.approx(1.0, abs=1e-3)    # the fixture's

        def publish(ks):
            for k in ks:
                sh.publish(arr, k * 1e-3, [0.01 * k] * 4, [0.0] * 4)
        publish(range(2, 7))                                        # five conversions before the next poll
        assert dev.poll()
        got = _conversions(block, first)
        assert [c - first for c, _ in got] == [1, 2, 3, 4, 5]
        assert [v[0] for _, v in got] == pytest.approx([0.02, 0.03, 0.04, 0.05, 0.06], abs=1e-4)
        assert not dev.poll()                                       # nothing new: nothing published
        publish(range(7, 57))                                       # fifty: beyond the entries of one request
        assert dev.poll()
        got = _conversions(block, first + 5)
        assert [v[0] for _, v in got] == pytest.approx([0.01 * k for k in range(7, 57)], abs=1e-4)
        assert block.device_row(1)[ex.D_MISSED] == 0
        lost = block.part("accel") + ex.A_LOST
        assert block.io[lost] == -1.0                               # none lost yet
        publish(range(57, 127))                                     # seventy: six fall out of the FIFO
        assert dev.poll()
        got = _conversions(block, first + 55)
        assert len(got) == 70
        assert [v[0] for _, v in got] == pytest.approx([0.01 * k for k in range(57, 127)], abs=1e-4)
        assert block.device_row(1)[ex.D_MISSED] == 6
        assert block.io[lost] == first + 61                         # the newest estimated one (the kernel's cue)
    finally:
        dev.close()


def test_a_fetch_with_its_conversion_in_is_one_request(modbus_alone):
    """The module's status register (the host watchdog's bit) is read apart from the fetches, after a fetch's
    conversion went out: read first, its round trip held every 50th conversion up by that long at 2 kHz.
    (The status is still read: test_module_watchdog_trip_is_a_fault.)"""
    arr, _c, port = modbus_alone
    dev, block = _analog(port)
    try:
        asked = []
        read = dev.client.read_holding_registers

        def spy(address, **kw):
            asked.append(address)
            return read(address, **kw)
        dev.client.read_holding_registers = spy
        for k in range(2, 2 + 2 * 50 + 3):
            sh.publish(arr, k * 1e-3, [0.01 * k] * 4, [0.0] * 4)
            n = len(asked)
            assert dev.poll()
            assert asked[n:] == [mm.REG_FIFO], (k, asked[n:])
    finally:
        dev.close()


def test_a_fast_reply_waits_for_the_period_that_takes_it(modbus_alone):
    """With the design taking a conversion two periods after its SYNC, one fetched early is handed to the loop
    only from its hold time on (drivers.accel_hold_s): before it the block has not got it, after it it has,
    once and in order. The process is not held meanwhile: the next SYNC's fetch can come first (three periods)."""
    arr, _c, port = modbus_alone
    dev, block = _analog(port)
    a = block.part("accel")
    try:
        first = int(dev.count)
        sh.publish(arr, 2e-3, [0.02] * 4, [0.0] * 4)
        release = dev.not_before_ns = time.monotonic_ns() + 60_000_000
        assert dev.poll()
        assert time.monotonic_ns() < release                 # the fetch came back without waiting out the hold
        sh.publish(arr, 3e-3, [0.03] * 4, [0.0] * 4)        # the next conversion, fetched while one is held
        dev.not_before_ns = 0
        assert dev.poll()
        assert int(block.io[a + ex.A_NEWEST]) == first      # both still held: in order, behind the first
        dev._release_due()
        assert int(block.io[a + ex.A_NEWEST]) == first
        dev._sleep(time.monotonic_ns() + 1000)               # a sleep hands on what falls due in it
        assert int(block.io[a + ex.A_NEWEST]) == first
        dev._wait_sync(int(block.futex[ex.FUTEX_SYNC]), 200_000_000)    # no SYNC: the release is made meanwhile
        assert time.monotonic_ns() >= release
        got = _conversions(block, first)
        assert [c - first for c, _ in got] == [1, 2]
        assert [v[0] for _, v in got] == pytest.approx([0.02, 0.03], abs=1e-3)
    finally:
        dev.close()


def test_a_fast_reply_waits_for_the_loop_to_have_taken_the_period_before(modbus_alone):
    """The loop running, a conversion is handed on once the loop wrote its commands for the period before the one
    due to take it (the period its SYNC's commands were for, plus accel_delay_periods - 1), whenever that is: a
    loop woken late would otherwise take it a period early and find none the period after."""
    arr, _c, port = modbus_alone
    dev, block = _analog(port)
    io, a = block.io, block.part("accel")
    P = dev.period_ns
    try:
        first = int(dev.count)
        T = float(time.monotonic_ns())                      # the period whose commands the SYNC carried
        ex.put_commands(io, T, np.zeros(4))
        dev.after_T = T + P                                  # accel_delay_periods 2: the loop's next period
        sh.publish(arr, 2e-3, [0.02] * 4, [0.0] * 4)
        assert dev.poll()
        dev._sleep(time.monotonic_ns() + P // 2)             # time alone does not hand it on (the loop is late)
        assert int(io[a + ex.A_NEWEST]) == first
        ex.put_commands(io, T + P, np.zeros(4))              # the loop took its inputs for the period before
        dev._sleep(time.monotonic_ns() + P // 4)
        assert [c - first for c, _ in _conversions(block, first)] == [1]
    finally:
        dev.close()


def test_a_reply_for_a_loop_that_is_not_running_goes_by_time():
    """No commands from the loop (not started, or stopped): the hold is by time alone, never for ever."""
    from drivers.modbus_io import AnalogIO as _A
    dev = _A.__new__(_A)
    dev.period_ns = 1_000_000
    dev.io = np.zeros(64)
    dev._loop_T = 3
    assert not dev._loop_before(1e9, 2_000_000_000)         # nothing written: not running
    dev.io[3] = 1e9 - 1e6
    assert dev._loop_before(1e9, 1_000_100_000)            # running, a period behind
    assert not dev._loop_before(1e9, 1_010_000_000)        # written ten periods ago: not running any more


def test_the_hold_is_for_designs_that_take_a_conversion_periods_later():
    from drivers import accel_hold_s
    from rig.config import load_config
    from tests.paths import REPO
    d2 = load_config(REPO / "drivers" / "devicemaps" / "hil_2khz.toml").drivers
    assert accel_hold_s(d2, 5e-4) == pytest.approx(5e-4 - d2.sync_offset_s + 1.25e-4)   # a quarter period into
    assert accel_hold_s(load_config(REPO / "drivers" / "devicemaps" / "hil.toml").drivers, 2e-3) == 0.0


def test_conversion_counter_wraps(modbus_alone):
    """The module's 16-bit counter wraps; the block's counter goes on (the kernel's replay counts on it)."""
    arr, _c, port = modbus_alone
    arr[sh.COUNT] = 65533
    sh.publish(arr, 0.0, [0.5] * 4, [0.0] * 4)                      # conversion 65534
    dev, block = _analog(port)
    try:
        first = int(dev.count)
        for k in range(3):                                          # 65535, 0 (65536), 1
            sh.publish(arr, 0.0, [0.6 + 0.1 * k] * 4, [0.0] * 4)
        assert dev.poll()
        got = _conversions(block, first)
        assert [c - first for c, _ in got] == [1, 2, 3]
        assert [v[0] for _, v in got] == pytest.approx([0.6, 0.7, 0.8], abs=1e-3)
    finally:
        dev.close()


def test_floor_accelerometers_on_ch4_7_with_the_mounts_in_one_conversion(modbus_alone):
    """The floor accelerometers ([sensors] floor_accel) on AI ch4-7: in the live registers and in every FIFO
    entry, with the same conversion counter as the mount accelerometers; the driver hands them over after the
    mount values, in every conversion."""
    arr, client, port = modbus_alone
    floor = [0.03, -0.07, 0.11, -0.22]
    for k in range(2, 4):
        sh.publish(arr, k * 1e-3, [0.01 * k] * 4, [0.0] * 4, floor_mps2=[g * k for g in floor])
    r = client.read_holding_registers(0, count=10, device_id=1)
    assert [mm.raw_to_volts(x) / 2.0 for x in r.registers[4:8]] == pytest.approx([g * 3 for g in floor],
                                                                                 abs=20 / 65535)
    dev, block = _analog(port, channels=(0, 1, 2, 3, 4, 5, 6, 7), k=(2.0,) * 8)
    try:
        first = int(dev.count)
        for k in range(4, 6):
            sh.publish(arr, k * 1e-3, [0.01 * k] * 4, [0.0] * 4, floor_mps2=[g * k for g in floor])
        assert dev.poll()
        for (c, v), k in zip(_conversions(block, first), (4, 5)):
            assert v == pytest.approx([0.01 * k] * 4 + [g * k for g in floor], abs=1e-4)
    finally:
        dev.close()


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


def test_serial_request_due_on_the_loops_grid():
    """[drivers] serial_offset_s: the first instant offset after a start of the loop's periods; none without it."""
    from drivers.serial_dta import request_due
    S, P = 10_000_000, 500_000                                  # a period's start the loop wrote, its period
    assert request_due(S + 30_000, S, P, 25_000) == S + 525_000
    assert request_due(S + 25_000, S, P, 25_000) == S + 25_000  # on it: at once
    assert request_due(S - 100_000, S, P, 25_000) == S + 25_000  # the grid before the newest start too
    assert request_due(S + 30_000, S, P, 525_000) == S + 525_000  # modulo the period
    assert request_due(S + 30_000, S, P, -1) == S + 30_000        # no grid: its own rate
    assert request_due(S + 30_000, 0, P, 25_000) == S + 30_000    # the loop not running yet


def test_transducer_asked_on_the_loops_grid():
    """The transducer's I/O against the emulated amplifier on a pty, with offset_s: every request due offset_s
    after a start of the loop's periods (the block's commands say where they start), every whole number of
    periods at most rate_hz apart; without offset_s, at rate_hz whatever the phase."""
    from drivers.process import IODevice
    from drivers.serial_dta import TransducerIO
    from sim_backend.emulators import serial_device
    arr = sh.new_shared()
    sh.publish(arr, 0.0, [0.0] * 4, [1e-6] * 4)
    path, here, th = start_device(serial_device.serve, arr)
    block = ex.Block.local(ex.Layout(4, devices=("valves", "accelerometer module", "transducer amplifier")))
    spec = {"device": 2, "name": "amplifier", "port": path, "baud": 921600, "names": list("abcd"),
            "channels": conversion.to_dict(conversion.channels(range(4), [1.0] * 4)), "stale_s": 1.0,
            "rate_hz": 750.0, "period_s": 1e-3, "offset_s": 2.5e-4}
    assert TransducerIO(dict(spec, offset_s=-1.0), block).period_ns == round(1e9 / 750)
    dev = TransducerIO(spec, block)
    assert dev.period_ns == 2_000_000                            # 750 Hz at most: every second 1 ms period
    start = time.monotonic_ns() - 3_300_000                      # the loop's newest period (its grid)
    block.io[int(block.io[ex.H_CMD]) + ex.C_T] = float(start)
    dues = []

    def sleep_until(t_ns):
        dues.append(t_ns)
        IODevice.sleep_until(dev, t_ns)
    dev.sleep_until = sleep_until
    stop = threading.Event()
    dev.open()
    try:
        runner = threading.Thread(target=dev.run, args=(stop,), daemon=True)
        runner.start()
        end = time.monotonic() + 10
        while len(dues) < 12 and time.monotonic() < end:
            time.sleep(0.01)
        stop.set()
        runner.join(5)
    finally:
        dev.close()
        stop_device(here, th)
    assert len(dues) >= 12 and dev.seq >= 0
    assert [(d - start - 250_000) % 1_000_000 for d in dues] == [0] * len(dues)
    assert min(b - a for a, b in zip(dues, dues[1:])) >= 1_000_000


def test_conversion_rows_are_the_one_place_of_a_channels_gain_and_offset():
    """drivers/conversion.py: a channel's source, gain and offset, applied the same way for any device."""
    chs = conversion.channels([2, 0], [0.5, -2.0], [0.1, 0.0])
    assert conversion.apply(chs, [1.0, 3.0, 4.0]) == pytest.approx([2.1, -2.0])
    assert conversion.from_dict(conversion.to_dict(chs)) == chs
    assert np.isfinite(conversion.apply(chs, [0.0, 0.0, 0.0])).all()
