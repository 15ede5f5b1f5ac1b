"""Heights from the sun in `predict` (`--sun`, `--acquired`, `--shadow-fusion`): which sun an orthophoto gets, the
shadow layers, the STAC fields, the switch-off that leaves every map as it was, and fusion that never raises ground.

The scene is a synthetic town, whose sun and heights are exact. The model reads the true heights from a fourth
band (so the network's objects are the town's), and its shadow classifier is fitted on the town at its sun.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import rasterio
import torch
from click.testing import CliRunner
from helpers.rasters import dated_mosaic
from torch import nn

from aerialmtl.classes import ClassDef, ClassScheme
from aerialmtl.cli import cli
from aerialmtl.data.synth import synthesize
from aerialmtl.errors import InputError
from aerialmtl.formats.checkpoint import ModelMeta
from aerialmtl.inference.jobs import predict_raster
from aerialmtl.inference.sun_choice import choose_sun, parse_sun
from aerialmtl.io.align import Grid
from aerialmtl.models.config import ModelConfig
from aerialmtl.sun import ShadowModel, Sun
from aerialmtl.sun.record import TrainingSun

HEIGHT_SCALE = 4.0  # band 4 holds 1 + the nDSM in quarter metres (uint8: 0-63.5 m; no 0, which reads as nodata)


class HeightBandModel(nn.Module):
    """Height = band 4 (the true nDSM) in metres, with a spread of 1 m; no classes."""

    def __init__(self, meta: ModelMeta) -> None:
        super().__init__()
        self.head = nn.Conv2d(4, 2, 1)
        with torch.no_grad():
            self.head.weight.zero_()
            self.head.weight[0, 3] = meta.std[3] / HEIGHT_SCALE
            self.head.bias.copy_(torch.tensor([(meta.mean[3] - 1.0) / HEIGHT_SCALE, 0.0]))

    def encode(self, x: torch.Tensor) -> list[torch.Tensor]:
        return [x]

    def decode(self, feats: list[torch.Tensor]) -> dict[str, torch.Tensor]:
        out = self.head(feats[0])
        return {"height": out[:, :1], "height_scale": torch.full_like(out[:, 1:], 0.7)}

    def forward(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        return self.decode(self.encode(x))


def with_height_band(ortho: Path, ndsm_path: Path, out: Path) -> tuple[Path, np.ndarray, np.ndarray]:
    """``ortho``'s RGB with the nDSM of ``ndsm_path`` as a fourth band (:data:`HEIGHT_SCALE`) written to ``out``;
    ``(out, rgb (3, H, W), nDSM (H, W) metres)``."""
    with rasterio.open(ortho) as src:
        rgb, profile = src.read(), src.profile
    with rasterio.open(ndsm_path) as src:
        ndsm = src.read(1)
    band4 = np.clip(np.round(ndsm * HEIGHT_SCALE) + 1, 1, 255).astype(np.uint8)
    profile.pop("photometric", None)
    profile.update(count=4)
    with rasterio.open(out, "w", **profile) as dst:
        dst.write(np.concatenate([rgb, band4[None]]))
    return out, rgb, ndsm


@pytest.fixture(scope="module")
def town(tmp_path_factory: pytest.TempPathFactory) -> dict[str, object]:
    """A 256 px town at 0.5 m as a 4-band orthophoto (RGB + the nDSM), its true heights and sun, and a
    :class:`TrainingSun` fitted there (true sun, shadow classifier)."""
    out = tmp_path_factory.mktemp("town")
    res = synthesize(out / "town", size=256, seed=7, gsd=0.5)
    ortho, rgb, ndsm = with_height_band(res.ortho, res.ndsm, out / "ortho4.tif")
    sun = Sun(res.sun_azimuth % 360.0, res.sun_elevation)
    model = ShadowModel().fit(rgb, ndsm, 0.5, sun)
    with rasterio.open(ortho) as src:
        bounds = tuple(src.bounds)
        crs = src.crs.to_string()
    training = TrainingSun(clear=True, reason="sun fitted (test)", azimuth_deg=sun.azimuth_deg,
                           elevation_deg=sun.elevation_deg, grid_azimuth_deg=sun.azimuth_deg, score=0.5,
                           sharpness=0.5, crs=crs, bounds=bounds,  # type: ignore[arg-type]
                           shadow_model=model.to_dict())
    return {"ortho": ortho, "ndsm": ndsm, "sun": sun, "training": training, "out": out}


def _meta(training: TrainingSun | None) -> ModelMeta:
    scheme = ClassScheme("one", (ClassDef(1, "all", (0, 0, 0)),))
    cfg = ModelConfig(in_channels=4, num_classes=1, tasks=("height",), aleatoric=True)
    return ModelMeta(cfg, scheme, (1, 2, 3, 4), (120.0, 120.0, 120.0, 20.0), (60.0, 60.0, 60.0, 20.0), 0.5,
                     ("red", "green", "blue", "ndsm"), sun=training)




def _read(folder: Path, name: str) -> np.ndarray:
    with rasterio.open(folder / f"{name}.tif") as src:
        return src.read(1)


def _predict(town: dict[str, object], tmp_path: Path, name: str, training: TrainingSun | None,
             **settings: object) -> Path:
    meta = _meta(training)
    out = tmp_path / name
    predict_raster(town["ortho"], (HeightBandModel(meta), meta), out,  # type: ignore[arg-type]
                   mc=1, window=128, overlap=32, precision="fp32", engine="torch", progress=False,
                   **settings)  # type: ignore[arg-type]
    return out


def test_sun_none_and_a_switched_off_sun_leave_every_map_as_without_the_feature(town: dict[str, object],
                                                                                  tmp_path: Path) -> None:
    """`--sun none`, and `--sun auto` on an orthophoto with no time far from the training area, write exactly the
    maps of a model without a sun fit (same bits), no shadow layer from `none`, and say why the feature is off."""
    plain = _predict(town, tmp_path, "plain", None)
    off = _predict(town, tmp_path, "none", town["training"], sun="none")  # type: ignore[arg-type]
    far = TrainingSun(**{**town["training"].__dict__, "bounds": (0.0, 0.0, 10.0, 10.0)})  # type: ignore[attr-defined]
    with pytest.warns(UserWarning, match="no shadow features: off: no acquisition time"):
        auto_off = _predict(town, tmp_path, "auto-off", far)
    for name in ("height", "height_std"):
        base = _read(plain, name)
        np.testing.assert_array_equal(_read(off, name), base, err_msg=name)
        np.testing.assert_array_equal(_read(auto_off, name), base, err_msg=name)
    assert not (off / "shadow.tif").exists() and not (plain / "shadow.tif").exists()
    assert (_read(auto_off, "shadow") == -9999.0).all() and (_read(auto_off, "shadow_height") == -9999.0).all()
    record = json.loads((auto_off / "prediction.json").read_text())
    assert record["sun"]["source"] == "none" and record["sun"]["azimuth_deg"] is None
    assert "view:sun_azimuth" not in json.loads((auto_off / "item.json").read_text())["properties"]


def test_a_known_sun_writes_the_shadow_layers_and_the_stac_view_fields(town: dict[str, object], tmp_path: Path) -> None:
    """With the sun given, `shadow.tif` (0-1) marks the town's cast shadows, `shadow_height.tif` holds heights
    measured from them on objects only, and prediction.json and item.json say which sun (true north)."""
    sun: Sun = town["sun"]  # type: ignore[assignment]
    out = _predict(town, tmp_path, "given", town["training"],  # type: ignore[arg-type]
                   sun=f"{sun.azimuth_deg},{sun.elevation_deg}")
    shadow = _read(out, "shadow")
    assert ((shadow >= 0) & (shadow <= 1)).all()  # every pixel valid, the sun known everywhere
    from aerialmtl.sun import cast_shadow_mask

    truth = cast_shadow_mask(town["ndsm"], 0.5, sun)  # type: ignore[arg-type]
    assert shadow[truth].mean() > shadow[~truth].mean() + 0.3  # the classifier separates the cast shadows
    measured = _read(out, "shadow_height")
    ndsm: np.ndarray = town["ndsm"]  # type: ignore[assignment]
    has = measured != -9999.0
    assert has.any() and (ndsm[has] >= 2.0).all()  # only on objects (the network's: heights ≥ 2 m)
    rel = np.median(np.abs(measured[has] - ndsm[has]) / ndsm[has])
    assert rel < 0.3, rel  # shadow heights of a synthetic town with its exact sun, per pixel of measured objects
    record = json.loads((out / "prediction.json").read_text())
    assert record["sun"]["source"] == "--sun"
    assert record["sun"]["azimuth_deg"] == pytest.approx(sun.azimuth_deg, abs=1e-3)
    props = json.loads((out / "item.json").read_text())["properties"]
    assert props["view:sun_azimuth"] == pytest.approx(sun.azimuth_deg, abs=1e-3)
    assert props["view:sun_elevation"] == pytest.approx(sun.elevation_deg, abs=1e-3)
    assert (out / "shadow.qml").is_file() and (out / "shadow_height.qml").is_file()


def test_fusion_moves_objects_only_and_never_raises_flat_ground(town: dict[str, object], tmp_path: Path) -> None:
    """`--shadow-fusion` changes heights and spreads inside the network's objects only: every pixel it predicts
    below 2 m keeps its height and spread to the bit."""
    sun: Sun = town["sun"]  # type: ignore[assignment]
    given = f"{sun.azimuth_deg},{sun.elevation_deg}"
    plain = _predict(town, tmp_path, "nofuse", town["training"], sun=given)  # type: ignore[arg-type]
    fused = _predict(town, tmp_path, "fuse", town["training"], sun=given, shadow_fusion=True)  # type: ignore[arg-type]
    h0, h1 = _read(plain, "height"), _read(fused, "height")
    s0, s1 = _read(plain, "height_std"), _read(fused, "height_std")
    ground = h0 < 2.0
    np.testing.assert_array_equal(h1[ground], h0[ground])
    np.testing.assert_array_equal(s1[ground], s0[ground])
    assert (h1 != h0).any()  # measured objects moved


def test_sun_values_out_of_range_are_refused_naming_the_option(town: dict[str, object], tmp_path: Path) -> None:
    ckpt = tmp_path / "m.pt"  # the values are refused before the model is read
    ckpt.write_bytes(b"not read")
    runner = CliRunner()
    for value, words in (("400,40", "azimuth 400° is outside 0–360°"), ("120,95", "elevation 95° is outside"),
                         ("sunny", "neither auto, none nor AZIMUTH,ELEVATION")):
        res = runner.invoke(cli, ["predict", str(town["ortho"]), "--model", str(ckpt), "--out", str(tmp_path / "o"),
                                  "--sun", value])
        assert res.exit_code != 0 and "--sun" in res.output and words in res.output, res.output
        assert not (tmp_path / "o").exists()
    res = runner.invoke(cli, ["predict", str(town["ortho"]), "--model", str(ckpt), "--out", str(tmp_path / "o"),
                              "--acquired", "2019-06-21"])
    assert res.exit_code != 0 and "--acquired" in res.output and "not a time of day" in res.output, res.output


def _grid() -> Grid:
    from affine import Affine
    from rasterio.crs import CRS

    # 1 km at 1 m in UTM 10N near Eugene, Oregon (44.05° N, 123.09° W)
    return Grid(CRS.from_epsg(32610), Affine(1.0, 0, 492000.0, 0, -1.0, 4878000.0), 1000, 1000)


def test_auto_takes_the_time_and_place_then_the_same_flight_fit_then_nothing(tmp_path: Path) -> None:
    """`--sun auto`: the acquisition time (--acquired, a STAC item beside the file, the TIFF DateTime) through the
    solar position library; a fit more than 10° away from it is preferred and both are said; without a time, the
    training fit only within 2 km of the training area; else off."""
    grid = _grid()
    path = tmp_path / "ortho.tif"
    fit = TrainingSun(clear=True, reason="fit", azimuth_deg=98.0, elevation_deg=43.0, grid_azimuth_deg=98.0,
                      crs="EPSG:32610", bounds=(491000.0, 4876000.0, 493500.0, 4879000.0))
    # the late-June sun at 16:45 UTC there: azimuth ≈ 98°, elevation ≈ 43° (NREL SPA through pvlib)
    c = choose_sun("auto", "2019-06-21T16:45:00Z", path, grid, {}, None)
    assert c.source == "--acquired" and c.azimuth_deg == pytest.approx(98.2, abs=0.5)
    assert c.elevation_deg == pytest.approx(42.9, abs=0.5)
    c = choose_sun("auto", None, path, grid, {"TIFFTAG_DATETIME": "2019:06:21 16:45:00"}, fit)
    assert c.source == "TIFF DateTime" and "no time zone" in c.note
    path.with_suffix(".json").write_text(json.dumps({"type": "Feature", "stac_version": "1.0.0",
                                                     "properties": {"datetime": "2019-06-21T16:45:00Z"}}))
    c = choose_sun("auto", None, path, grid, {"TIFFTAG_DATETIME": "2025:01:01 12:00:00"}, fit)
    assert c.source == "STAC datetime" and c.azimuth_deg == pytest.approx(98.2, abs=0.5)
    path.with_suffix(".json").unlink()
    c = choose_sun("auto", None, path, grid, {"TIFFTAG_DATETIME": "2019:12:21 20:00:00"}, fit)  # file written later
    assert c.source == "training fit" and "from the training fit" in c.note and c.azimuth_deg == 98.0
    c = choose_sun("auto", None, path, grid, {}, fit)
    assert c.source == "training fit" and "same flight" in c.note
    far = TrainingSun(**{**fit.__dict__, "bounds": (400000.0, 4700000.0, 401000.0, 4701000.0)})
    assert not choose_sun("auto", None, path, grid, {}, far).on
    assert not choose_sun("auto", "2019-06-21T04:00:00Z", path, grid, {}, None).on  # night: no shadows
    assert choose_sun("none", "2019-06-21T16:45:00Z", path, grid, {}, fit).on is False


def test_parse_sun_reads_the_three_forms() -> None:
    assert parse_sun("auto") == "auto" and parse_sun(" None ") == "none"
    assert parse_sun("135,42.5") == (135.0, 42.5) and parse_sun("360,10") == (0.0, 10.0)
    with pytest.raises(InputError, match="elevation 0° is outside"):
        parse_sun("10,0")


def test_a_mosaic_of_flights_with_different_suns_is_refused_naming_them(tmp_path: Path) -> None:
    """A VRT joining orthophotos flown at different times gets no single sun: `--sun auto` refuses it, naming the
    files and their times, and says how to predict them (one by one, each with its own sun)."""
    from rasterio.transform import from_origin

    vrt, grid = dated_mosaic(tmp_path, [("a.tif", "2019:06:21 16:45:00", from_origin(492000.0, 4878000.0, 1.0, 1.0)),
                                        ("b.tif", "2019:07:02 10:00:00", from_origin(492100.0, 4878000.0, 1.0, 1.0))],
                             crs="EPSG:32610")
    with pytest.raises(InputError, match=r"joins orthophotos flown at different times \(a.tif 2019:06:21 16:45:00, "
                       r"b.tif 2019:07:02 10:00:00\).*one by one"):
        choose_sun("auto", None, vrt, grid, {}, None)
    assert choose_sun("auto", "2019-06-21T16:45:00Z", vrt, grid, {}, None).on  # a time given: the user's word
    assert not choose_sun("none", None, vrt, grid, {}, None).on


def test_shadow_layers_do_not_depend_on_how_many_windows_run_at_once(town: dict[str, object]) -> None:
    """The shadow step works on a batch's windows in parallel (one thread per inference thread): the layers and
    the fused heights are those of one window after the other, to the bit."""
    from aerialmtl.inference.shadows import ShadowStep
    from aerialmtl.models.mc_dropout import McStatistics

    sun: Sun = town["sun"]  # type: ignore[assignment]
    model = ShadowModel.from_dict(town["training"].shadow_model)  # type: ignore[attr-defined]
    ndsm = np.nan_to_num(np.asarray(town["ndsm"], np.float32))
    with rasterio.open(town["ortho"]) as src:  # type: ignore[arg-type]
        rgb = src.read([1, 2, 3])
    # four overlapping 128 px windows of the town, as predict hands them over
    corners = [(0, 0), (0, 96), (96, 0), (96, 128)]
    windows = [np.ascontiguousarray(rgb[:, r:r + 128, c:c + 128]) for r, c in corners]
    heights = torch.from_numpy(np.stack([ndsm[r:r + 128, c:c + 128] for r, c in corners]))
    valid = torch.ones(heights.shape, dtype=torch.bool)
    valid[1, :10] = False

    def layers(workers: int) -> McStatistics:
        stats = McStatistics(height_mean=heights.clone(), height_std=torch.full_like(heights, 1.5))
        ShadowStep(model, 0.5, fuse=True, workers=workers).apply(stats, windows, valid, sun)
        return stats

    one, many = layers(1), layers(3)
    assert one.shadow_weight is not None and one.shadow_weight.sum() > 0  # objects were measured
    for name in ("shadow", "shadow_on", "shadow_height", "shadow_weight", "height_mean", "height_std"):
        torch.testing.assert_close(getattr(many, name), getattr(one, name), rtol=0, atol=0, msg=name)
    assert not torch.equal(one.height_mean, heights)  # fusion moved measured objects


def test_predict_reads_the_orthophotos_tiff_datetime(town: dict[str, object], tmp_path: Path) -> None:
    """`--sun auto` through predict: the TIFF DateTime of the orthophoto (read with its header, in the one opening
    predict makes of it) reaches the sun choice, which records it in prediction.json."""
    import shutil

    dated = tmp_path / "dated.tif"
    shutil.copy(town["ortho"], dated)  # type: ignore[arg-type]
    with rasterio.open(dated, "r+") as dst:
        dst.update_tags(TIFFTAG_DATETIME="2019:06:21 16:45:00")
    out = _predict({**town, "ortho": dated}, tmp_path, "dated", town["training"])  # type: ignore[arg-type]
    sun = json.loads((out / "prediction.json").read_text())["sun"]
    assert sun["acquired"] == "2019-06-21T16:45:00Z" and "TIFF DateTime" in sun["note"]
    undated = json.loads((_predict(town, tmp_path, "undated", town["training"]) / "prediction.json")  # type: ignore[arg-type]
                         .read_text())["sun"]
    assert undated["acquired"] is None and undated["source"] == "training fit"


def test_a_uint16_orthophoto_of_8_bit_values_gets_the_shadows_of_the_8_bit_one(town: dict[str, object],
                                                                                 tmp_path: Path) -> None:
    """The shadow classifier sees colours on the scale it was fitted on (the training data's type), whatever the
    orthophoto's own type: the same town written as uint16 (values unchanged) gives the same shadow layers, and
    a `--rescale-input` mapping is applied before the colours are scaled."""
    from aerialmtl.inference.shadows import unit_colours

    sun: Sun = town["sun"]  # type: ignore[assignment]
    given = f"{sun.azimuth_deg},{sun.elevation_deg}"
    with rasterio.open(town["ortho"]) as src:  # type: ignore[arg-type]
        data, profile = src.read(), src.profile
    wide = dict(town, ortho=tmp_path / "ortho16.tif")
    with rasterio.open(wide["ortho"], "w", **{**profile, "dtype": "uint16"}) as dst:
        dst.write(data.astype(np.uint16))
    a = _predict(wide, tmp_path, "u16", town["training"], sun=given)  # type: ignore[arg-type]
    b = _predict(town, tmp_path, "u8", town["training"], sun=given)  # type: ignore[arg-type]
    for name in ("shadow", "shadow_height"):
        np.testing.assert_array_equal(_read(a, name), _read(b, name), err_msg=name)
    raw = np.array([[[0, 1000]], [[2000, 65535]], [[10, 20]]], np.uint16)
    np.testing.assert_allclose(unit_colours(raw, (255 / 65535, 0.0), "uint8"), raw / 65535, rtol=1e-6)
    np.testing.assert_allclose(unit_colours(raw, None, "uint16"), raw / 65535, rtol=1e-6)
    np.testing.assert_array_equal(unit_colours(raw.astype(np.float32), None, "float32"), raw.astype(np.float32))
