"""The synthetic generator's pins: reference copies of one small town and a few city patches that it must keep
making.

The pin holds the town's rasters as the generator made them (``tests/data/town_pin.npz``). A test compares a
fresh town against it with tolerances that no CPU's kernels reach and every change of the generator exceeds
(:func:`town_differences`). Remake it only when the generator is meant to change (bump ``SYNTH_VERSION`` and the
demo's expected numbers with it)::

    python -m tests.helpers.pins

The city's patches (:data:`CITY_PIN`) are the synthetic pretraining's (``aerialmtl pretrain``, the shipped
start ``synthcity-lite0``): a changed city means a start whose card no longer says how it was made.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import rasterio

#: The pinned town: ``synthesize(out, **TOWN_ARGS)``, generator version :data:`TOWN_VERSION`.
TOWN_ARGS = {"size": 128, "seed": 5, "gsd": 0.5}
TOWN_VERSION = "1"
TOWN_PIN = Path(__file__).resolve().parent.parent / "data" / "town_pin.npz"
RASTERS = ("ortho", "dsm", "dtm", "ndsm", "labels")

#: Heights (dsm, dtm, ndsm) may differ from the pin by this much (m). Measured: OpenBLAS's float32 matrix
#: product (the value noise of ``data/synth/noise.py``) rounds differently per kernel (Haswell for AVX2 CPUs,
#: SkylakeX, Sandybridge), by one float32 step (≤ 4e-6 m) in 10-30 of the 16,384 pixels; 1 mm is 250x that and
#: far below what any change of a generator default moves (decimetres to metres over thousands of pixels).
HEIGHT_TOL_M = 1e-3
#: The orthophoto is 8-bit, rounded from floats: a one-step float difference can flip a rounding, so at most
#: this share of its values may differ, by one grey level at most (measured: none on the kernels above).
ORTHO_FLIP_SHARE = 1e-3


def make_town(out: Path) -> dict[str, np.ndarray]:
    """Generate the pinned town into ``out`` and read its rasters back (name → array as stored)."""
    from aerialmtl.data.synth import synthesize

    synthesize(out, **TOWN_ARGS)  # type: ignore[arg-type]
    arrays = {}
    for name in RASTERS:
        with rasterio.open(out / f"{name}.tif") as src:
            arrays[name] = src.read()
    return arrays


def town_differences(got: dict[str, np.ndarray], pin: dict[str, np.ndarray]) -> list[str]:
    """What in ``got`` differs from the pin beyond the tolerances, one line each (empty: the same town)."""
    kinds = {"ortho": "image", "labels": "labels", "dsm": "height", "dtm": "height", "ndsm": "height"}
    return differences(got, pin, kinds)


def differences(got: dict[str, np.ndarray], pin: dict[str, np.ndarray], kinds: dict[str, str]) -> list[str]:
    """What in ``got`` differs from ``pin`` beyond the tolerances, one line each; ``kinds``: name → ``"image"``
    (8-bit, :data:`ORTHO_FLIP_SHARE`), ``"labels"`` (exact) or ``"height"`` (:data:`HEIGHT_TOL_M`)."""
    problems = []
    for name, kind in kinds.items():
        a, b = got[name], pin[name]
        if a.shape != b.shape or a.dtype != b.dtype:
            problems.append(f"{name}: {a.dtype}{a.shape} instead of {b.dtype}{b.shape}")
        elif kind == "labels":
            if (n := int((a != b).sum())):
                problems.append(f"{name}: {n} pixels of another class")
        elif kind == "image":
            diff = np.abs(a.astype(np.int16) - b.astype(np.int16))
            if diff.max() > 1 or (diff > 0).mean() > ORTHO_FLIP_SHARE:
                problems.append(f"{name}: {int((diff > 0).sum())} values differ, by up to {int(diff.max())} levels")
        else:
            diff = np.abs(a.astype(np.float64) - b.astype(np.float64))
            if not np.isfinite(diff).all() or diff.max() > HEIGHT_TOL_M:
                problems.append(f"{name}: {int((diff > HEIGHT_TOL_M).sum())} pixels differ by more than "
                                f"{HEIGHT_TOL_M} m (up to {float(np.nanmax(diff)):.3g} m)")
    return problems


#: The pinned city patches: ``sample_city(seed, **CITY_ARGS)`` for each of :data:`CITY_SEEDS` (default style, no
#: textures), stored as ``image_SEED``, ``height_SEED``, ``classes_SEED``.
CITY_ARGS = {"size": 96, "gsd": 0.5}
CITY_SEEDS = (0, 7, 123)
CITY_PIN = TOWN_PIN.with_name("city_pin.npz")
CITY_KINDS = {"image": "image", "height": "height", "classes": "labels"}


def make_cities() -> dict[str, np.ndarray]:
    """The pinned city patches, as :data:`CITY_PIN` stores them."""
    from aerialmtl.data.synth.city import sample_city

    arrays = {}
    for seed in CITY_SEEDS:
        patch = sample_city(seed, **CITY_ARGS)  # type: ignore[arg-type]
        for name in CITY_KINDS:
            arrays[f"{name}_{seed}"] = getattr(patch, name)
    return arrays


def city_differences(got: dict[str, np.ndarray], pin: dict[str, np.ndarray]) -> list[str]:
    """What in ``got`` (:func:`make_cities`) differs from the city pin beyond the tolerances, one line each."""
    kinds = {f"{name}_{seed}": kind for seed in CITY_SEEDS for name, kind in CITY_KINDS.items()}
    return differences(got, pin, kinds)


def load_city_pin() -> dict[str, np.ndarray]:
    """The pinned city patches."""
    with np.load(CITY_PIN) as data:
        return {name: data[name] for name in data.files}


def load_pin() -> dict[str, np.ndarray]:
    """The pinned rasters."""
    with np.load(TOWN_PIN) as data:
        return {name: data[name] for name in RASTERS}


if __name__ == "__main__":
    with tempfile.TemporaryDirectory() as tmp:
        np.savez_compressed(TOWN_PIN, **make_town(Path(tmp)))
    np.savez_compressed(CITY_PIN, **make_cities())
    for pin in (TOWN_PIN, CITY_PIN):
        print(f"wrote {pin} ({pin.stat().st_size} bytes)")
