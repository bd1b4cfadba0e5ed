"""`rig prove --commission`: blind proof of `rig commission` on the emulated rig (issue 27).

Each case wires the emulated rig wrong in two or three ways drawn from the wiring-fault table
(drivers/devicemaps/hil_wiring_faults.md: the [hil] keys), runs `rig commission --backend hil` on it as a user
does, and grades what it names: right when the faults it names, channel and kind, are exactly the ones drawn
(nothing missed, nothing invented). The clean cases are rigs wired right: right when nothing is named. A mount
carries at most one fault (a swap takes two mounts), so that every drawn fault has one right name.
"""
from __future__ import annotations

import json
import random
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from rig.config import MOUNTS
from rig.errors import RigError

N_AI = 8                                # the analog module's channels (ch0-3 the mounts' table accelerometers)


@dataclass
class Wiring:
    """The [hil] keys of one case, as documented: the rig wired right until a fault is drawn."""
    ai_source: list = field(default_factory=lambda: list(range(N_AI)))
    ai_factor: list = field(default_factory=lambda: [1.0] * N_AI)
    ai_offset_mps2: list = field(default_factory=lambda: [0.0] * N_AI)
    ai_noise_mps2: list = field(default_factory=lambda: [0.0] * N_AI)
    dt_source: list = field(default_factory=lambda: list(range(len(MOUNTS))))
    dt_factor: list = field(default_factory=lambda: [1.0] * len(MOUNTS))
    dt_offset_m: list = field(default_factory=lambda: [0.0] * len(MOUNTS))
    dt_noise_m: list = field(default_factory=lambda: [0.0] * len(MOUNTS))
    valve_null_V: list = field(default_factory=lambda: [0.0] * len(MOUNTS))
    valve_gain: list = field(default_factory=lambda: [1.0] * len(MOUNTS))
    valve_node_id: list = field(default_factory=lambda: [1, 2, 3, 4])

    def toml(self) -> str:
        return "".join(f"{k} = {json.dumps(v)}\n" for k, v in vars(self).items())


# Sizes are drawn within what the table documents for each: a fault a real rig has, not a borderline one.
def _swap(key: str):
    def wire(w: Wiring, ms: list[int], rng: random.Random) -> None:
        a, b = ms
        src = getattr(w, key)
        src[a], src[b] = src[b], src[a]
    return wire


def _set(key: str, values):
    def wire(w: Wiring, ms: list[int], rng: random.Random) -> None:
        getattr(w, key)[ms[0]] = rng.choice(values)
    return wire


def _both(*wires):
    def wire(w: Wiring, ms: list[int], rng: random.Random) -> None:
        for f in wires:
            f(w, ms, rng)
    return wire


FAULTS = {
    # name: (mounts, wire, channel prefix, kind named)
    "accel_swap": (2, _swap("ai_source"), "accel", "swap"),
    "accel_sign": (1, _set("ai_factor", [-1.0]), "accel", "sign"),
    "accel_g_range": (1, _set("ai_factor", [1 / 9.80665]), "accel", "scale"),
    "accel_offset": (1, _set("ai_offset_mps2", [-0.5, 0.3, 0.8]), "accel", "offset"),
    "accel_dead": (1, _both(_set("ai_factor", [0.0]), _set("ai_noise_mps2", [0.002])), "accel", "dead"),
    "accel_noisy": (1, _set("ai_noise_mps2", [0.02, 0.05]), "accel", "noisy"),
    "stroke_swap": (2, _swap("dt_source"), "stroke", "swap"),
    "stroke_sign": (1, _set("dt_factor", [-1.0]), "stroke", "sign"),
    "stroke_range": (1, _set("dt_factor", [0.1, 10.0]), "stroke", "scale"),
    "stroke_offset": (1, _set("dt_offset_m", [-50e-6, 40e-6, 80e-6]), "stroke", "offset"),
    "stroke_dead": (1, _both(_set("dt_factor", [0.0]), _set("dt_noise_m", [5e-9])), "stroke", "dead"),
    "stroke_noisy": (1, _set("dt_noise_m", [2e-7, 5e-7]), "stroke", "noisy"),
    "valve_null": (1, _set("valve_null_V", [-0.3, 0.3, 0.5]), "valve", "null"),
    "valve_gain": (1, _set("valve_gain", [0.6, 1.6]), "valve", "gain"),
    "valve_nodes_swapped": (2, _swap("valve_node_id"), "valve", "swap"),
}


def draw(rng: random.Random, n_faults: int) -> tuple[Wiring, list[str], set[tuple[str, str]]]:
    """A wiring with `n_faults` faults on distinct mounts: (the wiring, the faults in words, what commissioning
    should name: {(channel, kind)})."""
    while True:
        names = [rng.choice(sorted(FAULTS)) for _ in range(n_faults)]
        if sum(FAULTS[k][0] for k in names) <= len(MOUNTS):
            break
    free = list(range(len(MOUNTS)))
    rng.shuffle(free)
    w, said, expected = Wiring(), [], set()
    for k in names:
        n, wire, prefix, kind = FAULTS[k]
        ms, free = sorted(free[:n]), free[n:]
        wire(w, ms, rng)
        said.append(f"{k}({', '.join(MOUNTS[m] for m in ms)})")
        expected |= {(f"{prefix}:{MOUNTS[m]}", kind) for m in ms}
    return w, said, expected


def named(res: dict) -> set[tuple[str, str]]:
    """What one commissioning named: {(channel, kind)} from its report's faults."""
    return {(f["channel"], f["kind"]) for f in res.get("faults", [])}


def commission(config: Path, out: Path, timeout_s: float = 600.0) -> tuple[dict | None, float, str]:
    """`rig commission --backend hil --config CONFIG --out OUT --json` as a user runs it: (its report, wall s,
    the last of its stderr when it failed)."""
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "rig.cli", "commission", "--backend", "hil", "--config", str(config),
                        "--out", str(out), "--json"], capture_output=True, text=True, timeout=timeout_s)
    wall = time.perf_counter() - t0
    if r.returncode not in (0, 4):
        return None, wall, r.stderr.strip().splitlines()[-1] if r.stderr.strip() else f"exit {r.returncode}"
    return json.loads(r.stdout), wall, ""


def run(args) -> int:
    """The proof: args.n drawn cases and args.clean clean ones from args.seed, on --config (default the HIL
    design); the table on stdout and in --out/proof.md (default prove-commission-<date>-<time>), the rows in
    proof.json."""
    from rig.backends import default_config
    base_config = Path(args.config) if args.config else default_config("hil")
    folder = args.out if args.out is not None else Path(time.strftime("prove-commission-%Y%m%d-%H%M%S"))
    rng = random.Random(args.seed)
    cases = [("clean", Wiring(), [], set()) for _ in range(args.clean)]
    for i in range(args.n):
        w, said, exp = draw(rng, 2 + i % 2)
        cases.append(("faults", w, said, exp))
    text = base_config.read_text()
    if "[hil]\n" not in text:
        raise RigError(f"{base_config}: expected a [hil] section to add the wiring faults to")
    rows = []
    folder.mkdir(parents=True, exist_ok=True)
    for i, (what, w, said, exp) in enumerate(cases):
        cfg = folder / f"case{i:03d}.toml"
        cfg.write_text(text.replace("[hil]\n", "[hil]\n" + w.toml(), 1))
        res, wall, err = commission(cfg, folder / f"case{i:03d}")
        got = named(res) if res is not None else set()
        right = res is not None and got == exp
        row = {"case": i, "what": what, "faults": said, "expected": sorted(map(list, exp)),
               "named": sorted(map(list, got)), "right": right, "wall_s": round(wall, 1), "error": err,
               "peak_stroke_pct_of_limit": (round(100 * res["peak_stroke_m"] / res["stroke_limit_m"], 1)
                                            if res is not None else None)}
        rows.append(row)
        missed, invented = exp - got, got - exp
        print(f"[{i + 1}/{len(cases)}] {'right' if right else 'WRONG'} {what}: {', '.join(said) or 'wired right'}"
              + (f"; missed {sorted(missed)}" if missed and res is not None else "")
              + (f"; invented {sorted(invented)}" if invented else "") + (f"; failed: {err}" if err else "")
              + f" ({wall:.0f} s)", file=sys.stderr, flush=True)
    summary = _summary(rows)
    (folder / "proof.json").write_text(json.dumps({"seed": args.seed, "summary": summary, "rows": rows}, indent=1))
    (folder / "proof.md").write_text(_markdown(args.seed, summary, rows))
    print(json.dumps(summary) if args.json else _markdown(args.seed, summary, rows))
    return 0


def _summary(rows: list[dict]) -> dict:
    """The score over the cases commissioning judged; a run that stopped on a fault (the safety rules: nothing
    judged, said in one line) is counted apart, not as a wrong name."""
    judged = [r for r in rows if not r["error"]]
    combo = [r for r in judged if r["what"] == "faults"]
    clean = [r for r in judged if r["what"] == "clean"]
    walls = sorted(r["wall_s"] for r in judged)
    return {"combinations": len(combo), "combinations_right": sum(r["right"] for r in combo),
            "clean": len(clean), "clean_flagged": sum(not r["right"] for r in clean),
            "stopped": [f"case {r['case']}: {r['error']}" for r in rows if r["error"]],
            "wall_s_median": walls[len(walls) // 2] if walls else None, "wall_s_max": walls[-1] if walls else None,
            "peak_stroke_pct_of_limit_max": max((r["peak_stroke_pct_of_limit"] or 0) for r in rows) if rows else None}


def _markdown(seed: int, s: dict, rows: list[dict]) -> str:
    out = [f"# rig prove --commission, seed {seed}", "",
           f"- combinations of two or three wiring faults named right: {s['combinations_right']} of "
           f"{s['combinations']}",
           f"- rigs wired right with something named: {s['clean_flagged']} of {s['clean']}",
           f"- runs stopped by a fault, nothing judged: {len(s['stopped'])}"
           + "".join(f"\n  - {x}" for x in s["stopped"]),
           f"- one commissioning (four mounts, wall time with its set-up): median {s['wall_s_median']} s, "
           f"max {s['wall_s_max']} s",
           f"- peak stroke: {s['peak_stroke_pct_of_limit_max']} % of the stroke limit at most", "",
           "| case | faults drawn | right | missed | invented |", "|---|---|---|---|---|"]
    for r in rows:
        exp, got = {tuple(x) for x in r["expected"]}, {tuple(x) for x in r["named"]}
        fmt = lambda xs: ", ".join(f"{c} {k}" for c, k in sorted(xs)) or ""   # noqa: E731
        out.append(f"| {r['case']} | {', '.join(r['faults']) or 'wired right'} | {'yes' if r['right'] else 'no'} | "
                   f"{fmt(exp - got) or (r['error'] if r['error'] else '')} | {fmt(got - exp)} |")
    return "\n".join(out) + "\n"
