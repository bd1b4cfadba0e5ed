"""Was a recording made in closed loop? Identification and diagnosis fit the open-loop plant from command to
position; when a controller computed the command from the measured position, the command carries the
position's noise and such fits are biased (Ljung, System Identification, ch. 13). Two kinds of evidence:

- the file says so: rig's own recorder writes command = "rig run" (the isolation loop) into its attributes;
- the data say so: an ARX model (position from its own past and the past command) leaves the innovations e(t);
  in open loop they never reach the command, in closed loop the command a few samples later reacts to them.
  The test looks at the correlation of e(t) with the prewhitened command at lags 0..20 ms after t, against its
  spread at far lags (an empirical null that holds for any noise colour). Lag 0 counts in rig's own formats, which
  sample the position before the command of the same instant acts (zero-order hold): a position can never answer
  the command of its own sample, but a controller's command does answer that position. Another lab's file (a plant
  file's signal map) may sample the output after the command of its instant acted (a slow process sampled every
  few seconds answers within the sample): there lag 0 proves nothing, and only later lags count.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

THRESHOLD = 10.0            # near-lag correlation / far-lag spread (open-loop recordings here: below 5)


@dataclass
class LoopEvidence:
    closed: bool
    statistic: float | None
    reason: str

    def as_dict(self) -> dict:
        return {"closed_loop": self.closed, "statistic": self.statistic, "reason": self.reason}


def _arx_innovations(y: np.ndarray, u: np.ndarray, order: int = 10) -> np.ndarray:
    n = len(y)
    cols = [y[order - i:n - i] for i in range(1, order + 1)] + [u[order - j:n - j] for j in range(1, order + 1)]
    X = np.column_stack(cols + [np.ones(n - order)])
    c, *_ = np.linalg.lstsq(X, y[order:], rcond=None)
    e = np.zeros(n)
    e[order:] = y[order:] - X @ c
    return e


def check(cmd_V: np.ndarray, position_m: np.ndarray, fs: float, meta: dict | None = None,
          max_samples: int = 200_000, stated: str = "") -> LoopEvidence:
    """Evidence that the command was computed from the measured position. `stated` is what the recording says
    of its loop (Recording.closed_loop: a plant file's [signals] reference or closed_loop, an operated run):
    the file's word counts as evidence, as rig's own recorder's does, where the data are too short to test."""
    from scipy.linalg import solve_toeplitz
    from scipy.signal import firwin, lfilter
    meta = meta or {}
    if str(meta.get("command", "")) == "rig run":
        iso = meta.get("isolation_at_start")
        return LoopEvidence(True, None, "recorded by `rig run` (the isolation loop"
                            + (f", isolation {iso} at start" if iso else "") + "): the command reacts to the sensors")
    if stated:
        return LoopEvidence(True, None, f"the recording says so ({stated})")
    u = np.asarray(cmd_V, float)
    y = np.asarray(position_m, float)
    step = max(1, int(fs // 2000))                     # at most 2 kHz: a causal low-pass on both, then every k-th
    if step > 1:
        h = firwin(8 * step + 1, 0.8 / step)
        u, y, fs = lfilter(h, 1.0, u)[::step], lfilter(h, 1.0, y)[::step], fs / step
    u, y = u[:max_samples], y[:max_samples]
    n = len(u)
    p = 20
    if n < 100 * p or np.ptp(u) <= 0 or np.ptp(y) <= 0:
        return LoopEvidence(False, None, "too short to test for feedback")
    u = (u - u.mean()) / np.std(u)
    y = (y - y.mean()) / np.std(y)
    e = _arx_innovations(y, u)
    m2 = 1 << int(math.ceil(math.log2(2 * n)))
    ac = np.fft.irfft(np.abs(np.fft.rfft(u, m2)) ** 2, m2)[: p + 1]
    try:
        a = solve_toeplitz(ac[:p], ac[1:p + 1])
    except (np.linalg.LinAlgError, ValueError):
        return LoopEvidence(False, None, "the command could not be prewhitened")
    A = np.r_[1.0, -a]
    uw = lfilter(A, [1.0], u)[p:]
    ew = lfilter(A, [1.0], e)[p:]
    if np.std(uw) <= 0 or np.std(ew) <= 0:
        return LoopEvidence(False, None, "the command could not be prewhitened")
    uw, ew = uw / np.std(uw), ew / np.std(ew)
    m = len(uw)

    def corr(k: int) -> float:          # corr(e(t), u(t + k))
        return float(np.dot(ew[: m - k], uw[k:]) / m) if k >= 0 else float(np.dot(ew[-k:], uw[: m + k]) / m)
    K = int(max(5, 0.02 * fs))
    far = int(max(4 * K, 0.2 * fs))
    if m < 2 * (far + 4 * K):
        return LoopEvidence(False, None, "too short to test for feedback")
    first = 1 if "signal_map" in meta else 0        # another lab's sample convention: lag 0 is ambiguous
    near = max(abs(corr(k)) for k in range(first, K + 1))
    null = np.std([corr(k) for k in list(range(far, far + 4 * K)) + list(range(-far - 4 * K, -far))])
    stat = float(near / max(null, 1e-12))
    if stat > THRESHOLD:
        return LoopEvidence(True, stat, f"the command reacts to the measured position: its correlation with the "
                                        f"position's innovations at the same or a few ms earlier instants is "
                                        f"{stat:.0f}x its spread")
    return LoopEvidence(False, stat, "no sign of feedback from the position to the command")
