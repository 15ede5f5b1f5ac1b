"""The time and place of an orthophoto in `predict --sun auto` (issue 59, and issue 58's stated-time test).

A time the user (`--acquired`) or a STAC item states is used as stated; a disagreement with the training fit is a
warning giving both suns, never a silent swap. A file's placeholder or impossible time is no time, with a warning
naming the file (train and predict read the tag alike). The STAC item beside the orthophoto is part of the input's
fingerprint and is read with limits. An orthophoto with no place on Earth is refused when it is opened. Each case
ends cleanly: a finished run with a warning, or one error line naming the file or option and the fix.

The checkpoint is a tiny D3-Net whose training fit is town A's known sun (and its shadow classifier); town B lies
at the same place under a sun 14° away, the sun of :data:`WHEN` there.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
from datetime import datetime
from pathlib import Path

import numpy as np
import pytest
import rasterio
from affine import Affine
from helpers.cli import run_cli
from helpers.models import tiny_d3net
from helpers.rasters import dated_mosaic, write_raster

from aerialmtl.data.synth import CityStyle, sample_city
from aerialmtl.formats.checkpoint import load_checkpoint, save_checkpoint
from aerialmtl.inference.sun_choice import choose_sun, flight_match, same_flight
from aerialmtl.io.align import Grid
from aerialmtl.io.fingerprint import input_fingerprint
from aerialmtl.sun import ShadowModel, Sun
from aerialmtl.sun.flight import SAME_FLIGHT_R, cut_chip
from aerialmtl.sun.record import TrainingSun
from aerialmtl.sun.solar_position import grid_convergence_deg, lonlat, sun_position, to_grid

BAD = ("Error: unexpected", "Traceback", "Aborted")
PREDICT = ("--mc", "1", "--window", "64", "--overlap", "16", "--engine", "torch", "--quiet")
#: The acquisition time of town B: its sun at the towns' place (45.15° N, 3.0° E) is azimuth ≈ 110°, elevation ≈ 49°.
WHEN = "2021-06-01T09:00:00Z"
ORIGIN = (500000.0, 5000064.0)  # EPSG:32631, on the zone's central meridian: grid north ≈ true north
SIZE = 128


def _town(path: Path, seed: int, azimuth: float, elevation: float) -> tuple[np.ndarray, np.ndarray]:
    """A 128 px true-orthophoto town at 0.5 m under the given sun (grid azimuth), written at :data:`ORIGIN`."""
    style = dataclasses.replace(CityStyle.plain().with_lean(0.0), sun_azimuth=(azimuth, azimuth),
                                sun_elevation=(elevation, elevation))
    patch = sample_city(seed, size=SIZE, gsd=0.5, style=style)
    write_raster(path, patch.image, transform=Affine(0.5, 0, ORIGIN[0], 0, -0.5, ORIGIN[1]))
    return patch.image, patch.height


@pytest.fixture(scope="module")
def towns(tmp_path_factory: pytest.TempPathFactory) -> dict[str, object]:
    """Town A (the training area: its sun is the checkpoint's fit) and town B (same place, the sun of
    :data:`WHEN`, 14° from A's in azimuth), and the checkpoint."""
    root = tmp_path_factory.mktemp("time_and_place")
    x, y = ORIGIN[0] + SIZE * 0.25, ORIGIN[1] - SIZE * 0.25
    lon, lat = lonlat("EPSG:32631", x, y)
    az_b, el_b = sun_position(datetime.fromisoformat(WHEN.replace("Z", "+00:00")), lon, lat)
    az_a = (az_b + 14.0) % 360.0
    convergence = grid_convergence_deg("EPSG:32631", x, y)
    image_a, height_a = _town(root / "a.tif", 1, to_grid(az_a, convergence), el_b)
    _town(root / "b.tif", 2, to_grid(az_b, convergence), el_b)
    shadows = ShadowModel().fit(image_a, height_a, 0.5, Sun(to_grid(az_a, convergence), el_b))
    fit = TrainingSun(clear=True, reason="sun fitted (town A)", azimuth_deg=az_a, elevation_deg=el_b,
                      grid_azimuth_deg=to_grid(az_a, convergence), score=0.5, sharpness=0.5, crs="EPSG:32631",
                      bounds=(ORIGIN[0], ORIGIN[1] - SIZE * 0.5, ORIGIN[0] + SIZE * 0.5, ORIGIN[1]),
                      shadow_model=shadows.to_dict())
    model, meta = tiny_d3net()
    save_checkpoint(root / "m.pt", model, dataclasses.replace(meta, sun=fit))
    # the same checkpoint as `train` fits it now: with squares of town A's orthophoto (one per 32 m patch)
    chips = tuple(c for r in (0, 64) for q in (0, 64) if (c := cut_chip(image_a[:, r:r + 64, q:q + 64],
                  np.ones((64, 64), bool), ORIGIN[0] + q * 0.5, ORIGIN[1] - r * 0.5, 0.5)) is not None)
    save_checkpoint(root / "chips.pt", model, dataclasses.replace(meta, sun=dataclasses.replace(fit, chips=chips)))
    # town A flown again at WHEN: every house where it was, its sun 14° away, its orthophoto registered 1 m off
    # (another flight's orthorectification)
    later, _ = _town(root / "a_later.tif", 1, to_grid(az_b, convergence), el_b)
    write_raster(root / "a_later.tif", later, transform=Affine(0.5, 0, ORIGIN[0] + 0.7, 0, -0.5, ORIGIN[1] - 0.7))
    return {"root": root, "ckpt": root / "m.pt", "a": root / "a.tif", "b": root / "b.tif", "fit": fit,
            "sun_b": (az_b, el_b), "chips": root / "chips.pt", "n_chips": len(chips),
            "a_later": root / "a_later.tif"}


def _predict(capsys: pytest.CaptureFixture, towns: dict[str, object], ortho: Path, out: Path,
             *options: str, model: str = "ckpt") -> tuple[int, str]:
    code, _, err = run_cli(capsys, "predict", ortho, "--model", towns[model], "--out", out, *PREDICT, *options)
    assert not any(b in err for b in BAD), err
    return code, " ".join(err.split())


def _sun(out: Path) -> dict[str, object]:
    return json.loads((out / "prediction.json").read_text())["sun"]


def _copy(src: object, dst: Path) -> Path:
    shutil.copy(str(src), dst)
    return dst


# ---- a stated time is used as stated ------------------------------------------------------------------------------
@pytest.mark.parametrize("how", ["--acquired", "STAC item"])
def test_a_stated_time_gives_its_own_sun_not_the_training_fit_and_says_both(how: str, towns, tmp_path: Path,
                                                                              capsys: pytest.CaptureFixture) -> None:
    """Issue 58: town B at town A's place, flown at WHEN (its sun 14° from A's fit). With the time given
    (`--acquired`, or a STAC item beside it), predict uses that time's sun, records it, and warns with both suns;
    without a time the same-flight fit is used (the default the time overrides)."""
    az_b, el_b = towns["sun_b"]
    fit: TrainingSun = towns["fit"]
    ortho = _copy(towns["b"], tmp_path / "b.tif")
    options: tuple[str, ...] = ()
    if how == "--acquired":
        options = ("--acquired", WHEN)
    else:
        (tmp_path / "b.json").write_text(json.dumps({"type": "Feature", "stac_version": "1.1.0", "id": "b",
                                                     "properties": {"datetime": WHEN}}))
    code, err = _predict(capsys, towns, ortho, tmp_path / "p", *options)
    assert code == 0, err
    sun = _sun(tmp_path / "p")
    assert sun["source"] == ("--acquired" if how == "--acquired" else "STAC datetime"), sun
    assert sun["azimuth_deg"] == pytest.approx(az_b, abs=0.01) and sun["elevation_deg"] == pytest.approx(el_b, abs=0.01)
    assert sun["acquired"] == WHEN
    item = json.loads((tmp_path / "p" / "item.json").read_text())["properties"]
    assert item["view:sun_azimuth"] == pytest.approx(az_b, abs=0.01)
    # the warning: both suns, and which is used
    assert "warning: b.tif:" in err and f"azimuth {az_b:.1f}°, elevation {el_b:.1f}°" in err, err
    assert f"training fit of this area (azimuth {fit.azimuth_deg:.1f}°" in err and "14°" in err, err
    assert ("as given" if how == "--acquired" else "as stated") in err
    if how == "--acquired":  # without the time: the same flight's fit, and the summary line says so
        code, out, err = run_cli(capsys, "predict", towns["b"], "--model", towns["ckpt"], "--out", tmp_path / "q",
                                 *PREDICT)
        assert code == 0 and _sun(tmp_path / "q")["source"] == "training fit", err
        assert _sun(tmp_path / "q")["azimuth_deg"] == pytest.approx(fit.azimuth_deg, abs=0.01)
        assert f"sun {fit.azimuth_deg:.0f}° / {fit.elevation_deg:.0f}° (training fit); files:" in out, out


def test_a_disagreeing_tiff_datetime_is_doubted_with_a_warning_giving_both_suns(towns, tmp_path: Path,
                                                                                capsys: pytest.CaptureFixture) -> None:
    """A TIFF DateTime (no zone, often the file's write time) far from the fit: the fit is used, and the user sees
    why in a warning with both suns and how to make the time count (`--acquired`)."""
    ortho = _copy(towns["a"], tmp_path / "a.tif")
    with rasterio.open(ortho, "r+") as dst:
        dst.update_tags(TIFFTAG_DATETIME="2021:12:21 15:00:00")
    code, err = _predict(capsys, towns, ortho, tmp_path / "p")
    assert code == 0, err
    sun = _sun(tmp_path / "p")
    assert sun["source"] == "training fit" and sun["acquired"] == "2021-12-21T15:00:00Z"
    assert "warning: a.tif: the sun of the TIFF DateTime 2021-12-21T15:00:00Z" in err, err
    assert f"training fit of this area (azimuth {towns['fit'].azimuth_deg:.1f}°" in err and "--acquired" in err


def test_an_acquired_time_at_night_is_used_as_given_and_switches_the_feature_off(towns, tmp_path: Path,
                                                                                 capsys: pytest.CaptureFixture) -> None:
    """`--acquired` wins even when its sun is below the horizon: the feature is off (said, with both suns), the
    training fit is not put in its place."""
    code, err = _predict(capsys, towns, towns["b"], tmp_path / "p", "--acquired", "2021-06-01T01:00:00Z")
    assert code == 0, err
    sun = _sun(tmp_path / "p")
    assert sun["source"] == "--acquired" and sun["azimuth_deg"] is None
    assert "no shadow features" in err and "below 5°" in err and "training fit of this area" in err, err


# ---- placeholder and impossible times -----------------------------------------------------------------------------
@pytest.mark.parametrize("stamp", ["0000:00:00 00:00:00", "    :  :     :  :  ", "", "2019:13:45 99:00:00",
                                   "0001:01:01 00:00:00"])
def test_a_placeholder_or_impossible_tiff_datetime_is_no_time_with_a_warning(stamp: str, towns, tmp_path: Path,
                                                                             capsys: pytest.CaptureFixture) -> None:
    """The TIFF/EXIF 'unknown' (zeros, blanks), an impossible date and a year no photograph has: no time, a warning
    naming the file (never an error blamed on --acquired, which the user did not give); the same flight's fit."""
    ortho = _copy(towns["b"], tmp_path / "b.tif")
    with rasterio.open(ortho, "r+") as dst:
        dst.update_tags(TIFFTAG_DATETIME=stamp)
    code, err = _predict(capsys, towns, ortho, tmp_path / "p")
    assert code == 0, err
    assert f"warning: orthophoto '{ortho}': its TIFF DateTime" in err and "read as no acquisition time" in err, err
    assert "Invalid value" not in err and _sun(tmp_path / "p")["source"] == "training fit"


def test_train_reads_a_placeholder_datetime_as_predict_does(tmp_path: Path) -> None:
    """`train`'s sun fit: the training orthophoto's placeholder DateTime is no time, said naming the file."""
    from aerialmtl.data.synth import synthesize
    from aerialmtl.tiling.tile import TileOptions, tile_dataset
    from aerialmtl.training.sun import fit_training_sun

    res = synthesize(tmp_path / "town", size=192, seed=11, gsd=0.5)
    with rasterio.open(res.ortho, "r+") as dst:
        dst.update_tags(TIFFTAG_DATETIME="0000:00:00 00:00:00")
    tile_dataset(res.ortho, tmp_path / "tiles", ndsm=res.ndsm, options=TileOptions(size=64, stride=64),
                 progress=False)
    with pytest.warns(UserWarning, match=r"training orthophoto '.*ortho.tif': its TIFF DateTime '0000:00:00 "
                                         r"00:00:00' is the placeholder for an unknown time"):
        sun = fit_training_sun(tmp_path / "tiles")
    assert sun.acquired is None and sun.time_sun is None


@pytest.mark.parametrize("when", ["0001-01-01T00:00:00+01:00", "9999-12-31T23:59:59-01:00"])
def test_acquired_at_the_ends_of_the_calendar_is_refused_naming_the_option(when: str, towns, tmp_path: Path,
                                                                           capsys: pytest.CaptureFixture) -> None:
    code, err = _predict(capsys, towns, towns["b"], tmp_path / "p", "--acquired", when)
    assert code == 2 and "--acquired" in err and "outside the years 1850–2199" in err, err
    assert not (tmp_path / "p").exists()


# ---- the STAC item beside the orthophoto --------------------------------------------------------------------------
@pytest.mark.parametrize("content", [
    "[" * 100_000 + "]" * 100_000,
    '{"type": "Feature", "properties": {"datetime": "2021-06-01T09:00:00Z", "x": ' + "[" * 200 + "]" * 200 + "}}",
    json.dumps({"type": "Feature", "properties": {"datetime": None, "start_datetime": 5, "end_datetime": 7}}),
    json.dumps({"type": "Feature", "properties": {"datetime": ["2021-06-01T09:00:00Z"]}}),
    json.dumps({"type": "Feature", "properties": {"datetime": "9999-12-31T23:59:59-01:00"}}),
    json.dumps({"type": "Feature", "properties": "2021-06-01"}),
    b"\xff\xfe not text",
], ids=["nested-100000", "nested-200", "numbers", "a-list", "end-of-calendar", "no-properties-object", "not-utf8"])
def test_a_hostile_stac_item_beside_is_not_read_and_named(content: str | bytes, towns, tmp_path: Path,
                                                          capsys: pytest.CaptureFixture) -> None:
    """The STAC item is read with limits (size, depth, types): a hostile one is named in a warning and gives no
    time; the run ends with its maps (here the same flight's fit)."""
    ortho = _copy(towns["b"], tmp_path / "b.tif")
    item = tmp_path / "b.json"
    item.write_bytes(content if isinstance(content, bytes) else content.encode())
    code, err = _predict(capsys, towns, ortho, tmp_path / "p")
    assert code == 0, err
    assert f"'{item}'" in err and "warning:" in err, err
    assert _sun(tmp_path / "p")["source"] == "training fit"


def test_a_stac_item_larger_than_the_limit_is_not_read(towns, tmp_path: Path, capsys: pytest.CaptureFixture,
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    from aerialmtl.formats import stac

    monkeypatch.setattr(stac, "SOURCE_ITEM_BYTES", 100)
    ortho = _copy(towns["b"], tmp_path / "b.tif")
    (tmp_path / "b.json").write_text(json.dumps({"type": "Feature", "properties": {"datetime": WHEN},
                                                 "padding": "x" * 200}))
    code, err = _predict(capsys, towns, ortho, tmp_path / "p")
    assert code == 0 and "more than the 100 a STAC item needs" in err, err
    assert _sun(tmp_path / "p")["source"] == "training fit"


def test_skip_existing_does_not_call_complete_a_folder_a_new_stac_item_would_change(
        towns, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """The STAC item decides the sun, so it is part of the input's fingerprint: once one appears beside an
    orthophoto predicted without a sun, `--skip-existing` recomputes the folder, now with the item's sun."""
    far = dataclasses.replace(towns["fit"], bounds=(400000.0, 4700000.0, 401000.0, 4701000.0))
    model, meta = tiny_d3net()
    save_checkpoint(tmp_path / "far.pt", model, dataclasses.replace(meta, sun=far))
    ortho = _copy(towns["b"], tmp_path / "b.tif")
    args = ("predict", ortho, "--model", tmp_path / "far.pt", "--out", tmp_path / "p", *PREDICT, "--skip-existing")
    code, _, err = run_cli(capsys, *args)
    assert code == 0 and _sun(tmp_path / "p")["source"] == "none", err
    (tmp_path / "b.json").write_text(json.dumps({"type": "Feature", "properties": {"datetime": WHEN}}))
    assert "b.json" in input_fingerprint(ortho)["sidecars"]
    code, out, err = run_cli(capsys, *args)
    said = " ".join((out + err).split())
    assert code == 0 and "recomputed" in said and "sidecar b.json appeared" in said, said
    sun = _sun(tmp_path / "p")
    assert sun["source"] == "STAC datetime" and sun["azimuth_deg"] == pytest.approx(towns["sun_b"][0], abs=0.01)


# ---- place ---------------------------------------------------------------------------------------------------------
LOCAL_CRS = 'LOCAL_CS["site grid",LOCAL_DATUM["site",0],UNIT["metre",1],AXIS["X",EAST],AXIS["Y",NORTH]]'


@pytest.mark.parametrize(("crs", "x0", "words"), [
    ("EPSG:32631", 3e7, "lie outside the domain of its CRS (EPSG:32631)"),
    (LOCAL_CRS, 1000.0, "is a local (engineering) one ('site grid')"),
], ids=["utm-at-3e7", "local-crs"])
@pytest.mark.parametrize("sun", ["auto", "none"])
def test_an_orthophoto_with_no_place_on_earth_is_refused_when_opened(crs: str, x0: float, words: str, sun: str,
                                                                     towns, tmp_path: Path,
                                                                     capsys: pytest.CaptureFixture) -> None:
    """UTM at x = 3e7, or a local engineering CRS: one line naming the file and the fix, before any work (no
    layer written), whatever --sun says."""
    data = np.random.default_rng(0).integers(1, 256, size=(3, 40, 56)).astype(np.uint8)
    ortho = write_raster(tmp_path / "o.tif", data, crs=crs, transform=Affine(0.5, 0, x0, 0, -0.5, 5000000.0))
    code, err = _predict(capsys, towns, ortho, tmp_path / "p", "--sun", sun)
    lines = err.split("Error: ")[1:]
    assert code == 1 and len(lines) == 1, err
    assert f"orthophoto '{ortho}'" in lines[0] and words in lines[0] and "gdal_edit.py -a_srs" in lines[0], err
    assert not (tmp_path / "p").exists() or not list((tmp_path / "p").glob("*.tif"))


def test_a_training_area_in_a_geographic_crs_is_measured_not_a_crash(towns) -> None:
    """A (crafted) training area in degrees: the same-flight test brings it onto the orthophoto's grid; one outside
    its CRS's domain is simply not of the same flight."""
    grid = Grid(rasterio.crs.CRS.from_epsg(32631), Affine(0.5, 0, ORIGIN[0], 0, -0.5, ORIGIN[1]), SIZE, SIZE)
    fit: TrainingSun = towns["fit"]
    lon, lat = lonlat("EPSG:32631", ORIGIN[0] + 32, ORIGIN[1] - 32)
    near = dataclasses.replace(fit, crs="EPSG:4326", bounds=(lon - 0.001, lat - 0.001, lon + 0.001, lat + 0.001))
    assert same_flight(grid, near)
    assert choose_sun("auto", None, towns["b"], grid, {}, near).source == "training fit"
    nowhere = dataclasses.replace(fit, crs="EPSG:4326", bounds=(0.0, 1000.0, 1.0, 1001.0))
    assert not same_flight(grid, nowhere)
    assert not choose_sun("auto", None, towns["b"], grid, {}, nowhere).on


# ---- unclear items -------------------------------------------------------------------------------------------------
def test_sun_90_90_is_refused_at_parse_with_the_real_reason(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """`--sun 90,90` (the zenith) is refused before the model is read, saying why, not later in other words."""
    ckpt = tmp_path / "m.pt"
    ckpt.write_bytes(b"not read")
    ortho = write_raster(tmp_path / "o.tif", np.full((3, 40, 56), 90, np.uint8))
    code, _, err = run_cli(capsys, "predict", ortho, "--model", ckpt, "--out", tmp_path / "p", "--sun", "90,90")
    err = " ".join(err.split())
    assert code == 2 and "--sun" in err and "elevation 90° is outside (0, 90)°" in err and "zenith" in err, err
    assert "'sun' elevation" not in err and not (tmp_path / "p").exists()


def test_a_mosaic_source_without_a_time_does_not_take_the_others(towns, tmp_path: Path) -> None:
    """A VRT of a dated and an undated orthophoto: the mosaic has no time (a warning names the undated source), so
    the sun is not the dated one's; here the same flight's fit."""
    west, east = Affine(0.5, 0, ORIGIN[0], 0, -0.5, ORIGIN[1]), Affine(0.5, 0, ORIGIN[0] + 32, 0, -0.5, ORIGIN[1])
    vrt, grid = dated_mosaic(tmp_path, [("dated.tif", "2021:06:01 09:00:00", west), ("undated.tif", None, east)])
    with pytest.warns(UserWarning, match=r"mosaic '.*mosaic.vrt': 1 of its 2 sources state no acquisition time "
                                         r"\(undated.tif\)"):
        choice = choose_sun("auto", None, vrt, grid, {}, towns["fit"])
    assert choice.source == "training fit" and choice.acquired is None


# ---- a later flight of the training town (issue 58, item 5) --------------------------------------------------------
@pytest.mark.parametrize("town", ["a_later", "b"])
def test_a_later_flight_of_the_training_place_without_a_time_gets_no_training_sun(town: str, towns, tmp_path: Path,
                                                                                 capsys: pytest.CaptureFixture) -> None:
    """Town A flown again at WHEN (every house in place, its sun 14° away; or town B, rebuilt): no time, and by place
    it is "the same flight". Its pixels over the training area are not the training orthophoto's, so the training
    fit is not its sun: the shadow layers are off, the warning says why and how to give its time, prediction.json
    records it. A checkpoint fitted before chips were kept decides by place alone, as before."""
    code, err = _predict(capsys, towns, towns[town], tmp_path / "p", model="chips")
    assert code == 0, err
    sun = _sun(tmp_path / "p")
    assert sun["source"] == "none" and sun["azimuth_deg"] is None, sun
    note = str(sun["note"])
    assert "covers the training area but is another flight" in note and "--acquired" in note, note
    assert "no shadow features: off: no acquisition time, and the orthophoto covers the training area" in err, err
    assert flight_match(towns[town], towns["fit"]).r is None  # a fit without chips: place alone decides
    code, err = _predict(capsys, towns, towns[town], tmp_path / "old")
    assert code == 0 and _sun(tmp_path / "old")["source"] == "training fit", err


def test_the_training_orthophoto_reprojected_and_recompressed_is_still_the_training_flight(
        towns, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """Town A's own orthophoto, warped onto a grid a third of a pixel off and saved as JPEG: the same flight, so
    the training fit's sun, and the note says its pixels matched."""
    from rasterio.warp import Resampling, reproject

    with rasterio.open(towns["a"]) as src:
        shifted = Affine(0.5, 0, ORIGIN[0] + 0.17, 0, -0.5, ORIGIN[1] - 0.17)
        data = np.zeros((3, SIZE - 1, SIZE - 1), np.uint8)
        for b in range(3):
            reproject(rasterio.band(src, b + 1), data[b], dst_transform=shifted, dst_crs=src.crs,
                      resampling=Resampling.bilinear)
    ortho = write_raster(tmp_path / "a_again.tif", data, transform=shifted, compress="JPEG", jpeg_quality=60,
                         tiled=True, blockxsize=64, blockysize=64)
    code, err = _predict(capsys, towns, ortho, tmp_path / "p", model="chips")
    assert code == 0, err
    sun = _sun(tmp_path / "p")
    assert sun["source"] == "training fit" and sun["azimuth_deg"] == pytest.approx(towns["fit"].azimuth_deg, abs=0.01)
    assert "same flight: its pixels match the training orthophoto's at r = " in str(sun["note"]), sun
    assert "no shadow features" not in err, err


def test_the_chips_tell_the_same_flight_from_a_later_one_with_a_margin(towns) -> None:
    """The measure behind the two tests above: town A's orthophoto matches its chips at r = 1; the same town under
    a sun 14° away, and another town, stay below SAME_FLIGHT_R."""
    fit = dataclasses.replace(towns["fit"], chips=_chips(towns))
    same = flight_match(towns["a"], fit)
    assert same.chips == towns["n_chips"] >= 3 and same.r == pytest.approx(1.0, abs=1e-3)
    later = flight_match(towns["a_later"], fit)
    assert later.chips == towns["n_chips"] and later.r is not None and later.r < SAME_FLIGHT_R - 0.01, later
    other = flight_match(towns["b"], fit)
    assert other.r is not None and other.r < 0.5, other


@pytest.mark.parametrize("how", ["--acquired", "TIFF DateTime"])
def test_a_later_flight_with_its_time_gets_its_own_sun(how: str, towns, tmp_path: Path,
                                                       capsys: pytest.CaptureFixture) -> None:
    """The later flight of town A with its time (given, or in its TIFF DateTime): its own sun, 14° from the fit,
    used as stated. The TIFF DateTime is not doubted in favour of the fit: the fit is another flight's."""
    az_b, el_b = towns["sun_b"]
    ortho = _copy(towns["a_later"], tmp_path / "later.tif")
    options: tuple[str, ...] = ("--acquired", WHEN) if how == "--acquired" else ()
    if how == "TIFF DateTime":
        with rasterio.open(ortho, "r+") as dst:
            dst.update_tags(TIFFTAG_DATETIME=WHEN.replace("-", ":").replace("T", " ").rstrip("Z"))
    code, err = _predict(capsys, towns, ortho, tmp_path / "p", *options, model="chips")
    assert code == 0, err
    sun = _sun(tmp_path / "p")
    assert sun["source"] == how and sun["acquired"] == WHEN, sun
    assert sun["azimuth_deg"] == pytest.approx(az_b, abs=0.01) and sun["elevation_deg"] == pytest.approx(el_b, abs=0.01)
    assert "training fit" not in err, err


def _chips(towns: dict[str, object]) -> tuple[object, ...]:
    sun = load_checkpoint(towns["chips"])[1].sun  # as predict reads them back
    assert sun is not None
    return sun.chips


@pytest.mark.parametrize("grey", ["not base64!", "AAAA"])
def test_a_damaged_flight_chip_in_a_checkpoint_is_refused_naming_the_fix(grey: str, towns) -> None:
    """A checkpoint whose training squares were cut short or garbled is refused when read, saying to refit the sun,
    rather than comparing an orthophoto with garbage."""
    from aerialmtl.config import from_dict, to_dict
    from aerialmtl.errors import CheckpointError

    record = to_dict(dataclasses.replace(towns["fit"], chips=_chips(towns)))
    record["chips"][0]["grey"] = grey
    with pytest.raises(CheckpointError, match=r"flight chip.*refit the sun"):
        from_dict(TrainingSun, record)
