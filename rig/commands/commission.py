"""`rig commission [--backend hil|sim] [--layout machine|prototype] [--config F] --out DIR`: check the rig's wiring
before any loop closes.

The valves stay under open-loop command (controllers/playback.py), one at a time: first QUIET_S with every valve at
null (each channel's noise floor and offset), then per mount a bounded chirp (AMPLITUDE_V, F0-F1 Hz over CHIRP_S;
without floor accelerometers louder and longer: chirp_size; the stroke a few um, far inside +-50 % of [safety]
stroke_limit_m), the safety rules on. rig/commissioning.py then
names, per channel: alive, noise, offset; which transducer and which accelerometer answer which valve (the response
matrix, a swap named); each accelerometer's sign and scale against the second derivative of its own mount's
stroke; then each valve held at +-STEP_V for HOLD_S each: its DC gain against the model's, its null offset
(rig/commissioning.py valve_checks) and which mount it moves (swapped CAN nodes). Out: DIR/report.txt, report.json,
commissioning.toml (per channel mount, sign, scale, offset; per valve the mount it moves, null, gain), one PNG
per mount, and the recording. Exit 0 when every channel is ok, 4 when
a channel needs the calibration file or is refused, 1 after a fault (rig/errors.py).
Rehearse wiring faults on the emulated rig: drivers/devicemaps/hil_wiring_faults.md.

The prototype (`--layout prototype`: drivers/devicemaps/prototype_hil.toml, the actuator alone on its stand; any
config with [layout] plant = "stand"): the same procedure for its one valve (about 6 s of motion). One valve, one
transducer, one accelerometer: no swap can happen, so no response matrix; a noise floor is judged against the
sensor's configured noise ([stand]) instead of the others of its kind, a dead transducer against the model's DC
gain (rig/commissioning.py). The command prints the run's wall time, start-up included.
"""
from __future__ import annotations

import dataclasses
import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

from rig import cliargs
from rig.config import hil_run_config, layout_mounts
from rig.errors import EXIT_FINDINGS, FaultError, RigError
from rig.runtime.clock import MonotonicClock, SimClock
from rig.runtime.recorder import read_recording

CONFIG_HELP = ("TOML configuration (default: drivers/devicemaps/hil.toml; with --layout prototype "
               "drivers/devicemaps/prototype_hil.toml)")
QUIET_S = 1.5
LEAD_S = 0.2                   # null before and after each mount's chirp
CHIRP_S = 2.0
F0_HZ, F1_HZ = 2.0, 40.0
AMPLITUDE_V = 2.0
# no floor accelerometer (the stand, a machine without them): the floor's motion stays in the table's accelerometer,
# as large as the chirp's x'' in the band, and scatters its scale (sd 0.12 over seeds at 2 V, 2 s; 0.03 at 5 V, 4 s)
FLOOR_IN_AMPLITUDE_V, FLOOR_IN_CHIRP_S = 5.0, 4.0
STEP_V, HOLD_S = 2.0, 0.6      # then one valve at a time held at +STEP_V and -STEP_V (its DC gain and null offset)
SAFE_SHARE = 0.5               # the stroke the procedure may ask for, of [safety] stroke_limit_m (issue 27)
ADC_LSB_V = 20.0 / 65535       # the analog module: raw 0..65535 = -10..+10 V (drivers/devicemaps/adam6024_modbus.md)
TRANSDUCER_LSB_M = 1e-9        # the DTA-4 reports um with three decimals (drivers/devicemaps/dta4_serial.md)


def sensor_noise(cfg) -> dict:
    """What one mount alone judges its noise floors against, having no others of its kind: each sensor's white
    noise as configured ([stand] accel_noise_mps2, position_noise_m) with its device's resolution (a uniform
    rounding error, LSB / sqrt 12), rms per sample in the loop's units."""
    q = math.sqrt(12.0)
    return {"accel": math.hypot(cfg.stand.accel_noise_mps2, ADC_LSB_V / cfg.drivers.accel_V_per_mps2 / q),
            "stroke": math.hypot(cfg.stand.position_noise_m, TRANSDUCER_LSB_M / q)}


def add_arguments(p) -> None:
    p.add_argument("--backend", choices=("hil", "sim", "hardware"), default="hil")
    cliargs.output_arg(p, "--out", kind="folder", metavar="DIR", default=None,
                       help="folder for the report, the calibration file and the plots (default: "
                            "commission-<date>-<time> in the current folder)")
    p.add_argument("--json", action="store_true", help="print only the report as JSON on stdout")
    p.add_argument("--layout", choices=("machine", "prototype"), default=None,
                   help="machine: the config's (default); prototype: the actuator on its stand "
                        "(drivers/devicemaps/prototype_hil.toml) unless --config names one")


def process_age_s() -> float:
    """Seconds since this process started (/proc/self/stat's start time: the interpreter's start-up counts too),
    0 where that cannot be read."""
    try:
        ticks = int(Path("/proc/self/stat").read_text().rsplit(")", 1)[1].split()[19])
        return max(0.0, time.clock_gettime(time.CLOCK_BOOTTIME) - ticks / os.sysconf("SC_CLK_TCK"))
    except (OSError, ValueError, IndexError, AttributeError):
        return 0.0


def chirp_size(cfg) -> tuple[float, float]:
    """The chirp's amplitude (V) and duration (s): louder and longer where no floor accelerometer is fitted."""
    return (AMPLITUDE_V, CHIRP_S) if cfg.sensors.floor_accel else (FLOOR_IN_AMPLITUDE_V, FLOOR_IN_CHIRP_S)


def check_bounded(cfg, dc_gain_m_per_V: float) -> None:
    """The commands are bounded: held at the larger of the chirp's and the steps' amplitude, the model's stroke
    (Eq. 9 at DC) must stay inside SAFE_SHARE of the stroke limit, or nothing moves (RigError naming the field)."""
    volts = max(chirp_size(cfg)[0], STEP_V)
    asked = abs(dc_gain_m_per_V) * volts
    if asked > SAFE_SHARE * cfg.safety.stroke_limit_m:
        raise RigError(f"{cfg.source}: safety.stroke_limit_m: {cfg.safety.stroke_limit_m:g} m; commissioning's "
                       f"{volts:g} V would move the stroke {asked * 1e6:.1f} um, beyond "
                       f"{100 * SAFE_SHARE:g} % of it")


def run(args) -> int:
    started = time.monotonic() - process_age_s()
    from rig.commands.run import layout_config
    # rig run's rule for --config / --layout, with the HIL's files on every backend: the procedure runs at
    # [hil] rate_hz whatever the backend (hil.toml, prototype_hil.toml without --config)
    cfg = layout_config(args, "hil")
    from controllers.playback import SignalPlayback        # heavy (numba, scipy): after the arguments are checked
    from rig import commissioning
    from rig.chirp import chirp_samples
    from rig.runtime.session import Session
    from sim_backend.linear import ActuatorParams
    rate = cfg.hil.rate_hz
    if args.backend == "hil":
        cfg = hil_run_config(cfg, rate)
    # the chirps move the table on purpose and no loop isolates: the do-no-harm supervisor has nothing to judge
    # (it took a noisy accelerometer's chirp slot for harm and stopped the slots after it); the safety rules stay on
    cfg = dataclasses.replace(cfg, supervisor=dataclasses.replace(cfg.supervisor, enabled=False))
    names = layout_mounts(cfg)
    dc_gain = ActuatorParams.from_config(cfg).dc_gain_m_per_V
    check_bounded(cfg, dc_gain)
    dt = 1.0 / rate
    chirp_V, chirp_s = chirp_size(cfg)
    slot_s = chirp_s + 2 * LEAD_S
    chirp = chirp_samples(chirp_V, F0_HZ, F1_HZ, chirp_s, dt)
    n_lead, n_slot = int(round(LEAD_S / dt)), int(round(slot_s / dt))
    # the playback starts at activation (after QUIET_S): mount j's chirp in its own slot, the others at null
    n_hold, n_step = int(round(HOLD_S / dt)), int(round((2 * HOLD_S + LEAD_S) / dt))
    pad = [0.0] * (len(names) * n_slot)                 # the chirps' slots, then each valve's held steps
    ctrls = [SignalPlayback(([0.0] * (j * n_slot + n_lead) + chirp + pad)[:len(pad)] + [0.0] * (j * n_step + n_lead) +
                            [STEP_V] * n_hold + [-STEP_V] * n_hold, dt, name=m) for j, m in enumerate(names)]
    out = Path(args.out) if args.out is not None else Path(time.strftime("commission-%Y%m%d-%H%M%S"))
    out.mkdir(parents=True, exist_ok=True)
    rec_path = out / "commissioning.h5"
    total = QUIET_S + len(names) * (slot_s + 2 * HOLD_S + LEAD_S) + LEAD_S
    if not args.json:
        mounts = f"{len(names)} mounts" if len(names) > 1 else f"the {names[0]} alone"
        print(f"rig commission: {args.backend}, {mounts} at {rate:g} Hz: {QUIET_S:g} s at null, then one "
              f"valve at a time a {chirp_V:g} V chirp {F0_HZ:g}-{F1_HZ:g} Hz over {chirp_s:g} s, then held at "
              f"+-{STEP_V:g} V for {HOLD_S:g} s each ({total:.1f} s)",
              file=sys.stderr)
    through = cfg.drivers.calibration if args.backend != "sim" else ""     # (the drivers apply it; sim has none)
    if through:
        print(f"rig commission: through the calibration {through} ([drivers] calibration): a check of it; what this "
              f"run writes is relative to it, not a calibration in its place (commission without it for that)",
              file=sys.stderr)
    clock = SimClock() if args.backend == "sim" else MonotonicClock()
    with Session(cfg, args.backend, controllers=ctrls, clock=clock, rate_hz=rate, isolation=True, names=names,
                 record=rec_path, record_attrs={"command": "rig commission"}, signals=True,
                 record_floor=cfg.sensors.floor_accel,      # the floor accelerometers, checked against the table
                 realtime=args.backend != "sim" and cfg.loop.realtime) as s:
        if args.backend == "hil":
            time.sleep(0.2)          # the I/O processes refresh their samples after the set-up pause
        moving = time.monotonic()
        s.run(seconds=total, activate_after_s=QUIET_S)
        fault = s.loop.lc.fault_reason
        moved = time.monotonic()
    if fault:
        raise FaultError(f"commission: the run faulted ({fault}): nothing judged")
    rec = read_recording(rec_path)
    steps = (QUIET_S + len(names) * slot_s + LEAD_S, HOLD_S, LEAD_S)
    res = commissioning.analyse(rec, names, rate, QUIET_S, slot_s, LEAD_S, dc_gain, steps=steps,
                                sensor_noise=sensor_noise(cfg) if len(names) == 1 else None)
    peak = float(np.abs(np.asarray(rec["stroke_m"])).max())
    res["peak_stroke_m"] = float(peak)
    res["stroke_limit_m"] = cfg.safety.stroke_limit_m
    res["through_calibration"] = through or None
    write_report(res, rec, out, rec_path, steps)
    res["wall_s"] = time.monotonic() - started
    res["wall_parts_s"] = {"start_up": moving - started, "excitation": moved - moving,
                           "close_and_analysis": started + res["wall_s"] - moved}
    if args.json:
        print(json.dumps(res))
    else:
        print(commissioning.text(res))
        print(f"peak stroke {peak * 1e6:.1f} um ({100 * peak / cfg.safety.stroke_limit_m:.1f} % of the stroke limit); "
              f"report, calibration and plots in {out}")
    print(f"rig commission: took {res['wall_s']:.1f} s wall (start-up included: " + ", ".join(
        f"{k.replace('_', ' ')} {v:.1f} s" for k, v in res["wall_parts_s"].items()) + ")", file=sys.stderr)
    return 0 if res["all_ok"] else EXIT_FINDINGS


def write_report(res: dict, rec: dict, out: Path, rec_path: Path, steps) -> None:
    """report.txt, report.json, commissioning.toml and a PNG per mount (one mount alone: nothing to swap, its
    polarity and its valve's held steps instead of the response matrix)."""
    from rig import commissioning
    (out / "report.txt").write_text(commissioning.text(res) + "\n")
    (out / "report.json").write_text(json.dumps(res, indent=1))
    (out / "commissioning.toml").write_text(commissioning.calibration_toml(res, str(rec_path)))
    names = res["mounts"]
    if len(names) == 1:
        commissioning.plot_alone(res, rec, out / f"{names[0]}.png", QUIET_S, LEAD_S, steps)
    else:
        for m in names:
            commissioning.plot(res, rec, m, out / f"{m}.png")
