"""numba's on-disk cache knows a compiled function by its own file only: a law compiled together with functions
of other files (a shared section step, another law, the runtime's constants) keeps their old code after they
changed. `drop_stale` stamps the files a cache depends on and drops the cache when the stamp changes, so the
next call compiles afresh."""
from __future__ import annotations

import hashlib
import os
from pathlib import Path


def drop_stale(cache_of: Path, deps: list[Path], stems: list[str] | None = None) -> None:
    """Drop the cached code of the modules `stems` (default: cache_of's own) of cache_of's folder when the
    files `deps` are not what they were at the last call."""
    here = Path(cache_of).resolve()
    stamp = hashlib.sha1(b"".join(Path(p).read_bytes() for p in deps)).hexdigest()
    where = os.environ.get("NUMBA_CACHE_DIR")        # (numba's own setting, read without importing numba)
    cache = Path(where) / str(here.parent).lstrip("/") if where else here.parent / "__pycache__"
    mark = cache / f"{here.stem}.deps"
    try:
        if mark.read_text() == stamp:
            return
    except OSError:
        pass
    for stem in stems or [here.stem]:
        for f in cache.glob(f"{stem}.*.nb[ic]"):
            f.unlink(missing_ok=True)
    try:
        cache.mkdir(parents=True, exist_ok=True)
        mark.write_text(stamp)
    except OSError:             # a read-only install: its cache came with it
        pass
