"""`rig prove --commission`: blind proof of `rig commission` on the emulated rig (issue 27).

Each case wires the emulated rig wrong in two or three ways drawn from the wiring-fault table
(drivers/devicemaps/hil_wiring_faults.md: the [hil] keys), runs `rig commission --backend hil` on it as a user
does, and grades what it names: right when the faults it names, channel and kind, are exactly the ones drawn
(nothing missed, nothing invented). The clean cases are rigs wired right: right when nothing is named. A mount
carries at most one fault (a swap takes two mounts), so that every drawn fault has one right name. The floor
accelerometers' faults (AI ch4-7) are drawn only where the configuration has them ([sensors] floor_accel).
"""
from __future__ import annotations

import json
import os
import random
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from rig.config import MOUNTS
from rig.errors import EXIT_FAULT, EXIT_FINDINGS, EXIT_HARM, EXIT_SUSPECT, RigError

N_AI = 8                                # the analog module's channels (ch0-3 the mounts' table accelerometers)
FLOOR_AI = 4                            # AI ch4-7: the floor accelerometers under the mounts, in MOUNTS order


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
# `first`: the channel of the first mount (the floor's: AI ch4-7).
def _swap(key: str, first: int = 0):
    def wire(w: Wiring, ms: list[int], rng: random.Random) -> None:
        a, b = (first + m for m in ms)
        src = getattr(w, key)
        src[a], src[b] = src[b], src[a]
    return wire


def _set(key: str, values, first: int = 0):
    def wire(w: Wiring, ms: list[int], rng: random.Random) -> None:
        getattr(w, key)[first + ms[0]] = rng.choice(values)
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
    # the floor accelerometers (AI ch4-7), the same keys and sizes as the table's; dead also at a constant (no
    # safety rule stops a floor channel that does not move: only NaN or out of range)
    "floor_swap": (2, _swap("ai_source", FLOOR_AI), "floor", "swap"),
    "floor_sign": (1, _set("ai_factor", [-1.0], FLOOR_AI), "floor", "sign"),
    "floor_g_range": (1, _set("ai_factor", [1 / 9.80665], FLOOR_AI), "floor", "scale"),
    "floor_offset": (1, _set("ai_offset_mps2", [-0.5, 0.3, 0.8], FLOOR_AI), "floor", "offset"),
    "floor_dead": (1, _both(_set("ai_factor", [0.0], FLOOR_AI), _set("ai_noise_mps2", [0.0, 0.002], FLOOR_AI)),
                   "floor", "dead"),
    "floor_noisy": (1, _set("ai_noise_mps2", [0.02, 0.05], FLOOR_AI), "floor", "noisy"),
}


def fault_kinds(floor: bool) -> list[str]:
    """The faults a rig can be wired with: the floor accelerometers' only where they are fitted."""
    return [k for k in FAULTS if floor or FAULTS[k][2] != "floor"]


def draw(rng: random.Random, n_faults: int, floor: bool = True) -> tuple[Wiring, list[str], set[tuple[str, str]]]:
    """A wiring with `n_faults` faults on distinct mounts, the floor accelerometers' among them only with `floor`:
    (the wiring, the faults in words, what commissioning should name: {(channel, kind)})."""
    kinds = sorted(fault_kinds(floor))
    while True:
        names = [rng.choice(kinds) for _ in range(n_faults)]
        if sum(FAULTS[k][0] for k in names) <= len(MOUNTS):
            break
    free = list(range(len(MOUNTS)))
    rng.shuffle(free)
    w, said, expected = Wiring(), [], set()
    for k in names:
        n = FAULTS[k][0]
        ms, free = sorted(free[:n]), free[n:]
        said.append(place(w, k, ms, rng, expected))
    return w, said, expected


def place(w: Wiring, fault: str, ms: list[int], rng: random.Random, expected: set) -> str:
    """Wire `fault` on the mounts `ms` (indices into MOUNTS) of `w`; what commissioning should name added to
    `expected`. The fault in words."""
    _, wire, prefix, kind = FAULTS[fault]
    wire(w, ms, rng)
    expected |= {(f"{prefix}:{MOUNTS[m]}", kind) for m in ms}
    return f"{fault}({', '.join(MOUNTS[m] for m in ms)})"


def named(res: dict) -> set[tuple[str, str]]:
    """What one commissioning named: {(channel, kind)} from its report's faults."""
    return {(f["channel"], f["kind"]) for f in res.get("faults", [])}


def case_config(text: str, w: Wiring, calibration: Path | None = None) -> str:
    """The base configuration `text` (with its [hil] section) wired as `w`; with `calibration`, its
    [drivers] calibration set to that commissioning.toml."""
    out = text.replace("[hil]\n", "[hil]\n" + w.toml(), 1)
    if calibration is not None:
        key = f"calibration = {json.dumps(str(calibration.resolve()))}\n"
        out = out.replace("[drivers]\n", "[drivers]\n" + key, 1) if "[drivers]\n" in out else \
            out + "\n[drivers]\n" + key
    return out


def _rig_json(argv: list[str], ok_codes: tuple, timeout_s: float,
              log: Path | None = None) -> tuple[dict | None, float, str, int]:
    """`rig ARGV --json` as a user runs it: (its JSON, wall s, the last line of its stderr when it gave none or
    exited otherwise than ok_codes, its exit status); its stderr kept in `log`."""
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "rig.cli", *argv, "--json"], capture_output=True, text=True,
                       timeout=timeout_s)
    wall = time.perf_counter() - t0
    if log is not None:
        log.parent.mkdir(parents=True, exist_ok=True)
        log.write_text(r.stderr)
    last = r.stderr.strip().splitlines()[-1] if r.stderr.strip() else f"exit {r.returncode}"
    try:
        res = json.loads(r.stdout) if r.stdout.strip() else None
    except json.JSONDecodeError:
        res = None
    if res is None or r.returncode not in ok_codes:
        return res, wall, last, r.returncode
    return res, wall, "", r.returncode


def commission(config: Path, out: Path, timeout_s: float = 600.0) -> tuple[dict | None, float, str]:
    """`rig commission --backend hil --config CONFIG --out OUT --json` as a user runs it: (its report, wall s,
    the last of its stderr when it failed)."""
    res, wall, err, _ = _rig_json(["commission", "--backend", "hil", "--config", str(config), "--out", str(out)],
                                  (0, EXIT_FINDINGS), timeout_s, out / "commission.log")
    return (None if err else res), wall, err


def run(args) -> int:
    """The proof: args.n drawn cases and args.clean clean ones from args.seed, on --config (default the HIL
    design); the table on stdout and in --out/proof.md (default prove-commission-<date>-<time>), the rows in
    proof.json."""
    if getattr(args, "single", False):
        return run_single(args)
    text, folder = _base(args)
    floor = _floor_fitted(folder, text)
    rng = random.Random(args.seed)
    cases = [("clean", Wiring(), [], set()) for _ in range(args.clean)]
    for i in range(args.n):
        w, said, exp = draw(rng, 2 + i % 2, floor)
        cases.append(("faults", w, said, exp))
    rows = []
    for i, (what, w, said, exp) in enumerate(cases):
        cfg = folder / f"case{i:03d}.toml"
        cfg.write_text(case_config(text, w))
        stopped = []                    # attempts stopped by a fault (a loaded host: a device stall, missed deadlines)
        for attempt in range(1 + getattr(args, "retries", 0)):
            res, wall, err = commission(cfg, folder / f"case{i:03d}" / (f"retry{attempt}" if attempt else ""))
            if not err:
                break
            stopped.append(err)
            print(f"[{i + 1}/{len(cases)}]   stopped: {err}", file=sys.stderr, flush=True)
        got = named(res) if res is not None else set()
        right = res is not None and got == exp
        row = {"case": i, "what": what, "faults": said, "expected": sorted(map(list, exp)),
               "named": sorted(map(list, got)), "right": right, "wall_s": round(wall, 1), "error": err,
               "commission_stopped": stopped, "load_average": round(os.getloadavg()[0], 1),
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


def _base(args) -> tuple[str, Path]:
    """The HIL configuration's text the cases are wired from (--config, default the HIL design) and the --out
    folder, made (default prove-commission-<date>-<time>)."""
    from rig.backends import default_config
    base_config = Path(args.config) if args.config else default_config("hil")
    try:
        text = base_config.read_text()
    except OSError as e:
        raise RigError(f"--config {base_config}: cannot be read ({e.strerror})") from None
    if "[hil]\n" not in text:
        raise RigError(f"{base_config}: expected a [hil] section to add the wiring faults to")
    folder = args.out if args.out is not None else Path(time.strftime("prove-commission-%Y%m%d-%H%M%S"))
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise RigError(f"--out {folder}: cannot be made ({e.strerror})") from None
    return text, folder


def _floor_fitted(folder: Path, text: str) -> bool:
    """[sensors] floor_accel of the base configuration, as the rig loads it (a copy in the --out folder: its
    relative paths are not needed to read it)."""
    from rig.config import load_config
    probe = folder / "base.toml"
    probe.write_text(text)
    return load_config(probe).sensors.floor_accel


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
            "stopped_then_run_again": [f"case {r['case']}: {e}" for r in rows if not r["error"]
                                       for e in r.get("commission_stopped", [])],
            "per_fault": per_fault(combo),
            "wall_s_median": walls[len(walls) // 2] if walls else None, "wall_s_max": walls[-1] if walls else None,
            "peak_stroke_pct_of_limit_max": max((r["peak_stroke_pct_of_limit"] or 0) for r in rows) if rows else None}


def per_fault(rows: list[dict]) -> dict:
    """Per fault of the table: the judged cases that drew it, and in how many of them its own channels were named
    with its kind (nothing missed on them; an invented name elsewhere is the case's, not the fault's)."""
    out = {}
    for r in rows:
        got = {tuple(x) for x in r["named"]}
        for said in r["faults"]:
            k, ms = said.split("(")[0], said[len(said.split("(")[0]) + 1:-1].split(", ")
            _, _, prefix, kind = FAULTS[k]
            d = out.setdefault(k, {"drawn": 0, "named": 0, "case_right": 0})
            d["drawn"] += 1
            d["named"] += all((f"{prefix}:{m}", kind) in got for m in ms)
            d["case_right"] += bool(r["right"])
    return {k: out[k] for k in FAULTS if k in out}


def _markdown(seed: int, s: dict, rows: list[dict]) -> str:
    out = [f"# rig prove --commission, seed {seed}", "",
           f"- combinations of two or three wiring faults named right: {s['combinations_right']} of "
           f"{s['combinations']}",
           f"- rigs wired right with something named: {s['clean_flagged']} of {s['clean']}",
           f"- runs stopped by a fault, nothing judged: {len(s['stopped'])}"
           + "".join(f"\n  - {x}" for x in s["stopped"]),
           f"- runs stopped by a fault, then judged on a run again (--retries): {len(s['stopped_then_run_again'])}"
           + "".join(f"\n  - {x}" for x in s["stopped_then_run_again"]),
           f"- one commissioning (four mounts, wall time with its set-up): median {s['wall_s_median']} s, "
           f"max {s['wall_s_max']} s",
           f"- peak stroke: {s['peak_stroke_pct_of_limit_max']} % of the stroke limit at most", "",
           "| fault | judged cases that drew it | its channels named with its kind | the whole case right |",
           "|---|---|---|---|",
           *(f"| {k} | {d['drawn']} | {d['named']} | {d['case_right']} |" for k, d in s["per_fault"].items()), "",
           "| case | faults drawn | right | missed | invented |", "|---|---|---|---|---|"]
    for r in rows:
        exp, got = {tuple(x) for x in r["expected"]}, {tuple(x) for x in r["named"]}
        fmt = lambda xs: ", ".join(f"{c} {k}" for c, k in sorted(xs)) or ""   # noqa: E731
        out.append(f"| {r['case']} | {', '.join(r['faults']) or 'wired right'} | {'yes' if r['right'] else 'no'} | "
                   f"{fmt(exp - got) or (r['error'] if r['error'] else '')} | {fmt(got - exp)} |")
    return "\n".join(out) + "\n"


# --- Single faults (`rig prove --commission --single`): each fault alone, named, corrected, then isolating ---

REFUSED = ("dead", "noisy")   # no calibration takes these out: commissioning refuses them, the rig does not run on them
WITHIN_DB = 1.0               # the target: calibrated, the miswired rig isolates within this of a rig wired right


def single_cases(kinds=None, all_mounts: bool = False) -> list[tuple[str, list[int]]]:
    """Every fault of the table alone (or those of `kinds`), as (fault, mount indices): on every mount with
    all_mounts, else on mount i % 4 for the table's i-th fault, so that every mount comes up; a swap takes its
    mount and the next."""
    order = list(FAULTS)
    out = []
    for k in (order if kinds is None else [k for k in order if k in set(kinds)]):
        i = order.index(k)
        for m in (range(len(MOUNTS)) if all_mounts else [i % len(MOUNTS)]):
            out.append((k, sorted({m, (m + 1) % len(MOUNTS)}) if FAULTS[k][0] == 2 else [m]))
    return out


def single_wirings(rng: random.Random, kinds=None, all_mounts: bool = False) -> list[tuple]:
    """The cases of single_cases wired: (fault, mount indices, wiring, the fault in words, what commissioning
    should name). The sizes are drawn over the whole table in order and `kinds` then picked, so that a case of
    --kinds is wired as the same case of the whole table (a case re-run alone is the same case)."""
    out = []
    for k, ms in single_cases(None, all_mounts):
        w, exp = Wiring(), set()
        said = place(w, k, ms, rng, exp)
        if kinds is None or k in set(kinds):
            out.append((k, ms, w, said, exp))
    return out


def parse_kinds(text: str | None) -> list[str] | None:
    """--kinds: fault names of the table, comma separated (None: all)."""
    if text is None:
        return None
    kinds = [k.strip() for k in text.split(",") if k.strip()]
    bad = [k for k in kinds if k not in FAULTS]
    if bad or not kinds:
        raise RigError(f"--kinds: expected fault names of {', '.join(FAULTS)} (comma separated), got "
                       f"{', '.join(bad) or repr(text)}")
    return kinds


def hil(config: Path, record: Path, seconds: float | None, timeout_s: float = 900.0) -> dict:
    """`rig hil --config CONFIG --record RECORD [--seconds S] --json` as a user runs it: its isolation figures
    (feedback, feedback + feedforward, the lockstep twin's feedback), exit status, the supervisor's harm, and
    `error` when it did not finish clean (a fault, the supervisor, no JSON)."""
    argv = ["hil", "--config", str(config), "--record", str(record)]
    if seconds is not None:
        argv += ["--seconds", f"{seconds:g}"]
    # finished: a mode worse than off and a host that let periods come late are figures here, not stops
    res, wall, err, code = _rig_json(argv, (0, EXIT_HARM, EXIT_SUSPECT), timeout_s, record.with_suffix(".log"))
    res = res or {}
    if code == EXIT_FAULT:
        err = _fault_reason(record) or err
    elif res.get("harm"):
        err = res["harm"]
    late = res.get("late_periods") or {}
    fb, ff = res.get("isolation_reduction_db"), res.get("feedforward_reduction_db")
    twin = res.get("lockstep_reduction_db") or {}
    ls, ls_ff = twin.get("feedback"), twin.get("feedback_feedforward")
    return {"feedback_db": _r2(fb), "feedforward_db": _r2(ff),
            "lockstep_feedback_db": _r2(ls), "lockstep_feedforward_db": _r2(ls_ff),
            # against the same design on the same stretch of floor in lockstep (the simulated backend carries no
            # [hil] wiring fault and no calibration: the twin is the rig wired right): the floor's own variation
            # between runs (the stretch each mode meets depends on the start-up's length, pre_steps) taken out
            "feedback_vs_lockstep_db": None if fb is None or ls is None else _r2(fb - ls),
            "feedforward_vs_lockstep_db": None if ff is None or ls_ff is None else _r2(ff - ls_ff),
            "pre_steps": res.get("pre_steps"),
            "late_feedback_pct": None if late.get("feedback") is None else round(100 * late["feedback"], 1),
            "exit": code, "harm": res.get("harm"), "error": err, "wall_s": round(wall, 1)}


def _fault_reason(record: Path) -> str:
    """The fault that stopped a run, as its recording holds it ("" when there is none to read)."""
    import h5py
    try:
        with h5py.File(record, "r") as f:
            why = f.attrs.get("fault_reason", "")
    except OSError:
        return ""
    return f"FAULT: {why}" if why else ""


def _r2(x):
    return None if x is None else round(float(x), 2)


def _mean(xs: list) -> float | None:
    return round(sum(xs) / len(xs), 2) if xs else None


def _figures(runs: list[dict], key: str) -> dict:
    """One figure (feedback_db or feedforward_db) of a case's hil runs: each rig's runs in order, their means and
    the difference calibrated - clean (runs that did not finish clean left out)."""
    got = {who: [r[key] for r in runs if r["rig"] == who and not r["error"] and r[key] is not None]
           for who in ("calibrated", "clean")}
    cal, clean = _mean(got["calibrated"]), _mean(got["clean"])
    return {"calibrated": got["calibrated"], "clean": got["clean"], "calibrated_mean": cal, "clean_mean": clean,
            "difference": None if cal is None or clean is None else round(cal - clean, 2)}


def run_single(args) -> int:
    """Each fault of the table alone (--kinds: some; --all-mounts: on every mount), on the emulated rig: commission
    it and grade what is named (the channel, the kind; correctable faults `corrected`, dead and noisy ones
    `refused`); then, for a correctable one, `rig hil` with the calibration it wrote against `rig hil` on the rig
    wired right, --repeats of each, alternately. The table on stdout (--json: the proof as JSON) and in
    --out/proof.md, every case in proof.json."""
    kinds = parse_kinds(getattr(args, "kinds", None))
    text, folder = _base(args)
    if not _floor_fitted(folder, text):
        if kinds is not None and set(kinds) - set(fault_kinds(False)):
            raise RigError(f"--kinds: {', '.join(k for k in kinds if k not in fault_kinds(False))}: the "
                           f"configuration has no floor accelerometers ([sensors] floor_accel = false)")
        kinds = kinds if kinds is not None else fault_kinds(False)
    cases = single_wirings(random.Random(args.seed), kinds, getattr(args, "all_mounts", False))
    repeats, seconds = getattr(args, "repeats", 2), getattr(args, "hil_seconds", None)
    retries = getattr(args, "retries", 0)
    clean_cfg = folder / "clean.toml"
    clean_cfg.write_text(case_config(text, Wiring()))
    load0 = os.getloadavg()
    print(f"rig prove --commission --single: {len(cases)} single faults, each commissioned; the correctable ones "
          f"then `rig hil` calibrated and wired right, {repeats} of each alternately (load average "
          f"{load0[0]:.1f})", file=sys.stderr, flush=True)
    rows = []
    for i, (k, ms, w, said, exp) in enumerate(cases):
        kind = FAULTS[k][3]
        case_dir = folder / f"case{i:03d}"
        cfg = folder / f"case{i:03d}.toml"
        cfg.write_text(case_config(text, w))
        load = os.getloadavg()[0]
        stopped = []                    # attempts stopped by a fault (a loaded host: a device stall, missed deadlines)
        for attempt in range(1 + retries):
            res, wall, err = commission(cfg, case_dir / (f"retry{attempt}" if attempt else ""))
            if not err:
                break
            stopped.append(err)
        if res is not None and stopped:
            case_dir = case_dir / f"retry{len(stopped)}"
        got = named(res) if res is not None else set()
        want = "refused" if kind in REFUSED else "corrected"
        verdicts = {c: (res or {}).get("verdicts", {}).get(c) for c, _ in sorted(exp)}
        row = {"case": i, "fault": k, "kind": kind, "mounts": [MOUNTS[m] for m in ms], "wiring": said,
               "hil_keys": {key: v for key, v in vars(w).items() if v != getattr(Wiring(), key)},
               "expected": sorted(map(list, exp)), "named": sorted(map(list, got)),
               "named_right": res is not None and got == exp, "verdicts": verdicts, "verdict_expected": want,
               "verdict_right": res is not None and all(v == want for v in verdicts.values()),
               "commission_wall_s": round(wall, 1), "error": err, "commission_stopped": stopped,
               "load_average": round(load, 1), "hil": [], "hil_stopped": [],
               "feedback_db": None, "feedforward_db": None, "feedback_vs_lockstep_db": None,
               "feedforward_vs_lockstep_db": None, "within_1db": None}
        said_named = "named right" if row["named_right"] else "STOPPED" if res is None else "NAMED WRONG"
        print(f"[{i + 1}/{len(cases)}] {said}: {said_named} "
              f"({', '.join(f'{c} {kd}' for c, kd in sorted(got)) or err or 'nothing named'}), "
              f"{', '.join(f'{c} {v}' for c, v in verdicts.items())} ({wall:.0f} s)", file=sys.stderr, flush=True)
        cal = case_dir / "commissioning.toml"
        if want == "corrected" and res is not None and cal.exists():
            cal_cfg = folder / f"case{i:03d}-calibrated.toml"
            cal_cfg.write_text(case_config(text, w, cal))
            compare_hil(row, f"[{i + 1}/{len(cases)}]", {"clean": clean_cfg, "calibrated": cal_cfg}, case_dir,
                        repeats, seconds, retries)
        rows.append(row)
    summary = single_summary(rows, load0, os.getloadavg())
    proof = {"command": "rig prove --commission --single", "seed": args.seed, "repeats": repeats,
             "hil_seconds": seconds, "date_utc": time.strftime("%Y-%m-%d %H:%M", time.gmtime()),
             "summary": summary, "rows": rows}
    (folder / "proof.json").write_text(json.dumps(proof, indent=1))
    (folder / "proof.md").write_text(single_markdown(proof))
    print(json.dumps(proof) if args.json else single_markdown(proof))
    return 0


def compare_hil(row: dict, tag: str, configs: dict, case_dir: Path, repeats: int, seconds: float | None,
                retries: int) -> None:
    """`rig hil` on the calibrated miswired rig and on the rig wired right (configs: {"calibrated", "clean"}),
    `repeats` of each alternately, a run stopped by a fault run again up to `retries` times; the runs and their
    figures into `row`."""
    order = ("clean", "calibrated") if row["case"] % 2 == 0 else ("calibrated", "clean")   # drift cancels over cases
    for n in range(repeats):
        for who in order:
            for attempt in range(1 + retries):    # a run stopped by a fault (exit 1) has no figure
                r = dict(rig=who, **hil(configs[who],
                                         case_dir / f"hil-{who}-{n + 1}{'.' * bool(attempt)}"
                                                    f"{attempt or ''}.h5", seconds), attempts=attempt + 1)
                if r["exit"] != 1:
                    break
                row["hil_stopped"].append(f"{who}: {r['error']}")
                print(f"{tag}   rig hil stopped: {r['error']}", file=sys.stderr, flush=True)
            row["hil"].append(r)
            print(f"{tag}   rig hil, {'wired right' if who == 'clean' else 'calibrated'} "
                  f"{n + 1}/{repeats}: feedback {r['feedback_db']} dB, feedback + feedforward "
                  f"{r['feedforward_db']} dB" + (f"; {r['error']}" if r["error"] else "")
                  + f" ({r['wall_s']:.0f} s)", file=sys.stderr, flush=True)
    fb, ff = _figures(row["hil"], "feedback_db"), _figures(row["hil"], "feedforward_db")
    row["feedback_db"], row["feedforward_db"] = fb, ff
    ls, ls_ff = (_figures(row["hil"], k) for k in ("feedback_vs_lockstep_db", "feedforward_vs_lockstep_db"))
    row["feedback_vs_lockstep_db"], row["feedforward_vs_lockstep_db"] = ls, ls_ff
    # judged on the same stretch of floor: the calibrated rig through the drivers against its lockstep twin, the
    # rig wired right in simulated time (two `rig hil` runs meet different stretches: the floor's own variation,
    # up to 1.5 dB between runs of the same rig, measured in docs/COMMISSIONING.md)
    broke = any(r["error"] for r in row["hil"] if r["rig"] == "calibrated")
    same = ls["calibrated_mean"]
    row["within_1db"] = (False if broke and same is None else None if same is None else abs(same) <= WITHIN_DB)
    print(f"{tag}   calibrated - wired right on the same floor (its lockstep twin): feedback {same} dB, "
          f"feedback + feedforward {ls_ff['calibrated_mean']} dB; between the runs (different stretches of floor): "
          f"feedback {fb['difference']} dB, feedback + feedforward {ff['difference']} dB", file=sys.stderr,
          flush=True)


def _spread(xs: list[float]) -> dict:
    if not xs:
        return {"n": 0}
    m = sum(xs) / len(xs)
    sd = (sum((x - m) ** 2 for x in xs) / (len(xs) - 1)) ** 0.5 if len(xs) > 1 else None
    return {"n": len(xs), "min": round(min(xs), 2), "max": round(max(xs), 2), "mean": round(m, 2),
            "sd": None if sd is None else round(sd, 2)}


def single_summary(rows: list[dict], load0, load1) -> dict:
    """The score, and the rig wired right's run-to-run spread measured in the same run: every clean run's figure,
    and within each case the difference between its clean runs (what 1 dB is to be judged against)."""
    compared = [r for r in rows if r["feedback_db"] is not None]
    out = {"cases": len(rows), "named_right": sum(r["named_right"] for r in rows),
           "verdict_right": sum(r["verdict_right"] for r in rows),
           "stopped": [f"case {r['case']}: {e}" for r in rows for e in r["commission_stopped"]],
           "stopped_not_judged": sum(bool(r["error"]) for r in rows),
           "hil_stopped": [f"case {r['case']} {e}" for r in rows for e in r["hil_stopped"]],
           "refused": sum(r["verdict_expected"] == "refused" for r in rows),
           "refused_right": sum(r["verdict_expected"] == "refused" and r["verdict_right"] for r in rows),
           "hil_compared": len(compared),
           "hil_runs_not_clean": [f"case {r['case']} {h['rig']}: {h['error']}" for r in rows for h in r["hil"]
                                  if h["error"]],
           "load_average_start": [round(x, 1) for x in load0], "load_average_end": [round(x, 1) for x in load1]}
    for key in ("feedback_db", "feedforward_db", "feedback_vs_lockstep_db", "feedforward_vs_lockstep_db"):
        if any(r.get(key) is None for r in compared):
            continue
        diffs = [r[key]["difference"] for r in compared if r[key]["difference"] is not None]
        clean = [x for r in compared for x in r[key]["clean"]]
        pairs = [abs(r[key]["clean"][0] - r[key]["clean"][1]) for r in compared if len(r[key]["clean"]) >= 2]
        out[key] = {"within_1db": sum(abs(d) <= WITHIN_DB for d in diffs), "judged": len(diffs),
                    "difference": _spread(diffs), "clean_runs": _spread(clean),
                    "clean_pair_abs_difference": _spread(pairs),
                    # one clean run against the next (in time order, across cases): the spread with one run a case
                    "clean_successive_abs_difference": _spread([abs(b - a) for a, b in zip(clean, clean[1:])])}
        if key.endswith("_vs_lockstep_db"):
            # the calibrated rig against the rig wired right on the same stretch of floor (its lockstep twin)
            same = [r[key]["calibrated_mean"] for r in compared if r[key]["calibrated_mean"] is not None]
            out[key]["same_floor"] = {"within_1db": sum(abs(d) <= WITHIN_DB for d in same), "judged": len(same),
                                      "calibrated_vs_twin": _spread(same)}
    return out


def single_markdown(proof: dict) -> str:
    s, rows = proof["summary"], proof["rows"]
    fb, ff, ls = s["feedback_db"], s["feedforward_db"], s["feedback_vs_lockstep_db"]
    same, same_ff = ls["same_floor"], s.get("feedforward_vs_lockstep_db", {}).get("same_floor")

    def spread(d: dict) -> str:
        return "none" if not d["n"] else (f"{d['min']} to {d['max']} dB (mean {d['mean']}, sd {d['sd']}, "
                                          f"n {d['n']})")

    def figs(f: dict | None) -> tuple[str, str, str]:
        if f is None:
            return "", "", ""
        return (", ".join(f"{x:.2f}" for x in f["calibrated"]) or "none", ", ".join(f"{x:.2f}" for x in f["clean"])
                or "none", "" if f["difference"] is None else f"{f['difference']:+.2f}")
    out = [f"# {proof['command']}, seed {proof['seed']}, {proof['date_utc']} UTC", "",
           f"- faults named right (channel and kind, nothing else named): {s['named_right']} of {s['cases']}",
           f"- verdicts right (corrected, or refused for dead and noisy): {s['verdict_right']} of {s['cases']} "
           f"(refused right {s['refused_right']} of {s['refused']}, no `rig hil` on those)",
           f"- commissionings stopped by a fault (a stall of the loaded host; --retries runs it again): "
           f"{len(s['stopped'])}, of which cases left not judged: {s['stopped_not_judged']}"
           + "".join(f"\n  - {x}" for x in s["stopped"]),
           f"- `rig hil` runs stopped by a fault: {len(s['hil_stopped'])}"
           + "".join(f"\n  - {x}" for x in s["hil_stopped"]),
           f"- **calibrated within {WITHIN_DB:g} dB of the rig wired right on the same stretch of floor** (the "
           f"calibrated run through the drivers against its lockstep twin, the rig wired right in simulated time), "
           f"feedback: {same['within_1db']} of {same['judged']} ({spread(same['calibrated_vs_twin'])})"
           + ("" if same_ff is None else f"; feedback + feedforward: {same_ff['within_1db']} of {same_ff['judged']} "
              f"({spread(same_ff['calibrated_vs_twin'])})"),
           f"- between the runs (each `rig hil` run meets its own stretch of floor: the start-up's length), "
           f"calibrated - wired right, feedback: {fb['within_1db']} of {fb['judged']} within {WITHIN_DB:g} dB "
           f"(difference {spread(fb['difference'])}); feedback + feedforward: {ff['within_1db']} of "
           f"{ff['judged']} (difference {spread(ff['difference'])})",
           f"- the drivers' cost (through the drivers - in lockstep), calibrated - wired right: {ls['within_1db']} "
           f"of {ls['judged']} within {WITHIN_DB:g} dB (difference {spread(ls['difference'])})",
           f"- the rig wired right, run to run (`rig hil` {proof['repeats']} x per case"
           f"{'' if proof['hil_seconds'] is None else ', ' + format(proof['hil_seconds'], 'g') + ' s'}): feedback "
           f"{spread(fb['clean_runs'])}, |difference| between a case's two runs "
           f"{spread(fb['clean_pair_abs_difference'])}"
           f"; feedback + feedforward {spread(ff['clean_runs'])}, |difference| "
           f"{spread(ff['clean_pair_abs_difference'])}; |difference| between successive runs: feedback "
           f"{spread(fb['clean_successive_abs_difference'])}, feedback + feedforward "
           f"{spread(ff['clean_successive_abs_difference'])}, feedback - lockstep "
           f"{spread(ls['clean_successive_abs_difference'])}",
           f"- `rig hil` runs that did not finish clean (left out of the means): {len(s['hil_runs_not_clean'])}"
           + "".join(f"\n  - {x}" for x in s["hil_runs_not_clean"]),
           f"- load average (1, 5, 15 min): {s['load_average_start']} at the start, {s['load_average_end']} at the "
           f"end", "",
           "| case | fault (mounts) | named | verdict | feedback dB, calibrated | wired right | difference | "
           "feedback + feedforward dB, calibrated | wired right | difference | feedback - lockstep dB, calibrated | "
           "wired right | difference | within 1 dB of the rig wired right on the same floor (feedback) | "
           "plant steps before the loop (the floor's stretch), calibrated / wired right |",
           "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        got = ", ".join(f"{c} {k}" for c, k in r["named"]) or (f"stopped: {r['error']}" if r["error"] else "nothing")
        verdict = ", ".join(sorted({str(v) for v in r["verdicts"].values()}))
        within = {True: "yes", False: "NO", None: "refused, no hil" if r["verdict_expected"] == "refused"
                  else "not judged"}[r["within_1db"]]
        out.append(f"| {r['case']} | {r['fault']} ({', '.join(r['mounts'])}) | "
                   f"{got}{'' if r['named_right'] or r['error'] else ' (WRONG)'} | {verdict} | "
                   + " | ".join(" | ".join(figs(r[k])) for k in ("feedback_db", "feedforward_db",
                                                                   "feedback_vs_lockstep_db"))
                   + f" | {within} | " + " / ".join(", ".join(str(h.get("pre_steps")) for h in r["hil"] if h["rig"] == who)
                                                    or "-" for who in ("calibrated", "clean")) + " |")
    return "\n".join(out) + "\n"
