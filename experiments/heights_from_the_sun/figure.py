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

from experiments.heights_from_the_sun.run import DATA, ROOT, _reference_on

FIGURE = ROOT / "docs" / "images" / "heights_from_the_sun.png"
#: Colour range of the height panels (metres).
HEIGHT_MAX_M = 30.0


def figure(out: Path, seed: int) -> Path:
    """Draw the six panels and write :data:`FIGURE`."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from aerialmtl.evaluation.maps import layer_cmap, load_prediction_maps

    pred = out / "pred"
    recipe = load_prediction_maps(pred / f"recipe_test_s{seed}", ortho=DATA / "ortho_1ft.tif", max_side=None)
    tuned, fused = (load_prediction_maps(pred / f"{arm}_test_s{seed}", max_side=None).layers["height"]
                    for arm in ("tune30", "shadows"))
    height = recipe.layers["height"]
    rows, cols = np.nonzero(np.isfinite(height))
    crop = (slice(rows.min(), rows.max() + 1), slice(cols.min(), cols.max() + 1))
    ref = np.where(np.isfinite(height), _reference_on(pred / f"recipe_test_s{seed}" / "height.tif"), np.nan)
    panels = [("orthophoto", np.nan_to_num(recipe.rgb, nan=1.0), None),
              ("lidar: DSM − DTM", ref, "height"),
              ("recipe (--sun none)", height, "height"),
              ("--sun-tune 30", tuned, "height"),
              ("--shadow-fusion", fused, "height"),
              ("--sun-tune 30 − recipe", tuned - height, "change")]
    fig, axes = plt.subplots(2, 3, figsize=(11.0, 6.6), layout="constrained")
    for ax, (title, data, kind) in zip(axes.ravel(), panels, strict=True):
        ax.set_title(title, fontsize=10)
        ax.set_axis_off()
        if kind is None:
            ax.imshow(data[crop])
            continue
        if kind == "height":
            im = ax.imshow(data[crop], cmap=layer_cmap("height"), vmin=0.0, vmax=HEIGHT_MAX_M,
                           interpolation="nearest")
        else:
            im = ax.imshow(data[crop], cmap="RdBu_r", vmin=-4.0, vmax=4.0, interpolation="nearest")
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
