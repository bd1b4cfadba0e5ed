"""The analog input module's Modbus register map (drivers/devicemaps/adam6024_modbus.md; ADAM-6024-style
registers, eight AI channels as an ADAM-6017 has): holding registers, 0-based address = 4xxxx - 40001, and the
raw <-> volts scaling of its converters."""
from __future__ import annotations

REG_AI, N_AI = 0, 8               # 40001-40008 AI ch0-7 (ch0-3 the mount accelerometers, ch4-7 the floor ones)
REG_COUNT = 8                     # 40009 conversion counter (+1 per ADC conversion, wraps at 65536)
REG_STATUS = 9                    # 40010 status: bit0 host watchdog tripped (write 0 to clear)
REG_AO = 10                       # 40011-40012 AO ch0-1
REG_AO_SAFE = 12                  # 40013-40014 AO safe values, applied when the host watchdog trips
REG_WDOG = 20                     # 40021 host watchdog timeout in 0.1 s (0 = off)
# 40025-40600 conversion FIFO, newest first: FIFO_DEPTH entries of [counter, AI ch0-7]
REG_FIFO, FIFO_DEPTH, FIFO_WIDTH = 24, 64, 1 + N_AI
N_REGS = REG_FIFO + FIFO_DEPTH * FIFO_WIDTH


def raw_to_volts(raw: int) -> float:
    """0..65535 -> -10..+10 V."""
    return raw * 20.0 / 65535.0 - 10.0


def volts_to_raw(v: float) -> int:
    """-10..+10 V -> 0..65535, clamped like the module's ADC."""
    raw = round((v + 10.0) * 65535.0 / 20.0)
    return 0 if raw < 0 else 65535 if raw > 65535 else int(raw)
