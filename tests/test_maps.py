"""Display helpers of the uncertainty notebook: reading a prediction folder, ranking uncertain areas, shared zoom."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from affine import Affine
from helpers.rasters import write_prediction_folder

from aerialmtl.classes import IGNORE_INDEX
from aerialmtl.errors import InputError
from aerialmtl.evaluation.maps import (
    load_prediction_maps,
    most_uncertain_areas,
    plot_maps,
    plot_sparsification,
    uncertainty_summary,
    zoom_to,
)
from aerialmtl.evaluation.uncertainty import sparsification

T = Affine(0.5, 0, 500000.0, 0, -0.5, 5000000.0)


def test_most_uncertain_areas_finds_the_hot_cell_with_map_bounds(rng: np.random.Generator) -> None:
    values = rng.uniform(0, 0.1, (96, 128))
    values[64:96, 32:64] += 1.0   # hottest cell: row 2, column 1 of a 32-px grid
    values[0:32, 96:128] += 0.5   # second
    areas = most_uncertain_areas(values, T, size=32, top_k=2)
    assert [(a["row_off"], a["col_off"]) for a in areas] == [(64, 32), (0, 96)]
    first = areas[0]
    assert first["rank"] == 1 and first["width"] == first["height"] == 32
    assert first["mean"] == pytest.approx(values[64:96, 32:64].mean())
    assert (first["left"], first["right"]) == (500016.0, 500032.0)
    assert (first["bottom"], first["top"]) == (4999952.0, 4999968.0)
    assert (first["x"], first["y"]) == (500024.0, 4999960.0)


def test_most_uncertain_areas_skips_mostly_nodata_cells_and_handles_edges() -> None:
    values = np.zeros((40, 40))
    values[:20, :20] = np.nan
    values[0, 0] = 50.0            # a lone valid pixel in an almost empty cell: must not win
    values[32:, 32:] = 2.0         # the 8×8 edge cell
    areas = most_uncertain_areas(values, T, size=16, top_k=100, min_valid=0.5)
    assert (areas[0]["row_off"], areas[0]["col_off"], areas[0]["width"]) == (32, 32, 8)
    assert all((a["row_off"], a["col_off"]) != (0, 0) for a in areas)
    assert len(areas) == 9 - 1
    with pytest.raises(InputError, match="size"):
        most_uncertain_areas(values, T, size=0)


@pytest.fixture
def pred_dir(tmp_path: Path, rng: np.random.Generator) -> Path:
    return write_prediction_folder(tmp_path / "pred", rng)


def test_load_prediction_maps_puts_everything_on_one_grid(pred_dir: Path) -> None:
    maps = load_prediction_maps(pred_dir, ortho=pred_dir.parent / "ortho.tif")
    assert set(maps.layers) == {"height", "height_std", "class_entropy", "class_mutual_info"}
    assert maps.rgb is not None and maps.rgb.shape == (64, 64, 3)
    assert np.nanmin(maps.rgb) >= 0 and np.nanmax(maps.rgb) <= 1
    assert np.isnan(maps.layers["height"][:4, :4]).all() and np.isfinite(maps.layers["height"][4:, 4:]).all()
    assert (maps.classes[:4, :4] == IGNORE_INDEX).all()
    assert maps.scheme is not None and maps.scheme.name == "synthetic"
    assert maps.extent == (500000.0, 500032.0, 4999968.0, 5000000.0)

    small = load_prediction_maps(pred_dir, max_side=32)
    assert small.decimation == 2 and small.layers["height_std"].shape == (32, 32) and small.rgb is None
    assert small.extent == maps.extent


def test_load_prediction_maps_names_the_fix_for_a_wrong_folder(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="PRED_DIR"):
        load_prediction_maps(tmp_path / "nope")


def test_plot_maps_shares_the_zoom_and_shows_the_class_legend(pred_dir: Path) -> None:
    pytest.importorskip("matplotlib")
    maps = load_prediction_maps(pred_dir, ortho=pred_dir.parent / "ortho.tif")
    fig, axes = plot_maps(maps)
    assert [ax.get_title() for ax in axes] == ["orthophoto", "predicted height (m)", "height std (m)",
                                               "predicted classes", "class entropy (nats)",
                                               "mutual information (nats)"]
    legend = axes[3].get_legend()
    assert [t.get_text() for t in legend.get_texts()] == maps.scheme.names
    area = most_uncertain_areas(maps.layers["class_mutual_info"], maps.grid.transform, size=16, top_k=1)[0]
    zoom_to(axes[:1], area)  # zoom one panel: all follow
    for ax in axes:
        assert ax.get_xlim() == pytest.approx((area["left"], area["right"]))
        assert ax.get_ylim() == pytest.approx((area["bottom"], area["top"]))
    zoom_to(axes, area, margin=1000.0, within=maps.extent)  # a margin never leaves the raster
    assert axes[-1].get_xlim() == pytest.approx(maps.extent[:2])
    assert axes[-1].get_ylim() == pytest.approx(maps.extent[2:])


def test_uncertainty_summary_and_sparsification_plot(rng: np.random.Generator) -> None:
    pytest.importorskip("matplotlib")
    err = rng.uniform(0, 1, 500)
    good = sparsification(err, err + rng.normal(0, 0.05, 500))
    bad = sparsification(err, rng.uniform(0, 1, 500))
    report = {"uncertainty": {
        "height_std": {"sparsification": good, "spearman_std_vs_abs_error": 0.9},
        "class_mutual_info": {"sparsification": bad, "spearman_vs_error": 0.0},
        "calibration": {"ece": 0.1},
    }}
    s = uncertainty_summary(report)
    assert set(s) == {"height_std", "class_mutual_info"}
    assert s["height_std"]["ause"] < s["class_mutual_info"]["ause"]
    assert s["height_std"]["spearman"] == 0.9 and s["height_std"]["n_pixels"] == 500
    fig = plot_sparsification(report)
    assert len(fig.axes) == 2
    assert len(fig.axes[0].lines) == 3  # curve, oracle, random
    with pytest.raises(InputError, match="--mc"):
        plot_sparsification({"uncertainty": {}})
