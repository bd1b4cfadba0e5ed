"""The recording row of a loop run: its channels, and the column offsets derived from them in one place.

The period kernel (rig/runtime/kernel.py) writes the row with offsets from `RowLayout`, the recorder stores one
dataset per channel, and adapters that keep a few columns (rig/chirp.py) look them up here too.
"""
from __future__ import annotations

from rig.runtime.recorder import Channel

# Per-row flag columns recorded after the per-mount channels.
FLAG_CHANNELS = (
    Channel("lifecycle_state", "", description="0 UNCONFIGURED, 1 INACTIVE, 2 ACTIVE, 3 FAULT"),
    Channel("isolation_on", "", description="1 when isolation is enabled in the controllers"),
    Channel("fault", "", description="1 from the period a fault was detected on"),
    Channel("overruns", "", description="cumulative count of cycles that ended after their period"),
    Channel("skipped_periods", "", description="cumulative count of periods skipped (skip policy)"),
    Channel("cmd_limited", "", description="1 when a command was clamped or slew-limited this period"),
    Channel("wake_latency_us", "us", description="wake-up time minus the period's deadline"),
    Channel("compute_prev_us", "us", description="compute time of the previous period (read..record)"),
)


def loop_channels(names: tuple[str, ...], state_labels: tuple[str, ...] = (), published=(),
                  floor: bool = False) -> list[Channel]:
    """The channels of a loop run over mounts `names`; state_labels name the controller-state columns
    (`mount.state`, mount-major), none: no controller_state channel; published: the channels of the
    controllers' published state (one column per mount, e.g. the operating mode and the reference).
    floor: the floor accelerometers and the feedforward path (controllers/feedforward.py) are in the loop."""
    n = len(names)
    ch = [Channel("time_s", "s", description="loop time of the period (deadline) since start"),
          Channel("accel_mps2", "m/s^2", n, names, "absolute vertical acceleration at the mount"),
          Channel("stroke_m", "m", n, names, "displacement transducer, piston relative to housing"),
          Channel("valve_cmd_V", "V", n, names, "valve command written to the port (after limits)"),
          Channel("valve_cmd_raw_V", "V", n, names, "controller output before clamp and slew limit")]
    if floor:
        ch += [Channel("floor_accel_mps2", "m/s^2", n, names, "floor accelerometer at the mount"),
               Channel("ff_cmd_V", "V", n, names, "floor feedforward's part of valve_cmd_raw_V"),
               Channel("feedforward_on", "", description="1 while the feedforward is switched on (its output "
                                                        "fades in and out over its fade_s)")]
    if state_labels:
        ch.append(Channel("controller_state", "", len(state_labels), tuple(state_labels),
                          "controller states by name (mount.state), mount-major"))
    return ch + list(published) + list(FLAG_CHANNELS)


class RowLayout:
    """Column offsets of a channel list: layout["stroke_m"] is the first column of that channel."""

    def __init__(self, channels) -> None:
        self.channels = list(channels)
        self._off: dict[str, int] = {}
        self._width: dict[str, int] = {}
        col = 0
        for c in self.channels:
            self._off[c.name] = col
            self._width[c.name] = c.width
            col += c.width
        self.ncols = col

    def __getitem__(self, name: str) -> int:
        return self._off[name]

    def __contains__(self, name: str) -> bool:
        return name in self._off

    def width(self, name: str) -> int:
        return self._width[name]
