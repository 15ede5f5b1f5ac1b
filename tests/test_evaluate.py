"""evaluate_prediction and `aerialmtl evaluate` on prediction folders written in tmp_path.

The prediction grid is 0.5 m pixels in UTM 31N just west of 6°E; the height reference is a tilted
plane at 1 m pixels in UTM 32N (another CRS and GSD), so bilinear reprojection reproduces it almost
exactly and the MAE must equal the offsets we added to the prediction.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import rasterio
import yaml
from affine import Affine
from click.testing import CliRunner
from helpers.rasters import write_raster
from rasterio.warp import transform as warp_transform
from rasterio.warp import transform_bounds

from aerialmtl.classes import IGNORE_INDEX, ClassScheme
from aerialmtl.cli import cli
from aerialmtl.cli.options import flags_for
from aerialmtl.errors import InputError, LabelError, OutputExistsError
from aerialmtl.evaluation.evaluate import CLASS_SCHEME_TAG, EvaluateOptions, evaluate_prediction

NODATA = -9999.0
W, H = 40, 32
PRED_CRS, REF_CRS = "EPSG:32631", "EPSG:32632"
PRED_TF = Affine(0.5, 0, 736300.0, 0, -0.5, 4987340.0)
SCHEME = ClassScheme.from_dict({
    "name": "toy", "ignore_codes": [0],
    "classes": [{"code": 1, "name": "ground"}, {"code": 2, "name": "building"}, {"code": 3, "name": "tree"}],
})


def _plane(x: np.ndarray, y: np.ndarray, x0: float, y0: float) -> np.ndarray:
    return 5.0 + 0.05 * (x - x0) - 0.03 * (y - y0)


def make_scene(tmp: Path, *, std: bool = True, tag: bool = True, probs: bool = True) -> dict:
    """Prediction folder + references; returns paths and the expected numbers computed from the arrays."""
    rng = np.random.default_rng(7)
    pred_dir = tmp / "pred"
    pred_dir.mkdir()
    # --- height reference: plane on a 1 m grid in UTM 32N covering the prediction with a margin
    left, bottom, right, top = transform_bounds(PRED_CRS, REF_CRS, 736300.0, 4987340.0 - H * 0.5,
                                                736300.0 + W * 0.5, 4987340.0)
    x0, y0 = math.floor(left) - 8, math.ceil(top) + 8
    rw, rh = int(right - x0) + 10, int(y0 - bottom) + 10
    cx, cy = np.meshgrid(x0 + 0.5 + np.arange(rw), y0 - 0.5 - np.arange(rh))
    write_raster(tmp / "ndsm_utm32.tif", _plane(cx, cy, x0, y0).astype(np.float32), crs=REF_CRS,
                 transform=Affine(1.0, 0, x0, 0, -1.0, y0), nodata=NODATA)
    # --- predicted height: the plane at prediction pixel centres + known offsets
    px, py = np.meshgrid(736300.0 + 0.25 + 0.5 * np.arange(W), 4987340.0 - 0.25 - 0.5 * np.arange(H))
    qx, qy = warp_transform(PRED_CRS, REF_CRS, px.ravel(), py.ravel())
    truth = _plane(np.array(qx), np.array(qy), x0, y0).reshape(H, W)
    offset = np.full((H, W), 0.5)
    offset[:8, :10] = -2.0
    height = (truth + offset).astype(np.float32)
    height[-1, :] = NODATA  # prediction nodata → not counted
    write_raster(pred_dir / "height.tif", height, crs=PRED_CRS, transform=PRED_TF, nodata=NODATA)
    if std:
        sd = np.abs(offset).astype(np.float32)
        sd[-1, :] = NODATA
        write_raster(pred_dir / "height_std.tif", sd, crs=PRED_CRS, transform=PRED_TF, nodata=NODATA)
    # --- labels: raw codes 0..3 on a 1 m grid in the same CRS; prediction = upsampled indices with errors
    codes = rng.integers(0, 4, (H // 2, W // 2)).astype(np.uint8)
    write_raster(tmp / "labels.tif", codes, crs=PRED_CRS, transform=Affine(1.0, 0, 736300.0, 0, -1.0, 4987340.0))
    ref_idx = SCHEME.remap(np.kron(codes, np.ones((2, 2), np.uint8)))
    pred_idx = np.where(ref_idx == IGNORE_INDEX, 0, ref_idx).astype(np.uint8)
    wrong = np.zeros((H, W), bool)
    wrong[:, :6] = True
    pred_idx[wrong] = (pred_idx[wrong] + 1) % 3
    tags = {CLASS_SCHEME_TAG: json.dumps(SCHEME.to_dict())} if tag else {}
    with rasterio.open(pred_dir / "classes.tif", "w", driver="GTiff", width=W, height=H, count=1, dtype="uint8",
                       crs=PRED_CRS, transform=PRED_TF, nodata=IGNORE_INDEX) as dst:
        dst.write(pred_idx, 1)
        dst.update_tags(**tags)
    write_raster(pred_dir / "class_entropy.tif", np.where(wrong, 1.0, 0.1).astype(np.float32),
                 crs=PRED_CRS, transform=PRED_TF, nodata=NODATA)
    write_raster(pred_dir / "class_mutual_info.tif", np.where(wrong, 0.5, 0.05).astype(np.float32),
                 crs=PRED_CRS, transform=PRED_TF, nodata=NODATA)
    if probs:
        p = np.zeros((3, H, W), np.float32)
        for k in range(3):
            p[k] = np.where(pred_idx == k, np.where(wrong, 0.4, 1.0), np.where(wrong, 0.3, 0.0))
        write_raster(pred_dir / "class_probabilities.tif", p, crs=PRED_CRS, transform=PRED_TF, nodata=NODATA)
    labelled = ref_idx != IGNORE_INDEX
    valid_h = np.ones((H, W), bool)
    valid_h[-1, :] = False
    return {
        "pred": pred_dir, "ndsm": tmp / "ndsm_utm32.tif", "labels": tmp / "labels.tif",
        "mae": float(np.abs(offset[valid_h]).mean()), "bias": float(offset[valid_h].mean()),
        "n_height": int(valid_h.sum()), "n_labelled": int(labelled.sum()),
        "oa": 1 - (wrong & labelled).sum() / labelled.sum(),
        "ece": 0.4 * (wrong & labelled).sum() / labelled.sum(),
        "ref_idx": ref_idx, "pred_idx": pred_idx,
    }


def test_reference_in_other_crs_and_gsd_gives_known_mae(tmp_path: Path) -> None:
    s = make_scene(tmp_path)
    rep = evaluate_prediction(s["pred"], height_ref=s["ndsm"], out=tmp_path / "ev" / "report.json")
    h = rep["height"]
    assert h["n_pixels"] == s["n_height"]
    assert h["mae"] == pytest.approx(s["mae"], abs=0.01)
    assert h["bias"] == pytest.approx(s["bias"], abs=0.01)
    assert h["median_abs_error"] == pytest.approx(0.5, abs=0.01)
    u = rep["uncertainty"]["height_std"]
    assert u["sparsification"]["ause"] < 0.01  # std equals the error magnitude
    assert u["sparsification"]["aurg"] > 0.1
    assert u["spearman_std_vs_abs_error"] > 0.5
    assert rep["classes"] is None


def test_the_unfamiliarity_layer_is_scored_against_the_errors_per_height_bin(tmp_path: Path) -> None:
    """A user opens unfamiliarity.tif to find the misses: evaluate says whether it ranks the height errors
    within each reference-height bin (here it is high exactly where the prediction is off by 2 m)."""
    s = make_scene(tmp_path)
    with rasterio.open(s["pred"] / "height.tif") as src:
        height = src.read(1)
    u = np.full(height.shape, 0.1, np.float32)
    u[:8, :10] = 0.9  # where the offset is -2 m instead of +0.5 m
    u += np.linspace(0, 0.01, u.size, dtype=np.float32).reshape(u.shape)  # no ties: every pixel ranked
    u[height == NODATA] = NODATA
    write_raster(s["pred"] / "unfamiliarity.tif", u, crs=PRED_CRS, transform=PRED_TF, nodata=NODATA)
    out = tmp_path / "ev" / "report.json"
    rep = evaluate_prediction(s["pred"], height_ref=s["ndsm"], out=out)
    un = rep["uncertainty"]["unfamiliarity"]
    # 80 of 1240 pixels are off by 2 m: a two-level layer that flags exactly them reaches ρ ≈ 0.3
    assert un["n_sampled"] == s["n_height"] and un["spearman_vs_abs_error"] > 0.2
    assert [b["range_m"][0] for b in un["bins"]] == [b["range_m"][0] for b in rep["height"]["per_bin"]]
    assert "## Unfamiliarity per reference-height bin" in (tmp_path / "ev" / "report.md").read_text()
    flipped = np.where(u == NODATA, NODATA, 1.0 - u).astype(np.float32)  # high where the prediction is right
    write_raster(s["pred"] / "unfamiliarity.tif", flipped, crs=PRED_CRS, transform=PRED_TF, nodata=NODATA)
    rep = evaluate_prediction(s["pred"], height_ref=s["ndsm"], out=tmp_path / "ev2" / "report.json")
    assert rep["uncertainty"]["unfamiliarity"]["spearman_vs_abs_error"] < -0.2


def test_report_files_json_markdown_and_plots(tmp_path: Path) -> None:
    s = make_scene(tmp_path)
    out = tmp_path / "ev" / "report.json"
    evaluate_prediction(s["pred"], height_ref=s["ndsm"], labels_ref=s["labels"], out=out)
    data = json.loads(out.read_text())  # strict JSON: nan written as null
    assert data["height"]["mae"] == pytest.approx(s["mae"], abs=0.01)
    assert data["height"]["per_bin"][-1]["range_m"][1] is None  # open-ended last bin
    md = (tmp_path / "ev" / "report.md").read_text()
    assert "height MAE" in md and "mIoU" in md
    strata = data["uncertainty"]["height_std"]["strata"]["bins"]  # per bin: ranks the misses? follows the height?
    assert all("spearman_std_vs_predicted_height" in b for b in strata if b["n_pixels"])
    assert "| Spearman | vs height |" in md
    pytest.importorskip("matplotlib")
    plots = {"report_sparsification.png", "report_confusion.png", "report_reliability.png",
             "report_height_reliability.png"}
    for name in plots:
        assert (tmp_path / "ev" / name).stat().st_size > 1000
    assert set(data["plots"]) == plots


def test_classes_from_tag_confusion_ece_and_entropy(tmp_path: Path) -> None:
    s = make_scene(tmp_path)
    rep = evaluate_prediction(s["pred"], labels_ref=s["labels"], out=None)
    c = rep["classes"]
    assert c["n_pixels"] == s["n_labelled"]  # code 0 is an ignore code
    assert c["overall_accuracy"] == pytest.approx(s["oa"])
    labelled = s["ref_idx"] != IGNORE_INDEX
    expected_cm = np.zeros((3, 3), int)
    np.add.at(expected_cm, (s["ref_idx"][labelled], s["pred_idx"][labelled]), 1)
    assert c["confusion_matrix"] == expected_cm.tolist()
    assert list(c["per_class"]) == ["ground", "building", "tree"]
    u = rep["uncertainty"]
    assert u["calibration"]["ece"] == pytest.approx(s["ece"], abs=1e-6)
    assert u["class_entropy"]["sparsification"]["ause"] == pytest.approx(0.0, abs=1e-9)
    assert u["class_mutual_info"]["sparsification"]["aurg"] > 0


def test_streaming_in_small_bands_and_subsample_give_the_same_exact_metrics(tmp_path: Path) -> None:
    s = make_scene(tmp_path)
    full = evaluate_prediction(s["pred"], height_ref=s["ndsm"], labels_ref=s["labels"], out=None)
    small = evaluate_prediction(
        s["pred"], height_ref=s["ndsm"], labels_ref=s["labels"], out=None,
        options=EvaluateOptions(block_pixels=3 * W, sample_size=200, seed=5),
    )
    assert small["height"]["mae"] == pytest.approx(full["height"]["mae"])
    assert small["height"]["rmse"] == pytest.approx(full["height"]["rmse"])
    assert small["classes"]["confusion_matrix"] == full["classes"]["confusion_matrix"]
    assert small["uncertainty"]["calibration"]["ece"] == pytest.approx(full["uncertainty"]["calibration"]["ece"])
    assert small["sampling"]["height_sampled"] == 200 and small["height"]["median_exact"] is False
    assert full["height"]["median_exact"] is True


def test_per_class_height_errors_with_labels(tmp_path: Path) -> None:
    s = make_scene(tmp_path)
    rep = evaluate_prediction(s["pred"], height_ref=s["ndsm"], labels_ref=s["labels"], out=None)
    per = rep["height"]["per_class"]
    assert sum(v["n_pixels"] for v in per.values()) <= rep["height"]["n_pixels"]
    for v in per.values():
        assert 0.49 < v["mae"] < 2.01


def test_missing_uncertainty_files_are_skipped_with_notes(tmp_path: Path) -> None:
    s = make_scene(tmp_path, std=False, probs=False)
    rep = evaluate_prediction(s["pred"], height_ref=s["ndsm"], labels_ref=s["labels"], out=None)
    assert "height_std" not in rep["uncertainty"] and "calibration" not in rep["uncertainty"]
    assert any("height_std.tif" in n for n in rep["notes"])
    assert any("class_probabilities.tif" in n for n in rep["notes"])
    assert rep["height"]["mae"] == pytest.approx(s["mae"], abs=0.01)


def test_unknown_label_codes_raise_unless_ignored(tmp_path: Path) -> None:
    s = make_scene(tmp_path)
    with rasterio.open(s["labels"], "r+") as dst:
        arr = dst.read(1)
        arr[0, 0] = 9
        dst.write(arr, 1)
    with pytest.raises(LabelError, match="9"):
        evaluate_prediction(s["pred"], labels_ref=s["labels"], out=None)
    rep = evaluate_prediction(
        s["pred"], labels_ref=s["labels"], out=None, options=EvaluateOptions(ignore_unknown_codes=True),
    )
    assert rep["classes"]["n_pixels"] == s["n_labelled"] - (1 if s["ref_idx"][0, 0] != IGNORE_INDEX else 0) * 4


def test_scheme_from_option_when_tag_missing(tmp_path: Path) -> None:
    s = make_scene(tmp_path, tag=False)
    with pytest.raises(InputError, match="pass classes with the scheme"):
        evaluate_prediction(s["pred"], labels_ref=s["labels"], out=None)
    yml = tmp_path / "toy.yaml"
    yml.write_text(yaml.safe_dump(SCHEME.to_dict()))
    rep = evaluate_prediction(s["pred"], labels_ref=s["labels"], classes=yml, out=None)
    assert rep["classes"]["overall_accuracy"] == pytest.approx(s["oa"])


def test_a_scheme_other_than_the_predictions_is_refused(tmp_path: Path) -> None:
    """--classes with other class names than classes.tif's scheme scored class k as another class (exit 0)."""
    s = make_scene(tmp_path)
    other = ClassScheme.from_dict({"name": "other", "ignore_codes": [0], "classes": [
        {"code": 1, "name": "water"}, {"code": 2, "name": "building"}, {"code": 3, "name": "tree"}]})
    with pytest.raises(InputError, match=r"not the one the prediction was made with \(ground, building, tree"):
        evaluate_prediction(s["pred"], labels_ref=s["labels"], classes=other, out=None)
    recoded = ClassScheme.from_dict({"name": "toy", "ignore_codes": [0], "classes": [  # same classes, other codes
        {"code": 1, "name": "ground"}, {"code": 2, "name": "building"}, {"code": 3, "name": "tree"}]})
    assert evaluate_prediction(s["pred"], labels_ref=s["labels"], classes=recoded, out=None)["classes"]


def test_refuses_to_overwrite_and_rejects_bad_inputs(tmp_path: Path) -> None:
    s = make_scene(tmp_path)
    out = tmp_path / "report.json"
    evaluate_prediction(s["pred"], height_ref=s["ndsm"], out=out, options=EvaluateOptions(plots=False))
    with pytest.raises(OutputExistsError, match="overwrite=True"):
        evaluate_prediction(s["pred"], height_ref=s["ndsm"], out=out)
    evaluate_prediction(
        s["pred"], height_ref=s["ndsm"], out=out, overwrite=True, options=EvaluateOptions(plots=False),
    )
    with pytest.raises(InputError, match="does not exist"):
        evaluate_prediction(tmp_path / "nope", height_ref=s["ndsm"], out=None)
    with pytest.raises(InputError, match="no reference"):
        evaluate_prediction(s["pred"], out=None)


def test_cli_prints_headline_and_writes_report(tmp_path: Path) -> None:
    s = make_scene(tmp_path)
    out = tmp_path / "cli" / "report.json"
    args = ["evaluate", "--pred", str(s["pred"]), "--height", str(s["ndsm"]), "--labels", str(s["labels"]),
            "--height-bins", "0,2,6,inf", "--no-plots", "--out", str(out)]
    res = CliRunner().invoke(cli, args)
    assert res.exit_code == 0, res.output
    assert "height MAE (m)" in res.output and "mIoU" in res.output
    data = json.loads(out.read_text())
    assert [b["range_m"][0] for b in data["height"]["per_bin"]] == [0.0, 2.0, 6.0]
    assert data["classes"]["overall_accuracy"] == pytest.approx(s["oa"])
    again = CliRunner().invoke(cli, args)
    # refused like every command's outputs
    assert again.exit_code == 1 and "--overwrite" in again.exception.render(flags_for("evaluate"))


@pytest.mark.parametrize(
    ("extra", "message"),
    [([], "at least one reference"), (["--height", "X", "--height-threshold", "-1"], "--height-threshold"),
     (["--height", "X", "--height-bins", "5,2"], "--height-bins")],
)
def test_cli_bad_options(tmp_path: Path, extra: list[str], message: str) -> None:
    (tmp_path / "pred").mkdir()
    (tmp_path / "X").touch()  # raster inputs are checked to exist first (a missing one is its own usage error)
    res = CliRunner().invoke(cli, ["evaluate", "--pred", str(tmp_path / "pred"), "--out",
                                   str(tmp_path / "r.json"), *[str(tmp_path / e) if e == "X" else e for e in extra]])
    assert res.exit_code == 2
    assert message in res.output


def test_height_only_prediction_uses_labels_for_per_class_errors_when_scheme_given(tmp_path: Path) -> None:
    s = make_scene(tmp_path)
    for name in ("classes.tif", "class_entropy.tif", "class_mutual_info.tif", "class_probabilities.tif"):
        (s["pred"] / name).unlink()
    rep = evaluate_prediction(s["pred"], height_ref=s["ndsm"], labels_ref=s["labels"], out=None)
    assert rep["classes"] is None and "per_class" not in rep["height"]
    assert any("per-class height errors skipped" in n for n in rep["notes"])
    rep = evaluate_prediction(s["pred"], height_ref=s["ndsm"], labels_ref=s["labels"], classes=SCHEME, out=None)
    assert list(rep["height"]["per_class"]) == ["ground", "building", "tree"]
    with pytest.raises(InputError, match="nothing to evaluate"):
        evaluate_prediction(s["pred"], labels_ref=s["labels"], classes=SCHEME, out=None)
