"""The control laws (compiled) and their design tools. The laws call one another's compiled functions across
files (the section step, isolation inside the operating modes): their cached code is dropped whenever any file
here changes (compiled_cache.py)."""
from pathlib import Path as _Path

from controllers.compiled_cache import drop_stale as _drop_stale

_laws = sorted(_Path(__file__).resolve().parent.glob("*.py"))
_drop_stale(_Path(__file__), _laws, [p.stem for p in _laws])
