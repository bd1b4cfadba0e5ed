"""The machine-level effects (issue 28): one definition each, with what the diagnosis fits, how it reports it,
how the blind proof draws it and the simulator's term that hides it ([rig_error] of the config,
sim_backend/rig_error.py). Written to become entries of the diagnosis's effect catalogue.

Each effect has instances -- one per flexible mode, mount or sensor -- and an instance's `location` is what the
proof grades as "the right mount or sensor". The replay's effects are fitted in the frequency domain
(engine.py); the valve's null offset (a constant: only the start of a run from rest shows it) and the floor's
rocking (the floor is the replay's input, not its model) have their own tests (offsets.py, floor.py).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from rig.config import MOUNTS
from rig.diagnose.machine.fitting import Slot

SENSORS = ("accel", "stroke", "floor")
SENSOR_KEY = {"accel": "gain_a", "stroke": "gain_s", "floor": "gain_g"}
SENSOR_TEXT = {"accel": "accelerometer", "stroke": "stroke transducer", "floor": "floor accelerometer"}
# flexible modes the four mounts see too little of (Table 2's heave: at most 0.022 at a mount) to tell
# a mode the model lacks is a resonance of the machine's structure: damped a few per cent (Table 2: 0.03), at
# most this (Q 5); a broader one has no peak a run resolves, and an estimate on this bound is a broadband misfit
EXTRA_MODE_MAX_DAMPING = 0.1
MIN_MOUNT_SHAPE = 0.05          # modal model units (1/sqrt(t)): Table 2's yaw (0.044) and heave (0.022) barely move them


@dataclass(frozen=True)
class Param:
    name: str
    unit: str
    lo: float
    hi: float


@dataclass(frozen=True)
class Instance:
    effect: "Effect"
    index: int                  # the mode, mount or sensor channel
    location: str               # "rear_left", "accelerometer at front_right", "1st torsion"
    slots: tuple

    @property
    def key(self) -> str:
        return f"{self.effect.name}[{self.location}]"

    @property
    def mounts(self) -> tuple[int, ...]:
        """The mounts whose loops it sits in (a mode or the machine: all four)."""
        if self.effect.where in ("mount", "valve"):
            return (self.index,)
        if self.effect.where == "sensor":
            return (self.index % len(MOUNTS),)
        return tuple(range(len(MOUNTS)))


@dataclass(frozen=True)
class Effect:
    """One effect: what the diagnosis fits (its instances' slots of the model's parameters, the start grid of the
    first), how it reports and says it, what evidence it stands on, how the blind proof draws it (DRAWS below)
    and the simulator's term (docs/MODEL.md, [rig_error])."""
    name: str
    short: str
    where: str                  # mode, machine, mount, sensor, valve, floor
    params: tuple
    evidence: str               # the signature the diagnosis looks for (one line, for the report)
    make_instances: Callable | None = None    # (effect, ctx) -> [Instance]; None: tested apart (offsets, floor)
    report: Callable | None = None            # (instance, theta, ctx) -> parameters as reported
    say: Callable = str                       # parameters -> one line
    needs_valves: bool = False  # its instances are candidates only when the valves were driven
    grid: tuple = ()            # start values of the first slot, screened before a fit
    nonlinear: bool = False     # the model sees an effective command (time domain) rather than a response
    margins_note: str = ""      # for an effect outside the loop: what it does to the margins
    typical: tuple = ()         # (size, unit): a typical size ("%": a factor 1 + size, "x": a factor, else
                                # added), for what a recording can tell (detect.py)
    started: bool = False       # its start is the engine's own search (the extra mode), not a grid
    shared_place: bool = False  # a second one of it in a case may sit where the first does (proof)
    size: Callable | None = None    # parameters as reported -> the size compared with `least` (None: any size)
    least: float = 0.0          # the least size worth naming: below it the part is within its own tolerance
    tolerance: str = ""         # what `least` stands for (for the report)


def _mode_instances(key: str, lo: float, hi: float):
    def make(eff: Effect, ctx) -> list[Instance]:
        shape = np.abs(ctx.modal.phi_mounts[ctx.modal.w_n > 0]) / ctx.modal.shape_unit_scale
        return [Instance(eff, r, name, (Slot(key, r, "log", lo, hi),))
                for r, name in enumerate(ctx.modal.flexible_names) if shape[r].max() >= MIN_MOUNT_SHAPE]
    return make


def _mount_instances(key: str, lo: float, hi: float, scale: str = "log"):
    def make(eff: Effect, ctx) -> list[Instance]:
        return [Instance(eff, i, m, (Slot(key, i, scale, lo, hi),)) for i, m in enumerate(MOUNTS)]
    return make


def _sensor_instances(eff: Effect, ctx) -> list[Instance]:
    return [Instance(eff, 4 * SENSORS.index(s) + i, f"{SENSOR_TEXT[s]} at {m}",
                     (Slot(SENSOR_KEY[s], i, "signed", 0.05, 10.0),))
            for s in SENSORS if s != "floor" or ctx.floor for i, m in enumerate(MOUNTS)]


def _extra_instances(eff: Effect, ctx) -> list[Instance]:
    slots = (Slot("extra", 0, "log", 3.0, 300.0), Slot("extra", 1, "log", 0.005, EXTRA_MODE_MAX_DAMPING)) + tuple(
        Slot("extra", 2 + i, "lin", -1.5, 1.5) for i in range(4))
    return [Instance(eff, 0, "machine", slots)]


def _flex(ctx, key: str, i: int) -> float:
    return float(getattr(ctx.modal, key)[ctx.modal.w_n > 0][i])


def _report_frequency(inst, th, ctx) -> dict:
    f0 = _flex(ctx, "w_n", inst.index) / (2 * math.pi)
    return {"mode": inst.location, "frequency_hz": f0 * float(th["mode_f"][inst.index]), "model_hz": f0}


def _report_damping(inst, th, ctx) -> dict:
    z0 = _flex(ctx, "zeta", inst.index)
    return {"mode": inst.location, "damping_ratio": z0 * float(th["mode_z"][inst.index] * th["modal_zeta"][0]),
            "model_damping_ratio": z0}


def _report_extra(inst, th, ctx) -> dict:
    x = np.asarray(th["extra"], dtype=float)
    v = x[2:6]
    sign = 1.0 if v[int(np.argmax(np.abs(v)))] >= 0 else -1.0      # a mode's shape has no sign of its own
    return {"frequency_hz": float(x[0]), "damping_ratio": float(x[1]),
            "shape": dict(zip(MOUNTS, (float(sign * a) for a in v)))}


def _report_factor(inst, th, ctx) -> dict:
    return {"mount": inst.location, "factor": float(inst.slots[0].get(th))}


def _report_gain(inst, th, ctx) -> dict:
    s = SENSORS[inst.index // 4]
    return {"sensor": s, "mount": MOUNTS[inst.index % 4], "gain": float(th[SENSOR_KEY[s]][inst.index % 4])}


def _report_value(name: str):
    def report(inst, th, ctx) -> dict:
        return {"mount": inst.location, name: float(inst.slots[0].get(th))}
    return report


def _say_gain(p) -> str:
    sign = " (sign reversed)" if p["gain"] < 0 else ""
    return f"{p['mount']}: {SENSOR_TEXT[p['sensor']]} reads x{p['gain']:.3f}{sign}"


MODE_FREQUENCY = Effect(
    "mode_frequency", "mode f", "mode", (Param("frequency_hz", "Hz", 1.0, 500.0),),
    "the resonance of a machine mode in the mounts' responses stands at another frequency than Table 2's",
    _mode_instances("mode_f", 0.6, 1.6), _report_frequency,
    lambda p: f"mode '{p['mode']}' at {p['frequency_hz']:.2f} Hz (Table 2: {p['model_hz']:.2f} Hz)",
    grid=tuple(np.round(np.arange(0.78, 1.25, 0.04), 3)), typical=(1.03, "%"))
MODE_DAMPING = Effect(
    "mode_damping", "mode zeta", "mode", (Param("damping_ratio", "", 0.001, 0.5),),
    "a machine mode's resonance in the mounts' responses is sharper or broader than the model's",
    _mode_instances("mode_z", 0.1, 10.0), _report_damping,
    lambda p: f"mode '{p['mode']}' damped {p['damping_ratio']:.4f} (model {p['model_damping_ratio']:.4f})",
    grid=(0.3, 0.5, 0.7, 1.5, 2.2, 3.5), typical=(2.0, "x"))
EXTRA_MODE = Effect(
    "extra_mode", "extra mode", "machine",
    (Param("frequency_hz", "Hz", 3.0, 300.0), Param("damping_ratio", "", 0.005, EXTRA_MODE_MAX_DAMPING),
     Param("shape", "1/sqrt(t)", -1.5, 1.5)),
    "a resonance in the mounts' responses where the model has no mode", _extra_instances, _report_extra,
    lambda p: (f"a mode the model lacks at {p['frequency_hz']:.2f} Hz, damping {p['damping_ratio']:.4f}, shape at "
               "the mounts " + ", ".join(f"{m} {v:+.3f}" for m, v in p["shape"].items()) + " (1/sqrt(t))"),
    started=True, shared_place=True)
MOUNT_STIFFNESS = Effect(
    "mount_stiffness", "K_L", "mount", (Param("factor", "", 0.2, 5.0),),
    "one mount's stroke per valve volt (below the 7 Hz lag: 1 / K_L) and its share of the machine's weight "
    "differ from the others'", _mount_instances("mount_K", 0.2, 5.0), _report_factor,
    lambda p: f"{p['mount']}: membrane stiffness K_L x{p['factor']:.3f}", grid=(0.5, 0.7, 1.4, 2.0),
    typical=(1.3, "%"))
MOUNT_DAMPING = Effect(
    "mount_damping", "C", "mount", (Param("factor", "", 0.05, 30.0),),
    "one mount's viscous term: force on its stroke velocity", _mount_instances("mount_C", 0.05, 30.0),
    _report_factor, lambda p: f"{p['mount']}: viscous coefficient C x{p['factor']:.3f}", grid=(0.2, 5.0, 20.0),
    typical=(3.0, "x"))
SENSOR_GAIN = Effect(
    "sensor_gain", "gain", "sensor", (Param("gain", "", -10.0, 10.0),),
    "one channel reads the replay scaled (a sign reversed: opposite phase) in every band where it is seen",
    _sensor_instances, _report_gain, _say_gain, grid=(-1.0, 0.8, 1.25), typical=(1.1, "%"),
    # a sensitivity is known to its calibration's uncertainty: a back-to-back comparison (ISO 16063-21) gives an
    # accelerometer's to 1-2 %, a displacement transducer's gain is known to about 1 %; a sign reversed is a fault
    size=lambda p: math.inf if p["gain"] < 0 else abs(p["gain"] - 1.0), least=0.02,
    tolerance="a sensor's calibration uncertainty (1-2 %)")
TRANSPORT_DELAY = Effect(
    "transport_delay", "delay", "valve", (Param("delay_s", "s", 0.0, 0.01),),
    "one valve's response lags the others' by a phase growing with frequency (-w tau)",
    _mount_instances("delay_s", 0.0, 0.01, "lin"), _report_value("delay_s"),
    lambda p: f"{p['mount']}: valve delay {p['delay_s'] * 1e3:.3f} ms", needs_valves=True,
    grid=(0.0002, 0.0005, 0.001, 0.002, 0.004), typical=(3e-4, "s"))
VALVE_DEADBAND = Effect(
    "valve_deadband", "deadband", "valve", (Param("width_ma", "mA", 0.0, 20.0),),
    "one valve moves less than the replay for small commands (its spool's overlap), as much for large ones",
    _mount_instances("deadband_ma", 0.0, 20.0, "lin"), _report_value("width_ma"),
    lambda p: f"{p['mount']}: spool deadband {p['width_ma']:.3f} mA", needs_valves=True,
    grid=(0.1, 0.3, 0.6, 1.0, 2.0), nonlinear=True, typical=(0.5, "mA"))
VALVE_NULL_OFFSET = Effect(
    "valve_null_offset", "null", "valve", (Param("offset_V", "V", -10.0, 10.0),),
    "from rest, one actuator drifts with its valve at null, and holds a mean command to stay centred",
    say=lambda p: f"{p['mount']}: valve null offset {p['offset_V']:+.3f} V (+-{p['se_V']:.3f})",
    margins_note="a constant at the valve",
    size=lambda p: abs(p["offset_V"]), least=0.03, tolerance="a valve's null tolerance (V)")
FLOOR_ROCKING = Effect(
    "floor_rocking", "rocking", "floor", (Param("rocking_over_heave", "", 0.0, 10.0),),
    "the floor's front mounts move against its rear (pitch) or its left against its right (roll), coherently, "
    "beyond the independent motion the model assumes",
    say=lambda p: (f"the floor rocks ({p['axis']}): its rocking {p['rocking_over_heave']:.2f} of its heave, "
                   f"{p['ratio']:.1f}x the twist's power"),
    margins_note="the floor is the loop's input, not part of it", shared_place=True,
    size=lambda p: p["ratio"], least=1.6,       # a third more in rms than twist
    tolerance="the share independent motion at the mounts puts into pitch or roll (as much as into twist)")

REPLAY_EFFECTS = (MODE_FREQUENCY, MODE_DAMPING, EXTRA_MODE, MOUNT_STIFFNESS, MOUNT_DAMPING, SENSOR_GAIN,
                  TRANSPORT_DELAY, VALVE_DEADBAND)
CATALOGUE = REPLAY_EFFECTS + (VALVE_NULL_OFFSET, FLOOR_ROCKING)
BY_NAME = {e.name: e for e in CATALOGUE}


def instances(ctx, *, valves_driven: bool) -> list[Instance]:
    """Every instance of the replay's effects this recording can show (valve effects need driven valves,
    floor-sensor gains need floor accelerometers)."""
    return [i for eff in REPLAY_EFFECTS if valves_driven or not eff.needs_valves for i in eff.make_instances(eff, ctx)]


def parameters(inst: Instance, th: dict, ctx) -> dict:
    """The instance's parameters as reported (physical units)."""
    return inst.effect.report(inst, th, ctx)


def worth_naming(effect: Effect, params: dict) -> bool:
    """Whether the effect's size reaches the least worth naming (its `least`): a smaller one is within the
    part's tolerance, not a fault, however sure the fit is of it."""
    return effect.size is None or effect.size(params) >= effect.least


def shortfall(effect: Effect, params: dict) -> str:
    """Empty if the effect is worth naming, else one line saying why not."""
    if worth_naming(effect, params):
        return ""
    return f"its size {effect.size(params):.3g} is below {effect.least:g}: within {effect.tolerance}"


def describe(name: str, params: dict) -> str:
    """One line saying a named effect and its parameters."""
    return BY_NAME[name].say(params)


# ---- how the blind proof draws each effect (rig prove --rig): (location, truth, [rig_error] keys, [vibration]
# keys), sizes a physical rig would show and its run can tell (valve effects need the valves driven; an
# accelerometer's or a floor accelerometer's sensitivity needs the floor measured; a sign reversed only where
# the loop survives it: an accelerometer with isolation off, a floor accelerometer)
def _size(rng, lo: float, hi: float) -> float:
    """A factor off 1 by lo..hi either way."""
    d = float(rng.uniform(lo, hi))
    return 1.0 + d if rng.random() < 0.5 else 1.0 / (1.0 + d)


def _mode_draw(key: str):
    def draw(rng, cond):
        names = [i.location for i in MODE_FREQUENCY.make_instances(MODE_FREQUENCY, cond)]
        r = cond.modal.flexible_names.index(str(rng.choice(names)))
        nflex = len(cond.modal.flexible_names)
        f = [1.0] * nflex
        if key == "mode_frequency_factor":
            f[r] = round(_size(rng, 0.04, 0.12), 4)
            f0 = cond.modal.w_n[cond.modal.w_n > 0][r] / (2 * math.pi)
            truth = {"frequency_hz": round(f0 * f[r], 4)}
        else:
            f[r] = round(float(rng.uniform(0.35, 0.6)) if rng.random() < 0.5 else float(rng.uniform(1.8, 3.0)), 3)
            truth = {"damping_factor": f[r]}
        return cond.modal.flexible_names[r], truth, {key: f}, {}
    return draw


def _extra_draw(rng, cond):
    for _ in range(200):
        hz = round(float(np.exp(rng.uniform(math.log(12.0), math.log(100.0)))), 3)
        if all(abs(hz - f) / f > 0.12 for f in cond.coupled_hz):
            break
    v = rng.uniform(-1.0, 1.0, 4)
    shape = [round(float(x), 4) for x in v / np.abs(v).max() * rng.uniform(0.08, 0.2)]
    zeta = round(float(rng.uniform(0.02, 0.05)), 4)
    return "machine", {"frequency_hz": hz, "damping_ratio": zeta, "shape": shape}, {
        "extra_mode_hz": hz, "extra_mode_damping": zeta, "extra_mode_shape": shape}, {}


def _mount_draw(key: str, size):
    def draw(rng, cond):
        i = int(rng.integers(4))
        v = [1.0] * 4
        v[i] = round(size(rng), 4)
        return MOUNTS[i], {"factor": v[i]}, {key: v}, {}
    return draw


def _gain_kinds(cond) -> list[str]:
    """The sensors a run can judge: strokes when the valves move them (with isolation off they rest at their
    noise), accelerometers and floor accelerometers only with the floor measured (else the floor takes an
    accelerometer's sensitivity up)."""
    return (["stroke"] if cond.mode != "off" else []) + (["accel", "floor"] if cond.floor_sensors else [])


def _gain_draw(rng, cond):
    kinds = _gain_kinds(cond)
    s = str(rng.choice(kinds))
    i = int(rng.integers(4))
    g = round(_size(rng, 0.08, 0.25), 4)
    if (s == "floor" or (s == "accel" and cond.mode == "off")) and rng.random() < 0.25:
        g = -1.0
    v = [1.0] * 4
    v[i] = g
    return f"{SENSOR_TEXT[s]} at {MOUNTS[i]}", {"gain": g}, {f"{s}_gain": v}, {}


def _valve_draw(key: str, lo: float, hi: float, signed: bool = False):
    def draw(rng, cond):
        i = int(rng.integers(4))
        x = round(float(rng.uniform(lo, hi)), 6) * (float(rng.choice([-1.0, 1.0])) if signed else 1.0)
        v = [0.0] * 4
        v[i] = x
        return MOUNTS[i], {_TRUTH_KEY[key]: x}, {key: v}, {}
    return draw


_TRUTH_KEY = {"valve_delay_s": "delay_s", "valve_deadband_ma": "width_ma", "valve_null_V": "offset_V"}


def _rocking_draw(rng, cond):
    axis = str(rng.choice(["pitch", "roll"]))
    r = round(float(rng.uniform(0.6, 1.2)), 3)
    return axis, {"rocking_rms_over_floor_rms": r}, {}, {"rocking_axis": axis, "rocking_over_floor": r}


def _valves(cond) -> bool:
    return cond.mode != "off"


def _machine_seen(cond) -> bool:
    """A machine mode is seen in the mounts' responses to the valves (driven) or to the floor (measured); with
    isolation off and the floor unmeasured the floor, projected out, takes the mounts' responses with it."""
    return cond.mode != "off" or cond.floor_sensors


DRAWS = {   # effect -> (draw, whether the run can tell it)
    MODE_FREQUENCY.name: (_mode_draw("mode_frequency_factor"), _machine_seen),
    MODE_DAMPING.name: (_mode_draw("mode_damping_factor"), _machine_seen),
    EXTRA_MODE.name: (_extra_draw, _machine_seen),
    MOUNT_STIFFNESS.name: (_mount_draw("mount_stiffness_factor", lambda rng: _size(rng, 0.25, 0.6)),
                           lambda cond: True),
    SENSOR_GAIN.name: (_gain_draw, lambda cond: bool(_gain_kinds(cond))),
    TRANSPORT_DELAY.name: (_valve_draw("valve_delay_s", 1.5e-4, 4e-4), _valves),
    VALVE_DEADBAND.name: (_valve_draw("valve_deadband_ma", 0.2, 1.0), _valves),
    VALVE_NULL_OFFSET.name: (_valve_draw("valve_null_V", 0.1, 0.4, signed=True), lambda cond: True),
    FLOOR_ROCKING.name: (_rocking_draw, lambda cond: True),
}
