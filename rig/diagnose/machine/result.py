"""The diagnosis of a run of the four-mount rig as one typed result: the stages of engine.py, the floor's and the
valves' offsets' own tests, what the recording can tell, the transmissibilities and the margins.

`diagnose_rig(run, cfg)` is the one function a script or a notebook calls; report.py writes what it returns.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from rig.config import MOUNTS, Config
from rig.diagnose.machine import effects as fx
from rig.diagnose.machine import detect, floor as floor_mod, margins as margins_mod, offsets as offsets_mod
from rig.diagnose.machine.engine import Selection, diagnose_run, u_of, without_effect
from rig.diagnose.machine.residual import Replay
from rig.diagnose.machine.rigmodel import ACT_KEYS, Base, responses
from rig.recordings.runfile import RunRecording
from rig.diagnose.machine.spectra import BANDS_HZ, Spectra
from rig.diagnose.machine.transmissibility import transmissibility

CHANNELS = tuple(f"accel {m}" for m in MOUNTS) + tuple(f"stroke {m}" for m in MOUNTS)
EXPLAINED = 1.3                 # augmented held-out residual over what the noise and the model's fidelity leave
NOT_DESCRIBED = 3.0


@dataclass(frozen=True)
class NamedEffect:
    name: str
    location: str               # the mode, mount or sensor: what the proof grades
    parameters: dict
    tests: dict
    evidence: str
    margins: tuple = ()         # at the mounts whose loops it sits in: the diagnosed rig with it against without it


@dataclass
class RigDiagnosis:
    source: str
    fs_hz: float
    duration_s: float
    floor_measured: bool
    modes: dict                 # seconds of each isolation mode
    valves_driven: bool
    effects: list               # [NamedEffect]
    refit: dict                 # the common factors and the latency
    mismatch: dict              # model -> (8 channels x bands) held-out residual over expected
    located: list               # where the refit leaves most: [{"channel", "band_hz", "excess"}]
    fit: dict                   # model -> per mount {"accel", "stroke"}: held-out residual over expected
    candidates: list            # every candidate fitted, with its tests
    floor: floor_mod.FloorMotion | None
    offsets: list               # [offsets.MountOffset]
    starts_at_rest: bool
    detectability: list         # [detect.Detectability]
    transmissibility: dict
    margins: list               # [margins.MountLine] on the diagnosed rig
    verdict: str
    summary: str
    timing_s: float = 0.0
    theta: dict = field(default_factory=dict)
    notes: list = field(default_factory=list)
    base: Base | None = None    # the configured rig it was diagnosed against (the replay of theta runs on it)


def _per_channel(ev, f_hz, bands=BANDS_HZ) -> list:
    """(8, n_bands) rms of the whitened residual (per complex bin) over each band's bins."""
    f = f_hz[ev.mask]
    out = []
    for c in range(ev.r.shape[1]):
        row = []
        for lo, hi in bands:
            s = (f >= lo) & (f < hi)
            p = np.abs(ev.r[s, c]) ** 2 / np.maximum(ev.keep[s, c], 0.05)
            row.append(float(math.sqrt(np.mean(p))) if s.any() else None)
        out.append(row)
    return out


def _mount_fit(ev) -> dict:
    out = {}
    for i, m in enumerate(MOUNTS):
        out[m] = {}
        for name, c in (("accel", i), ("stroke", 4 + i)):
            p = np.abs(ev.r[:, c]) ** 2 / np.maximum(ev.keep[:, c], 0.05)
            out[m][name] = float(math.sqrt(np.mean(p)))
    return out


def _located(table: list, limit: float = 3.0) -> list:
    cells = [{"channel": CHANNELS[c], "band_hz": list(BANDS_HZ[b]), "excess": v}
             for c, row in enumerate(table) for b, v in enumerate(row) if v is not None and v > limit]
    return sorted(cells, key=lambda x: -x["excess"])[:8]


def _named(sel: Selection, ctx) -> list:
    return [NamedEffect(t.instance.effect.name, t.instance.location, fx.parameters(t.instance, sel.th_final, ctx),
                        dict(t.tests), t.instance.effect.evidence) for t in sel.chosen]


def _offset_effects(offs: list, rest: bool, dc) -> tuple[list, list]:
    """Named valve null offsets (one valve standing out, the start at rest reading zero) and notes."""
    named, notes = [], []
    out = [o for o in offs if o.stands_out]
    if not out:
        return named, notes
    if not rest:
        notes.append("a constant offset stands out at " + ", ".join(o.mount for o in out) + ": a valve's null or its "
                     "stroke transducer's zero; the recording does not start at rest, so they cannot be told apart")
        return named, notes
    for o in out:
        if o.transducer_zero:
            notes.append(f"{o.mount}: the stroke transducer's zero is off by {o.start_m * 1e6:.2f} um (read at rest "
                         "before anything moved): a sensor term, not a valve offset")
            continue
        named.append(NamedEffect(fx.VALVE_NULL_OFFSET.name, o.mount,
                                 {"mount": o.mount, "offset_V": o.offset_V, "se_V": o.se_V},
                                 {"t": o.t, "passed": True}, fx.VALVE_NULL_OFFSET.evidence))
    return named, notes


def _dc_gains(ctx, th) -> np.ndarray:
    R = responses(ctx.base, th, np.array([2 * math.pi * 0.01]), floor=False)
    return np.array([abs(R.Hu[0, 4 + i, i]) for i in range(4)])


def _floor_replay(ctx, th) -> Replay | None:
    """Without floor accelerometers: the replay with the floor's estimate taken for a measurement (what
    fitting them would show)."""
    if ctx.floor:
        return None
    sp = ctx.sp
    X = floor_mod.floor_estimate(ctx.rp, th, u_of(ctx)(th))
    G = -X * (sp.w ** 2)[:, None]
    sp2 = Spectra(sp.fs_hz, sp.n, sp.f_hz, sp.Y, sp.U, G, sp.fit, sp.hold, sp.bin_index,
                  np.concatenate([sp.noise[:8], np.full(4, 1e-30)]))
    return Replay(sp2, ctx.base, ctx.rp.s2)


def _verdict(over: float, named: list) -> str:
    if over <= EXPLAINED:
        return "explained"
    return "partly" if over <= NOT_DESCRIBED else "not_described"


def diagnose_rig(run: RunRecording, cfg: Config, progress=None) -> RigDiagnosis:
    say = progress or (lambda s: None)
    t0 = time.perf_counter()
    sel = diagnose_run(run, cfg, say)
    ctx = sel.ctx
    th = sel.th_final
    named = _named(sel, ctx)
    say("the floor, the valves' offsets and what this recording can tell")
    fm = floor_mod.floor_motion(ctx.rp, th, u_of(ctx)(th))
    if fm.rocking:
        named.append(NamedEffect(fx.FLOOR_ROCKING.name, fm.axis,
                                 {"axis": fm.axis, "rocking_over_heave": fm.rocking_over_heave, "ratio": fm.ratio},
                                 {"z": fm.z, "passed": True}, fx.FLOOR_ROCKING.evidence))
    offs = offsets_mod.null_offsets(run, _dc_gains(ctx, th))
    rest = offsets_mod.starts_at_rest(run)
    off_named, notes = _offset_effects(offs, rest, None)
    named += off_named
    det = detect.detectability(ctx.rp, th, ctx.sp.hold, u_of(ctx), ctx, rp_floor=_floor_replay(ctx, th))
    say("transmissibility per mount and band, measured against predicted")
    tr = transmissibility(run, ctx.base, {"model": sel.th_nominal, "diagnosed": th}, ctx.sp.noise)
    say("rig design on the diagnosed rig: margins per mount")
    lines = margins_mod.mount_lines(ctx.base, sel.th_nominal, th)
    named = [_with_margins(e, sel, ctx) for e in named]
    evh = {k: ctx.rp.evaluate(v, ctx.sp.hold, U=u_of(ctx)(v))
           for k, v in (("nominal", sel.th_nominal), ("refit", sel.th_refit), ("augmented", th))}
    mismatch = {k: _per_channel(ev, ctx.sp.f_hz) for k, ev in evh.items()}
    over = math.sqrt(evh["augmented"].rss / max(float(evh["augmented"].keep.sum()), 1.0))
    verdict = _verdict(over, named)
    diag = RigDiagnosis(run.source, run.fs_hz, run.duration_s, run.floor_measured, run.mode_seconds(),
                        ctx.valves_driven, named, _refit_dict(sel), mismatch, _located(mismatch["refit"]),
                        {k: _mount_fit(ev) for k, ev in evh.items()}, _candidates(sel), fm, offs, rest, det, tr,
                        lines, verdict, "", time.perf_counter() - t0, {k: v.tolist() for k, v in th.items()}, notes,
                        ctx.base)
    if run.gaps:
        diag.notes.insert(0, run.gaps)
    return diag


def _with_margins(e: NamedEffect, sel: Selection, ctx) -> NamedEffect:
    """The effect's margins line at each mount whose loop it sits in: the diagnosed rig against the same rig
    without it (rig design's loop on both)."""
    note = fx.BY_NAME[e.name].margins_note
    if note:
        lines = (f"margins unchanged: {note} (the loop's gain and phase are as on the diagnosed rig without it)",)
        return NamedEffect(e.name, e.location, e.parameters, e.tests, e.evidence, lines)
    inst = next(t.instance for t in sel.chosen if t.instance.key == f"{e.name}[{e.location}]")
    without = without_effect(sel.th_final, inst, ctx.base)
    lines = tuple(line.text("without it") for line in margins_mod.mount_lines(ctx.base, without, sel.th_final,
                                                                              mounts=inst.mounts))
    return NamedEffect(e.name, e.location, e.parameters, e.tests, e.evidence, lines)


def _refit_dict(sel: Selection) -> dict:
    th = sel.th_final
    out = {f"{k}_factor": float(v) for k, v in zip(ACT_KEYS, th["act"])}
    out["modal_damping_factor"] = float(th["modal_zeta"][0])
    out["latency_s"] = float(th["latency_s"][0])
    return out


def _candidates(sel: Selection) -> list:
    return [{"effect": t.instance.effect.name, "location": t.instance.location, "round": t.step + 1,
             "named": any(t is c for c in sel.chosen), **{k: (float(v) if isinstance(v, (float, np.floating)) else v)
                                                         for k, v in t.tests.items()}} for t in sel.tried]
