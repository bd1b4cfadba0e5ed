"""transport_delay: dead time between the recorded command and the drive (digital electronics, a bus)."""
import numpy as np

from rig.diagnose.catalogue.effect import Draw, Effect, Evidence, Param
from rig.diagnose.starts import Grid


def _finding(prm: dict, band) -> str:
    tau = prm.get("delay_s", 0.0)
    return (f"the measured phase falls behind the model without the delay linearly with frequency, by "
            f"{360 * tau * band[1]:.0f} deg at {band[1]:.0f} Hz (a {tau * 1e3:.2f} ms dead time), with the "
            f"magnitude unchanged")


def _longest(s) -> float:
    """The longest delay sought: 8 ms (the valve's electronics, a drive's bus), and on a plant file's plant at
    least 10 samples (a slow process's dead time, a transport of air or heat: seconds at a few Hz)."""
    return 8e-3 if s.family == "eha" else max(8e-3, 10.0 / s.fs)


def _grid(s, slow: bool, coarse: bool):
    g = np.r_[0.0, 0.5e-3, 1e-3, 1.5e-3, 2.2e-3, 3.2e-3, 4.5e-3] if slow else \
        np.r_[0.0, 0.2e-3, np.arange(0.5e-3, 6.01e-3, 0.5e-3)]
    if s.family == "eha":
        return g
    # whole and half samples too: a low rate's dead time is a few samples, far beyond the ms grid
    g = np.unique(np.r_[g, np.array([0.5, 1.0, 1.5, 2.0, 3.0, 4.0, 6.0, 8.0]) / s.fs])
    return g[g <= _longest(s)]


def _in_samples(prm: dict, fs: float) -> dict:
    """The delay in samples, and the dead time as a sampled model counts it (an ARX model's nk): the samples from
    a command to the first output sample that answers it. The recording holds each command until the next sample
    (zero-order hold) and samples the output before it acts, so a plant without delay answers one sample later."""
    d = prm["delay_s"] * fs
    return {"delay_samples": d, "dead_time_samples": d + 1.0}


EFFECT = Effect(
    name="transport_delay", short="delay", order=10,
    families=("eha", "mechanical_axis", "transfer_function"),
    params=(Param("delay_s", "ms", 1e3),),
    meaning=lambda family, load: ("dead time between command and valve driver" if family == "eha" else
                                  "dead time between the command and the drive's force"),
    bounds=lambda s: [(0.0, _longest(s))],
    start=Grid(_grid),
    evidence=Evidence("frf", "phase lag growing with frequency, magnitude unchanged", _finding),
    derived=_in_samples,
    terms={"eha_model": lambda p, u: {"delay_s": p["delay_s"]},
           "axis_model": lambda p, u: {"delay_s": p["delay_s"]},
           "stand": lambda p, u: {"delay_s": p["delay_s"]},
           "axis": lambda p, u: {"delay_s": p["delay_s"]}},
    draws={"stand": Draw(1, lambda rng, c: ({"delay_s": round(float(rng.uniform(0.5e-3, 3.0e-3)), 5)}, {})),
           "axis": Draw(1, lambda rng, c: ({"delay_s": round(float(rng.uniform(2e-3, 6e-3)), 5)}, {}))},
)
