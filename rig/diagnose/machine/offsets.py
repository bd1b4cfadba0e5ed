"""A valve's null offset: what a constant does to the replay, and why only the start of a run tells who has it.

A valve whose amplifier adds u0 to every command moves its actuator by dc x u0 (the actuator's static stroke
per volt, Eq. 9's lag: K_v K_Q A_p / (K_C K_L)); the loop's slow centring answers by holding the command's mean
at -u0, and the stroke stays centred. The replay of the recorded commands then puts that actuator at
-dc x u0 while it stands at 0. A stroke transducer whose zero is off by b does the same (the centring holds
the reading at 0, the command at -b / dc): in steady state the two cannot be told apart. From rest they can:
at the first sample a transducer's zero already reads b, a valve's offset has moved nothing yet. So:

  offset_V  = mean over the centred stretch of (stroke / dc - command), per mount (its spread from 2 s blocks)
  start_m   = the stroke read at the first samples, when the run starts at rest (valves at null, INACTIVE)
and the valve is named when offset_V stands out, the others' do not, and the start reads zero.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from rig.config import MOUNTS
from rig.diagnose.machine.effects import VALVE_NULL_OFFSET, worth_naming
from rig.recordings.runfile import RunRecording

MIN_T = 6.0                     # offset / its standard error to stand out
SETTLE_S = 2.0                  # the centring's and the filters' start left out
START_ROWS = 5                  # the first rows: the run's start at rest


@dataclass(frozen=True)
class MountOffset:
    mount: str
    offset_V: float             # the valve offset the steady relation asks for
    se_V: float
    start_m: float              # the stroke read at the start (nan: the run does not start at rest)
    start_noise_m: float

    @property
    def t(self) -> float:
        return abs(self.offset_V) / self.se_V if self.se_V > 0 else math.inf

    @property
    def stands_out(self) -> bool:
        return worth_naming(VALVE_NULL_OFFSET, {"offset_V": self.offset_V}) and self.t >= MIN_T

    @property
    def transducer_zero(self) -> bool:
        """The start reads what the offset would have the transducer read: its zero, not the valve."""
        return math.isfinite(self.start_m) and abs(self.start_m) > max(5 * self.start_noise_m, 1e-9)


def starts_at_rest(run: RunRecording) -> bool:
    """The record begins at the run's start: first rows INACTIVE (or off) with the valves at null."""
    k = START_ROWS
    u0 = np.abs(run.valve_cmd_V[:k]).max()
    first_mode = run.mode[:k] if run.mode is not None else np.zeros(k)
    return bool(run.t_s[0] < 0.01 and u0 == 0.0 and np.all(first_mode == 0))


def null_offsets(run: RunRecording, dc_m_per_V: np.ndarray) -> list[MountOffset]:
    """Per mount: the valve offset that the steady relation between stroke and command asks for."""
    fs = run.fs_hz
    a = int(SETTLE_S * fs)
    ok = np.ones(run.n, bool) if run.mode is None else run.mode >= 0
    ok[:a] = False
    if ok.sum() < 2 * fs:
        ok[:] = True
        ok[:min(a, run.n // 2)] = False
    rest = starts_at_rest(run)
    block = int(2 * fs)
    out = []
    for i, m in enumerate(MOUNTS):
        x = run.stroke_m[ok, i] / dc_m_per_V[i] - run.valve_cmd_V[ok, i]
        nb = len(x) // block
        means = x[:nb * block].reshape(nb, block).mean(axis=1) if nb >= 3 else np.array([x.mean()] * 3)
        se = float(np.std(means, ddof=1) / math.sqrt(len(means))) if nb >= 3 else math.inf
        s = run.stroke_m[:START_ROWS, i]
        start = float(np.mean(s)) if rest else math.nan
        noise = float(np.std(np.diff(run.stroke_m[:int(0.02 * fs), i])) / math.sqrt(2 * START_ROWS))
        out.append(MountOffset(m, float(x.mean()), max(se, 1e-6), start, noise))
    return out
