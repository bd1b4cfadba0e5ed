"""A batch's summary, rewritten after every recording (so an interrupted batch leaves a current one):

  summary.csv   one line per recording: name, date, status, verdict, the named effects ("name: key=value; ..."),
                each effect's and each identified parameter's value in its own column (effect.key, parameter and
                parameter_std), the fit's figures, wall and CPU time, the error of a failed one, the file
  summary.md    the same as a table to read (values to 4 significant digits; the CSV and JSON keep them exact)
  summary.json  {"command", "rows": [...]}: every row as rig.batch.run made it (floats exact)

The rows come in the batch's input order; a failed recording is one line with its error.
"""
from __future__ import annotations

import csv
import io
import json
import os
from pathlib import Path

FILES = {"csv": "summary.csv", "markdown": "summary.md", "json": "summary.json"}
FIRST = ("recording", "date_utc", "status", "verdict", "effects")
LAST = ("wall_s", "cpu_s", "worker", "error", "path")


def effects_text(effects: dict) -> str:
    """{"transport_delay": {"delay_s": 0.003}} -> "transport_delay: delay_s=0.003" ("; " between effects)."""
    return "; ".join(f"{name}: " + ", ".join(f"{k}={_short(v)}" for k, v in prm.items()) if prm else name
                     for name, prm in effects.items())


def _short(v) -> str:
    return f"{v:.4g}" if isinstance(v, float) else str(v)


def _columns(rows: list[dict]) -> list[str]:
    """The value columns the rows have between them: effects' parameters, then parameters and their 1-sigma,
    then the fit's figures, each in the order first met."""
    cols: dict[str, None] = {}
    for r in rows:
        for name, prm in r.get("effects", {}).items():
            for k in prm:
                cols[f"{name}.{k}"] = None
    for r in rows:
        for k in r.get("parameters", {}):
            cols[k] = None
            if k in r.get("std", {}):
                cols[f"{k}_std"] = None
    for r in rows:
        for k in r.get("figures", {}):
            cols[f"fit.{k}"] = None
    return list(cols)


def _flat(r: dict) -> dict:
    out = {"recording": r["recording"], "date_utc": r.get("date_utc", ""), "status": r["status"],
           "verdict": r.get("verdict", ""), "effects": effects_text(r.get("effects", {})),
           "wall_s": round(r.get("wall_s", 0.0), 3), "cpu_s": round(r.get("cpu_s", 0.0), 3),
           "worker": r.get("worker", ""), "error": r.get("error", ""), "path": r.get("path", "")}
    for name, prm in r.get("effects", {}).items():
        out.update({f"{name}.{k}": v for k, v in prm.items()})
    out.update(r.get("parameters", {}))
    out.update({f"{k}_std": v for k, v in r.get("std", {}).items()})
    out.update({f"fit.{k}": v for k, v in r.get("figures", {}).items()})
    return out


def csv_text(rows: list[dict]) -> str:
    cols = [*FIRST, *_columns(rows), *LAST]
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=cols, restval="", lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: ("" if v is None else repr(v) if isinstance(v, float) else v) for k, v in _flat(r).items()})
    return buf.getvalue()


def markdown_text(command: str, rows: list[dict]) -> str:
    ok = [r for r in rows if r["status"] == "ok"]
    params = [c for c in _columns(rows) if not c.startswith("fit.") and "." not in c and not c.endswith("_std")]
    head = ["recording", "date (UTC)", "status", "verdict", "named effects", *params, "time [s]"]
    lines = [f"# rig {command}: {len(rows)} recordings, {len(ok)} done, {len(rows) - len(ok)} failed", "",
             "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        f = _flat(r)
        status = r["status"] if r["status"] == "ok" else f"failed: {r['error']}".replace("|", "/")
        cells = [r["recording"], f["date_utc"], status, f["verdict"], f["effects"] or ("none" if ok else ""),
                 *(_short(f[p]) if f.get(p) is not None and p in f else "" for p in params), f"{f['wall_s']:.1f}"]
        lines.append("| " + " | ".join(str(c) for c in cells) + " |")
    return "\n".join(lines) + "\n"


def _write(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)                  # atomic: a reader never sees half a summary


def write(out_root: Path, command: str, rows: list[dict], *, final: bool = False) -> dict[str, Path]:
    """Write the three files of the summary into out_root; their paths. (final: the batch has ended.)"""
    out_root = Path(out_root)
    paths = {k: out_root / name for k, name in FILES.items()}
    _write(paths["json"], json.dumps({"command": command, "complete": final, "rows": rows}, indent=1))
    _write(paths["csv"], csv_text(rows))
    _write(paths["markdown"], markdown_text(command, rows))
    return paths


def read_rows(out_root: Path) -> list[dict]:
    """The rows of a batch's summary.json (for its trends, or a notebook)."""
    return json.loads((Path(out_root) / FILES["json"]).read_text())["rows"]
