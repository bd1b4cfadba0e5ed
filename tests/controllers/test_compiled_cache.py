"""The compiled laws' cache is dropped when a file it depends on changes (numba itself looks at the function's own
file only: a law compiled with an old coefficient layout from another file ran unstable here once)."""
from __future__ import annotations

from controllers.compiled_cache import drop_stale


def test_a_changed_dependency_drops_the_cached_code_and_nothing_else(tmp_path, monkeypatch):
    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    law, dep = tmp_path / "law.py", tmp_path / "layout.py"
    law.write_text("x = 1\n")
    dep.write_text("N = 14\n")
    cache = tmp_path / "__pycache__"
    cache.mkdir()
    compiled = [cache / "law.step-10.py311.nbi", cache / "law.step-10.py311.1.nbc"]
    other = cache / "layout.put-3.py311.nbi"

    def fill():
        for f in compiled + [other]:
            f.write_bytes(b"code")
    fill()
    drop_stale(law, [law, dep])                  # no stamp yet: dropped
    assert not any(f.exists() for f in compiled) and other.exists()
    fill()
    drop_stale(law, [law, dep])                  # nothing changed: kept
    assert all(f.exists() for f in compiled)
    dep.write_text("N = 15\n")
    drop_stale(law, [law, dep])                  # the layout changed: dropped
    assert not any(f.exists() for f in compiled) and other.exists()
