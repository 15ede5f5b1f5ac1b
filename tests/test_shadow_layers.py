"""The shadow layers through `aerialmtl predict` on hostile inputs (issue 59): pixels that are not data (NaN,
nodata) are nodata in the shadow layers and change no other pixel's layer beyond their neighbourhood's share; a
window without contrast (all black) gets nodata and one warning, not shadow = 1; a checkpoint whose shadow
classifier is damaged is refused at load, naming the file and the fix; `--shadow-fusion` where it cannot act is
refused naming the option, and prediction.json records whether fusion was applied; warnings never land on the
progress bar's line.

The model is the tiny D3-Net with the shadow classifier of a synthetic town fitted at its sun; the orthophoto is
that town (float colours, NaN the nodata, or uint8).
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
import rasterio
import torch
from affine import Affine
from helpers.cli import run_cli
from helpers.models import tiny_d3net

from aerialmtl.data.synth import synthesize
from aerialmtl.formats.checkpoint import save_checkpoint
from aerialmtl.sun import ShadowModel, Sun
from aerialmtl.sun.record import TrainingSun

NODATA = -9999.0
BAD = ("Error: unexpected", "Traceback")
RUN = ("--window", "128", "--overlap", "32", "--engine", "torch", "--precision", "fp32", "--quiet")


@pytest.fixture(scope="module")
def town(tmp_path_factory: pytest.TempPathFactory) -> dict[str, object]:
    """A 256 px synthetic town at 0.5 m (uint8 RGB), its sun, and tiny checkpoints holding its shadow classifier
    (``plain``: no aleatoric head; ``spread``: with one)."""
    out = tmp_path_factory.mktemp("shadow_layers")
    res = synthesize(out / "town", size=256, seed=7, gsd=0.5)
    with rasterio.open(res.ortho) as src:
        rgb, profile, bounds, crs = src.read(), src.profile, tuple(src.bounds), src.crs.to_string()
    with rasterio.open(res.ndsm) as src:
        ndsm = src.read(1)
    sun = Sun(res.sun_azimuth % 360.0, res.sun_elevation)
    training = TrainingSun(clear=True, reason="sun fitted (test)", azimuth_deg=sun.azimuth_deg,
                           elevation_deg=sun.elevation_deg, grid_azimuth_deg=sun.azimuth_deg, score=0.5,
                           sharpness=0.5, crs=crs, bounds=bounds,  # type: ignore[arg-type]
                           shadow_model=ShadowModel().fit(rgb, ndsm, 0.5, sun).to_dict())
    ckpts = {}
    for name, extra in (("plain", {}), ("spread", {"aleatoric": True})):
        model, meta = tiny_d3net(**extra)  # type: ignore[arg-type]
        meta = type(meta)(**{**meta.__dict__, "sun": training})
        ckpts[name] = out / f"{name}.pt"
        save_checkpoint(ckpts[name], model, meta)
    profile.pop("photometric", None)
    return {"rgb": rgb, "profile": profile, "sun": sun, "ckpt": ckpts, "out": out,
            "given": f"{sun.azimuth_deg},{sun.elevation_deg}"}


def _float_ortho(town: dict[str, object], path: Path, nan: np.ndarray | None = None, far: bool = False) -> Path:
    """The town as float32 colours (its 8-bit values, as the model trained on them; NaN nodata), NaN where
    ``nan`` (h, w) is True; ``far``: moved 100 km east (away from the training area: no sun without a time)."""
    rgb = np.asarray(town["rgb"], np.float32)
    if nan is not None:
        rgb[:, nan] = np.nan
    profile = {**town["profile"], "dtype": "float32", "nodata": float("nan")}  # type: ignore[dict-item]
    if far:
        profile["transform"] = profile["transform"] * Affine.translation(200_000, 0)  # 200,000 px of 0.5 m
    with rasterio.open(path, "w", **profile) as dst:
        dst.write(rgb)
    return path


def _read(folder: Path, name: str) -> np.ndarray:
    with rasterio.open(folder / f"{name}.tif") as src:
        return src.read(1)


def _predict(capsys: pytest.CaptureFixture, town: dict[str, object], ortho: Path, out: Path, *args: object,
             ckpt: str = "plain") -> tuple[int, str]:
    code, _, err = run_cli(capsys, "predict", ortho, "--model", town["ckpt"][ckpt], "--out", out,  # type: ignore[index]
                           *RUN, *args)
    assert not any(b in err for b in BAD), err
    return code, err


def test_nan_pixels_are_nodata_in_the_shadow_layers_and_nothing_else_is(town: dict[str, object], tmp_path: Path,
                                                                      capsys: pytest.CaptureFixture) -> None:
    """One NaN pixel and a NaN quarter of a float orthophoto: `shadow.tif` is nodata at exactly those pixels (the
    classifier's 2-40 m neighbourhoods leave them out instead of spreading NaN, written as 0 = no shadow, over
    18,000 pixels), its values elsewhere stay 0-1 and near those of the whole town, and `shadow_height.tif` still
    measures the objects of the other three quarters."""
    whole = _float_ortho(town, tmp_path / "whole.tif")
    nan = np.zeros((256, 256), bool)
    nan[200, 60] = True
    nan[:128, 128:] = True
    holed = _float_ortho(town, tmp_path / "holed.tif", nan)
    given = ("--mc", "1", "--sun", town["given"])
    assert _predict(capsys, town, whole, tmp_path / "a", *given)[0] == 0
    assert _predict(capsys, town, holed, tmp_path / "b", *given)[0] == 0
    ref, got = _read(tmp_path / "a", "shadow"), _read(tmp_path / "b", "shadow")
    np.testing.assert_array_equal(got == NODATA, nan)
    assert ((got[~nan] >= 0) & (got[~nan] <= 1)).all()
    assert np.abs(got[~nan] - ref[~nan]).max() < 0.35  # only the share of the neighbourhood that is gone
    far = np.zeros_like(nan)
    far[140:, :40] = True  # more than 40 m from every NaN pixel: the same values (to float rounding)
    np.testing.assert_allclose(got[far], ref[far], rtol=0, atol=1e-4)
    assert (_read(tmp_path / "b", "shadow_height")[nan] == NODATA).all()


def test_a_nan_quarter_leaves_the_shadow_heights_of_the_other_three(tmp_path: Path) -> None:
    """`shadow_height.tif` of a town whose float orthophoto has a NaN quarter: nodata there, and the objects of the
    other quarters measured as in the whole town (a model that reads the true heights, so objects are found; one
    window holds the whole town, as the default window holds a 1024 px orthophoto)."""
    from test_sun_predict import HEIGHT_SCALE, HeightBandModel, _meta

    from aerialmtl.inference.jobs import predict_raster

    res = synthesize(tmp_path / "town", size=256, seed=7, gsd=0.5)
    with rasterio.open(res.ortho) as src:
        rgb, profile = src.read(), src.profile
    with rasterio.open(res.ndsm) as src:
        ndsm = src.read(1)
    sun = Sun(res.sun_azimuth % 360.0, res.sun_elevation)
    with rasterio.open(res.ortho) as src:
        training = TrainingSun(clear=True, reason="test", azimuth_deg=sun.azimuth_deg,
                               elevation_deg=sun.elevation_deg, grid_azimuth_deg=sun.azimuth_deg,
                               crs=src.crs.to_string(), bounds=tuple(src.bounds),  # type: ignore[arg-type]
                               shadow_model=ShadowModel().fit(rgb, ndsm, 0.5, sun).to_dict())
    band4 = np.clip(np.round(np.nan_to_num(ndsm) * HEIGHT_SCALE) + 1, 1, 255)
    data = np.concatenate([rgb, band4[None]]).astype(np.float32)
    nan = np.zeros((256, 256), bool)
    nan[:128, 128:] = True
    layers = {}
    for name, holes in (("whole", None), ("holed", nan)):
        img = data.copy()
        if holes is not None:
            img[:, holes] = np.nan
        path = tmp_path / f"{name}.tif"
        profile.pop("photometric", None)
        with rasterio.open(path, "w", **{**profile, "count": 4, "dtype": "float32", "nodata": float("nan")}) as dst:
            dst.write(img)
        meta = _meta(training)
        predict_raster(path, (HeightBandModel(meta), meta), tmp_path / name, mc=1, window=256, overlap=32,
                       precision="fp32", engine="torch", progress=False, sun=f"{sun.azimuth_deg},{sun.elevation_deg}")
        layers[name] = _read(tmp_path / name, "shadow_height")
    whole, holed = layers["whole"], layers["holed"]
    assert (holed[nan] == NODATA).all()
    rest = ~nan
    rest[:140, 116:] = False  # objects that may cast into the quarter or stand by it
    assert (whole[rest] != NODATA).sum() > 100
    measured, before = (holed[rest] != NODATA).sum(), (whole[rest] != NODATA).sum()
    assert measured >= 0.95 * before, (measured, before)  # a NaN spread over 40 m lost two thirds of them


def test_an_orthophoto_without_contrast_gets_no_shadow_layers_and_one_warning(town: dict[str, object],
                                                                               tmp_path: Path,
                                                                               capsys: pytest.CaptureFixture) -> None:
    """An all-black orthophoto: no shadow = 1 and no shadow heights measured from it; both layers nodata, one
    warning that says why, exit 0 (the height and class maps are the network's as ever)."""
    black = tmp_path / "black.tif"
    with rasterio.open(black, "w", **town["profile"]) as dst:  # type: ignore[arg-type]
        dst.write(np.zeros((3, 256, 256), np.uint8))
    code, err = _predict(capsys, town, black, tmp_path / "o", "--mc", "1", "--sun", town["given"])
    assert code == 0, err
    assert (_read(tmp_path / "o", "shadow") == NODATA).all()
    assert (_read(tmp_path / "o", "shadow_height") == NODATA).all()
    warned = [line for line in err.splitlines() if "no contrast" in line]
    assert len(warned) == 1 and warned[0].startswith("warning: black.tif: no shadow layers"), err


@pytest.mark.parametrize("damage, words", [
    ("nan_weight", "weights are not all finite"),
    ("zero_scale", "scales are not all > 0"),
    ("nan_threshold", "threshold nan is not a probability"),
    ("few_weights", "holds 5 weights where the feature set needs 13"),
])
def test_a_damaged_shadow_classifier_is_refused_at_load_naming_the_checkpoint(damage: str, words: str,
                                                                               town: dict[str, object],
                                                                               tmp_path: Path,
                                                                               capsys: pytest.CaptureFixture) -> None:
    """NaN weights, a zero scale, a NaN threshold or too few weights in the checkpoint's shadow classifier: exit
    1 before any output, one line naming the checkpoint, what is wrong and how to refit it — not a shadow.tif of
    0 everywhere or an empty shadow_height.tif called complete."""
    payload = torch.load(town["ckpt"]["plain"], weights_only=True)  # type: ignore[index]
    record = payload["meta"]["sun"]["shadow_model"]
    if damage == "nan_weight":
        record["weights"][3] = float("nan")
    elif damage == "zero_scale":
        record["scale"][5] = 0.0
    elif damage == "nan_threshold":
        record["threshold"] = float("nan")
    else:
        record["weights"] = record["weights"][:5]
    ckpt = tmp_path / "damaged.pt"
    torch.save(payload, ckpt)
    ortho = _float_ortho(town, tmp_path / "o.tif")
    code, _, err = run_cli(capsys, "predict", ortho, "--model", ckpt, "--out", tmp_path / "out", *RUN, "--mc", "1",
                           "--sun", town["given"])
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == 1 and len(lines) == 1, err
    assert f"checkpoint '{ckpt}'" in lines[0] and "shadow classifier" in lines[0] and words in lines[0], err
    assert "sun_checkpoint" in lines[0] and not any(b in err for b in BAD), err
    assert not (tmp_path / "out").exists()


def test_shadow_fusion_that_cannot_act_is_refused_naming_the_option(town: dict[str, object], tmp_path: Path,
                                                                     capsys: pytest.CaptureFixture) -> None:
    """`--shadow-fusion` with `--sun none` (no shadows) or `--mc 1` on a model without an aleatoric head (no spread
    to weigh) would change nothing and be recorded as done: refused, one line naming the options and the fix."""
    ortho = _float_ortho(town, tmp_path / "o.tif")
    for args, words in ((("--sun", "none", "--mc", "2"), "--sun none turns the shadows off"),
                        (("--sun", town["given"], "--mc", "1"), "with --mc 1 the heights of")):
        code, err = _predict(capsys, town, ortho, tmp_path / "out", "--shadow-fusion", *args)
        lines = [line for line in err.splitlines() if line.strip()]
        assert code == 1 and len(lines) == 1 and lines[0].startswith("Error: --shadow-fusion"), err
        assert words in lines[0] and "drop --shadow-fusion" in lines[0], err
        assert not (tmp_path / "out").exists()


def test_prediction_json_records_whether_fusion_was_applied(town: dict[str, object], tmp_path: Path,
                                                            capsys: pytest.CaptureFixture) -> None:
    """With a spread (an aleatoric head at `--mc 1`) and a sun, fusion runs and says so; with `--sun auto` and no
    sun for the orthophoto it did not run, and prediction.json says that and why (`shadow_fusion` stays what was
    asked)."""
    ortho = _float_ortho(town, tmp_path / "o.tif")
    assert _predict(capsys, town, ortho, tmp_path / "on", "--shadow-fusion", "--mc", "1", "--sun", town["given"],
                    ckpt="spread")[0] == 0
    record = json.loads((tmp_path / "on" / "prediction.json").read_text())
    assert record["shadow_fusion"] is True and record["fusion"]["applied"] is True
    far = _float_ortho(town, tmp_path / "far.tif", far=True)  # no time, 100 km from the training area: no sun
    code, err = _predict(capsys, town, far, tmp_path / "off", "--shadow-fusion", "--mc", "1", ckpt="spread")
    assert code == 0, err
    record = json.loads((tmp_path / "off" / "prediction.json").read_text())
    assert record["shadow_fusion"] is True and record["fusion"]["applied"] is False
    assert "no sun for this orthophoto" in record["fusion"]["reason"]
    plain = _predict(capsys, town, ortho, tmp_path / "plain", "--mc", "1", "--sun", town["given"], ckpt="spread")
    assert plain[0] == 0
    assert json.loads((tmp_path / "plain" / "prediction.json").read_text())["fusion"]["applied"] is False


def test_warnings_never_land_on_the_progress_bars_line(town: dict[str, object], tmp_path: Path,
                                                       capsys: pytest.CaptureFixture) -> None:
    """A warning issued while predict's bar is on screen (the shadow step's, in the stitching thread) starts a line
    of its own: the bar is cleared before it and drawn again after, never `...it/s]warning: ...`."""
    black = tmp_path / "black.tif"
    with rasterio.open(black, "w", **town["profile"]) as dst:  # type: ignore[arg-type]
        dst.write(np.zeros((3, 256, 256), np.uint8))
    code, _, err = run_cli(capsys, "predict", black, "--model", town["ckpt"]["plain"],  # type: ignore[index]
                           "--out", tmp_path / "o", *RUN[:-1], "--mc", "1", "--sun", town["given"])
    assert code == 0, err
    assert "%|" in err  # the bar was drawn
    starts = [m.start() for m in re.finditer("warning: ", err)]
    assert starts and all(s == 0 or err[s - 1] in "\r\n" for s in starts), err
