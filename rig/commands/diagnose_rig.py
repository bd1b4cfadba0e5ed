"""`rig diagnose RUN.h5 [--out DIR]` on a run of the four-mount rig (`rig run --record`, `rig hil`; the layout of
docs/RUN_RECORDING.md): where the rig differs from its model, per mount, sensor and band, which machine-level
physics explains it, the fit it gives, the transmissibilities measured against predicted and the margins on the
diagnosed rig (rig/diagnose/machine/; docs/DIAGNOSIS.md, "Runs of the four-mount rig").

The model is the configured rig (--config; default Table 1 and Table 2 with the assumed geometry of
docs/MODEL.md) and its isolation controllers: give the config the run was made with.
"""
from __future__ import annotations

import os

# hundreds of small matrix products: BLAS threads only contend for them on the shared 2-core machine (set
# before numpy loads: this module is imported before any of them)
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

from rig.errors import RigError  # noqa: E402


def machine_config(config):
    """The configured rig (a TOML path, or None for Table 1 and 2): refused in one line unless it is the machine."""
    from rig.config import load_config

    cfg = load_config(config) if config else load_config(None)
    if cfg.layout.plant != "machine":
        raise RigError(f"{cfg.source}: [layout] plant = {cfg.layout.plant!r}: a run of the four-mount rig is "
                       "diagnosed against the machine's model (--config of the run, or none for Table 1 and 2)")
    return cfg


def diagnose_file(path, cfg, out=None, progress=None):
    """Diagnose the run recorded in path against cfg, writing the outputs into out if given: (diagnosis, the
    recording, the paths written). The one piece of work of `rig diagnose RUN.h5` and of a batch's run."""
    import numpy as np

    from rig.diagnose.machine import report
    from rig.diagnose.machine.engine import nominal_theta
    from rig.diagnose.machine.result import diagnose_rig
    from rig.diagnose.machine.series import replay_series
    from rig.recordings.runfile import read_run

    say = progress or (lambda s: None)
    rec = read_run(path)                                # RecordingError: one line naming file and dataset
    if rec.gaps:
        say(f"note: {rec.gaps}")
    say(f"diagnosing {rec.source}: {rec.n} rows at {rec.fs_hz:g} Hz, the four-mount rig against {cfg.source}")
    diag = diagnose_rig(rec, cfg, progress=progress)
    paths = {}
    if out is not None:
        say("writing outputs (and the replay as time series)")
        th = {k: np.asarray(v) for k, v in diag.theta.items()}
        try:
            series = replay_series(rec, diag.base, {"model": nominal_theta(diag.base), "diagnosed": th}, th)
            paths = report.write_outputs(Path(out), diag, series)
        except OSError as e:
            raise RigError(f"--out {out}: cannot write ({e.strerror or e})") from None
    return diag, rec, paths


def batch_work(config, path: str, out: str) -> dict:
    """A batch's work on a run of the four-mount rig (in a worker): diagnosed into out as `rig diagnose RUN.h5
    --out` does; its summary row."""
    from rig.batch.rows import rig_diagnosis_row

    diag, rec, _ = diagnose_file(Path(path), machine_config(config), Path(out))
    return rig_diagnosis_row(diag, rec)


def run(args) -> int:
    from rig.diagnose.machine import report

    cfg = machine_config(args.config)
    t0 = time.perf_counter()

    def progress(msg: str) -> None:
        print(f"[{time.perf_counter() - t0:6.1f} s] {msg}", file=sys.stderr, flush=True)

    diag, _, paths = diagnose_file(args.recording, cfg, args.out, progress)
    progress(f"done in {time.perf_counter() - t0:.1f} s")
    if args.json:
        print(json.dumps(report.diagnosis_dict(diag), indent=1))
    else:
        print(report.console_text(diag))
        print("written: " + ", ".join(str(p) for p in paths.values()) if paths else
              "(add --out DIR for diagnosis.json, report.md, replay.csv and the plots)")
    return 0

