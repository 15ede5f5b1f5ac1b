"""Sanity checks that stop silent garbage, and inputs a user can type that must never be `Error: unexpected`.

Covers: a diverged training (NaN validation, NaN loss) never becomes best.pt and says how to go on;
checkpoints with NaN weights or an edited training state are refused with the file named; config values
out of range name the key path; swapped DSM/DTM, an empty tile set and an AOI that misses the raster are
errors with the numbers; GeoJSON without a ``crs`` member is WGS 84 and projected coordinates name the CRS
to declare; a full disk while saving names the path and leaves no partial file.
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers.cli import run_cli
from helpers.models import tiny_d3net
from helpers.rasters import write_raster
from helpers.tilefolder import write_tile_folder
from helpers.tmpfs import mount_tmpfs

from aerialmtl.errors import CheckpointError, ConfigError, InputError, NonFiniteError, OutputError
from aerialmtl.formats.checkpoint import load_checkpoint, save_checkpoint
from aerialmtl.training.config import TrainConfig
from aerialmtl.training.loop import train

CRS = "EPSG:32631"
TINY_MODEL = {"growth_rate": 4, "block_config": [1, 1, 1, 1], "num_init_features": 8, "bn_size": 2}


def tiny_cfg(**over: dict) -> TrainConfig:
    base = TrainConfig.from_dict({
        "model": TINY_MODEL, "data": {"batch_size": 4, "num_workers": 0}, "optim": {"lr": 2e-3},
        "schedule": {"epochs": 100, "log_every": 1}, "seed": 0, "device": "cpu",
    })
    return base.with_overrides(**over) if over else base


def one_error_line(result: tuple[int, str, str], *needles: str, code: int = 1) -> str:
    """Exit ``code`` with one ``Error:`` line (never `Error: unexpected`) holding every needle."""
    rc, out, err = result
    assert rc == code, (rc, out, err)
    assert "Traceback" not in err and "unexpected" not in err, err
    line = [ln for ln in err.splitlines() if ln.startswith("Error: ")]
    assert len(line) == 1, err
    for needle in needles:
        assert needle in line[0], (needle, line[0])
    return line[0]


@pytest.fixture(scope="module")
def tiles(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_tile_folder(tmp_path_factory.mktemp("t") / "tiles", size=64, counts={"train": 8, "val": 2})


def val_rows(log: Path) -> list[dict[str, str]]:
    with log.open() as fh:
        return [r for r in csv.DictReader(fh) if r["kind"] == "val"]


# ---- training: NaN never best, stops with what to do ------------------------------------------------
def test_nan_validation_stops_and_never_becomes_best(tiles: Path, tmp_path: Path,
                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    from aerialmtl.training.trainer import Trainer

    scores = iter([1.0, 0.8, math.nan])  # a validation every 2 steps; the 3rd diverges

    def fake_validate(self: Trainer) -> dict[str, float]:
        v = next(scores)
        return {"val_loss_height": v, "val_loss_classes": v}

    monkeypatch.setattr(Trainer, "validate", fake_validate)
    run = tmp_path / "r"
    with pytest.raises(NonFiniteError) as info:
        train(tiny_cfg(), tiles, run, progress=False)
    msg = str(info.value)
    assert "validation score at step 6 is nan" in msg and f"'{run / 'last.pt'}' (step 4)" in msg
    assert "optim.lr" in msg and "--resume" in msg
    best = load_checkpoint(run / "best.pt")[0]["train_state"]
    assert best["step"] == 4 and best["best_score"] == pytest.approx(1.6)
    assert load_checkpoint(run / "last.pt")[0]["train_state"]["step"] == 4  # the last whole checkpoint stays
    assert [r["step"] for r in val_rows(run / "log.csv")] == ["2", "4", "6"]  # the NaN row is logged


def test_validation_keeps_nan_batches_instead_of_scoring_them_zero(tiles: Path, tmp_path: Path,
                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    from aerialmtl.training.setup import prepare_training
    from aerialmtl.training.trainer import Trainer

    trainer = Trainer(prepare_training(tiny_cfg(), tiles, tmp_path / "r", progress=False), progress=False)
    try:
        real = trainer.objective.__call__

        def nan_height(out: dict, batch: dict, **kw: object) -> dict:  # kw: the trainer's scoring=True
            losses = real(out, batch, **kw)
            return {**losses, "height": losses["height"] * math.nan}

        monkeypatch.setattr(trainer, "objective", type("O", (), {"__call__": staticmethod(nan_height)})())
        metrics = trainer.validate()
    finally:
        trainer.close()
    assert math.isnan(metrics["val_loss_height"]) and math.isfinite(metrics["val_loss_classes"])


def test_nan_loss_stops_training_then_resume_with_lower_lr(tiles: Path, tmp_path: Path,
                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    from aerialmtl.training.trainer import Trainer

    real_step = Trainer.train_step

    def poisoned(self: Trainer, batch: dict) -> tuple:
        if self.state.step == 2:  # after the first validation (step 2) the weights blow up
            with torch.no_grad():
                next(self.model.parameters()).fill_(math.inf)
        return real_step(self, batch)

    monkeypatch.setattr(Trainer, "train_step", poisoned)
    run = tmp_path / "r"
    with pytest.raises(NonFiniteError, match=r"training diverged at step 3: the loss is nan") as info:
        train(tiny_cfg(), tiles, run, progress=False)
    assert f"'{run / 'last.pt'}' (step 2) is the last good state" in str(info.value)
    payload, _ = load_checkpoint(run / "last.pt")  # finite, loads
    assert payload["train_state"]["step"] == 2
    monkeypatch.setattr(Trainer, "train_step", real_step)
    res = train(tiny_cfg(optim={"lr": 2e-4}, schedule={"max_steps": 4}), tiles, run, resume=True, progress=False)
    assert res.step == 4 and math.isfinite(res.best_score)
    ts = load_checkpoint(run / "last.pt")[0]["train_state"]
    assert ts["optimizer"]["param_groups"][0]["lr"] == pytest.approx(2e-4)  # the config's lr, not the stored one


# ---- checkpoints: NaN weights, edited training state -----------------------------------------------
def test_checkpoint_with_nan_weights_is_refused_on_save_and_load(tmp_path: Path, capsys) -> None:
    model, meta = tiny_d3net()
    good = tmp_path / "good.pt"
    save_checkpoint(good, model, meta)
    with torch.no_grad():
        model.heads["height"].head.weight.view(-1)[0] = math.nan
    with pytest.raises(NonFiniteError, match=r"refusing to write checkpoint .*heads\.height\.head\.weight"):
        save_checkpoint(good, model, meta)
    load_checkpoint(good)  # unchanged
    assert sorted(p.name for p in tmp_path.iterdir()) == ["good.pt"]
    payload = torch.load(good, weights_only=True)
    key = next(k for k, v in payload["state_dict"].items() if v.is_floating_point())
    payload["state_dict"][key] = payload["state_dict"][key].clone().fill_(math.inf)
    bad = tmp_path / "bad.pt"
    torch.save(payload, bad)
    with pytest.raises(CheckpointError, match=rf"checkpoint '{bad}' holds NaN or inf weights \('{key}'\)"):
        load_checkpoint(bad)
    ortho = write_raster(tmp_path / "o.tif", np.full((3, 32, 32), 100, np.uint8), CRS)
    one_error_line(run_cli(capsys, "predict", ortho, "--model", bad, "--out", tmp_path / "p", "--quiet"),
                   f"checkpoint '{bad}'", "NaN or inf weights", "diverged")
    assert not (tmp_path / "p").exists() or not any((tmp_path / "p").iterdir())


def test_checkpoint_with_a_negative_batchnorm_variance_is_refused(tmp_path: Path, capsys) -> None:
    """An edited running_var < 0 gave NaN with the torch engine but finite garbage with OpenVINO (exit 0)."""
    model, meta = tiny_d3net()
    good = tmp_path / "good.pt"
    save_checkpoint(good, model, meta)
    payload = torch.load(good, weights_only=True)
    key = next(k for k in payload["state_dict"] if k.endswith("running_var"))
    payload["state_dict"][key] = payload["state_dict"][key].clone().fill_(-1.0)
    bad = tmp_path / "bad.pt"
    torch.save(payload, bad)
    with pytest.raises(CheckpointError, match=rf"'{bad}' holds a negative BatchNorm variance \('{key}'\)"):
        load_checkpoint(bad)
    ortho = write_raster(tmp_path / "o.tif", np.full((3, 32, 32), 100, np.uint8), CRS)
    for engine in ("torch", "openvino"):
        one_error_line(run_cli(capsys, "predict", ortho, "--model", bad, "--out", tmp_path / "p", "--quiet",
                               "--engine", engine), f"checkpoint '{bad}'", "negative BatchNorm variance")
    assert not (tmp_path / "p").exists()


def test_an_orthophoto_without_a_valid_pixel_is_predicted_with_a_warning(tmp_path: Path, capsys) -> None:
    """All nodata: a complete folder of nodata maps (a tile of a batch may be blank), but never silently."""
    model, meta = tiny_d3net()
    ckpt = tmp_path / "m.pt"
    save_checkpoint(ckpt, model, meta)
    ortho = write_raster(tmp_path / "o.tif", np.zeros((3, 32, 32), np.uint8), CRS, nodata=0)
    rc, _, err = run_cli(capsys, "predict", ortho, "--model", ckpt, "--out", tmp_path / "p", "--mc", "1", "--quiet")
    assert rc == 0 and "has no valid pixel" in err and "every layer in" in err, err


@pytest.fixture(scope="module")
def run_dir(tiles: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    run = tmp_path_factory.mktemp("run") / "run"
    train(tiny_cfg(schedule={"max_steps": 2}), tiles, run, progress=False)
    return run


def _edit(payload: dict, how: str) -> None:
    ts = payload["train_state"]
    if how == "optimizer":
        ts["optimizer"] = {"state": {}, "param_groups": "x"}
    elif how == "no_rng":
        del ts["rng"], ts["rng_ranks"]
    elif how == "rng":
        ts["rng"]["torch"] = torch.zeros(3, dtype=torch.uint8)
        ts["rng_ranks"] = [ts["rng"]]
    elif how == "step":
        ts["step"] = "twelve"
    elif how == "weights":
        key = next(iter(payload["state_dict"]))
        payload["state_dict"][key] = torch.zeros(1)
    elif how == "meta":
        payload["meta"]["model"]["growth_rate"] = 0
    elif how == "nan_optimizer":
        state = next(iter(ts["optimizer"]["state"].values()))
        state["exp_avg"].fill_(math.nan)


@pytest.mark.parametrize("how", ["optimizer", "no_rng", "rng", "step", "weights", "meta", "nan_optimizer"])
def test_hand_edited_checkpoint_on_resume_is_a_checkpoint_error(run_dir: Path, tmp_path: Path, capsys,
                                                                how: str) -> None:
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.yaml").write_bytes((run_dir / "config.yaml").read_bytes())
    payload = torch.load(run_dir / "last.pt", weights_only=True)
    _edit(payload, how)
    torch.save(payload, run / "last.pt")
    line = one_error_line(run_cli(capsys, "train", "--out", run, "--resume", "--max-steps", "4", "--quiet"),
                          f"checkpoint '{run / 'last.pt'}'")
    assert "model.growth_rate" in line if how == "meta" else True


# ---- config values ---------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "text, needles",
    [
        ("optim:\n  lr: .nan\n", ["optim.lr", "finite number", "nan"]),
        ("optim:\n  lr: 0\n", ["optim.lr", "(0, 1]", "2.0e-4"]),
        ("optim:\n  betas: [2, 3]\n", ["optim.betas", "[0, 1)", "[2.0, 3.0]"]),
        ("optim:\n  weight_decay: -.inf\n", ["optim.weight_decay", "finite"]),
        ("model:\n  growth_rate: 0\n", ["model.growth_rate", "≥ 1", "got 0"]),
        ("model:\n  block_config: [6, 0, 24, 16]\n", ["model.block_config", "≥ 1 layer"]),
        ("model:\n  compression: 0\n", ["model.compression", "(0, 1]"]),
        ("model:\n  dropout: .nan\n", ["model.dropout", "finite"]),
        ("loss:\n  class_weights: [0, 0, 0]\n", ["loss.class_weights", "at least one > 0"]),
        ("weighting:\n  task_weights: {height: -1}\n", ["weighting.task_weights.height", "≥ 0"]),
        ("schedule:\n  max_time_s: .inf\n", ["schedule.max_time_s", "finite"]),
        ("seed: -1\n", ["seed", "0..2**63-1"]),
    ],
)
def test_config_values_out_of_range_name_the_key_path(tmp_path: Path, capsys, text: str,
                                                      needles: list[str]) -> None:
    cfg = tmp_path / "bad.yaml"
    cfg.write_text(text)
    (tmp_path / "tiles").mkdir()
    one_error_line(run_cli(capsys, "train", "--config", cfg, "--data", tmp_path / "tiles", "--out", tmp_path / "run"),
                   "bad.yaml", *needles)
    assert not (tmp_path / "run").exists()


def test_config_ranges_hold_from_python_too() -> None:
    from aerialmtl.models.config import ModelConfig
    from aerialmtl.training.config import OptimSection

    with pytest.raises(ConfigError, match="optim.lr"):
        OptimSection(lr=math.nan)
    with pytest.raises(ConfigError, match="optim.betas"):
        OptimSection(betas=(0.9, math.nan))
    with pytest.raises(ConfigError, match="model.growth_rate"):
        ModelConfig(growth_rate=0)


# ---- tile: swapped DSM/DTM, empty tile set, AOI outside -------------------------------------------
def _ortho(tmp_path: Path, n: int = 64, **kw: object) -> Path:
    img = np.random.default_rng(0).integers(1, 255, (3, n, n)).astype(np.uint8)
    return write_raster(tmp_path / "ortho.tif", img, CRS, **kw)  # type: ignore[arg-type]


def _surfaces(tmp_path: Path, n: int = 64) -> tuple[Path, Path]:
    """(dsm, dtm): ground at 100 m with noise; buildings 8 m high on a quarter of the pixels."""
    rng = np.random.default_rng(3)
    dtm = (100 + rng.normal(0, 0.05, (n, n))).astype(np.float32)
    dsm = dtm + rng.normal(0, 0.05, (n, n)).astype(np.float32)
    dsm[8:24, 8:40] += 8.0
    dsm[40:56, 20:52] += 6.0
    return (write_raster(tmp_path / "dsm.tif", dsm, CRS), write_raster(tmp_path / "dtm.tif", dtm, CRS))


def test_swapped_dsm_and_dtm_are_refused_naming_the_swap(tmp_path: Path, capsys) -> None:
    ortho, (dsm, dtm) = _ortho(tmp_path), _surfaces(tmp_path)
    args = ["tile", "--ortho", ortho, "--size", "32", "--split-ratios", "1,0,0", "--quiet"]
    rc, _, err = run_cli(capsys, *args, "--dsm", dtm, "--dtm", dsm, "--out", tmp_path / "t")
    assert rc == 2 and "Traceback" not in err and "unexpected" not in err
    assert f"the DSM '{dtm}' lies below the DTM '{dsm}' on 100 %" in err and "probably swapped" in err
    assert "--dsm" in err and "--dtm" in err
    assert not (tmp_path / "t").exists()
    assert run_cli(capsys, *args, "--dsm", dsm, "--dtm", dtm, "--out", tmp_path / "ok")[0] == 0  # the right order
    flat = write_raster(tmp_path / "flat.tif", np.full((64, 64), 100.0, np.float32), CRS)  # bare ground: no verdict
    assert run_cli(capsys, *args, "--dsm", flat, "--dtm", flat, "--out", tmp_path / "flat")[0] == 0


def test_orthophoto_smaller_than_one_patch_gives_numbers_and_fix(tmp_path: Path, capsys) -> None:
    ortho = _ortho(tmp_path, n=40)
    ndsm = write_raster(tmp_path / "n.tif", np.ones((40, 40), np.float32), CRS)
    args = ["tile", "--ortho", ortho, "--ndsm", ndsm, "--split-ratios", "1,0,0", "--out", tmp_path / "t", "--quiet"]
    one_error_line(run_cli(capsys, *args, "--size", "64"), "tile set would be empty", "40 × 40 pixels",
                   "64-pixel patch", "39 % valid", "--min-valid 0.9", "--size 32")
    assert not (tmp_path / "t").exists()
    assert run_cli(capsys, *args, "--size", "32")[0] == 0


def test_no_valid_patch_is_an_error_with_the_counts(tmp_path: Path, capsys) -> None:
    img = np.zeros((3, 64, 64), np.uint8)
    img[:, :10, :10] = 50  # nodata everywhere but a corner
    ortho = write_raster(tmp_path / "o.tif", img, CRS, nodata=0)
    ndsm = write_raster(tmp_path / "n.tif", np.ones((64, 64), np.float32), CRS)
    one_error_line(run_cli(capsys, "tile", "--ortho", ortho, "--ndsm", ndsm, "--size", "32", "--split-ratios", "1,0,0",
                           "--out", tmp_path / "t", "--quiet"),
                   "of 4 windows of 32 pixels, 4 have fewer valid", "the best has 10 %", "--min-valid")
    assert not (tmp_path / "t").exists()


def geojson(path: Path, rings: list[list[tuple[float, float]]], crs: str | None = None, **props: object) -> Path:
    data: dict = {"type": "FeatureCollection", "features": [
        {"type": "Feature", "properties": dict(props), "geometry": {"type": "Polygon", "coordinates": [ring]}}
        for ring in rings]}
    if crs is not None:
        data["crs"] = {"type": "name", "properties": {"name": crs}}
    path.write_text(json.dumps(data))
    return path


def _square(x0: float, y0: float, side: float) -> list[tuple[float, float]]:
    return [(x0, y0), (x0 + side, y0), (x0 + side, y0 + side), (x0, y0 + side), (x0, y0)]


@pytest.fixture(scope="module")
def ckpt(tmp_path_factory: pytest.TempPathFactory) -> Path:
    model, meta = tiny_d3net()
    path = tmp_path_factory.mktemp("ckpt") / "model.pt"
    save_checkpoint(path, model, meta)
    return path


PREDICT = ("--mc", "2", "--window", "32", "--overlap", "0", "--precision", "fp32", "--quiet")


def test_aoi_outside_the_orthophoto_names_both_extents(tmp_path: Path, capsys, ckpt: Path) -> None:
    ortho = _ortho(tmp_path)  # (500000, 4999968, 500032, 5000000) in EPSG:32631
    aoi = geojson(tmp_path / "aoi.geojson", [_square(600000, 4000000, 50)], crs="EPSG:32631")
    rc, _, err = run_cli(capsys, "predict", ortho, "--model", ckpt, "--aoi", aoi, "--out", tmp_path / "p", *PREDICT)
    assert rc == 2 and "--aoi" in err and "Traceback" not in err
    assert "does not overlap the orthophoto" in err and "(600000, 4e+06, 600050, 4e+06)" in err.replace("4.00005e+06",
                                                                                                       "4e+06")
    assert "(500000, 5e+06, 500032, 5e+06)" in err.replace("4.99997e+06", "5e+06")
    assert not (tmp_path / "p" / "height.tif").exists()
    split = geojson(tmp_path / "split.geojson", [_square(600000, 4000000, 50)], crs="EPSG:32631", split="train")
    ndsm = write_raster(tmp_path / "n.tif", np.ones((64, 64), np.float32), CRS)
    rc, _, err = run_cli(capsys, "tile", "--ortho", ortho, "--ndsm", ndsm, "--split-aoi", split, "--size", "32",
                         "--out", tmp_path / "t", "--quiet")
    assert rc == 2 and "--split-aoi" in err and "does not overlap the orthophoto" in err and "600050" in err


def test_geojson_without_crs_is_wgs84_and_projected_coordinates_name_the_crs(tmp_path: Path, capsys,
                                                                             ckpt: Path) -> None:
    ortho = _ortho(tmp_path)
    from rasterio.warp import transform_bounds

    lon0, lat0, lon1, lat1 = transform_bounds(CRS, "EPSG:4326", 500000, 4999968, 500032, 5000000)
    wgs = geojson(tmp_path / "wgs.geojson", [[(lon0, lat0), (lon1, lat0), (lon1, lat1), (lon0, lat1), (lon0, lat0)]])
    assert run_cli(capsys, "predict", ortho, "--model", ckpt, "--aoi", wgs, "--out", tmp_path / "ok", *PREDICT)[0] == 0
    utm = geojson(tmp_path / "utm.geojson", [_square(500000, 4999968, 32)])  # an export without its crs member
    one_error_line(run_cli(capsys, "predict", ortho, "--model", ckpt, "--aoi", utm, "--out", tmp_path / "p", *PREDICT),
                   f"AOI (--aoi) '{utm}' has no 'crs' member", "WGS 84", "x 500000..500032", '"name": "EPSG:32631"',
                   "ogr2ogr -t_srs EPSG:4326")
    labels = geojson(tmp_path / "labels.geojson", [_square(500000, 4999968, 32)], cls=1)
    one_error_line(run_cli(capsys, "tile", "--ortho", ortho, "--labels-vector", labels, "--class-field", "cls",
                           "--classes", "synthetic", "--size", "32", "--out", tmp_path / "t", "--quiet"),
                   f"labels vector '{labels}' has no 'crs' member", "EPSG:32631")
    broken = tmp_path / "broken.geojson"
    broken.write_text(json.dumps({"type": "Polygon", "coordinates": [[1, 2]]}))
    rc, _, err = run_cli(capsys, "predict", ortho, "--model", ckpt, "--aoi", broken, "--out", tmp_path / "b", *PREDICT)
    assert rc in (1, 2) and "invalid geometry" in err and "unexpected" not in err


# ---- disk full -------------------------------------------------------------------------------------
@pytest.fixture
def small_fs(tmp_path: Path):
    """A 2 MiB tmpfs mounted in tmp_path."""
    yield from mount_tmpfs(tmp_path / "small", "size=2m")


def test_full_disk_while_saving_a_checkpoint_names_the_path(small_fs: Path) -> None:
    model, meta = tiny_d3net()
    (small_fs / "filler").write_bytes(b"\0" * (2 * 1024 * 1024 - 64 * 1024))  # leave 64 KiB
    target = small_fs / "last.pt"
    with pytest.raises(OutputError) as info:
        save_checkpoint(target, model, meta, {"big": torch.zeros(200_000)})
    msg = str(info.value)
    assert f"no space left on the device holding '{target}'" in msg and "free space" in msg
    assert sorted(p.name for p in small_fs.iterdir()) == ["filler"]  # no partial file, no temporary file


def test_full_disk_keeps_the_previous_checkpoint(small_fs: Path) -> None:
    model, meta = tiny_d3net()
    target = small_fs / "last.pt"
    save_checkpoint(target, model, meta)
    before = target.read_bytes()
    (small_fs / "filler").write_bytes(b"\0" * (2 * 1024 * 1024 - len(before) - 96 * 1024))
    with pytest.raises(OutputError, match="no space left"):
        save_checkpoint(target, model, meta, {"big": torch.zeros(200_000)})
    assert target.read_bytes() == before and load_checkpoint(target)


def test_os_errors_become_output_errors_naming_the_path(tmp_path: Path) -> None:
    import errno

    from aerialmtl.io.oserrors import writing

    for code, needle in ((errno.ENOSPC, "no space left"), (errno.EACCES, "not allowed"), (errno.EIO, "could not")):
        with pytest.raises(OutputError, match=needle) as info, writing(tmp_path / "x.gpkg", "buildings.gpkg"):
            raise OSError(code, "boom")
        assert str(tmp_path / "x.gpkg") in str(info.value)
    with pytest.raises(InputError), writing(tmp_path / "x", "x"):  # aerialmtl's own errors pass through
        raise InputError("mine")
    with pytest.raises(OutputError, match="no space left"), writing(tmp_path / "x", "x"):
        raise RuntimeError("sqlite3_exec() failed: database or disk is full; No space left on device")


# ---- predict: input type/range against the checkpoint, non-finite outputs ----------------------------------
@pytest.fixture(scope="module")
def ckpt8(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The tiny checkpoint recording 8-bit training images (mean 120/110/100, std 40)."""
    import dataclasses

    from aerialmtl.formats.checkpoint import value_envelope

    model, meta = tiny_d3net()
    meta = dataclasses.replace(meta, input_dtype="uint8", input_range=value_envelope(meta.mean, meta.std, "uint8"))
    path = tmp_path_factory.mktemp("ckpt8") / "model.pt"
    save_checkpoint(path, model, meta)
    return path


def _image(tmp_path: Path, name: str, data: np.ndarray, **kw: object) -> Path:
    return write_raster(tmp_path / name, data, CRS, **kw)  # type: ignore[arg-type]


def test_training_records_the_input_type_and_range(run_dir: Path) -> None:
    _, meta = load_checkpoint(run_dir / "last.pt")
    assert meta.input_dtype == "uint8"
    lo, hi = meta.input_range
    assert 0.0 <= lo < hi <= 255.0


@pytest.mark.parametrize("kind", ["uint16", "float01"])
def test_orthophoto_unlike_the_training_data_is_refused(tmp_path: Path, capsys, ckpt8: Path, kind: str) -> None:
    rng = np.random.default_rng(4)
    data = (rng.integers(100, 4000, (3, 64, 64)).astype(np.uint16) if kind == "uint16"
            else rng.uniform(0, 1, (3, 64, 64)).astype(np.float32))
    ortho = _image(tmp_path, f"{kind}.tif", data)
    out = tmp_path / "p"
    dtype = "uint16" if kind == "uint16" else "float32"
    one_error_line(run_cli(capsys, "predict", ortho, "--model", ckpt8, "--out", out, *PREDICT),
                   f"orthophoto '{ortho}' holds {dtype} values about", "trained on uint8 values about 0..240",
                   "times the training range", "--rescale-input")
    assert not (out / "height.tif").exists()
    rc, _, err = run_cli(capsys, "predict", ortho, "--model", ckpt8, "--out", out, "--rescale-input", *PREDICT)
    assert rc == 0 and "rescaling its values linearly" in err, err
    info = json.loads((out / "prediction.json").read_text())
    a, b = info["input_rescale"]
    assert a > 0 and math.isfinite(b)
    import rasterio

    with rasterio.open(out / "height.tif") as ds:
        assert np.isfinite(ds.read(1)).all()


def test_matching_or_same_range_inputs_predict_as_before(tmp_path: Path, capsys, ckpt8: Path, ckpt: Path) -> None:
    rng = np.random.default_rng(5)
    img = rng.integers(1, 255, (3, 64, 64)).astype(np.uint8)
    ok = _image(tmp_path, "u8.tif", img)
    rc, _, err = run_cli(capsys, "predict", ok, "--model", ckpt8, "--out", tmp_path / "a", *PREDICT)
    assert rc == 0 and not err.strip(), err
    as_float = _image(tmp_path, "f32.tif", img.astype(np.float32))  # 8-bit values stored as float32
    rc, _, err = run_cli(capsys, "predict", as_float, "--model", ckpt8, "--out", tmp_path / "b", *PREDICT)
    assert rc == 0 and "holds float32 values but the model was trained on uint8" in err
    wide = _image(tmp_path, "u16.tif", rng.integers(100, 4000, (3, 64, 64)).astype(np.uint16))
    assert run_cli(capsys, "predict", wide, "--model", ckpt, "--out", tmp_path / "c", *PREDICT)[0] == 0  # old ckpt


def test_non_finite_model_outputs_fail_the_run(tmp_path: Path, capsys) -> None:
    model, meta = tiny_d3net()
    bn = next(m for m in model.modules() if isinstance(m, torch.nn.BatchNorm2d))
    with torch.no_grad():  # finite weights, NaN activations: (x - 3e38) / sqrt(1e-5) overflows to -inf, the
        bn.running_mean.fill_(3e38)  # negative gamma makes it +inf past the ReLU, and the next convolution
        bn.running_var.fill_(1e-30)  # sums +inf and -inf into NaN
        bn.weight.fill_(-1.0)
    broken = tmp_path / "broken.pt"
    save_checkpoint(broken, model, meta)
    ortho = _image(tmp_path, "o.tif", np.random.default_rng(6).integers(1, 255, (3, 64, 64)).astype(np.uint8))
    out = tmp_path / "p"
    # torch propagates the NaN; OpenVINO's folded BatchNorm gives finite values here
    one_error_line(run_cli(capsys, "predict", ortho, "--model", broken, "--out", out, *PREDICT, "--engine", "torch"),
                   f"checkpoint '{broken}' gives NaN or inf", "no prediction was written")
    assert not out.exists() or not any(p.suffix in (".tif", ".json") for p in out.iterdir())


def test_full_disk_while_writing_a_geopackage_or_tiles(small_fs: Path, tmp_path: Path, capsys) -> None:
    from helpers.rasters import write_prediction_layers

    pytest.importorskip("pyogrio")
    cls = np.zeros((64, 64), np.uint8)
    cls[5:25, 5:25] = cls[35:60, 10:60] = 2  # two buildings of the synthetic scheme
    height = np.where(cls == 2, 8.0, 0.1).astype(np.float32)
    pred = write_prediction_layers(tmp_path / "pred", cls, height)
    ortho, ndsm = _ortho(tmp_path), write_raster(tmp_path / "n.tif", np.ones((64, 64), np.float32), CRS)
    (small_fs / "filler").write_bytes(b"\0" * (2 * 1024 * 1024 - 16 * 1024))  # leave 16 KiB
    gpkg = small_fs / "b.gpkg"
    one_error_line(run_cli(capsys, "buildings", pred, "--out", gpkg, "--quiet"),
                   f"no space left on the device holding '{gpkg}'", "--out")
    one_error_line(run_cli(capsys, "tile", "--ortho", ortho, "--ndsm", ndsm, "--size", "32", "--out", small_fs / "t",
                           "--quiet"), f"no space left on the device holding '{small_fs / 't'}'", "--out")
    assert sorted(p.name for p in small_fs.iterdir()) == ["filler"]  # nothing partial, nothing hidden


@pytest.mark.parametrize("args, needle", [
    (["tile", "--split-block", "inf"], "--split-block"),
    (["tile", "--split-seed", "-1"], "--split-seed"),
    (["evaluate", "--seed", "-1"], "--seed"),
])
def test_typed_option_values_are_usage_errors(tmp_path: Path, capsys, args: list[str], needle: str) -> None:
    ortho = _ortho(tmp_path)
    ndsm = write_raster(tmp_path / "n.tif", np.ones((64, 64), np.float32), CRS)
    if args[0] == "tile":
        full = [*args, "--ortho", ortho, "--ndsm", ndsm, "--out", tmp_path / "t", "--quiet"]
    else:
        from helpers.rasters import write_prediction_layers

        pred = write_prediction_layers(tmp_path / "pred", np.zeros((64, 64), np.uint8), np.ones((64, 64), np.float32))
        full = [*args, "--pred", pred, "--height", ndsm, "--out", tmp_path / "e.json", "--quiet"]
    rc, _, err = run_cli(capsys, *full)
    assert rc == 2 and needle in err and "unexpected" not in err, err


def test_geojson_properties_that_are_not_an_object(tmp_path: Path, capsys, ckpt: Path) -> None:
    aoi = tmp_path / "aoi.geojson"
    ring = _square(500000, 4999968, 32)
    aoi.write_text(json.dumps({"type": "FeatureCollection", "crs": {"type": "name", "properties": {"name": CRS}},
                               "features": [{"type": "Feature", "properties": [1],
                                             "geometry": {"type": "Polygon", "coordinates": [ring]}}]}))
    assert run_cli(capsys, "predict", _ortho(tmp_path), "--model", ckpt, "--aoi", aoi, "--out", tmp_path / "p",
                   *PREDICT)[0] == 0


@pytest.mark.parametrize("key, value, needle", [
    ("std", [-1.0, -1.0, -1.0], "std [-1.0, -1.0, -1.0] finite and > 0"),
    ("gsd", 0.0, "gsd must be a positive pixel size"),
    ("input_range", [5.0, 1.0], "input_range must be [low, high]"),
    ("input_dtype", "foo", "input_dtype 'foo' is not a data type"),
])
def test_edited_checkpoint_metadata_is_refused_on_load(tmp_path: Path, ckpt: Path, key: str, value: object,
                                                       needle: str) -> None:
    payload = torch.load(ckpt, weights_only=True)
    payload["meta"][key] = value
    bad = tmp_path / "bad.pt"
    torch.save(payload, bad)
    with pytest.raises(CheckpointError, match=rf"checkpoint '{bad}' has invalid metadata") as info:
        load_checkpoint(bad)
    assert needle in str(info.value)
    payload = torch.load(ckpt, weights_only=True)
    payload["format_version"] = "x"
    torch.save(payload, bad)
    with pytest.raises(CheckpointError, match="invalid format_version 'x'"):
        load_checkpoint(bad)


def test_full_disk_during_training_names_the_checkpoint_and_keeps_nothing_partial(small_fs: Path, tiles: Path) -> None:
    (small_fs / "filler").write_bytes(b"\0" * (2 * 1024 * 1024 - 160 * 1024))  # config + log fit, a checkpoint not
    run = small_fs / "run"
    with pytest.raises(OutputError, match=r"no space left on the device holding '.*run/(best|last)\.pt' while writing "
                                          r"the checkpoint"):
        train(tiny_cfg(schedule={"max_steps": 2}), tiles, run, progress=False)
    assert sorted(p.name for p in run.iterdir()) == ["config.yaml", "log.csv"]  # no partial or hidden checkpoint


@pytest.fixture
def ro_fs(tmp_path: Path):
    """A read-only tmpfs (EROFS even for root)."""
    yield from mount_tmpfs(tmp_path / "ro", "ro,size=1m")


def test_read_only_folder_while_saving_a_checkpoint_names_the_path(ro_fs: Path) -> None:
    model, meta = tiny_d3net()
    with pytest.raises(OutputError, match=rf"not allowed to write '{ro_fs / 'last.pt'}' \(the checkpoint\)"):
        save_checkpoint(ro_fs / "last.pt", model, meta)


def test_output_check_looks_only_at_valid_pixels() -> None:
    from aerialmtl.inference.sanity import check_finite_outputs
    from aerialmtl.models.mc_dropout import McStatistics

    valid = torch.ones(2, 8, 8, dtype=torch.bool)
    valid[1, :4] = False
    ok = McStatistics(height_mean=torch.rand(2, 8, 8), probs=torch.rand(2, 8, 8, 3))
    check_finite_outputs(ok, valid, "m.pt")
    ok.height_mean[1, 0, 0] = math.nan  # outside the valid pixels: not the model's fault
    ok.probs[1, 1, 1, 2] = math.nan
    check_finite_outputs(ok, valid, "m.pt")
    for field, index in (("height_mean", (0, 3, 3)), ("probs", (1, 6, 6, 0))):
        stats = McStatistics(height_mean=torch.rand(2, 8, 8), probs=torch.rand(2, 8, 8, 3))
        getattr(stats, field)[index] = -math.inf if field == "height_mean" else math.nan
        with pytest.raises(NonFiniteError, match="checkpoint 'm.pt' gives NaN or inf"):
            check_finite_outputs(stats, valid, "m.pt")


def test_input_rescale_is_part_of_the_provenance(tmp_path: Path, capsys, ckpt8: Path) -> None:
    wide = _image(tmp_path, "u16.tif", np.random.default_rng(8).integers(100, 4000, (3, 64, 64)).astype(np.uint16))
    out = tmp_path / "p"
    assert run_cli(capsys, "predict", wide, "--model", ckpt8, "--out", out, "--rescale-input", *PREDICT)[0] == 0
    settings = json.loads((out / "prediction.json").read_text())["provenance"]["settings"]
    assert len(settings["input_rescale"]) == 2
    rc, stdout, _ = run_cli(capsys, "predict", wide, "--model", ckpt8, "--out", out, "--rescale-input",
                            "--skip-existing", *PREDICT)
    assert rc == 0 and "skipped" in stdout
