"""Robustness: every command ends in success, a one-line error (exit 1, 2 for usage) or a warned fallback.

Each case runs the command line as a user does (``aerialmtl.cli.main`` in-process, or ``python -m
aerialmtl`` in a subprocess where a real process is needed for signals) on tiny GeoTIFFs written in
``tmp_path`` with a real CRS, and checks the exit code, that stderr holds one line naming the file or
option, the value and the fix (no traceback), and the outputs where the command must work. The numbers
in the section titles are those of the project's robustness checklist (README, "Troubleshooting").
"""

from __future__ import annotations

import json
import os
import pickle
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
import rasterio
import torch
import yaml
from affine import Affine
from helpers.cli import run_cli
from helpers.models import TINY, tiny_d3net
from helpers.rasters import write_raster
from rasterio.warp import transform_bounds

from aerialmtl.cli import main
from aerialmtl.errors import AlignmentError
from aerialmtl.formats.checkpoint import load_checkpoint, save_checkpoint
from aerialmtl.formats.prediction import ALL_FILES
from aerialmtl.io.cog import cog_problems

CRS = "EPSG:32631"
T05 = Affine(0.5, 0, 500000.0, 0, -0.5, 5000000.0)  # 0.5 m pixels, the tiny checkpoint's GSD
PREDICT = ("--mc", "2", "--window", "32", "--overlap", "0", "--precision", "fp32", "--quiet")
MAIN_OUTPUTS = ("height.tif", "height_std.tif", "classes.tif", "class_entropy.tif", "class_mutual_info.tif",
                "prediction.json")


# ---- helpers ------------------------------------------------------------------------------------
run = run_cli


def assert_error(result: tuple[int, str, str], *needles: str, code: int = 1) -> str:
    """Exit ``code``, one ``Error:`` line on stderr containing every needle, no traceback.

    Usage errors (exit 2) keep click's format: the usage line and a ``--help`` hint before the error line.
    """
    rc, out, err = result
    assert rc == code, (rc, out, err)
    assert "Traceback" not in err
    lines = [line for line in err.splitlines() if line.strip()]
    if code == 2:
        assert lines[0].startswith("Usage: ") and "--help" in lines[1], err
        lines = lines[2:]
    assert len(lines) == 1 and lines[0].startswith("Error: "), err
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])
    return lines[0]


def assert_ok(result: tuple[int, str, str]) -> list[str]:
    """Exit 0 and no error; returns the stderr lines (warnings)."""
    rc, out, err = result
    assert rc == 0, (out, err)
    assert "Traceback" not in err and "Error" not in err
    lines = [line for line in err.splitlines() if line.strip()]
    assert all(line.startswith("warning: ") for line in lines), err
    return lines


def read(path: Path) -> np.ndarray:
    with rasterio.open(path) as ds:
        return ds.read(1)


def rgb(tmp_path: Path, name: str = "ortho.tif", size: tuple[int, int] = (64, 64), seed: int = 0, **kw: object) -> Path:
    img = np.random.default_rng(seed).integers(1, 255, (3, *size)).astype(np.uint8)
    return write_raster(tmp_path / name, img, CRS, kw.pop("transform", T05), **kw)  # type: ignore[arg-type]


def no_final_outputs(out: Path) -> bool:
    return not any((out / f).exists() for f in ALL_FILES)


@pytest.fixture(scope="module")
def ckpt(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A tiny D3-Net checkpoint: bands 1,2,3 (r, g, b), 0.5 m, 4 classes of the synthetic scheme, dropout."""
    model, meta = tiny_d3net()
    path = tmp_path_factory.mktemp("ckpt") / "model.pt"
    save_checkpoint(path, model, meta)
    return path


def tiny_train_yaml(path: Path) -> Path:
    cfg = {"model": {k: list(v) if isinstance(v, tuple) else v for k, v in TINY.items()},
           "data": {"batch_size": 2, "num_workers": 0}, "schedule": {"log_every": 1}, "device": "cpu"}
    path.write_text(yaml.safe_dump(cfg))
    return path


# ---- 1. orthophoto without CRS or geotransform ------------------------------------------------------
@pytest.mark.parametrize("missing", ["CRS", "geotransform"])
@pytest.mark.parametrize("command", ["predict", "tile"])
def test_ortho_without_crs_or_geotransform(tmp_path: Path, capsys, ckpt: Path, missing: str, command: str) -> None:
    path = tmp_path / "ortho.tif"
    profile = dict(driver="GTiff", width=32, height=32, count=3, dtype="uint8")
    if missing == "geotransform":
        profile["crs"] = CRS
    with warnings.catch_warnings():  # rasterio warns that the file will not be georeferenced: the point here
        warnings.simplefilter("ignore")
        with rasterio.open(path, "w", **profile) as dst:
            dst.write(np.ones((3, 32, 32), np.uint8))
    ndsm = write_raster(tmp_path / "ndsm.tif", np.ones((32, 32), np.float32), CRS, T05)
    args = (["predict", path, "--model", ckpt, "--out", tmp_path / "out", *PREDICT] if command == "predict" else
            ["tile", "--ortho", path, "--ndsm", ndsm, "--size", "32", "--out", tmp_path / "out", "--quiet"])
    assert_error(run(capsys, *args), f"orthophoto '{path}' has no {missing}", "gdal_edit.py")
    assert not (tmp_path / "out").exists()


def test_debug_shows_the_traceback_instead(tmp_path: Path, ckpt: Path) -> None:
    path = tmp_path / "ortho.tif"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with rasterio.open(path, "w", driver="GTiff", width=32, height=32, count=3, dtype="uint8") as dst:
            dst.write(np.ones((3, 32, 32), np.uint8))
    with pytest.raises(AlignmentError, match="no CRS"):
        main(["--debug", "predict", str(path), "--model", str(ckpt), "--out", str(tmp_path / "out")])


# ---- 2. layers that do not overlap -------------------------------------------------------------------
def test_layers_that_do_not_overlap(tmp_path: Path, capsys) -> None:
    ortho = rgb(tmp_path)
    far = write_raster(tmp_path / "dsm.tif", np.ones((10, 10), np.float32), CRS, Affine(1, 0, 600000.0, 0, -1, 4e6))
    dtm = write_raster(tmp_path / "dtm.tif", np.zeros((64, 64), np.float32), CRS, T05)
    line = assert_error(run(capsys, "tile", "--ortho", ortho, "--dsm", far, "--dtm", dtm, "--out", tmp_path / "t",
                            "--size", "32", "--quiet"), f"DSM '{far}' does not overlap", "same area")
    assert "(600000, 3.99999e+06" in line and "(500000, 4.99997e+06, 500032, 5e+06)" in line  # both footprints
    assert not (tmp_path / "t").exists()


# ---- 3. layers in different CRS (works) -------------------------------------------------------------
def test_layers_in_another_crs_are_reprojected(tmp_path: Path, capsys) -> None:
    ortho = rgb(tmp_path)
    left, bottom, right, top = transform_bounds(CRS, "EPSG:4326", 499990.0, 4999958.0, 500042.0, 5000010.0)
    t4326 = Affine((right - left) / 40, 0, left, 0, -(top - bottom) / 40, top)
    ndsm = write_raster(tmp_path / "ndsm_wgs84.tif", np.full((40, 40), 7.5, np.float32), "EPSG:4326", t4326)
    out = tmp_path / "t"
    assert_ok(run(capsys, "tile", "--ortho", ortho, "--ndsm", ndsm, "--size", "64", "--split-ratios", "1,0,0",
                  "--out", out, "--quiet"))
    (patch,) = (out / "train" / "height").glob("*.tif")
    with rasterio.open(patch) as ds:
        assert ds.crs == CRS and ds.transform == T05  # on the orthophoto's grid, not the nDSM's
        np.testing.assert_allclose(ds.read(1), 7.5, rtol=1e-6)  # every pixel covered and valid


# ---- 4. band count different from the checkpoint's ----------------------------------------------------
def test_fewer_bands_than_the_checkpoint_is_an_error(tmp_path: Path, capsys, ckpt: Path) -> None:
    two = write_raster(tmp_path / "two.tif", np.ones((2, 32, 32), np.uint8), CRS, T05)
    assert_error(run(capsys, "predict", two, "--model", ckpt, "--out", tmp_path / "p", *PREDICT),
                 f"orthophoto '{two}'", "band(s) [3]", "checkpoint (trained on bands [1, 2, 3] (r, g, b))",
                 "has 2 band(s)", "tile --bands")
    assert not (tmp_path / "p").exists()


def test_extra_bands_are_ignored_with_a_warning(tmp_path: Path, capsys, ckpt: Path) -> None:
    rng = np.random.default_rng(0)
    four = write_raster(tmp_path / "four.tif", rng.integers(1, 255, (4, 32, 32)).astype(np.uint8), CRS, T05,
                        photometric="MINISBLACK")  # 4 plain bands (uint8 RGBA would make the 4th an alpha)
    (warning,) = assert_ok(run(capsys, "predict", four, "--model", ckpt, "--out", tmp_path / "p", *PREDICT))
    assert "has 4 bands" in warning and "ignores band(s) [4]" in warning
    assert (read(tmp_path / "p" / "height.tif") != -9999.0).all()


def test_tile_bands_outside_the_file(tmp_path: Path, capsys) -> None:
    ortho = rgb(tmp_path)
    ndsm = write_raster(tmp_path / "n.tif", np.ones((64, 64), np.float32), CRS, T05)
    assert_error(run(capsys, "tile", "--ortho", ortho, "--ndsm", ndsm, "--bands", "1,2,5", "--out", tmp_path / "t",
                     "--quiet"), "band(s) [5] requested by --bands", "has 3 band(s)", "within 1..3")
    assert_error(run(capsys, "tile", "--ortho", ortho, "--ndsm", ndsm, "--bands", "0,1", "--out", tmp_path / "t"),
                 "--bands", "'0,1'", code=2)


# ---- 5. 16-bit, 4-band (RGBN) orthophotos, bands chosen at tiling ---------------------------------------
@pytest.fixture(scope="module")
def rgbn_run(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """uint16 RGBN ortho + nDSM + labels → `tile --bands 4,1,2` → `train` 1 step (through the CLI)."""
    root = tmp_path_factory.mktemp("rgbn")
    rng = np.random.default_rng(5)
    img = rng.integers(100, 4000, (4, 64, 64)).astype(np.uint16)
    img[:, :8, :8] = 0  # nodata corner
    paths = {
        "ortho": write_raster(root / "rgbn.tif", img, CRS, T05, nodata=0, photometric="MINISBLACK"),
        "ndsm": write_raster(root / "ndsm.tif", rng.uniform(0, 20, (64, 64)).astype(np.float32), CRS, T05),
        "labels": write_raster(root / "labels.tif", rng.integers(1, 6, (64, 64)).astype(np.uint8), CRS, T05),
        "tiles": root / "tiles", "run": root / "run", "config": tiny_train_yaml(root / "tiny.yaml"),
    }
    for args in (["tile", "--ortho", paths["ortho"], "--ndsm", paths["ndsm"], "--labels", paths["labels"],
                  "--classes", "synthetic", "--bands", "4,1,2", "--size", "32", "--min-valid", "0.5",
                  "--split-ratios", "1,0,0", "--out", paths["tiles"], "--quiet"],
                 ["train", "--config", paths["config"], "--data", paths["tiles"], "--out", paths["run"],
                  "--max-steps", "1", "--quiet"]):
        try:
            main([str(a) for a in args])
        except SystemExit as exc:  # pragma: no cover - shows why the fixture failed
            raise AssertionError(f"{args[0]} failed with exit code {exc.code}") from exc
    return paths


def test_16bit_rgbn_with_bands_selected_works_end_to_end(rgbn_run: dict[str, Path], tmp_path: Path, capsys) -> None:
    info = yaml.safe_load((rgbn_run["tiles"] / "dataset.yaml").read_text())
    assert info["bands"] == [4, 1, 2] and info["dtype"] == "uint16" and max(info["mean"]) > 255
    (patch, *_) = sorted((rgbn_run["tiles"] / "train" / "image").glob("*.tif"))
    with rasterio.open(patch) as ds:
        assert ds.count == 3 and ds.dtypes[0] == "uint16"
    _, meta = load_checkpoint(rgbn_run["run"] / "last.pt")
    assert meta.bands == (4, 1, 2)
    out = tmp_path / "pred"
    (warning,) = assert_ok(run(capsys, "predict", rgbn_run["ortho"], "--model", rgbn_run["run"] / "last.pt",
                               "--out", out, *PREDICT))
    assert "bands [4, 1, 2]" in warning and "ignores band(s) [3]" in warning
    h, c = read(out / "height.tif"), read(out / "classes.tif")
    assert h.shape == (64, 64) and (h[:8, :8] == -9999.0).all() and (c[:8, :8] == 255).all()
    assert np.isfinite(h).all() and (h[8:, 8:] != -9999.0).all() and (c[8:, 8:] < 6).all()


# ---- 6. RGBA: alpha → nodata ------------------------------------------------------------------------------
@pytest.mark.parametrize("gsd", [0.5, 0.25])  # on the model's grid, and resampled to it
def test_rgba_alpha_becomes_nodata(tmp_path: Path, capsys, ckpt: Path, gsd: float) -> None:
    n = int(16 / gsd)  # 16 m × 16 m
    rng = np.random.default_rng(1)
    img = rng.integers(1, 255, (4, n, n)).astype(np.uint8)
    img[3] = 255
    img[3, : n // 2, : n // 2] = 0  # transparent top-left quarter
    ortho = write_raster(tmp_path / "rgba.tif", img, CRS, Affine(gsd, 0, 500000.0, 0, -gsd, 5000000.0),
                         photometric="RGB", alpha="YES")
    lines = assert_ok(run(capsys, "predict", ortho, "--model", ckpt, "--out", tmp_path / "p", *PREDICT))
    assert len(lines) == (1 if gsd != 0.5 else 0)  # the resampling warning only
    for name, nodata in (("height.tif", -9999.0), ("class_entropy.tif", -9999.0), ("classes.tif", 255)):
        arr = read(tmp_path / "p" / name)
        assert arr.shape == (32, 32)
        assert (arr[:16, :16] == nodata).all() and (arr[16:, :] != nodata).all() and (arr[:, 16:] != nodata).all()


# ---- 7. NaN and nodata holes in DSM/DTM --------------------------------------------------------------------
def test_nan_and_nodata_holes_in_dsm_dtm_are_masked(tmp_path: Path, capsys) -> None:
    ortho = rgb(tmp_path)
    dtm = np.full((64, 64), 100.0, np.float32)
    dtm[5:9, 5:9] = np.nan
    dsm = np.full((64, 64), 112.0, np.float32)
    dsm[20:22, 30:33] = -32768.0
    write_raster(tmp_path / "dsm.tif", dsm, CRS, T05, nodata=-32768.0)
    write_raster(tmp_path / "dtm.tif", dtm, CRS, T05)  # NaN holes without a nodata value
    out = tmp_path / "t"
    assert_ok(run(capsys, "tile", "--ortho", ortho, "--dsm", tmp_path / "dsm.tif", "--dtm", tmp_path / "dtm.tif",
                  "--size", "64", "--min-valid", "0", "--split-ratios", "1,0,0", "--out", out, "--quiet"))
    (patch,) = (out / "train" / "height").glob("*.tif")
    h = read(patch)
    hole = np.zeros((64, 64), bool)
    hole[5:9, 5:9] = hole[20:22, 30:33] = True
    assert (h[hole] == -9999.0).all() and np.allclose(h[~hole], 12.0)


# ---- 8. label codes missing from the class scheme ------------------------------------------------------------
def test_label_codes_missing_from_the_scheme(tmp_path: Path, capsys) -> None:
    ortho = rgb(tmp_path)
    codes = np.random.default_rng(2).integers(1, 7, (64, 64)).astype(np.uint8)
    codes[40, 40] = 42
    labels = write_raster(tmp_path / "labels.tif", codes, CRS, T05)
    args = ["tile", "--ortho", ortho, "--labels", labels, "--classes", "synthetic", "--size", "32",
            "--split-ratios", "1,0,0", "--out", tmp_path / "t", "--quiet"]
    assert_error(run(capsys, *args), f"labels '{labels}'", "codes 42", "'synthetic'", "--ignore-unknown-codes")
    assert not (tmp_path / "t").exists()  # the failed run left no half dataset that would block a re-run
    assert_ok(run(capsys, *args, "--ignore-unknown-codes"))
    assert read(tmp_path / "t" / "train" / "classes" / "r000032_c000032.tif")[8, 8] == 255


# ---- 9. smaller than one tile, and 1 × 1 --------------------------------------------------------------------
@pytest.mark.parametrize("shape", [(40, 50), (1, 1)])
def test_raster_smaller_than_one_tile_predicts(tmp_path: Path, capsys, ckpt: Path, shape: tuple[int, int]) -> None:
    ortho = rgb(tmp_path, size=shape)
    out = tmp_path / "p"
    assert_ok(run(capsys, "predict", ortho, "--model", ckpt, "--out", out, "--mc", "2", "--window", "64",
                  "--overlap", "16", "--precision", "fp32", "--quiet"))
    for name in MAIN_OUTPUTS[:-1]:
        with rasterio.open(out / name) as ds:
            assert ds.shape == shape and ds.transform == T05
            assert (ds.read(1) != ds.nodata).all()


def test_one_pixel_raster_tiles_into_one_padded_patch(tmp_path: Path, capsys) -> None:
    ortho = rgb(tmp_path, size=(1, 1))
    ndsm = write_raster(tmp_path / "n.tif", np.full((1, 1), 3.0, np.float32), CRS, T05)
    assert_ok(run(capsys, "tile", "--ortho", ortho, "--ndsm", ndsm, "--size", "32", "--min-valid", "0",
                  "--split-ratios", "1,0,0", "--out", tmp_path / "t", "--quiet"))
    (patch,) = (tmp_path / "t" / "train" / "height").glob("*.tif")
    h = read(patch)
    assert h.shape == (32, 32) and h[0, 0] == 3.0 and (h.ravel()[1:] == -9999.0).all()


# ---- 10. truncated / corrupt TIFF ---------------------------------------------------------------------------
@pytest.mark.parametrize("damage", ["truncated", "garbage"])
def test_corrupt_ortho_in_predict(tmp_path: Path, capsys, ckpt: Path, damage: str) -> None:
    good = rgb(tmp_path, "good.tif", size=(96, 96))
    data = good.read_bytes()
    bad = tmp_path / "bad.tif"
    bad.write_bytes(data[: len(data) // 2] if damage == "truncated" else b"not a tiff at all")
    needle = "truncated or corrupt" if damage == "truncated" else "cannot be read as a raster"
    assert_error(run(capsys, "predict", bad, "--model", ckpt, "--out", tmp_path / "p", *PREDICT),
                 f"orthophoto '{bad}'", needle, "re-export")
    assert not (tmp_path / "p").exists()  # no file at a final path, no empty folder either


def test_truncated_dsm_in_tile(tmp_path: Path, capsys) -> None:
    ortho = rgb(tmp_path)
    good = write_raster(tmp_path / "good.tif", np.ones((64, 64), np.float32), CRS, T05)
    data = good.read_bytes()
    (tmp_path / "dsm.tif").write_bytes(data[: len(data) // 3])
    assert_error(run(capsys, "tile", "--ortho", ortho, "--dsm", tmp_path / "dsm.tif", "--dtm", good, "--size", "32",
                     "--out", tmp_path / "t", "--quiet"), f"DSM '{tmp_path / 'dsm.tif'}'", "truncated or corrupt")
    assert not (tmp_path / "t").exists()


# ---- 11. output exists / unwritable output folder ---------------------------------------------------------
def _command(name: str, tmp: Path, ckpt: Path, out: Path) -> list[object]:
    ortho = rgb(tmp, size=(32, 32))
    if name == "predict":
        return ["predict", ortho, "--model", ckpt, "--out", out, *PREDICT]
    if name == "tile":
        ndsm = write_raster(tmp / "n.tif", np.ones((32, 32), np.float32), CRS, T05)
        return ["tile", "--ortho", ortho, "--ndsm", ndsm, "--size", "32", "--out", out, "--quiet"]
    if name == "train":
        from helpers.tilefolder import write_tile_folder

        tiles = write_tile_folder(tmp / "tiles", size=32, counts={"train": 2, "val": 0})
        return ["train", "--config", tiny_train_yaml(tmp / "c.yaml"), "--data", tiles, "--out", out,
                "--max-steps", "1", "--quiet"]
    if name == "evaluate":
        pred = tmp / "pred"
        pred.mkdir()
        write_raster(pred / "height.tif", np.ones((32, 32), np.float32), CRS, T05, nodata=-9999.0)
        return ["evaluate", "--pred", pred, "--height", tmp / "n.tif", "--no-plots", "--quiet", "--out", out / "r.json"]
    return ["synth", out, "--size", "32"]


EXISTING = {"predict": "height.tif", "tile": "dataset.yaml", "train": "last.pt", "evaluate": "r.json",
            "synth": "ortho.tif"}


@pytest.mark.parametrize("name", list(EXISTING))
def test_existing_output_is_refused_without_overwrite(tmp_path: Path, capsys, ckpt: Path, name: str) -> None:
    out = tmp_path / "out"
    out.mkdir()
    (out / EXISTING[name]).write_text("precious")
    write_raster(tmp_path / "n.tif", np.ones((32, 32), np.float32), CRS, T05)
    args = _command(name, tmp_path, ckpt, out)
    assert_error(run(capsys, *args), str(out), "--overwrite")
    assert (out / EXISTING[name]).read_text() == "precious"
    if name in ("predict", "evaluate"):  # --overwrite replaces it
        assert_ok(run(capsys, *args, "--overwrite"))
        assert (out / EXISTING[name]).stat().st_size > len("precious")


@pytest.mark.parametrize("name", list(EXISTING))
def test_output_under_a_file_is_refused(tmp_path: Path, capsys, ckpt: Path, name: str) -> None:
    (tmp_path / "afile").write_text("x")
    write_raster(tmp_path / "n.tif", np.ones((32, 32), np.float32), CRS, T05)
    out = tmp_path / "afile" / "out"
    line = assert_error(run(capsys, *_command(name, tmp_path, ckpt, out)), str(tmp_path / "afile"))
    assert "writable" in line or "permissions" in line


@pytest.mark.skipif(os.name != "posix" or os.geteuid() == 0, reason="needs a non-root POSIX user")
def test_read_only_output_folder(tmp_path: Path, capsys, ckpt: Path) -> None:
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    try:
        assert_error(run(capsys, "predict", rgb(tmp_path), "--model", ckpt, "--out", ro / "p", *PREDICT),
                     str(ro / "p"), "writable --out")
    finally:
        ro.chmod(0o755)


# ---- 12. checkpoints: corrupt, another class scheme, code-running pickles -------------------------------
@pytest.mark.parametrize("kind", ["truncated", "empty", "a_tiff"])
def test_corrupt_checkpoint(tmp_path: Path, capsys, ckpt: Path, kind: str) -> None:
    bad = tmp_path / "bad.pt"
    data = {"truncated": ckpt.read_bytes()[:2000], "empty": b"", "a_tiff": rgb(tmp_path).read_bytes()}[kind]
    bad.write_bytes(data)
    needle = {"truncated": "corrupt or truncated", "empty": "is empty", "a_tiff": "not a PyTorch checkpoint"}[kind]
    assert_error(run(capsys, "predict", rgb(tmp_path), "--model", bad, "--out", tmp_path / "p", *PREDICT),
                 f"checkpoint '{bad}'", needle, "aerialmtl train" if kind == "a_tiff" else "another checkpoint")


def test_checkpoint_weights_from_another_class_scheme(tmp_path: Path, capsys, ckpt: Path) -> None:
    payload = torch.load(ckpt, weights_only=True)
    payload["state_dict"] = tiny_d3net(k=6)[0].state_dict()  # a 6-class head under 4-class metadata
    mixed = tmp_path / "mixed.pt"
    torch.save(payload, mixed)
    assert_error(run(capsys, "predict", rgb(tmp_path), "--model", mixed, "--out", tmp_path / "p", *PREDICT),
                 f"checkpoint '{mixed}'", "'synthetic' (4 classes)", "heads.classes", "[6,", "another class scheme")


def test_resume_on_tiles_of_another_class_scheme_is_refused(rgbn_run: dict[str, Path], tmp_path: Path,
                                                            capsys) -> None:
    other = tmp_path / "tiles_isprs"  # same 6-class size, other classes: weights would silently change meaning
    assert_ok(run(capsys, "tile", "--ortho", rgbn_run["ortho"], "--ndsm", rgbn_run["ndsm"], "--labels",
                  rgbn_run["labels"], "--classes", "isprs",
                  "--bands", "4,1,2", "--size", "32", "--min-valid", "0.5", "--split-ratios", "1,0,0",
                  "--out", other, "--quiet"))
    run_dir = tmp_path / "run"
    (run_dir).mkdir()
    for f in ("last.pt", "config.yaml"):
        (run_dir / f).write_bytes((rgbn_run["run"] / f).read_bytes())
    assert_error(run(capsys, "train", "--data", other, "--out", run_dir, "--resume", "--max-steps", "2", "--quiet"),
                 "last.pt", "class scheme 'synthetic'", "class scheme 'isprs'", "--data")


class _WritesMarker:
    """Unpickling this would create a marker file (what a malicious checkpoint would do)."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):  # noqa: D105
        return (Path.touch, (self.marker,))


@pytest.mark.parametrize("wrapper", ["torch.save", "raw pickle"])
def test_checkpoint_that_would_run_code_is_refused(tmp_path: Path, capsys, wrapper: str) -> None:
    marker = tmp_path / "PWNED"
    evil = tmp_path / "evil.pt"
    payload = {"format": "aerialmtl-checkpoint", "format_version": 1, "meta": _WritesMarker(marker)}
    if wrapper == "torch.save":
        torch.save(payload, evil)
    else:
        evil.write_bytes(pickle.dumps(payload, protocol=4))
    assert_error(run(capsys, "predict", rgb(tmp_path), "--model", evil, "--out", tmp_path / "p"),
                 f"checkpoint '{evil}' was refused", "run code")
    assert not marker.exists()
    pickle.loads(pickle.dumps(_WritesMarker(marker)))  # the payload is live: plain unpickling runs it
    assert marker.exists()


# ---- 13. YAML: unknown key, wrong type, typo'd choice ---------------------------------------------------------
@pytest.mark.parametrize(
    "text,needles",
    [
        ("model:\n  dropuot: 0.5\n", ["unknown key 'model.dropuot'", "valid keys here are", "did you mean 'dropout'"]),
        ("data:\n  batch_size: eight\n", ["data.batch_size", "expected an integer", "'eight'"]),
        ("loss:\n  height: l3\n", ["loss.height", "got 'l3'", "valid choices are 'l1', 'l2'"]),
        ("optim: [1, 2\n", ["not valid YAML", "line"]),
    ],
)
def test_bad_training_yaml(tmp_path: Path, capsys, text: str, needles: list[str]) -> None:
    cfg = tmp_path / "bad.yaml"
    cfg.write_text(text)
    (tmp_path / "tiles").mkdir()
    assert_error(run(capsys, "train", "--config", cfg, "--data", tmp_path / "tiles", "--out", tmp_path / "run"),
                 "bad.yaml", *needles)
    assert not (tmp_path / "run").exists()


def test_bad_class_scheme_yaml(tmp_path: Path, capsys) -> None:
    scheme = tmp_path / "scheme.yaml"
    scheme.write_text("name: mine\nclases:\n  - {code: 1, name: roof, color: [200, 0, 0]}\n")
    ortho = rgb(tmp_path)
    labels = write_raster(tmp_path / "l.tif", np.ones((64, 64), np.uint8), CRS, T05)
    assert_error(run(capsys, "tile", "--ortho", ortho, "--labels", labels, "--classes", scheme, "--out",
                     tmp_path / "t", "--quiet"), "scheme.yaml", "unknown key 'clases'", "did you mean 'classes'")


# ---- 14. predict interrupted by SIGINT / SIGKILL, then re-run ------------------------------------------------
#: One torch thread: on a busy 2-core machine two threads spin against each other (10–30× slower).
ONE_THREAD = {**os.environ, "OMP_NUM_THREADS": "1"}
SIDE = 512  # 121 windows of 64 px: ~2 s of work for the tiny model, so the signal lands mid-run


def _interrupt_predict(tmp_path: Path, ckpt: Path, sig: int) -> tuple[Path, subprocess.CompletedProcess]:
    ortho = rgb(tmp_path, size=(SIDE, SIDE), seed=3)
    out = tmp_path / "pred"
    cmd = [sys.executable, "-m", "aerialmtl", "predict", str(ortho), "--model", str(ckpt), "--out", str(out),
           "--mc", "4", "--window", "64", "--overlap", "16", "--batch-size", "1", "--precision", "fp32", "--quiet"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ONE_THREAD)
    try:
        deadline = time.monotonic() + 120
        while not (out.is_dir() and any(p.name.endswith(".staging") for p in out.iterdir())):
            assert proc.poll() is None, f"predict ended before it could be interrupted: {proc.communicate()}"
            assert time.monotonic() < deadline, "predict never started writing"
            time.sleep(0.02)
        time.sleep(0.3)  # a few windows into the run
        assert proc.poll() is None, "the run finished before the signal; use a larger raster"
        proc.send_signal(sig)
        stdout, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:  # pragma: no cover - only when an assertion above failed
            proc.kill()
            proc.communicate()
    return out, subprocess.CompletedProcess(cmd, proc.returncode, stdout, stderr)


def _rerun(capsys, args: list[str]) -> None:
    """The same command again, in-process (one torch thread, like the interrupted run)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        assert_ok(run(capsys, *args))
    finally:
        torch.set_num_threads(threads)


def _assert_complete_prediction(out: Path) -> None:
    styles = [n.replace(".tif", ".qml") for n in MAIN_OUTPUTS[:-1]]
    assert sorted(p.name for p in out.iterdir()) == sorted([*MAIN_OUTPUTS, *styles, "item.json"])  # nothing hidden
    for name in MAIN_OUTPUTS[:-1]:
        assert cog_problems(out / name) == []
        with rasterio.open(out / name) as ds:
            assert ds.shape == (SIDE, SIDE) and (ds.read(1) != ds.nodata).all()
    info = json.loads((out / "prediction.json").read_text())
    assert info["windows_computed"] == info["windows_total"] and info["mc_samples"] == 4


def test_predict_interrupted_by_sigint_then_rerun(tmp_path: Path, capsys, ckpt: Path) -> None:
    out, res = _interrupt_predict(tmp_path, ckpt, signal.SIGINT)
    assert res.returncode == 130 and "Traceback" not in res.stderr
    assert res.stderr.strip().splitlines() == [
        "Error: interrupted; no output was left at a final path. Re-run the command to finish."]
    assert no_final_outputs(out) and not out.exists()  # hidden files and the folder it created are gone
    _rerun(capsys, res.args[3:])  # the same command again
    _assert_complete_prediction(out)


def test_predict_killed_by_sigkill_then_plain_rerun(tmp_path: Path, capsys, ckpt: Path) -> None:
    out, res = _interrupt_predict(tmp_path, ckpt, signal.SIGKILL)
    assert res.returncode == -signal.SIGKILL
    assert no_final_outputs(out)
    assert any(p.name.startswith(".") for p in out.iterdir())  # a killed run cannot clean up its hidden files
    _rerun(capsys, res.args[3:])  # a plain re-run: no --overwrite needed, leftovers do not get in the way
    _assert_complete_prediction(out)


# ---- 15. GSD 20× away from the checkpoint's ---------------------------------------------------------------
@pytest.mark.parametrize("gsd", [0.025, 10.0])
def test_gsd_far_from_the_checkpoint_warns_and_stays_aligned(tmp_path: Path, capsys, ckpt: Path, gsd: float) -> None:
    n = int(round(20.0 / gsd))  # 20 m × 20 m: 40 × 40 pixels at the model's 0.5 m
    img = np.random.default_rng(4).integers(1, 255, (3, n, n)).astype(np.uint8)
    img[:, :, : n // 2] = 0  # western half is nodata
    ortho = write_raster(tmp_path / "o.tif", img, CRS, Affine(gsd, 0, 500000.0, 0, -gsd, 5000000.0), nodata=0)
    (warning,) = assert_ok(run(capsys, "predict", ortho, "--model", ckpt, "--out", tmp_path / "p", *PREDICT))
    assert f"GSD of {gsd:g} m" in warning and "trained at 0.5 m" in warning and "resampling" in warning
    with rasterio.open(ortho) as src, rasterio.open(tmp_path / "p" / "height.tif") as out:
        assert out.crs == src.crs and out.res == (0.5, 0.5)
        assert out.bounds == pytest.approx(src.bounds)  # same footprint, same corner
        h = out.read(1)
    assert h.shape == (40, 40)
    assert (h[:, :20] == -9999.0).all() and (h[:, 20:] != -9999.0).all()  # the nodata edge did not move
