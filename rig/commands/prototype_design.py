"""`rig design --layout prototype`: the prototype's two loops on its stand as the runtime runs them
(controllers/prototype.py): the tracking loop (bandwidth, margins, the Fig. 4 response, with and without the
reference feedforward; a 2 um step and a 10 um 5 Hz sine through the compiled law) and the isolation loop
(margins, floor -> load transmissibility, load motion under the floor spectrum)."""
from __future__ import annotations

import dataclasses
import json
import math
import sys

from controllers import prototype
from rig import cliargs


def _finite(v):
    if isinstance(v, dict):
        return {k: _finite(x) for k, x in v.items()}
    return None if isinstance(v, float) and not math.isfinite(v) else v


def run(args, cfg, model: dict) -> int:
    """Print the report (its figures on stdout, or --json), --out DIR: the figures and prototype_design.json.
    model: where the actuator came from (`rig design --identified`). --tune: both loops retuned first for
    this rate and delay (controllers/prototype.py tune), printed as a [controller] table (--out:
    controller.toml)."""
    dt = 1.0 / cfg.loop.rate_hz
    delay = cfg.controller.track_delay_periods
    tuned = None
    if args.tune:
        print(f"rig design: tuning both loops for the stand at {cfg.loop.rate_hz:g} Hz, {delay} period(s) of delay",
              file=sys.stderr)
        values = prototype.tune(cfg, dt, delay, progress=lambda m: print(f"rig design: {m}", file=sys.stderr))
        cfg = cfg.replace(controller=dataclasses.replace(cfg.controller, **values))
        tuned = {"toml": prototype.toml(values), "values": values}
    print(f"rig design: the prototype on its stand at {cfg.loop.rate_hz:g} Hz (ZOH + {delay} period(s)) from "
          f"{cfg.source}", file=sys.stderr)
    rep = prototype.design_report(cfg, dt, delay)
    out = _finite(prototype.clean(rep))
    out["design_model"] = model
    if tuned:
        out["tuned"] = tuned
    tr, iso = out["tracking"], out["isolation"]
    st, sn = tr["step_2um"], tr["sine_10um_5hz"]
    lines = [f"tracking (Fig. 4 PID): bandwidth {tr['bandwidth_hz']:.1f} Hz (paper ~{tr['paper_bandwidth_hz']:g} Hz), "
             f"GM {tr['gain_margin_db']:.1f} dB, PM {tr['phase_margin_deg']:.1f} deg, peak {tr['peak_db']:.2f} dB; "
             f"with the feedforward ({tr['preview_periods']} periods ahead) {tr['bandwidth_ff_hz']:.1f} Hz",
             f"  2 um step: settles within 2 % in {st['settling_2pct_ms']:.1f} ms, overshoot {st['overshoot_pct']:.1f} %,"
             f" command peak {st['peak_command_V']:.2f} V{' (AT THE CLAMP)' if st['at_clamp'] else ''}",
             f"  10 um 5 Hz sine: rms error {sn['rms_error_um']:.4f} um = {sn['rms_error_pct']:.2f} % of the amplitude",
             f"  holds at most +-{tr['hold_range_um']:.1f} um (leakage, controller.track_headroom of the clamp)",
             f"isolation on the stand: stable: {'yes' if iso['stable'] else 'NO'}, GM {iso['gain_margin_db']:.1f} dB, PM "
             f"{iso['phase_margin_deg']:.1f} deg; attenuation " + ", ".join(f"{k} {v:.1f} dB" for k, v in
                                                                     iso["attenuation_db"].items())
             + f"; load rms {iso['load_rms_off_um']:.3f} -> {iso['load_rms_on_um']:.3f} um ({iso['isolation_db']:.1f} dB)"]
    if not args.json:                        # the figures on stdout, progress on stderr
        print("\n".join(lines), flush=True)
    if args.out is not None:
        cliargs.make_out_dir(args.out)
        files = prototype.write_figures(rep, args.out, cfg, dt, delay)
        (args.out / "prototype_design.json").write_text(json.dumps(out, indent=2))
        if tuned:
            (args.out / "controller.toml").write_text(tuned["toml"])
        print(f"rig design: wrote {len(files) + 1 + bool(tuned)} files to {args.out}", file=sys.stderr)
    if tuned and not args.json:
        print(tuned["toml"], end="")
    if args.json:
        print(json.dumps(out, indent=2))
    ok = iso["stable"] and tr["gain_margin_db"] > 0 and tr["phase_margin_deg"] > 0
    return 0 if ok else 1
