"""Scoring extracted buildings against reference footprints (`aerialmtl evaluate --buildings`)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import rasterio
from click.testing import CliRunner
from helpers.cli import run_cli
from helpers.rasters import write_prediction_layers
from shapely import affinity
from shapely.geometry import box

from aerialmtl.buildings import write_buildings
from aerialmtl.classes import ClassScheme
from aerialmtl.cli import cli
from aerialmtl.data.synth import synthesize
from aerialmtl.evaluation.buildings import match_footprints, score_buildings
from aerialmtl.evaluation.evaluate import evaluate_prediction
from aerialmtl.formats.buildings import REFERENCE_FIELDS, FootprintWriter

pytest.importorskip("pyogrio")


def test_matching_is_one_to_one_at_iou_half() -> None:
    ref = [box(0, 0, 10, 10), box(20, 0, 30, 10), box(40, 0, 50, 10)]
    pred = [box(0, 0, 10, 10), box(1, 0, 11, 10),   # two candidates for the first: the better one wins
            box(20, 0, 30, 4),                      # IoU 0.4: no match
            box(41, 0, 51, 10)]                     # IoU 9/11
    m = match_footprints(pred, ref)
    assert [(p, r) for p, r, _ in m] == [(0, 0), (3, 2)]
    assert m[1][2] == pytest.approx(90 / 110)
    s = score_buildings(pred, [5, 7, 3, 12], [0.1, 0.5, 0.2, 2.0], ref, [6, 0, 9])
    assert (s["n_matched"], s["precision"], s["recall"]) == (2, 0.5, 2 / 3)
    assert s["f1"] == pytest.approx(2 * 0.5 * (2 / 3) / (0.5 + 2 / 3))
    assert s["height"]["mae"] == pytest.approx((1 + 3) / 2) and s["height"]["rmse"] == pytest.approx(math.sqrt(5))
    assert s["height"]["bias"] == pytest.approx((-1 + 3) / 2)
    assert s["spearman_std_vs_abs_error"] == pytest.approx(1.0)  # bigger spread, bigger error
    assert score_buildings([], [], [], ref, None)["f1"] == 0.0
    assert math.isnan(score_buildings([], [], [], [], None)["f1"])


def _perfect_prediction(town: Path, out: Path) -> Path:
    """The synthetic town's labels and nDSM as a prediction folder (a perfect model)."""
    scheme = ClassScheme.load("synthetic")
    with rasterio.open(town / "labels.tif") as src:
        cls = scheme.remap(src.read(1), on_unknown="ignore")
        transform, crs = src.transform, src.crs.to_string()
    with rasterio.open(town / "ndsm.tif") as src:
        height = src.read(1)
    std = np.full_like(height, 0.3)
    return write_prediction_layers(out, cls, height, std, np.zeros_like(height), crs=crs, transform=transform)


def test_perfect_prediction_of_a_synthetic_town_scores_one(tmp_path: Path) -> None:
    town = synthesize(tmp_path / "town", size=384, seed=4)
    pred = _perfect_prediction(tmp_path / "town", tmp_path / "pred")
    report = evaluate_prediction(pred, buildings_ref=town.buildings, out=tmp_path / "ev" / "report.json")
    b = report["buildings"]
    assert b["n_reference"] >= 5 and b["recall"] >= 0.9 and b["precision"] >= 0.9
    assert b["mean_iou_matched"] > 0.9
    assert b["height"]["mae"] < 0.1
    assert report["height"] is None and report["classes"] is None
    assert "building F1" in (tmp_path / "ev" / "report.md").read_text()
    saved = json.loads((tmp_path / "ev" / "report.json").read_text())
    assert saved["buildings"]["n_matched"] == b["n_matched"] and saved["references"]["buildings"] == str(town.buildings)


def test_cli_scores_a_buildings_file_against_a_reference_in_another_crs(tmp_path: Path) -> None:
    cls = np.zeros((80, 80), np.uint8)
    height = np.zeros((80, 80), np.float32)
    std = np.full((80, 80), 0.2, np.float32)
    for (r0, r1, c0, c1), h, s in (((5, 25, 5, 35), 6.0, 0.2), ((40, 75, 10, 60), 15.0, 2.0)):
        cls[r0:r1, c0:c1] = 2
        height[r0:r1, c0:c1] = h
        std[r0:r1, c0:c1] = s
    pred = write_prediction_layers(tmp_path / "pred", cls, height, std)
    write_buildings(pred, [tmp_path / "b.gpkg"])
    # the reference in Web Mercator: true heights 7 and 10 m, plus one building the prediction missed
    from rasterio.crs import CRS
    from rasterio.warp import transform_geom
    from shapely.geometry import mapping, shape

    def px(r0: int, r1: int, c0: int, c1: int):
        return box(500000 + 0.5 * c0, 5000000 - 0.5 * r1, 500000 + 0.5 * c1, 5000000 - 0.5 * r0)

    ref_utm = [px(5, 25, 5, 35), affinity.translate(px(40, 75, 10, 60), 0.5, 0), px(30, 36, 65, 78)]
    ref = [shape(transform_geom("EPSG:32631", "EPSG:3857", mapping(g))) for g in ref_utm]
    writer = FootprintWriter(tmp_path / "ref.gpkg", CRS.from_epsg(3857), REFERENCE_FIELDS)
    writer.write(ref, {"building_id": [1, 2, 3], "height_m": [7.0, 10.0, 4.0], "height_max_m": [8.0, 11.0, 4.0]})
    writer.close()
    res = CliRunner().invoke(cli, ["evaluate", "--pred", str(pred), "--buildings", str(tmp_path / "ref.gpkg"),
                                   "--pred-buildings", str(tmp_path / "b.gpkg"), "--out", str(tmp_path / "r.json"),
                                   "--quiet", "--no-plots"])
    assert res.exit_code == 0, res.output
    assert "building F1 (IoU ≥ 0.5)                    0.800" in res.output
    b = json.loads((tmp_path / "r.json").read_text())["buildings"]
    assert (b["n_predicted"], b["n_reference"], b["n_matched"]) == (2, 3, 2)
    assert b["height"]["mae"] == pytest.approx((1 + 5) / 2, abs=1e-3)
    assert b["spearman_std_vs_abs_error"] == pytest.approx(1.0)
    assert b["predicted"] == str(tmp_path / "b.gpkg")
    res = CliRunner().invoke(cli, ["evaluate", "--pred", str(pred), "--out", str(tmp_path / "r2.json")])
    assert res.exit_code != 0 and "--buildings" in res.output


def test_reference_geojson_in_projected_coordinates_without_crs_names_the_crs_to_declare(tmp_path: Path,
                                                                                         capsys) -> None:
    """A GeoJSON export in the project's CRS without a 'crs' member is read as WGS 84 (RFC 7946): one line
    naming the CRS to declare, not 'Error: unexpected' from PROJ."""
    cls = np.zeros((40, 40), np.uint8)
    cls[5:20, 5:20] = 2
    pred = write_prediction_layers(tmp_path / "pred", cls, np.where(cls == 2, 6.0, 0.0).astype(np.float32))
    ref = tmp_path / "ref.geojson"
    ring = [[500002.0, 4999990.0], [500008.0, 4999990.0], [500008.0, 4999996.0], [500002.0, 4999996.0],
            [500002.0, 4999990.0]]
    ref.write_text(json.dumps({"type": "FeatureCollection", "features": [
        {"type": "Feature", "properties": {"height_m": 6.0}, "geometry": {"type": "Polygon", "coordinates": [ring]}}]}))
    rc, _, err = run_cli(capsys, "evaluate", "--pred", pred, "--buildings", ref, "--out", tmp_path / "r.json",
                         "--quiet", "--no-plots")
    assert rc == 1 and "unexpected" not in err, err
    assert "--buildings" in err and "no 'crs' member" in err and "EPSG:32631" in err
    assert not (tmp_path / "r.json").exists()
