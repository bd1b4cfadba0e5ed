"""Per-channel conversion between a device's raw values and the loop's units, in one place for each device:
its I/O process applies it to every sample (drivers/modbus_io.py, serial_dta.py) and command
(canopen_valves.py) it handles. A channel's conversion is its source channel on the device, a gain (sign and
scale) and an offset: value = gain * raw_in_device_units + offset (a valve: setpoint = gain * command + null).
They come from the sensitivities and channel map of the configuration, corrected by the calibration `rig commission`
wrote (commissioning.toml, `[drivers] calibration`): `calibrated` gives the different `Channel` list, nothing
else changes.
"""
from __future__ import annotations

import tomllib
from dataclasses import dataclass
from pathlib import Path

from rig.errors import ConfigError
from rig.textfile import read_text


@dataclass(frozen=True)
class Channel:
    source: int            # the device's channel (AI ch, DTA-4 channel index, valve index)
    gain: float = 1.0      # loop units per device unit (sign included)
    offset: float = 0.0    # loop units (a valve: the command's null, in volts)


def channels(sources, gains, offsets=None) -> tuple[Channel, ...]:
    """One Channel per loop channel (mount order), from the device's channels and per-channel gains."""
    offsets = [0.0] * len(sources) if offsets is None else offsets
    return tuple(Channel(int(s), float(g), float(o)) for s, g, o in zip(sources, gains, offsets))


def to_dict(chs) -> list:
    return [[c.source, c.gain, c.offset] for c in chs]


def from_dict(rows) -> tuple[Channel, ...]:
    return tuple(Channel(int(s), float(g), float(o)) for s, g, o in rows)


def apply(chs, raw) -> list[float]:
    """The loop's values of one sample: raw[source] through each channel's gain and offset."""
    return [c.gain * raw[c.source] + c.offset for c in chs]


def read_calibration(path: str | Path) -> dict:
    """commissioning.toml as written by `rig commission` (one line naming the file when it cannot be read)."""
    text = read_text(path, "calibration file", ConfigError)
    try:
        cal = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"calibration {path}: cannot be read ({e})") from None
    return cal


def calibrated(chs, cal: dict, kind: str, names, offset_unit: str):
    """The loop channels of `names` (mount order; chs: the configuration's, mount i on chs[i]) through the
    calibration's `kind` table ([kind.<channel as mapped>]: the mount it carries, sign, scale, offset in the
    loop's units as read before): mount m takes the source of the channel found to carry it, that channel's
    gain times sign x scale, its offset taken off."""
    rows = cal.get(kind, {})
    out = list(chs)
    for ch, row in rows.items():
        if ch not in names or row.get("mount") not in names:
            raise ConfigError(f"calibration [{kind}.{ch}]: expected a mount of {', '.join(names)} and its mount")
        src, m = chs[names.index(ch)], names.index(row["mount"])
        k = float(row.get("sign", 1.0)) * float(row.get("scale", 1.0))
        off = float(row.get(f"offset_{offset_unit}", 0.0))
        out[m] = Channel(src.source, src.gain * k, k * (src.offset - off))
    return tuple(out)


def calibrated_valves(chs, cal: dict, names):
    """The valves' channels (chs[i]: the valve on node valve_node_id_base + i, configured for mount names[i])
    through the calibration's [valve.<mount as configured>] table: `mount` the mount that node's valve moves
    (swapped CAN nodes: the node carries that mount's command), `null_V` the command at which its spool
    centres, `gain` its flow gain over the model's. setpoint = command / gain + null: the valve then answers the
    loop's command as the model has it; its null is also what the port's safe state sends."""
    rows = cal.get("valve", {})
    out = list(chs)
    for m, row in rows.items():
        moves, g = row.get("mount", m), float(row.get("gain", 1.0))
        if m not in names or moves not in names or not g > 0:
            raise ConfigError(f"calibration [valve.{m}]: expected a mount of {', '.join(names)}, the mount its "
                              f"valve moves and a gain > 0")
        c = chs[names.index(m)]
        out[names.index(m)] = Channel(names.index(moves), c.gain / g, c.offset + float(row.get("null_V", 0.0)))
    if sorted(c.source for c in out) != list(range(len(out))):
        raise ConfigError(f"calibration [valve]: expected each mount moved by one valve, got "
                          f"{', '.join(f'{m} -> {names[c.source]}' for m, c in zip(names, out))}")
    return tuple(out)
