"""Protocol-level tests without any device: serial framing (incl. hypothesis), 408 scaling and states,
Modbus voltage scaling, and that a simulated run imports no hardware library."""
from __future__ import annotations

import subprocess
import sys

import pytest
from hypothesis import given, settings, strategies as st

from drivers.protocol import dta as proto
from drivers.protocol import modbus_map
from drivers import modbus_io
from drivers.protocol import valve408 as v4
from sim_backend.emulators import modbus_server


# ---- serial DTA-4 frames ---------------------------------------------------------------------------------
def test_checksum_is_xor_of_body():
    body = b"D,1,OK,+0000.000"
    cs = 0
    for b in body:
        cs ^= b
    assert proto.checksum(body) == f"{cs:02X}"
    assert proto.frame("D,1,OK,+0000.000") == b"$" + body + b"*" + f"{cs:02X}".encode() + b"\r\n"


def test_data_frame_round_trip_in_metres():
    raw = proto.data_frame(65535, ["OK", "UR", "OR", "NP"], [12.345, -2000.0, 2000.0, 0.0])
    [f] = proto.FrameParser().feed(raw)
    assert f.seq == 65535
    assert f.status == ("OK", "UR", "OR", "NP")
    assert f.position_m == pytest.approx((12.345e-6, -2000e-6, 2000e-6, 0.0), abs=1e-12)


def test_partial_frame_completes_across_feeds():
    raw = proto.data_frame(7, ["OK"] * 4, [1.0, -2.0, 3.5, -4.25])
    p = proto.FrameParser()
    out = []
    for i in range(len(raw)):                 # one byte at a time
        out += p.feed(raw[i:i + 1])
    assert len(out) == 1 and out[0].position_m[3] == pytest.approx(-4.25e-6)
    assert p.bad_frames == 0


def test_garbage_bad_checksum_and_cut_frames_are_dropped_not_raised():
    good = proto.data_frame(3, ["OK"] * 4, [1.0, 2.0, 3.0, 4.0])
    flipped = bytearray(good)
    flipped[5] ^= 0x01                         # one bit: the checksum must catch it
    cut = good[:20]                            # a frame cut off by the next '$'
    p = proto.FrameParser()
    frames = p.feed(b"\x00\xff junk" + bytes(flipped) + cut + good + b"tail")
    assert [f.seq for f in frames] == [3]
    assert p.bad_frames == 2
    assert p.garbage_bytes > 0


def test_overlong_frame_is_discarded():
    p = proto.FrameParser()
    assert p.feed(b"$" + b"A" * (proto.MAX_FRAME + 10)) == []
    assert p.bad_frames == 1
    assert p.feed(proto.frame("I,DTA-4,SN1,FW1"))[0].kind == "I"


@pytest.mark.parametrize("body", ["D,1,OK,1.0", "D,x,OK,+1.0,OK,+1.0,OK,+1.0,OK,+1.0",
                                  "D,1,XX,+1.0,OK,+1.0,OK,+1.0,OK,+1.0", "D,1,OK,nan,OK,+1.0,OK,+1.0,OK,+1.0",
                                  "D,99999,OK,+1.0,OK,+1.0,OK,+1.0,OK,+1.0", "Q,1", ""])
def test_malformed_bodies_are_rejected(body):
    p = proto.FrameParser()
    assert p.feed(proto.frame(body)) == []
    assert p.bad_frames == 1


@settings(max_examples=400, deadline=None)
@given(st.lists(st.binary(max_size=200), max_size=12))
def test_parser_never_raises_on_arbitrary_bytes(chunks):
    p = proto.FrameParser()
    for c in chunks:
        for f in p.feed(c):
            assert isinstance(f, (proto.DataFrame, proto.OtherFrame))
    assert len(p._buf) <= proto.MAX_FRAME + 1 + max((len(c) for c in chunks), default=0)


@settings(max_examples=200, deadline=None)
@given(seq=st.integers(0, 65535),
       vals=st.lists(st.floats(-2000, 2000, allow_nan=False), min_size=4, max_size=4),
       status=st.lists(st.sampled_from(proto.STATUS_CODES), min_size=4, max_size=4),
       junk=st.binary(max_size=50), split=st.integers(0, 200))
def test_valid_frame_survives_leading_junk_and_any_split(seq, vals, status, junk, split):
    raw = junk.replace(b"$", b"") + proto.data_frame(seq, status, vals)
    p = proto.FrameParser()
    k = split % (len(raw) + 1)
    frames = p.feed(raw[:k]) + p.feed(raw[k:])
    data = [f for f in frames if isinstance(f, proto.DataFrame)]
    assert len(data) == 1
    assert data[0].seq == seq and list(data[0].status) == status
    assert data[0].position_m == pytest.approx([round(v, 3) * 1e-6 for v in vals], abs=1e-12)


def test_channel_status_from_range():
    assert proto.channel_status(0.0) == "OK"
    assert proto.channel_status(-2000.5) == "UR"
    assert proto.channel_status(2000.5) == "OR"


# ---- CiA 408 valve ---------------------------------------------------------------------------------------
def test_setpoint_scaling_and_saturation():
    assert v4.volts_to_setpoint(10.0, 10.0) == 16384
    assert v4.volts_to_setpoint(-5.0, 10.0) == -8192
    assert v4.volts_to_setpoint(25.0, 10.0) == 16384          # saturates at 100 %
    assert v4.setpoint_to_volts(4096, 10.0) == pytest.approx(2.5)


@pytest.mark.parametrize("sw,state", [(0x000F, "ACTIVE"), (0x0009, "HOLD"), (0x000B, "HOLD"),
                                      (0x0008, "DISABLED"), (0x0007, "FAULT"), (0x0000, "FAULT")])
def test_statusword_states(sw, state):
    assert v4.state_of(sw) == state


def test_eds_has_the_408_objects_and_pdo_defaults():
    canopen = pytest.importorskip("canopen")
    od = canopen.import_od(str(v4.EDS_PATH), 5)
    assert od[0x1000].default == 0x198
    assert od[v4.SETPOINT][1].data_type == canopen.objectdictionary.INTEGER16
    assert od[v4.ACTUAL][1].data_type == canopen.objectdictionary.INTEGER16
    assert od[0x1400][1].default == 0x205 and od[0x1800][1].default == 0x185   # $NODEID resolved
    assert od[0x1A00][3].default == 0x20000008                                   # counter in TPDO1


# ---- Modbus scaling ----------------------------------------------------------------------------------------
@pytest.mark.parametrize("v,raw", [(-10.0, 0), (0.0, 32768), (10.0, 65535), (12.0, 65535), (-11.0, 0)])
def test_adam_voltage_scaling(v, raw):
    assert modbus_map.volts_to_raw(v) == raw
    assert modbus_server.volts_to_raw is modbus_map.volts_to_raw and modbus_io.raw_to_volts is modbus_map.raw_to_volts


def test_volts_round_trip_within_one_lsb():
    for v in (-9.99, -1.234, 0.0005, 3.3, 9.99):
        assert modbus_map.raw_to_volts(modbus_map.volts_to_raw(v)) == pytest.approx(v, abs=20 / 65535)


# ---- lazy imports ------------------------------------------------------------------------------------------
def test_sim_backend_imports_no_hardware_library():
    code = ("import sys\nfrom rig.config import Config\nfrom rig.backends import make_port\n"
            "p = make_port(Config(), 'sim')\n"
            "bad = [m for m in ('can', 'canopen', 'pymodbus', 'serial') if m in sys.modules]\n"
            "print(','.join(bad))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == ""


def test_unknown_backend_is_one_clear_error():
    from rig.backends import make_port
    from rig.config import Config
    from rig.errors import RigError
    with pytest.raises(RigError, match="backend.name: expected one of sim, hil, hardware"):
        make_port(Config(), "quantum")


def test_hardware_backend_constructs_and_fails_clearly_on_open():
    from rig.backends import make_port
    from rig.config import Config, DriversConfig
    from rig.errors import DeviceError
    cfg = Config().replace(drivers=DriversConfig(modbus_host="127.0.0.1", modbus_port=1, modbus_timeout_s=0.05,
                                                 serial_port="/nonexistent/ttyX"))
    port = make_port(cfg, "hardware")
    assert port.name == "hardware" and port.n_mounts == 4
    with pytest.raises(DeviceError, match=r"modbus_tcp 127\.0\.0\.1:1 unit 1: cannot connect"):
        port.open()
    port.close()


@pytest.mark.parametrize("name", ["hil.toml", "hil_1khz.toml", "hil_2khz.toml", "prototype_hil.toml",
                                  "prototype_hil_2khz.toml"])
def test_shipped_hil_configs_load(name):
    """The HIL configs carry a [controller] section: they must still load when the controller changes."""
    from pathlib import Path
    import drivers
    from rig.config import load_config
    cfg = load_config(Path(drivers.__file__).parent / "devicemaps" / name)
    assert cfg.loop.rate_hz == cfg.hil.rate_hz
    assert cfg.safety.stale_s == cfg.hil.stale_s and cfg.safety.watchdog_s == cfg.hil.watchdog_s


def test_hil_runs_take_rate_staleness_and_watchdog_from_the_hil_section():
    """`rig hil`, `rig run --backend hil` and `rig chirp --backend hil` run with [hil] rate_hz, stale_s and
    watchdog_s; the [safety] values of the real rig are left as configured."""
    from rig.commands.hil import hil_config
    from rig.config import config_from_dict, hil_run_config
    cfg = config_from_dict({"hil": {"rate_hz": 800.0, "stale_s": 0.2, "watchdog_s": 0.3}})
    run = hil_run_config(cfg)
    assert (run.loop.rate_hz, run.safety.stale_s, run.safety.watchdog_s) == (800.0, 0.2, 0.3)
    assert hil_run_config(cfg, 400.0).loop.rate_hz == 400.0 and hil_config(cfg, 400.0) == hil_run_config(cfg, 400.0)
    assert (cfg.safety.stale_s, cfg.safety.watchdog_s) == (0.002, 0.05)
