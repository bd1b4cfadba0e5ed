"""Isolation off, feedback and feedback + floor feedforward on the simulated four-mount rig, compared over the
SAME floor motion in simulated time (`rig demo`, and `rig.simulate` of the Python API).

Runs the product's control loop (rig/runtime/session.py Session) over the sim backend three times from the same
seed, once per isolation mode: each run sees the same floor realisation and sensor noise, so the reductions
are the isolation alone."""
from __future__ import annotations

import dataclasses
import math
import time

import numpy as np
import scipy.signal

from controllers.analysis import worst_model_error
from controllers.feedforward import make_feedforward_filters
from controllers.isolation import make_isolation_controllers
from controllers.vibration_criteria import vc_report
from rig.config import load_config
from rig.errors import FaultError, RigError
from rig.runtime.clock import SimClock
from rig.runtime.gate import ISOLATION_MODES as MODES
from rig.runtime.lifecycle import State
from rig.runtime.session import Session

LABELS = {"off": "isolation off", "feedback": "feedback", "feedback_feedforward": "feedback + feedforward"}


def mode_row(label: str, cells, width: int = 26) -> str:
    """One row of a per-mode table (`rig demo`, `rig hil`): the label, then a right-aligned cell per mode."""
    return f"{label:28s}" + "".join(f"{c:>{width}s}" for c in cells)


def rms(x):
    x = np.asarray(x, dtype=float)
    return float(np.sqrt(np.mean((x - x.mean()) ** 2)))


def band_1_100(x, fs, lo=1.0, hi=100.0):
    sos = scipy.signal.butter(4, (lo, hi), btype="bandpass", fs=fs, output="sos")
    return scipy.signal.sosfiltfilt(sos, np.asarray(x, dtype=float))


def demo_config(config=None, *, rms_um: float | None = None, model_error_pct: float = 10.0, log=None):
    """The config of the comparison (floor accelerometers fitted) and the description of its plant: the
    actuators model_error_pct off the controllers' model in the corner worst for the feedforward."""
    cfg = load_config(config)
    if rms_um is not None:
        cfg = cfg.replace(vibration=dataclasses.replace(cfg.vibration, rms_m=rms_um * 1e-6))
    cfg = cfg.replace(sensors=dataclasses.replace(cfg.sensors, floor_accel=True))
    if model_error_pct == 0:
        pe = dataclasses.asdict(cfg.plant_error)
        return cfg, {"model_error_pct": 0.0, "factors": pe,
                     "chosen": "as configured ([plant_error])" if any(x != 1 for x in pe.values()) else "as modelled"}
    dt = 1.0 / cfg.loop.rate_hz
    t0 = time.perf_counter()
    fac, db = worst_model_error(cfg, dt, make_isolation_controllers(cfg, dt), make_feedforward_filters(cfg, dt),
                                tol=model_error_pct / 100)
    (log or (lambda s: None))(f"model error: the worst of the 64 corners (+-{model_error_pct:g} %) for the feedforward, by linear "
         f"prediction ({db:.1f} dB), found in {time.perf_counter() - t0:.1f} s")
    cfg = cfg.replace(plant_error=dataclasses.replace(cfg.plant_error, **fac))
    return cfg, {"model_error_pct": model_error_pct, "factors": fac, "predicted_reduction_db": db,
                 "chosen": "the corner where the linear prediction of feedback + feedforward is worst"}


def compare(cfg, *, seconds: float = 10.0, settle_s: float = 1.0, log=None) -> tuple[dict, dict]:
    """The three runs (settle_s, then seconds metered, each) and their figures: (figures, traces per mode)."""
    say = log or (lambda s: None)
    rate = cfg.loop.rate_hz
    s = int(round(settle_s * rate))
    n = s + int(round(seconds * rate))
    traces, wall = {}, 0.0
    for mode in MODES:
        traces[mode], w = simulate_mode(cfg, n, mode)
        wall += w
    say(f"{3 * n} periods in {wall:.1f} s wall ({wall / (3 * n) * 1e6:.1f} us per period)")
    same = max(float(np.max(np.abs(traces[m]["floor"] - traces["off"]["floor"]))) for m in MODES)
    if same != 0.0:
        raise RigError(f"demo: the runs saw different floor motion (largest difference {same:g} m)")
    res = figures(traces, slice(s, n), rate)
    res["comparison"] = (f"three runs over the same floor realisation (seed {cfg.vibration.seed}) and sensor "
                         f"noise: the reductions are the isolation alone, table (or tool) rms with isolation over "
                         f"without")
    res["loop"] = {"periods": 3 * n, "wall_s": wall, "path": "rig.runtime.session.Session over SimBackend(RigPlant)"}
    res["harm"] = {m: traces[m]["harm"] for m in MODES if traces[m]["harm"]}   # issue 27: never silently
    return res, traces


def simulate_mode(cfg, n: int, mode: str):
    """n periods in one isolation mode from activation on, in simulated time: the plant's traces."""
    tr = {"table": np.empty(n), "tool": np.empty(n), "floor": np.empty(n), "cmd": np.empty((n, 4)),
          "ff": np.zeros((n, 4)), "stroke": np.empty((n, 4)), "limited": np.zeros(n, dtype=bool)}
    dt = 1.0 / cfg.loop.rate_hz
    with Session(cfg, "sim", clock=SimClock(), isolation=mode != "off", feedforward=mode == MODES[2],
                 port_options={"cmd_delay_periods": 1}) as session:
        loop, plant = session.loop, session.port.plant
        lay, row = loop.kernel.layout, loop.kernel.row
        rf = lay["ff_cmd_V"]
        loop.sched.t0_ns = 0           # loop time from the first period: the supervisor's windows run on it
        loop.activate()
        t0 = time.perf_counter()
        for k in range(n):
            loop.cycle(k * loop.period_ns)
            if loop.state is State.FAULT:
                raise FaultError(f"demo: the loop faulted at t = {k * dt:.3f} s ({LABELS[mode]}): "
                                 f"{loop.lc.fault_reason}")
            tr["table"][k] = plant.table_m
            tr["tool"][k] = plant.tool_m
            tr["floor"][k] = sum(plant.floor_m) * 0.25
            tr["cmd"][k] = loop.cmd
            tr["ff"][k] = row[rf:rf + 4]
            tr["stroke"][k] = plant.stroke_m
            tr["limited"][k] = loop.limiter.limited
        tr["harm"] = loop.harm       # the do-no-harm supervisor's line if it switched isolation off, else None
        return tr, time.perf_counter() - t0


def figures(traces, sl, fs) -> dict:
    res = {"floor_rms_um": rms(traces["off"]["floor"][sl]) * 1e6, "table_rms_um": {}, "tool_rms_um": {},
           "reduction_db": {}, "valve_limited_fraction": {}, "valve_rms_V": {}, "feedforward_rms_V": {},
           "max_abs_stroke_um": {}}
    for mode, tr in traces.items():
        res["table_rms_um"][mode] = rms(tr["table"][sl]) * 1e6
        res["tool_rms_um"][mode] = rms(tr["tool"][sl]) * 1e6
        res["table_rms_um"][mode + "_1_100hz"] = rms(band_1_100(tr["table"][sl], fs)) * 1e6
        res["tool_rms_um"][mode + "_1_100hz"] = rms(band_1_100(tr["tool"][sl], fs)) * 1e6
        res["valve_limited_fraction"][mode] = float(tr["limited"][sl].mean())
        res["valve_rms_V"][mode] = float(np.sqrt(np.mean(tr["cmd"][sl] ** 2)))
        res["feedforward_rms_V"][mode] = float(np.sqrt(np.mean(tr["ff"][sl] ** 2)))
        res["max_abs_stroke_um"][mode] = float(np.max(np.abs(tr["stroke"][sl]))) * 1e6
    for key in ("table", "tool"):
        r = res[f"{key}_rms_um"]
        for mode in MODES[1:]:
            res["reduction_db"].setdefault(key, {})[mode] = 20 * math.log10(r["off"] / r[mode])
            res["reduction_db"].setdefault(key + "_1_100hz", {})[mode] = \
                20 * math.log10(r["off_1_100hz"] / r[mode + "_1_100hz"])
    res["vc"] = {key: vc_report({m: traces[m][key][sl] for m in MODES}, fs) for key in ("table", "tool")}
    res["vc_class"] = res["vc"]["table"]["vc_class"]
    res["vc_class_tool"] = res["vc"]["tool"]["vc_class"]
    # per one-third-octave band, like with like: the band's rms velocity with isolation over without (null for
    # a band no frequency bin of the record falls in: a record shorter than a few seconds at the lowest bands)
    vt = res["vc"]["table"]["velocity_um_s"]
    res["band_reduction_db"] = {m: [20 * math.log10(a / b) if a > 0 and b > 0 else None
                                    for a, b in zip(vt["off"], vt[m])] for m in MODES[1:]}
    res["max_band_amplification_db"] = {m: max([0.0] + [-x for x in v if x is not None])
                                        for m, v in res["band_reduction_db"].items()}
    return res


