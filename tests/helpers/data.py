"""Where the real sample data shipped beside the repository lie (see ../shared/data/README.md)."""

from __future__ import annotations

from pathlib import Path

#: Real sample data shipped beside the repository.
SHARED_DATA = Path(__file__).resolve().parents[3] / "shared" / "data"
NEON_DIR = SHARED_DATA / "neon_bart"
