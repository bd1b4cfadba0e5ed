"""A run of the four-mount rig written as docs/RUN_RECORDING.md says another tool would write it (h5py, the
datasets and units the page lists): the simulated rig driven open loop by band-limited commands under its
floor, so the replay's exactness can be held against it without a session."""
from __future__ import annotations

import dataclasses

import h5py
import numpy as np
import scipy.signal

from rig.config import MOUNTS, Config
from sim_backend.rig_plant import FloorMotion, RigPlant

DT = 1 / 5000


def rig_cfg(floor: bool = True, **rig_error) -> Config:
    c = Config()
    c = c.replace(sensors=dataclasses.replace(c.sensors, floor_accel=floor))
    return c.replace(rig_error=dataclasses.replace(c.rig_error, **rig_error)) if rig_error else c


def open_loop_run(cfg: Config, seconds: float, *, seed: int = 0, noise: bool = True) -> dict:
    """Rows of a run: time, the four mounts' accelerations, strokes, commands and floor accelerations. The
    commands (white noise below 100 Hz, 0.5 V rms) are written in row k and act from row k + 1."""
    n = int(seconds / DT)
    rng = np.random.default_rng(seed)
    sos = scipy.signal.butter(4, 100.0, fs=1 / DT, output="sos")
    cmd = 0.5 * scipy.signal.sosfilt(sos, rng.standard_normal((n, 4)), axis=0) / 0.2
    kw = {} if noise else {"accel_noise_mps2": 0.0, "stroke_noise_m": 0.0, "floor_noise_mps2": 0.0}
    plant = RigPlant(cfg, DT, floor=FloorMotion.from_config(cfg, DT), seed=seed, **kw)
    rows = {"accel": [], "stroke": [], "floor": []}
    prev = [0.0] * 4
    for k in range(n):
        rows["accel"].append(plant.accel_mps2)
        rows["stroke"].append(plant.stroke_m)
        rows["floor"].append(plant.floor_accel_mps2)
        plant.step(prev)
        prev = cmd[k].tolist()
    return {"time_s": np.arange(n) * DT, "accel_mps2": np.array(rows["accel"]), "stroke_m": np.array(rows["stroke"]),
            "valve_cmd_V": cmd, "floor_accel_mps2": np.array(rows["floor"])}


def write_run(path, run: dict, *, floor: bool = True, flags: bool = True, units=None) -> None:
    """The file as docs/RUN_RECORDING.md's minimal writer makes it."""
    units = units or {"accel_mps2": "m/s^2", "stroke_m": "m", "valve_cmd_V": "V", "floor_accel_mps2": "m/s^2"}
    with h5py.File(path, "w") as f:
        f.attrs["rate_hz"] = 1 / DT
        f.attrs["layout"] = "machine"
        f["time_s"] = run["time_s"]
        for name in ("accel_mps2", "stroke_m", "valve_cmd_V") + (("floor_accel_mps2",) if floor else ()):
            f[name] = run[name]
            f[name].attrs["unit"] = units[name]
            f[name].attrs["labels"] = list(MOUNTS)
        if flags:
            n = len(run["time_s"])
            f["lifecycle_state"] = np.full(n, 2.0)
            f["isolation_on"] = np.zeros(n)
