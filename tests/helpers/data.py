"""Where the real sample areas lie: ``samples/`` in the repository (see samples/README.md).

``../shared/data`` beside the clone (the folder they were copied from) is only a fallback for a checkout
that predates ``samples/``.
"""

from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
#: The sample areas shipped with the repository.
SAMPLES = ROOT / "samples"
#: Where they came from (read only when a sample is missing from SAMPLES).
SHARED_DATA = ROOT.parent / "shared" / "data"


def sample_dir(name: str) -> Path:
    """The folder of sample area ``name`` (``neon_bart``, ``autzen_west``, ``ign_montpellier_lidarhd``)."""
    here = SAMPLES / name
    return here if here.is_dir() or not (SHARED_DATA / name).is_dir() else SHARED_DATA / name


NEON_DIR = sample_dir("neon_bart")
AUTZEN_DIR = sample_dir("autzen_west")
IGN_DIR = sample_dir("ign_montpellier_lidarhd")
