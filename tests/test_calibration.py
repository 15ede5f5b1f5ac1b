"""Calibration fitted on validation: a known compression is undone; checkpoints carry it; predict applies it."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import rasterio
import torch
from helpers.rasters import write_raster
from helpers.tilefolder import toy_patch, write_tile_folder

from aerialmtl.formats.checkpoint import load_checkpoint, load_model, save_checkpoint
from aerialmtl.inference.predict import predict_raster
from aerialmtl.models.calibration import Calibration, fit_calibration
from aerialmtl.models.spread_fit import interval_coverage
from aerialmtl.training.config import TrainConfig
from aerialmtl.training.loop import train


def _compressed(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Reference heights (many low, a tail of tall) and predictions squeezed to 40 % of them, with noise."""
    ref = np.where(rng.random(n) < 0.7, rng.random(n) * 1.0, 2.0 + rng.gamma(2.0, 4.0, n))
    noise = rng.normal(0.0, 0.5, n)
    pred = np.maximum(0.4 * ref + noise, 0.0)
    std = np.full(n, 0.05)  # over-confident MC spread
    return pred, ref, std


@pytest.mark.parametrize("method", ["isotonic", "median", "quantile"])
def test_known_compression_is_undone_on_new_pixels(method: str) -> None:
    rng = np.random.default_rng(0)
    cal = fit_calibration(*_compressed(rng, 40_000), method=method)  # type: ignore[arg-type]
    pred, ref, std = _compressed(rng, 40_000)
    tall = ref >= 2.0
    assert (pred - ref)[tall].mean() < -5.0  # the compression: tall pixels ~6 m too low
    h = cal.height(pred)
    assert abs(float((h - ref)[tall].mean())) < 1.0
    assert np.abs(h - ref).mean() < 0.6 * np.abs(pred - ref).mean()
    assert np.all(np.diff(cal.height_y) >= 0) and h.min() >= 0.0
    # spread: ±1 σ covers 68 % of the new pixels (±2 σ less than a Gaussian's 95 %: the errors are heavy-tailed)
    cov = interval_coverage(np.abs(h - ref), cal.std(std, pred))
    assert 0.62 < cov["within_1sigma"] < 0.74 and cov["within_2sigma"] > 0.8
    # the device path (predict's stitcher) gives the same heights
    np.testing.assert_allclose(cal.height_torch(torch.from_numpy(pred)).numpy(), h, rtol=1e-6, atol=1e-6)


def test_spread_covers_per_range_of_predicted_height_not_only_on_average() -> None:
    """Errors of 0.3 m on the ground and 6 m on tall pixels, one constant MC spread: one factor for all would
    cover the ground at ~100 % and tall pixels far less; per range each covers ~68 %."""
    rng = np.random.default_rng(3)
    n = 60_000
    ref = np.where(rng.random(n) < 0.6, rng.uniform(0, 0.5, n), rng.uniform(5, 25, n))
    pred = ref + rng.normal(0, np.where(ref > 1, 6.0, 0.3))
    std = np.full(n, 0.5)
    cal = fit_calibration(pred, ref, std, "isotonic")
    assert cal.std_edges and cal.spread_applied
    p2 = ref + rng.normal(0, np.where(ref > 1, 6.0, 0.3))  # new pixels
    err, sigma = np.abs(cal.height(p2) - ref), cal.std(std, p2)
    for sel in (p2 < 1.0, p2 >= 10.0):
        assert 0.6 < interval_coverage(err[sel], sigma[sel])["within_1sigma"] < 0.76
    torch_sigma = cal.std_torch(torch.from_numpy(std.astype(np.float32)), torch.from_numpy(p2.astype(np.float32)))
    np.testing.assert_allclose(torch_sigma.numpy(), sigma, rtol=1e-5)  # the stitcher's path agrees


def test_a_part_that_does_not_help_on_held_out_validation_is_not_applied() -> None:
    """Accurate predictions: the map's bins (64 equal-count bins, each its mean) can only add error, so the
    cross-fitted check keeps heights as they are; a compressed model's map is kept. Old calibrations (no flags)
    stay applied."""
    rng = np.random.default_rng(4)
    n = 40_000
    ref = rng.uniform(0, 30, n)
    folds = (np.arange(n) // 500) % 2  # whole "patches" of 500 pixels
    good = ref + rng.normal(0, 0.05, n)
    std = np.abs(good - ref) + rng.uniform(0, 0.3, n)  # a spread that already ranks and covers
    cal = fit_calibration(good, ref, std, "isotonic", folds=folds)
    assert not cal.height_applied and "height map off" in cal.notes
    np.testing.assert_array_equal(cal.height(good), good)
    np.testing.assert_array_equal(cal.height_torch(torch.from_numpy(good)).numpy(), good)
    squeezed = 0.4 * good
    cal2 = fit_calibration(squeezed, ref, std, "isotonic", folds=folds)
    assert cal2.height_applied and np.abs(cal2.height(squeezed) - ref).mean() < np.abs(squeezed - ref).mean()
    assert Calibration((0.0, 1.0), (0.0, 2.0)).height_applied  # checkpoints written before the flags


def test_spread_of_confident_ground_gets_a_floor() -> None:
    rng = np.random.default_rng(1)
    n = 20_000
    err = np.abs(rng.normal(0.0, 1.0, n))
    std = np.where(rng.random(n) < 0.5, 1e-8, 0.02)  # half the pixels: every MC sample alike
    cal = Calibration((0.0, 1.0), (0.0, 1.0))
    scale, floor = __import__("aerialmtl.models.spread_fit", fromlist=["fit_spread"]).fit_spread(err, std)
    cal = dataclasses.replace(cal, std_scale=scale, std_floor=floor)
    cov = interval_coverage(err, cal.std(std))
    assert floor > 0.1 and abs(cov["within_1sigma"] - 0.683) < 0.02 and cov["within_2sigma"] > 0.85


def test_map_continues_beyond_the_knots() -> None:
    cal = Calibration((0.0, 1.0, 4.0), (0.5, 2.0, 10.0), std_scale=2.0)
    np.testing.assert_allclose(cal.height(np.array([-1.0, 0.5, 4.0, 6.0])), [0.5, 1.25, 10.0, 12.0])
    np.testing.assert_allclose(cal.std(np.array([1.5])), [3.0])
    with pytest.raises(ValueError):
        Calibration((0.0, 0.0), (1.0, 2.0))


def test_a_validation_of_bare_ground_calibrates_no_tall_height_and_no_spread() -> None:
    """Validation all ground (the reference never reaches 1 m), the model predicting up to 1.2 m there: the
    map it fits ("everything is ground") must not shift the heights it never saw (it shifted a 10 m roof
    down by a metre, slope 1 beyond the last knot), and a spread fitted on centimetre errors must not shrink
    every interval."""
    rng = np.random.default_rng(7)
    n = 40_000
    ref = rng.uniform(0.0, 0.1, n)
    pred = np.clip(ref + rng.gamma(1.0, 0.3, n), 0.0, 1.2)
    std = rng.uniform(0.2, 0.6, n)
    folds = (np.arange(n) // 500) % 2
    cal = fit_calibration(pred, ref, std, "isotonic", folds=folds)
    assert cal.height_applied  # below 1 m the map is supported: it pulls the ground down
    assert cal.height_limit == 1.0 and "heights ≥ 1 m keep no calibration" in cal.unsupported
    tall = np.array([1.0, 2.0, 5.0, 10.0, 40.0])
    np.testing.assert_array_equal(cal.height(tall), tall)
    np.testing.assert_allclose(cal.height_torch(torch.from_numpy(tall)).numpy(), tall)
    assert np.all(np.diff(cal.height(np.linspace(0.0, 3.0, 301))) >= 0)  # still monotone across the cut
    assert not cal.spread_applied and "spread map off" in cal.unsupported
    np.testing.assert_array_equal(cal.std(np.full(5, 0.4), tall), np.full(5, 0.4))
    # enough tall pixels: the map and the spread reach them again
    ref2 = np.where(rng.random(n) < 0.5, ref, rng.uniform(2.0, 30.0, n))
    cal2 = fit_calibration(0.5 * ref2, ref2, std, "isotonic", folds=folds)
    assert cal2.height_limit is None and not cal2.unsupported and cal2.spread_applied
    assert cal2.height(np.array([10.0]))[0] > 15.0


def test_tall_heights_above_the_supported_range_keep_no_spread_factor() -> None:
    """Validation reaches 5 m often but 10 m rarely (< MIN_SUPPORT_PIXELS): ranges from 10 m up keep factor 1."""
    from aerialmtl.models.calibration import MIN_SUPPORT_PIXELS, support_limit

    rng = np.random.default_rng(8)
    n = 30_000
    ref = np.concatenate([rng.uniform(0, 0.5, n - 3000), rng.uniform(5.0, 9.0, 3000 - 50), rng.uniform(10, 12, 50)])
    assert support_limit(ref) == 10.0 and 50 < MIN_SUPPORT_PIXELS
    pred = ref + rng.normal(0, 0.5, ref.size)
    cal = fit_calibration(pred, ref, np.full(ref.size, 0.01), "isotonic")
    assert cal.spread_applied and 10.0 in cal.std_edges
    np.testing.assert_allclose(cal.std(np.array([0.01, 0.01]), np.array([11.0, 30.0])), [0.01, 0.01])
    assert cal.std(np.array([0.01]), np.array([6.0]))[0] > 0.1  # below the limit the spread is widened
    np.testing.assert_array_equal(cal.height(np.array([10.0, 25.0])), [10.0, 25.0])


def _flatten_val_heights(root: Path, height: float = 0.3) -> None:
    """Make every validation patch bare ground (``height`` metres everywhere) and say so in the manifest."""
    import csv

    manifest = root / "manifest.csv"
    with manifest.open(newline="") as fh:
        reader = csv.DictReader(fh)
        fields, rows = reader.fieldnames, list(reader)
    for row in rows:
        if row["split"] == "val":
            with rasterio.open(root / row["height_path"], "r+") as dst:
                dst.write(np.full((1, dst.height, dst.width), height, np.float32))
            row.update(height_min=height, height_mean=height, height_max=height)
    with manifest.open("w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(fields or []))
        writer.writeheader()
        writer.writerows(rows)


def test_train_with_a_validation_of_bare_ground_says_so_and_calibrates_no_tall_height(tmp_path: Path) -> None:
    """A run whose validation split holds no pixel ≥ 2 m (its images show buildings, its heights say ground):
    best.pt calibrates no height ≥ 2 m and scales no spread, and `train` says so on one line."""
    import yaml
    from click.testing import CliRunner

    from aerialmtl.cli import cli

    tiles = write_tile_folder(tmp_path / "tiles", size=64, counts={"train": 4, "val": 2}, tasks=("height",))
    _flatten_val_heights(tiles)
    cfg = tmp_path / "c.yaml"
    cfg.write_text(yaml.safe_dump(_cfg("densenet121").to_dict()))
    res = CliRunner().invoke(cli, ["train", "--config", str(cfg), "--data", str(tiles), "--out", str(tmp_path / "run"),
                                   "--max-steps", "2", "--quiet", "--device", "cpu"])
    assert res.exit_code == 0, res.output
    lines = [ln for ln in res.output.splitlines() if ln.startswith("warning: calibration:")]
    assert len(lines) == 1 and "keep no calibration" in lines[0] and "--split-block" in lines[0], res.output
    cal = load_checkpoint(tmp_path / "run" / "best.pt")[1].calibration
    assert cal is not None and cal.height_limit is not None and cal.height_limit <= 2.0
    tall = np.array([2.0, 4.0, 8.0, 30.0])
    np.testing.assert_array_equal(cal.height(tall), tall)
    np.testing.assert_array_equal(cal.std(np.full(4, 0.5), tall), np.full(4, 0.5))
    assert not cal.spread_applied


# ---- end to end ---------------------------------------------------------------------------------
def _cfg(encoder: str) -> TrainConfig:
    model = ({"growth_rate": 4, "block_config": [1, 1, 1, 1], "num_init_features": 8, "bn_size": 2}
             if encoder == "densenet121" else {"encoder": encoder})
    return TrainConfig.from_dict({"model": model, "data": {"batch_size": 4, "num_workers": 0},
                                  "schedule": {"epochs": 100, "log_every": 1}, "seed": 0, "device": "cpu",
                                  "calibration": {"mc_samples": 4}})


@pytest.fixture(scope="module")
def tiles(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_tile_folder(tmp_path_factory.mktemp("cal") / "tiles", size=64, counts={"train": 4, "val": 2},
                             tasks=("height",))


@pytest.mark.slow
@pytest.mark.parametrize("encoder", ["densenet121", "efficientnet_lite0"])
def test_checkpoints_of_both_encoders_round_trip_through_predict(encoder: str, tiles: Path, tmp_path: Path) -> None:
    res = train(_cfg(encoder), tiles, tmp_path / "run", max_steps=2, progress=False)
    _, meta = load_checkpoint(res.best_checkpoint)
    assert meta.model.encoder == encoder and meta.calibration is not None and meta.calibration.n_pixels > 0
    image, _, _ = toy_patch(np.random.default_rng(5), 64)
    ortho = write_raster(tmp_path / "o.tif", image.astype(np.uint8))
    on = predict_raster(ortho, res.best_checkpoint, tmp_path / "on", mc=4, progress=False)
    off = predict_raster(ortho, res.best_checkpoint, tmp_path / "off", mc=4, progress=False, calibration=False)
    info_on = json.loads((on.out_dir / "prediction.json").read_text())["calibration"]
    info_off = json.loads((off.out_dir / "prediction.json").read_text())["calibration"]
    cal = meta.calibration
    assert info_on["height_map_applied"] is cal.height_applied and info_on["spread_map_applied"] is cal.spread_applied
    assert info_on["applied"] is (cal.height_applied or cal.spread_applied) and info_off["applied"] is False
    assert "validation MAE" in info_on["summary"]  # what the cross-fitted check said
    with rasterio.open(on.out_dir / "height.tif") as a, rasterio.open(off.out_dir / "height.tif") as b:
        raw, cal = b.read(1), a.read(1)
    np.testing.assert_allclose(cal, meta.calibration.height(raw), rtol=1e-5, atol=1e-4)


def test_an_old_checkpoint_without_calibration_predicts_uncalibrated(tmp_path: Path) -> None:
    from helpers.models import tiny_d3net

    model, meta = tiny_d3net()
    path = tmp_path / "old.pt"
    save_checkpoint(path, model, meta)
    payload = torch.load(path, weights_only=True)
    for key in ("calibration", "normalization"):  # what checkpoints written before these fields hold
        payload["meta"].pop(key)
    torch.save(payload, path)
    _, loaded = load_model(path)
    assert loaded.calibration is None and loaded.normalization == "dataset" and loaded.model.encoder == "densenet121"
    cal = Calibration((0.0, 10.0), (0.0, 20.0), 1.5, n_pixels=1)
    save_checkpoint(path, model, dataclasses.replace(meta, calibration=cal))
    assert load_checkpoint(path)[1].calibration == cal


# ---- the spread fit's score, and the validation pixels it is fitted on -------------------------------------
def test_the_spread_fit_scores_spreads_by_the_gaussian_crps_of_the_evaluation() -> None:
    """The score the spread fit minimises is the evaluation's Gaussian CRPS (its 1 cm floor included), whatever
    the spread: tiny, zero, huge."""
    from aerialmtl.evaluation.uncertainty import crps_gaussian
    from aerialmtl.models.spread_fit import mean_crps

    rng = np.random.default_rng(1)
    err = np.abs(rng.normal(0.0, 2.0, 5000))
    sigma = np.concatenate([rng.gamma(2.0, 1.0, 4990), [0.0, 1e-9, 1e-4, 0.005, 0.01, 0.02, 0.5, 3.0, 50.0, 1e4]])
    want = float(crps_gaussian(np.zeros_like(err), sigma, err, min_std=0.01).mean())
    assert mean_crps(err, sigma) == pytest.approx(want, rel=1e-12)


def test_the_spread_fit_finds_the_factor_the_errors_were_drawn_with() -> None:
    """Errors drawn from N(0, (2.5·std)² + 0.3²): the fitted spread scores as well as the true one (within 0.2 %
    of its CRPS) and its factor is the true one within 12 %; where the spread says nothing of the errors, a
    floor carries the fit and scores as well as the best constant spread (within 0.5 %)."""
    from aerialmtl.evaluation.uncertainty import crps_gaussian
    from aerialmtl.models.spread_fit import fit_spread_crps

    def crps(err: np.ndarray, sigma: np.ndarray) -> float:
        return float(crps_gaussian(np.zeros_like(err), sigma, err, min_std=0.01).mean())

    rng = np.random.default_rng(2)
    n = 40_000
    std = rng.lognormal(0.0, 0.5, n)
    true = np.hypot(2.5 * std, 0.3)
    err = np.abs(rng.normal(0.0, true))
    scale, floor = fit_spread_crps(err, std)
    assert crps(err, np.hypot(scale * std, floor)) <= 1.002 * crps(err, true) < crps(err, std)
    assert 2.2 < scale < 2.8
    unrelated = rng.random(n)
    err = np.abs(rng.normal(0.0, 1.5, n))
    scale, floor = fit_spread_crps(err, unrelated)
    assert floor > 1.0 and crps(err, np.hypot(scale * unrelated, floor)) <= 1.005 * crps(err, np.full(n, 1.5))


def test_validation_pixels_read_back_in_groups_are_the_pixels_of_each_batch(tmp_path: Path,
                                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    """The MC predictions stay on the device for several batches before their valid pixels are read back: the
    pixels, their order and their patch indices are those read back batch by batch (10 patches in batches of 4:
    groups of 8 patches and a last group of one short batch; invalid pixels left out)."""
    import csv

    from helpers.models import tiny_d3net

    from aerialmtl.training import calibrate

    tiles = write_tile_folder(tmp_path / "tiles", size=32, counts={"train": 1, "val": 10}, tasks=("height",))
    with (tiles / "manifest.csv").open(newline="") as fh:
        val = [row["height_path"] for row in csv.DictReader(fh) if row["split"] == "val"]
    for i, name in enumerate(val):  # no height in a corner of each patch, a corner as wide as its number
        with rasterio.open(tiles / name, "r+") as dst:
            heights = dst.read(1)
            heights[:i, :i] = dst.nodata
            dst.write(heights, 1)
    model, meta = tiny_d3net()
    runs = {}
    for group in (4, 8):  # 4: one batch per read-back, as before the grouping
        monkeypatch.setattr(calibrate, "READ_BACK_PATCHES", group)
        runs[group] = calibrate.validation_pixels(model, meta, tiles, mc=3, batch_size=4)
    for a, b in zip(runs[4], runs[8]):
        np.testing.assert_array_equal(a, b)
    pred, ref, std, patch = runs[8]
    assert np.array_equal(np.unique(patch), np.arange(10)) and np.all(np.diff(patch) >= 0)
    np.testing.assert_array_equal(np.bincount(patch), [32 * 32 - i * i for i in range(10)])
    assert pred.size == ref.size == std.size and np.all(np.isfinite(ref)) and ref.min() > -1


def test_a_run_whose_last_validation_was_its_best_calibrates_its_network_once(tiles: Path, tmp_path: Path,
                                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    """best.pt and last.pt of a 2-step run hold the same network: its validation pixels are predicted once and
    both checkpoints carry the same calibration (the one fitted on it)."""
    from aerialmtl.training import calibrate

    calls = []
    real = calibrate.validation_pixels

    def counted(*args, **kwargs):  # type: ignore[no-untyped-def]
        calls.append(args[2])
        return real(*args, **kwargs)

    monkeypatch.setattr(calibrate, "validation_pixels", counted)
    res = train(_cfg("densenet121"), tiles, tmp_path / "run", max_steps=2, progress=False)
    best, last = load_checkpoint(res.best_checkpoint)[1], load_checkpoint(res.last_checkpoint)[1]
    assert len(calls) == 1 and best.calibration is not None and best.calibration.n_pixels > 0
    assert last.calibration == best.calibration


def test_checkpoints_hold_the_same_weights_only_when_every_weight_is_equal(tmp_path: Path) -> None:
    from helpers.models import tiny_d3net

    from aerialmtl.formats.checkpoint import same_weights

    model, meta = tiny_d3net()
    save_checkpoint(tmp_path / "a.pt", model, meta)
    save_checkpoint(tmp_path / "b.pt", model, dataclasses.replace(meta, calibration=Calibration((0.0, 1.0), (0.0, 2.0),
                                                                                              1.0, n_pixels=1)))
    assert same_weights(tmp_path / "a.pt", tmp_path / "b.pt")  # other records may differ
    with torch.no_grad():
        next(model.parameters()).view(-1)[0] += 1e-6
    save_checkpoint(tmp_path / "c.pt", model, meta)
    assert not same_weights(tmp_path / "a.pt", tmp_path / "c.pt")
    other, other_meta = tiny_d3net(k=3)
    save_checkpoint(tmp_path / "d.pt", other, other_meta)
    assert not same_weights(tmp_path / "a.pt", tmp_path / "d.pt")
    save_checkpoint(tmp_path / "e.pt", model, dataclasses.replace(meta, mean=(0.0, 0.0, 0.0)))
    assert not same_weights(tmp_path / "c.pt", tmp_path / "e.pt")


def _ground_with_missed_trees(seed: int, n: int = 60_000) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Validation pixels like a small real area's: ``(pred, ref, std, folds)``, whole patches of 500 pixels.

    Two thirds ground predicted within centimetres with an MC spread of decimetres, and among them 0.2 % trees the
    network missed (predicted ~0 m, 8–20 m tall); a third objects of 3–30 m predicted with metres of error.
    """
    rng = np.random.default_rng(seed)
    ground = rng.random(n) < 2 / 3
    ref = np.where(ground, 0.0, rng.uniform(3.0, 30.0, n))
    pred = np.where(ground, np.abs(rng.normal(0.0, 0.03, n)), ref + rng.normal(0.0, 3.0, n)).clip(0.0)
    std = np.where(ground, rng.uniform(0.3, 0.8, n), rng.uniform(1.0, 4.0, n))
    missed = ground & (rng.random(n) < 0.002)
    ref = np.where(missed, rng.uniform(8.0, 20.0, n), ref)
    return pred, ref, std, (np.arange(n) // 500) % 2


def test_a_few_missed_trees_do_not_switch_the_spread_map_off() -> None:
    """On confident ground the CRPS alone would choose a spread of millimetres, the few trees the network missed
    then lie hundreds of σ away, and the cross-fitted NLL check switched the whole spread map off (autzen_west:
    NLL 3.4 → 600 on every seed). The fit keeps to spreads whose NLL is no worse than the raw spread's: the map is
    applied, and it lowers the CRPS and the NLL of new pixels of the same kind."""
    from aerialmtl.models.spread_fit import fit_spread_crps, mean_crps, mean_nll

    pred, ref, std, folds = _ground_with_missed_trees(5)
    err = np.abs(pred - ref)
    ground = pred < 1.0
    scale, floor = fit_spread_crps(err[ground], std[ground])  # the CRPS's own optimum: millimetres
    assert mean_nll(err[ground], np.hypot(scale * std[ground], floor)) > mean_nll(err[ground], std[ground])
    scale, floor = fit_spread_crps(err[ground], std[ground], nll_bound=True)
    assert mean_nll(err[ground], np.hypot(scale * std[ground], floor)) <= mean_nll(err[ground], std[ground])
    cal = fit_calibration(pred, ref, std, "isotonic", folds=folds)
    assert cal.spread_applied, cal.notes
    p2, r2, s2, _ = _ground_with_missed_trees(6)
    e2, sigma = np.abs(p2 - r2), cal.std(s2, p2)
    assert mean_crps(e2, sigma) < mean_crps(e2, s2) and mean_nll(e2, sigma) < mean_nll(e2, s2)
