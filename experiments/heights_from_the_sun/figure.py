"""Before/after pictures of the study's options on the held-out block (seed 0), for the docs.

The orthophoto, the lidar's height (DSM − DTM), the recipe's height (`predict --sun none`), the height with
`--sun-tune 30`, with `--shadow-fusion`, and the change tuning made. Reads the study's predictions
(``run.py``, ``selfsup.py``), writes ``docs/images/heights_from_the_sun.png``.

Usage::

    python -m experiments.heights_from_the_sun.figure --out study58
"""

from __future__ import annotations

import argparse
import io
from pathlib import Path

import numpy as np
import rasterio
from rasterio.enums import Resampling
from rasterio.windows import from_bounds

from experiments.heights_from_the_sun.run import DATA, ROOT, _reference_on

FIGURE = ROOT / "docs" / "images" / "heights_from_the_sun.png"
#: Colour range of the height panels (metres).
HEIGHT_MAX_M = 30.0


def _height(path: Path) -> tuple[np.ndarray, tuple[slice, slice]]:
    """The height of a prediction cropped to its valid pixels (NaN elsewhere), and that crop."""
    with rasterio.open(path) as src:
        a = src.read(1).astype(np.float64)
        a[a == src.nodata] = np.nan
    ok = np.isfinite(a)
    rows, cols = np.flatnonzero(ok.any(1)), np.flatnonzero(ok.any(0))
    crop = (slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1))
    return a[crop], crop


def _ortho(grid_file: Path, crop: tuple[slice, slice]) -> np.ndarray:
    """The orthophoto averaged onto the crop of the prediction grid, (h, w, 3) uint8."""
    with rasterio.open(grid_file) as grid:
        t = grid.window_transform(rasterio.windows.Window.from_slices(*crop))
        h, w = crop[0].stop - crop[0].start, crop[1].stop - crop[1].start
        left, top = t * (0, 0)
        right, bottom = t * (w, h)
    with rasterio.open(DATA / "ortho_1ft.tif") as src:
        rgb = src.read((1, 2, 3), window=from_bounds(left, bottom, right, top, src.transform), out_shape=(3, h, w),
                       resampling=Resampling.average)
    result: np.ndarray = np.moveaxis(rgb, 0, -1)
    return result


def figure(out: Path, seed: int) -> Path:
    """Draw the six panels and write :data:`FIGURE`."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pred = out / "pred"
    recipe, crop = _height(pred / f"recipe_test_s{seed}" / "height.tif")
    tuned, _ = _height(pred / f"tune30_test_s{seed}" / "height.tif")
    fused, _ = _height(pred / f"shadows_test_s{seed}" / "height.tif")
    ref = _reference_on(pred / f"recipe_test_s{seed}" / "height.tif")[crop]
    ref = np.where(np.isfinite(recipe), ref, np.nan)
    panels = [("orthophoto", _ortho(pred / f"recipe_test_s{seed}" / "height.tif", crop), None),
              ("lidar: DSM − DTM", ref, "height"),
              ("recipe (--sun none)", recipe, "height"),
              ("--sun-tune 30", tuned, "height"),
              ("--shadow-fusion", fused, "height"),
              ("--sun-tune 30 − recipe", tuned - recipe, "change")]
    fig, axes = plt.subplots(2, 3, figsize=(11.0, 6.6), layout="constrained")
    for ax, (title, data, kind) in zip(axes.ravel(), panels, strict=True):
        ax.set_title(title, fontsize=10)
        ax.set_axis_off()
        if kind is None:
            ax.imshow(data)
            continue
        if kind == "height":
            im = ax.imshow(data, cmap="viridis", vmin=0.0, vmax=HEIGHT_MAX_M, interpolation="nearest")
        else:
            im = ax.imshow(data, cmap="RdBu_r", vmin=-4.0, vmax=4.0, interpolation="nearest")
        fig.colorbar(im, ax=ax, shrink=0.8, label="m")
    fig.suptitle(f"autzen_west, held-out block (1 m), the study's seed {seed}", fontsize=11)
    FIGURE.parent.mkdir(parents=True, exist_ok=True)
    buf = io.BytesIO()
    fig.savefig(buf, dpi=72)
    plt.close(fig)
    from PIL import Image  # a palette of 256 colours: a third of the bytes, the same picture to the eye

    Image.open(buf).convert("RGB").quantize(256).save(FIGURE, optimize=True)
    return FIGURE


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    print(figure(a.out, a.seed))


if __name__ == "__main__":
    main()
