"""Per-channel conversion between a device's raw values and the loop's units, in one place for each device:
its I/O process applies it to every sample (drivers/modbus_io.py, serial_dta.py) and command
(canopen_valves.py) it handles. A channel's conversion is its source channel on the device, a gain (sign and
scale) and an offset: value = gain * raw_in_device_units + offset (a valve: setpoint = gain * command + null).
Today they come from the sensitivities and channel map of the configuration; a per-channel calibration (sign,
scale, offset, channel map, valve nulls) is a different `Channel` list here, nothing else changes.
"""
from __future__ import annotations

from dataclasses import dataclass


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
