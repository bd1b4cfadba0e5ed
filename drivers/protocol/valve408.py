"""CiA 408-style proportional valve: object indices, control/status word bits and scaling.

Shared by the driver (drivers/canopen_valves.py) and the emulated node (sim_backend/emulators/canopen_valve.py);
documented in drivers/devicemaps/valve408_canopen.md. Pure Python (no canopen import).
"""
from __future__ import annotations

from pathlib import Path

EDS_PATH = Path(__file__).parent.parent / "devicemaps" / "valve408.eds"

CONTROLWORD, STATUSWORD, DEVICE_MODE, CONTROL_MODE = 0x6040, 0x6041, 0x6042, 0x6043
SETPOINT, ACTUAL, SAMPLE_COUNTER = 0x6300, 0x6301, 0x2000

DEVICE_MODE_BUS = 1            # 0x6042: setpoint from the bus
CONTROL_MODE_SPOOL_CL = 2      # 0x6043: spool position, closed loop (valve electronics)

# control word bits (host requests) and status word bits (valve reports)
BIT_D, BIT_H, BIT_M, BIT_R = 0x1, 0x2, 0x4, 0x8     # D enabled, H out of hold, M device mode active, R ready
CW_ACTIVE = BIT_D | BIT_H | BIT_M                  # request DEVICE MODE ACTIVE
CW_DISABLE = 0
CW_RESET_FAULT = BIT_R                             # rising edge clears a fault

FULL_SCALE = 16384             # INT16 setpoint / actual value: 0x4000 = 100 % spool stroke


def state_of(statusword: int) -> str:
    """The valve state a status word reports."""
    if not statusword & BIT_R:
        return "FAULT"
    dhm = statusword & (BIT_D | BIT_H | BIT_M)
    if dhm == BIT_D | BIT_H | BIT_M:
        return "ACTIVE"
    if dhm & BIT_D:
        return "HOLD"
    return "DISABLED"


def volts_to_setpoint(v: float, max_V: float) -> int:
    """Valve command in volts (amplifier range +-max_V) -> INT16 setpoint, saturated."""
    x = round(v / max_V * FULL_SCALE)
    return -FULL_SCALE if x < -FULL_SCALE else FULL_SCALE if x > FULL_SCALE else int(x)


def setpoint_to_volts(sp: int, max_V: float) -> float:
    return sp * max_V / FULL_SCALE
