"""What `rig hil` holds its run against: the same design under the same floor, simulated in lockstep at the
same rate, and the isolation of both as the table's rms in 1-100 Hz.

The emulated plant (sim_backend/emulators) steps once per SYNC from the moment it starts; before the loop's first
period it has stepped `pre_steps` times with the valves at null. The lockstep run (the simulated backend, the
same RigPlant, floor and seed) takes those steps first, then runs the loop period by period with the same
activation and the same isolation modes switched at the same loop times, and meters the same windows: each
mode from settle_s after its start, the last one up to settle_s before the run's end, so that no window touches
either end of the trace (the band filter's edges: a window ending at the trace's end reads the filter's edge
transient, as much as 1.5 dB of a 15 dB reduction, different in each run). The
accelerometer conversions reach the controllers one period after their SYNC in both (the drivers' timing and the
simulated backend's sample-driven rig mode), the command acts from the next SYNC; the lockstep run quantises the
accelerations to the Modbus module's 16 bits, as the module does, and holds the transducer's samples at its
rate and delay ([drivers] serial_rate_hz, serial_latency_s: rig.config.channel_delays). What differs is the
drivers: late or lost conversions, the transducer's actual timing, the plant's catch-up steps when the loop
fell behind.
"""
from __future__ import annotations

import math

import numpy as np
import scipy.signal

from rig.config import channel_delays
from rig.runtime.clock import SimClock
from rig.runtime.gate import ISOLATION_MODES
from rig.runtime.session import Session

BAND_HZ = (1.0, 100.0)
MIN_WINDOW_S = 1.0 / BAND_HZ[0]     # a mode metered for less than one period of the band's lower edge is not metered


def band(x: np.ndarray, fs: float, lo: float = BAND_HZ[0], hi: float = BAND_HZ[1]) -> np.ndarray:
    """x band-limited to lo-hi Hz (4th-order Butterworth, forward and back: no phase shift)."""
    hi = min(hi, 0.45 * fs)
    sos = scipy.signal.butter(4, (lo, hi), btype="bandpass", fs=fs, output="sos")
    return scipy.signal.sosfiltfilt(sos, np.asarray(x, dtype=float))


def windows(seconds: float, modes, settle_s: float) -> list[tuple[float, float]]:
    """Each mode's metered window in loop time (s): its equal share of the run from settle_s after its start, the
    last one up to settle_s before the run's end (no window at either end of the band-limited trace). settle_s is
    at most a third of the share: the last window loses it twice and is never empty."""
    share = seconds / len(modes)
    settle_s = min(settle_s, share / 3)
    return [(j * share + settle_s, (j + 1) * share - (settle_s if j == len(modes) - 1 else 0.0))
            for j in range(len(modes))]


def phase_rms(table: np.ndarray, codes: np.ndarray, fs: float, phases: dict[str, int],
              end: int | None = None) -> dict[str, float]:
    """The table's rms in 1-100 Hz over the steps of each metered phase (the trace band-limited whole first, up to
    step `end`: the run's end, as the lockstep trace ends; what the plant did after the loop stopped would reach
    back into the last phase through the filter's backward pass)."""
    table, codes = table[:end], codes[:end]
    if table.size < 64:
        return {m: math.nan for m in phases}
    b = band(table, fs)
    return {m: float(np.sqrt(np.mean(b[codes == c] ** 2))) if np.any(codes == c) else math.nan
            for m, c in phases.items()}


def lockstep(cfg, seconds: float, modes, settle_s: float, activate_after_s: float, pre_steps: int = 0) -> dict:
    """The run of `rig hil` in lockstep simulated time: {mode: table rms in 1-100 Hz over its metered window}."""
    rate = cfg.loop.rate_hz
    share = seconds / len(modes)
    adc = (cfg.drivers.accel_V_per_mps2, cfg.sensors.floor_V_per_mps2)
    da, ds = channel_delays(cfg, rate)
    timing = (ds - da, max(1, int(round(rate / min(cfg.drivers.serial_rate_hz, rate)))))
    # the simulated rig applies a command one period after its sample; a later conversion ([drivers]
    # accel_delay_periods) is the same loop delay as a command applied that much later
    with Session(cfg, "sim", clock=SimClock(), isolation=False,
                 port_options={"adc": adc, "stroke_timing": timing,
                               "cmd_delay_periods": cfg.drivers.accel_delay_periods}) as s:
        loop, plant = s.loop, s.port.plant
        null = [0.0] * loop.n
        for _ in range(pre_steps):
            plant.step(null)
        n = int(round(seconds * rate))
        act = max(1, int(round(activate_after_s * rate)))
        table = np.empty(n)
        k_mode = 0
        for k in range(n):
            t = k * loop.period_ns
            if k == act:
                loop.request_active(True)
            if k_mode + 1 < len(modes) and k * loop.dt >= (k_mode + 1) * share:
                k_mode += 1
                loop.request_isolation_mode(modes[k_mode])
            loop.cycle(t)
            table[k] = plant.table_m
        fault = loop.lc.fault_reason
    b = band(table, rate)
    out = {}
    for m, (t0, t1) in zip(modes, windows(seconds, modes, settle_s)):
        w = slice(int(round(t0 * rate)), int(round(t1 * rate)))
        out[m] = float(np.sqrt(np.mean(b[w] ** 2))) if b[w].size else math.nan
    return {"table_rms_m": out, "fault": fault}


def unmetered(seconds: float, modes, settle_s: float) -> list[str]:
    """The modes whose metered window is shorter than MIN_WINDOW_S: no figure of theirs means anything."""
    return [m for m, (t0, t1) in zip(modes, windows(seconds, modes, settle_s)) if t1 - t0 < MIN_WINDOW_S - 1e-9]


def seconds_to_meter(modes, settle_s: float) -> float:
    """The shortest run whose every mode is metered for MIN_WINDOW_S (the last one loses settle_s twice)."""
    return len(modes) * (MIN_WINDOW_S + 2 * min(MIN_WINDOW_S, settle_s))


def reductions(rms: dict) -> dict:
    """20 log10(off / mode) per isolation mode (None where not measured)."""
    off = rms.get("off", math.nan)
    out = {}
    for m in ISOLATION_MODES[1:]:
        on = rms.get(m, math.nan)
        out[m] = round(20 * math.log10(off / on), 2) if off > 0 and on > 0 else None
    return out
