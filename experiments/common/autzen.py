"""The real-data survey every study uses, ``samples/autzen_west`` (samples/README.md), and its fixed split.

Defined once here; :mod:`experiments.real_data.run` tiles, trains and predicts on it, the other studies read
what it left behind.
"""

from __future__ import annotations

import os
import platform
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT / "samples" / "autzen_west"
ORTHO, DSM, DTM = "ortho_1ft.tif", "dsm_1m_utm.tif", "dtm_1m_utm.tif"

#: Bands along the north–south axis, as fractions of the orthophoto's extent from its north edge. The
#: held-out test block is the same in both. ``south-val`` (the first protocol) validates on the southern
#: 20 %: river and forest, 16 % of its pixels ≥ 2 m against 28 % in the train bands, so validation prefers
#: models that keep everything low. ``middle-val`` validates on the 20 % band whose height distribution is
#: closest to the rest (mean 3.1 m and 23 % ≥ 2 m against 3.8 m and 25 %; chosen from the reference heights
#: of the train and val region only) and trains on the bands on either side of it.
SPLITS: dict[str, dict[str, list[tuple[float, float]]]] = {
    "south-val": {"test": [(0.0, 0.25)], "train": [(0.25, 0.80)], "val": [(0.80, 1.0)]},
    "middle-val": {"test": [(0.0, 0.25)], "train": [(0.25, 0.45), (0.65, 1.0)], "val": [(0.45, 0.65)]},
    # Cross-fit folds of middle-val's training block (experiments/crossfit): each trains on two of its
    # three bands, validates on the same band as middle-val, and its "test" is the held-out band, whose
    # prediction gives out-of-fold errors. The real test block (north 25 %) is in none of them.
    "cv3-a": {"test": [(0.25, 0.45)], "train": [(0.65, 1.0)], "val": [(0.45, 0.65)]},
    "cv3-b": {"test": [(0.65, 0.825)], "train": [(0.25, 0.45), (0.825, 1.0)], "val": [(0.45, 0.65)]},
    "cv3-c": {"test": [(0.825, 1.0)], "train": [(0.25, 0.45), (0.65, 0.825)], "val": [(0.45, 0.65)]},
}
DEFAULT_SPLIT = "middle-val"
#: Metres left unused on each side of an inner block edge (between test/train and train/val).
GAP_M = 10.0
#: Reference-height threshold (metres) of the "tall pixels" MAE.
TALL_M = 2.0


def cpu_model() -> str:
    """The CPU as ``lscpu`` names it, with its family, model and core count (recorded beside every result)."""
    try:
        text = subprocess.run(["lscpu"], capture_output=True, text=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError):
        return platform.processor() or "unknown CPU"
    fields = dict(line.split(":", 1) for line in text.splitlines() if ":" in line)
    name = fields.get("Model name", "?").strip()
    return f"{name} (family {fields.get('CPU family', '?').strip()}, model {fields.get('Model', '?').strip()}), " \
           f"{os.cpu_count()} cores"
