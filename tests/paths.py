"""Where the shared material is: `../shared` beside the repository (as on CI's clean clone)."""
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
RECORDINGS = SHARED / "recordings"
