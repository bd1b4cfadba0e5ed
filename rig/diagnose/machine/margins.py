"""What the refitted model means for the controller: `rig design`'s SISO view (paper Figs. 5, 11) re-run on it.

Per mount, the configured isolation controller (controllers/isolation.py, the objects the runtime steps) closes
its loop on the rig as diagnosed (controllers/analysis.py siso: ZOH, the commands' latency as whole periods plus
that valve's own delay, the others' valves at null): stability, gain and phase margins, the disk margin, and
the attenuation ground -> table in the paper's bands. A sensor's gain scales what the controller sees of it.
The rule is rig design's (GM >= 6 dB and PM >= 35 deg); where it fails, or holds with room, the retuning line
gives the mount's gain trim that meets it with the most gain (bisection on the loop gain, then checked for
stability) and what that trim buys or costs in attenuation. A deadband makes the loop's gain smaller for small
commands: the linear margins are for commands well beyond it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from controllers.analysis import DiscreteRig, _css, attenuation_db, band_summary, disk_margin, is_stable, margins, siso
from controllers.isolation import IsolationController
from rig.config import MOUNTS
from rig.diagnose.machine.rigmodel import Base
from sim_backend.rig_plant import I_TABLE

GM_MIN_DB, PM_MIN_DEG = 6.0, 35.0       # rig design's rule (rig/commands/design.py _meets)
TRIM_RANGE = (0.1, 4.0)


class SensedController:
    """An isolation controller as it acts through sensors of gain ga (accelerometer) and gs (stroke)."""

    def __init__(self, ctrl: IsolationController, ga: float, gs: float):
        self.ctrl, self.ga, self.gs = ctrl, float(ga), float(gs)
        self.p = ctrl.p

    def frf(self, w):
        Ka, Ks = self.ctrl.frf(w)
        return Ka * self.ga, Ks * self.gs

    def _scaled(self, mats):
        A, B, C, D = mats
        g = np.array([self.ga, self.gs])
        return A, B * g[None, :], C, D * g[None, :]

    def ss(self):
        return self._scaled(self.ctrl.ss())

    def css(self):
        return self._scaled(_css(self.ctrl))

    def trimmed(self, g: float) -> "SensedController":
        """The same controller with its gain trimmed by g (gain_trim scales kp, i.e. the whole law)."""
        return SensedController(self.ctrl, self.ga * g, self.gs * g)


@dataclass(frozen=True)
class MountMargins:
    mount: str
    stable: bool
    gain_margin_db: float
    phase_margin_deg: float
    disk_margin: float
    crossover_hz: float
    table_db: dict              # attenuation ground -> table per band (BANDS)

    @property
    def holds(self) -> bool:
        return self.stable and self.gain_margin_db >= GM_MIN_DB and self.phase_margin_deg >= PM_MIN_DEG


@dataclass(frozen=True)
class MountLine:
    """One mount: the margins on the configured model, on the diagnosed one, and the retuning."""
    mount: str
    nominal: MountMargins
    diagnosed: MountMargins
    trim: float                 # the gain trim that meets the rule with the most gain (or comes closest)
    meets: bool                 # whether that trim meets the rule
    retuned: MountMargins | None

    def text(self, against: str = "model") -> str:
        """The line; `against` names what the nominal margins are of (the model, or the rig without an effect)."""
        d, n = self.diagnosed, self.nominal
        head = (f"{self.mount}: margins {'hold' if d.holds else 'do NOT hold'} on the diagnosed rig: "
                + (f"GM {d.gain_margin_db:.1f} dB, PM {d.phase_margin_deg:.1f} deg, disk {d.disk_margin:.2f}"
                   if d.stable else "the loop is UNSTABLE")
                + f" ({against}: GM {n.gain_margin_db:.1f} dB, PM {n.phase_margin_deg:.1f} deg)")
        r, t = self.retuned, self.trim
        if r is None:
            return head + "; no gain trim keeps the loop stable: the compensator needs retuning (rig design --tune)"
        gains = (f"GM {r.gain_margin_db:.1f} dB, PM {r.phase_margin_deg:.1f} deg, table 1 Hz {r.table_db['1hz']:.1f} "
                 f"dB, 5-10 Hz {r.table_db['5_10hz']:.1f} dB, 20-60 Hz {r.table_db['20_60hz']:.1f} dB (now "
                 f"{d.table_db['1hz']:.1f}, {d.table_db['5_10hz']:.1f}, {d.table_db['20_60hz']:.1f} dB)")
        if not self.meets:
            return (head + f"; no gain trim meets GM 6 dB and PM 35 deg (the closest, x{t:.2f}: {gains}): the "
                    "compensator needs retuning (rig design --tune)")
        if d.holds and abs(t - 1.0) < 0.02:
            return head + "; retuning: none needed (the gain is already the most the margins allow)"
        verb = "restores the margins" if not d.holds else "keeps the margins with more gain"
        return head + f"; retuning: gain_trim x{t:.2f} {verb}: {gains}"


def _rig(base: Base, th: dict, f: np.ndarray) -> tuple[DiscreteRig, object]:
    dev = base.deviation(th)
    rig = DiscreteRig(base.config(th), base.dt, f, modal=dev.modal(base.modal), mounts=dev.mount_factors())
    return rig, dev


def _delay(th: dict, dev, i: int, dt: float) -> int:
    return max(0, int(round((float(th["latency_s"][0]) + float(dev.valve_delay_s[i])) / dt)))


def _margins_of(rig, ctrl, i, delay) -> MountMargins:
    r = siso(rig, ctrl, i, delay)
    m = r["margins"]
    att = band_summary(rig.f, attenuation_db(r["tr_passive"][:, I_TABLE + 1], r["tr_controlled"][:, I_TABLE + 1]))
    return MountMargins(MOUNTS[i], bool(m.stable), float(m.gain_margin_db), float(m.phase_margin_deg),
                        float(disk_margin(r["L"])), float(m.gain_crossover_hz), att)


def _best_trim(rig, ctrl: SensedController, i: int, delay: int) -> tuple[float, bool]:
    """(trim, meets): the largest loop-gain factor within TRIM_RANGE meeting the rule with the loop stable;
    when none does, the stable one closest to it (the largest min(GM / 6 dB, PM / 35 deg)), meets False; nan
    when no trim on the grid is stable."""
    L = siso(rig, ctrl, i, delay)["L"]

    def score(g):
        m = margins(rig.f, g * L, True)
        return min(m.gain_margin_db / GM_MIN_DB, m.phase_margin_deg / PM_MIN_DEG)

    def stable(g):
        return is_stable(rig, [ctrl.trimmed(g)] * 4, loops=(i,), delay=delay)[0]
    grid = np.unique(np.concatenate([np.geomspace(*TRIM_RANGE, 41), [1.0]]))
    scores = np.array([score(g) for g in grid])
    good = grid[scores >= 1.0 - 1e-3]
    if len(good):
        lo = float(max(good))
        hi = float(grid[min(len(grid) - 1, int(np.searchsorted(grid, lo)) + 1)])
        for _ in range(16):
            mid = math.sqrt(lo * hi)
            lo, hi = (mid, hi) if score(mid) >= 1.0 - 1e-3 else (lo, mid)
        for g in [lo] + sorted(good[good < lo], reverse=True):
            if stable(g):
                return float(g), True
    for k in np.argsort(-scores):
        if stable(grid[k]):
            return float(grid[k]), False
    return math.nan, False


def mount_lines(base: Base, th_nominal: dict, th_diag: dict, *, n_f: int = 900, mounts=None) -> list[MountLine]:
    """One line per mount (see the module docstring); `mounts`: only those (indices)."""
    dt = base.dt
    f = np.unique(np.concatenate([np.geomspace(0.05, 0.49 / dt, n_f), [1.0, 5.0, 10.0, 20.0, 60.0, 100.0]]))
    ctrls = base.controllers
    rig0, dev0 = _rig(base, th_nominal, f)
    rig1, dev1 = _rig(base, th_diag, f)
    out = []
    for i, c in enumerate(ctrls):
        if mounts is not None and i not in mounts:
            continue
        nom = _margins_of(rig0, SensedController(c, dev0.accel_gain[i], dev0.stroke_gain[i]), i,
                          _delay(th_nominal, dev0, i, dt))
        sensed = SensedController(c, dev1.accel_gain[i], dev1.stroke_gain[i])
        d = _delay(th_diag, dev1, i, dt)
        diag = _margins_of(rig1, sensed, i, d)
        trim, meets = _best_trim(rig1, sensed, i, d)
        retuned = _margins_of(rig1, sensed.trimmed(trim), i, d) if math.isfinite(trim) else None
        out.append(MountLine(MOUNTS[i], nom, diag, trim, meets, retuned))
    return out


