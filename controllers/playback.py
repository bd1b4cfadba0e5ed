"""Open-loop playback of a prepared valve-command signal (an identification chirp, a multisine, steps).

The signal is a table of samples, one per loop period, made off the hot path by whoever wants the excitation
(rig/commands/chirp.py). The mount ignores its sensors. Playback starts from the first sample when the loop
enables the controller at activation (set_enabled(state, True)); while disabled (INACTIVE, where the loop
still steps every controller) it outputs null and does not advance; after the last sample it outputs null.
`playback_step` (numba) is the law; rig/runtime/kernel.py runs it for a mount of this kind.
"""
from __future__ import annotations

import numba
import numpy as np

from controllers.state import step_law

KIND = 2                      # rig/runtime/kernel.py dispatches on it

STATE_NAMES = ("sample", "running")
_K, _RUN = range(2)


class SignalPlayback:
    """One mount's command table (volts, one sample per period); coefficients = the table."""

    kind = KIND
    state_names = STATE_NAMES

    def __init__(self, samples_V, dt: float, name: str = "") -> None:
        self.samples_V = np.ascontiguousarray(samples_V, dtype=np.float64).ravel()
        self.dt = float(dt)
        self.name = name

    def coefficients(self) -> np.ndarray:
        return self.samples_V

    def initial_state(self) -> list[float]:
        return [0.0, 0.0]

    def set_enabled(self, state, on: bool):
        if on and not state[_RUN]:
            return [0.0, 1.0]              # (re)start from the first sample
        return [state[_K], 1.0 if on else 0.0]

    def step(self, state, meas, dt: float):
        return step_law(playback_step, state, self.samples_V), state


@numba.njit(cache=True)
def playback_step(st, table):
    """The next sample while running (null after the table's end); nothing while stopped."""
    if st[_RUN] < 0.5:
        return 0.0
    k = int(st[_K])
    st[_K] = k + 1.0
    if k < table.shape[0]:
        return table[k]
    return 0.0
