"""The replay as time series: what each model (the configured one, the diagnosed one) says every sensor read,
beside what it read, in the diagnosis's band (replay.csv).

Every bin of the band is evaluated (the fits used a subset), the model's prediction being the recording less
its residual after the nuisance terms (and, without floor accelerometers, with the floor estimated from the
mounts); both sides go back to time by the inverse DFT of the band alone, then are kept every q-th sample
(still over twice the band's top).
"""
from __future__ import annotations

import numpy as np

from rig.config import MOUNTS
from rig.diagnose.machine.residual import Replay
from rig.diagnose.machine.rigmodel import Base
from rig.recordings.runfile import RunRecording
from rig.diagnose.machine.spectra import spectra_of
from rig.diagnose.machine.spool import Spools
from rig.diagnose.machine.weights import expected


def replay_series(run: RunRecording, base: Base, thetas: dict, th_weights: dict) -> dict:
    """{"time_s": ..., "<mount>_accel_mps2_measured": ..., "<mount>_accel_mps2_<model>": ..., strokes alike}."""
    sp = spectra_of(run, max_bins=10 ** 9)
    rp = Replay(sp, base, expected(sp, base, th_weights))
    spools = Spools(run.valve_cmd_V, sp.bin_index, base, sp.U)
    nfreq = run.n // 2 + 1
    hi = float(sp.f_hz.max())
    q = max(1, int(run.fs_hz / (4.0 * hi)))

    def back(X):
        full = np.zeros((nfreq, X.shape[1]), dtype=complex)
        full[sp.bin_index] = X
        return np.fft.irfft(full, n=run.n, axis=0)[::q]
    out = {"time_s": run.t_s[::q]}
    meas = back(sp.Y)
    preds = {}
    for name, th in thetas.items():
        ev = rp.evaluate(th, None, U=spools.effective(th))
        preds[name] = back(sp.Y - ev.r * ev.sd)
    for i, m in enumerate(MOUNTS):
        for kind, c in (("accel_mps2", i), ("stroke_m", 4 + i)):
            out[f"{m}_{kind}_measured"] = meas[:, c]
            for name, P in preds.items():
                out[f"{m}_{kind}_{name}"] = P[:, c]
    return out
