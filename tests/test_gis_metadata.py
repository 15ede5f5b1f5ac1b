"""What GIS tools read beside the rasters: STAC item/collection, QGIS styles, mosaic overviews."""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
import rasterio
from affine import Affine
from helpers.models import IdentityModel, identity_meta
from helpers.rasters import write_raster
from shapely.geometry import Point, shape
from stac_pydantic import Collection as PydanticCollection
from stac_pydantic import Item as PydanticItem

from aerialmtl.errors import OutputExistsError
from aerialmtl.formats.qgis_style import layer_style, write_style
from aerialmtl.formats.stac import read_item
from aerialmtl.inference.jobs import predict_many
from aerialmtl.inference.predict import predict_raster
from aerialmtl.io.stats import band_stats
from aerialmtl.io.vrt import mosaic_vrt

T = Affine(0.5, 0, 500000.0, 0, -0.5, 5000000.0)  # EPSG:32631, near 0°E 45°N


def _ortho(path: Path, seed: int, transform: Affine = T) -> Path:
    rng = np.random.default_rng(seed)
    img = rng.integers(1, 101, size=(3, 48, 64)).astype(np.uint8)  # identity model: height = band 1 (m)
    img[:, :6, :6] = 0  # nodata corner
    return write_raster(path, img, crs="EPSG:32631", transform=transform, nodata=0)


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One multi-input run (two inputs, T = 2): folders a/ and b/, mosaics, collection."""
    tmp = tmp_path_factory.mktemp("gis")
    meta = identity_meta()
    model = IdentityModel(meta.mean, meta.std, dropout=0.5)
    a = _ortho(tmp / "a.tif", 1)
    b = _ortho(tmp / "b.tif", 2, Affine(0.5, 0, 500032.0, 0, -0.5, 5000000.0))  # overlaps a by half
    predict_many([a, b], (model, meta), tmp / "out", mc=2, window=32, overlap=0, progress=False)
    return tmp / "out"


def _qml(path: Path) -> ET.Element:
    text = path.read_text(encoding="utf-8")
    assert text.startswith("<!DOCTYPE qgis")
    return ET.fromstring(text.split("\n", 1)[1])


def _core_schema_valid(data: dict) -> None:
    """The STAC 1.1 core JSON schema, from the copy pystac ships (the extension schemas would be fetched)."""
    import pystac.validation

    assert pystac.validation.validate_dict(dict(data, stac_extensions=[]))


def test_item_validates_and_describes_the_layers(run: Path) -> None:
    data = json.loads((run / "a" / "item.json").read_text())
    PydanticItem.model_validate(data)  # STAC 1.1 core, offline
    _core_schema_valid(data)
    assert data["stac_version"] == "1.1.0" and data["id"] == "a"
    assert any("projection" in e for e in data["stac_extensions"])
    assert any("classification" in e for e in data["stac_extensions"])
    # WGS 84 footprint around the grid (UTM 31N, 500000 E = 3° E)
    with rasterio.open(run / "a" / "height.tif") as src:
        bounds, crs = src.bounds, src.crs
    footprint = shape(data["geometry"])
    lon, lat = rasterio.warp.transform(crs, "EPSG:4326", [(bounds.left + bounds.right) / 2],
                                       [(bounds.bottom + bounds.top) / 2])
    assert footprint.contains(Point(lon[0], lat[0])) and 2.9 < lon[0] < 3.1
    assert data["bbox"] == pytest.approx(list(footprint.bounds))
    props = data["properties"]
    assert props["proj:code"] == "EPSG:32631" and props["proj:shape"] == [48, 64]
    assert props["aerialmtl:model"]["class_names"] == ["band 1", "band 2", "band 3"]
    assert props["aerialmtl:mc_samples"] == 2
    assets = data["assets"]
    for layer in ("height", "height_std", "classes", "class_entropy", "class_mutual_info"):
        assert assets[layer]["href"] == f"./{layer}.tif" and "data" in assets[layer]["roles"]
        assert (run / "a" / assets[layer]["href"]).is_file()
        assert assets[f"{layer}_style"]["href"] == f"./{layer}.qml"
    assert "uncertainty" in assets["height_std"]["roles"]
    band = assets["height"]["raster:bands"][0]
    assert band["unit"] == "m" and band["nodata"] == -9999.0 and band["data_type"] == "float32"
    assert 1.0 <= band["statistics"]["minimum"] <= band["statistics"]["maximum"] <= 100.0
    classes = assets["classes"]["classification:classes"]
    assert [c["name"] for c in classes[:3]] == ["band 1", "band 2", "band 3"]
    assert classes[0]["color_hint"] == "0050C8" and classes[-1] == {"value": 255, "name": "nodata", "nodata": True}
    assert read_item(run / "a" / "item.json").id == "a"  # pystac reads it back


def test_collection_links_items_and_mosaics(run: Path) -> None:
    data = json.loads((run / "collection.json").read_text())
    PydanticCollection.model_validate(data)
    _core_schema_valid(data)
    items = [link["href"] for link in data["links"] if link["rel"] == "item"]
    assert sorted(items) == ["./a/item.json", "./b/item.json"]
    assert all((run / h).is_file() for h in items)
    west, south, east, north = data["extent"]["spatial"]["bbox"][0]
    a_box = json.loads((run / "a" / "item.json").read_text())["bbox"]
    b_box = json.loads((run / "b" / "item.json").read_text())["bbox"]
    assert west == min(a_box[0], b_box[0]) and east == max(a_box[2], b_box[2])
    assert data["assets"]["height_mosaic"]["href"] == "./height.mosaic.vrt"
    assert (run / "height.mosaic.vrt").is_file() and (run / "height.mosaic.qml").is_file()


def test_every_layer_and_mosaic_has_a_style_qgis_can_apply(run: Path) -> None:
    for folder in (run / "a", run / "b"):
        for tif in folder.glob("*.tif"):
            assert tif.with_suffix(".qml").is_file(), tif
    for vrt in run.glob("*.mosaic.vrt"):
        assert vrt.with_suffix(".qml").is_file(), vrt

    # height: pseudocolour 0..p98 (m), nodata transparent; p98 from the data
    root = _qml(run / "a" / "height.qml")
    renderer = root.find("pipe/rasterrenderer")
    assert renderer is not None and renderer.get("type") == "singlebandpseudocolor"
    with rasterio.open(run / "a" / "height.tif") as src:
        h = src.read(1, masked=True).compressed()
    p98 = float(np.percentile(h, 98))
    assert float(renderer.get("classificationMin", "nan")) == 0.0
    assert float(renderer.get("classificationMax", "nan")) == pytest.approx(p98, rel=1e-6)
    items = renderer.findall("rastershader/colorrampshader/item")
    assert len(items) >= 2 and items[-1].get("label", "").endswith(" m")
    # the continuous legend QGIS draws in the layers panel and print layouts: "0 m" ... "12.4 m"
    legend = renderer.find("rastershader/colorrampshader/rampLegendSettings")
    assert legend is not None and legend.get("suffix") == " m" and legend.get("useContinuousLegend") == "1"
    entry = renderer.find("rasterTransparency/singleValuePixelList/pixelListEntry")
    assert entry is not None and float(entry.get("min", "0")) == -9999.0 and entry.get("percentTransparent") == "100"
    for name in ("height_std", "class_entropy", "class_mutual_info"):
        r = _qml(run / "a" / f"{name}.qml").find("pipe/rasterrenderer")
        assert r is not None and r.get("type") == "singlebandpseudocolor"

    # classes: paletted with the class names, nodata (255) not in the palette but transparent
    for path in (run / "a" / "classes.qml", run / "classes.mosaic.qml"):
        renderer = _qml(path).find("pipe/rasterrenderer")
        assert renderer is not None and renderer.get("type") == "paletted"
        entries = renderer.findall("colorPalette/paletteEntry")
        assert [(e.get("value"), e.get("label")) for e in entries] == [("0", "band 1"), ("1", "band 2"),
                                                                       ("2", "band 3")]
        assert entries[0].get("color") == "#0050c8"
        t = renderer.find("rasterTransparency/singleValuePixelList/pixelListEntry")
        assert t is not None and t.get("min") == "255"

    # the height mosaic's range comes from the mosaic
    mosaic = _qml(run / "height.mosaic.qml").find("pipe/rasterrenderer")
    assert mosaic is not None and 50.0 < float(mosaic.get("classificationMax", "0")) <= 100.0


def test_mosaics_report_overviews_from_the_sources(tmp_path: Path) -> None:
    from aerialmtl.io.cog import to_cog

    sources = []
    for k in range(2):
        raw = write_raster(tmp_path / f"r{k}.tif", np.full((1, 600, 600), k + 1.0, np.float32),
                           transform=Affine(0.5, 0, 500000.0 + 300 * k, 0, -0.5, 5000000.0), nodata=-9999.0)
        to_cog(raw, tmp_path / f"c{k}.tif")
        sources.append(tmp_path / f"c{k}.tif")
    vrt = mosaic_vrt(tmp_path / "m.vrt", sources)
    with rasterio.open(vrt) as src:
        assert src.overviews(1) == [2, 4]  # 1200 × 600 px down to ≥ 256 px
        small = src.read(1, out_shape=(150, 300))
        assert set(np.unique(small)) == {1.0, 2.0}
    with rasterio.open(mosaic_vrt(tmp_path / "n.vrt", sources, overviews=False)) as src:
        assert src.overviews(1) == []


def test_style_of_an_empty_layer_and_stats_without_valid_pixels(tmp_path: Path) -> None:
    path = write_raster(tmp_path / "e.tif", np.full((1, 8, 8), -9999.0, np.float32), nodata=-9999.0)
    assert band_stats(path) is None
    spec = identity_meta()  # any spec will do: take the height layer of a prediction schema
    from aerialmtl.formats.prediction import prediction_layers

    height = prediction_layers(("height",), spec.classes, 1)[0]
    out = write_style(tmp_path / "e.qml", layer_style(height, None))
    r = _qml(out).find("pipe/rasterrenderer")
    assert r is not None and float(r.get("classificationMax", "0")) > 0.0  # a valid range, not 0..0


def test_single_input_writes_item_but_no_collection(tmp_path: Path) -> None:
    meta = identity_meta()
    res = predict_raster(_ortho(tmp_path / "o.tif", 3), (IdentityModel(meta.mean, meta.std), meta), tmp_path / "p",
                         mc=1, window=32, overlap=0, progress=False)
    info = json.loads(res.files["prediction"].read_text())
    assert info["files"]["item"] == "item.json" and info["files"]["height_style"] == "height.qml"
    assert (tmp_path / "p" / "item.json").is_file() and not (tmp_path / "p" / "collection.json").exists()


# ---- building footprints -----------------------------------------------------------------------
def _edge_buildings(folder: Path) -> Path:
    """Buildings rotated 12-40° and cut by the right edge of a 64 × 64 px (32 m) raster."""
    from helpers.rasters import write_prediction_layers
    from rasterio.features import rasterize
    from shapely import affinity
    from shapely.geometry import box

    polys = [affinity.rotate(box(50, 4, 74, 22), 12), affinity.rotate(box(52, 36, 76, 56), 40)]
    mask = rasterize(polys, out_shape=(64, 64)).astype(bool)
    cls = np.where(mask, 2, 0).astype(np.uint8)  # 2 = building in the synthetic scheme
    height = np.where(mask, 8.0, 0.1).astype(np.float32)
    return write_prediction_layers(folder, cls, height)


def test_footprints_stay_inside_the_raster_and_geopackage_is_version_1_2(tmp_path: Path) -> None:
    import sqlite3

    from shapely.geometry import box

    from aerialmtl.buildings import iter_buildings, write_buildings
    from aerialmtl.formats.buildings import read_footprints

    pred = _edge_buildings(tmp_path / "pred")
    raster = box(500000.0, 5000000.0 - 32.0, 500000.0 + 32.0, 5000000.0)
    buildings = list(iter_buildings(pred))
    assert len(buildings) == 2
    for b in buildings:  # regularised walls used to meet up to 1.4 m beyond the edge here
        assert raster.covers(b.geometry) and b.geometry.bounds[2] == pytest.approx(500032.0)
    out = tmp_path / "b.gpkg"
    write_buildings(pred, [out])
    geoms, _, _ = read_footprints(out)
    assert all(raster.covers(g) for g in geoms)
    with sqlite3.connect(out) as db:  # GDAL 3.6 (QGIS LTR) reads 1.2 without a version warning
        assert db.execute("PRAGMA application_id").fetchone()[0] == 0x47504B47  # 'GPKG'
        assert db.execute("PRAGMA user_version").fetchone()[0] == 10200


# ---- PNG previews --------------------------------------------------------------------------------
def test_demo_preview_has_class_names_and_colour_bars_with_units(run: Path, tmp_path: Path) -> None:
    pytest.importorskip("matplotlib")
    import matplotlib.pyplot as plt

    from aerialmtl.demo import preview_figure, write_previews

    ortho = run.parent / "a.tif"
    fig = preview_figure(ortho, run / "a", None, None)
    try:
        legends = [ax.get_legend() for ax in fig.axes if ax.get_legend() is not None]
        assert len(legends) == 1  # the predicted classes
        assert [t.get_text() for t in legends[0].get_texts()] == ["band 1", "band 2", "band 3"]
        bar_labels = {ax.get_ylabel() for ax in fig.axes if ax.get_ylabel()}
        assert {"predicted height (m)", "height std (MC dropout) (m)", "class entropy (nats)",
                "mutual information (nats)"} <= bar_labels
        assert not any("class" in label and "(" not in label for label in bar_labels)  # no index colour bar
    finally:
        plt.close(fig)
    png = write_previews(tmp_path / "prev", ortho, run / "a", None, None)
    assert png is not None and png.read_bytes()[:4] == b"\x89PNG"


def test_notebook_maps_use_the_qgis_ramps_and_label_units(run: Path) -> None:
    pytest.importorskip("matplotlib")
    from aerialmtl.evaluation.maps import load_prediction_maps, plot_maps

    fig, axes = plot_maps(load_prediction_maps(run / "a"))
    labels = {ax.get_ylabel() for ax in fig.axes}
    assert "predicted height (m)" in labels and "class entropy (nats)" in labels
    cmaps = {ax.get_title(): ax.images[0].get_cmap().name for ax in axes if ax.images}
    assert cmaps["predicted height (m)"] == "viridis" and cmaps["height std (m)"] == "YlOrRd"


def test_band_stats_of_a_large_raster_come_from_its_overviews(tmp_path: Path) -> None:
    from aerialmtl.io.cog import to_cog

    rng = np.random.default_rng(0)
    y, x = np.mgrid[0:1024, 0:1024]
    data = (10 + 8 * np.sin(x / 50.0) * np.cos(y / 70.0) + rng.normal(0, 0.3, (1024, 1024))).astype(np.float32)
    data[:128, :128] = -9999.0
    to_cog(write_raster(tmp_path / "raw.tif", data[None], nodata=-9999.0), tmp_path / "h.tif")
    valid = data[data != -9999.0]
    stats = band_stats(tmp_path / "h.tif", max_pixels=256 * 256)  # a 4× decimated read: the overviews
    assert stats is not None and stats.approximate
    assert stats.p98 == pytest.approx(np.percentile(valid, 98), rel=0.03)
    assert stats.mean == pytest.approx(valid.mean(), rel=0.01)
    assert stats.valid_percent == pytest.approx(100 * valid.size / data.size, abs=0.5)
    exact = band_stats(tmp_path / "h.tif")  # small enough to be read whole
    assert exact is not None and not exact.approximate
    assert exact.p98 == pytest.approx(np.percentile(valid, 98), rel=1e-6)


def test_edited_styles_and_item_keep_a_folder_complete_for_skip_existing(tmp_path: Path) -> None:
    meta = identity_meta()
    model = IdentityModel(meta.mean, meta.std)
    a, b = _ortho(tmp_path / "a.tif", 1), _ortho(tmp_path / "b.tif", 2)
    args = dict(mc=1, window=32, overlap=0, progress=False)
    predict_many([a, b], (model, meta), tmp_path / "out", **args)
    qml = tmp_path / "out" / "a" / "height.qml"
    qml.write_text(qml.read_text().replace('opacity="1"', 'opacity="0.5"'))  # QGIS "Save as default"
    item = tmp_path / "out" / "a" / "item.json"
    data = json.loads(item.read_text())
    data["properties"]["datetime"] = "2024-05-01T10:00:00Z"  # the flight date, set by the user
    item.write_text(json.dumps(data))
    job = predict_many([a, b], (model, meta), tmp_path / "out", skip_existing=True, **args)
    assert sorted(Path(s).name for s in job.skipped) == ["a.tif", "b.tif"] and not job.recomputed
    assert 'opacity="0.5"' in qml.read_text()


def test_a_users_collection_or_mosaic_in_out_is_never_replaced_without_overwrite(tmp_path: Path) -> None:
    """A multi-input run claims its mosaics, their styles and collection.json like the layers: a user's own
    are refused before any work (they were replaced silently, exit 0); the run's own are replaced by
    --skip-existing (its collection.json lists them)."""
    meta = identity_meta()
    model = IdentityModel(meta.mean, meta.std, dropout=0.5)
    a, b = _ortho(tmp_path / "a.tif", 1), _ortho(tmp_path / "b.tif", 2, Affine(0.5, 0, 500032.0, 0, -0.5, 5000000.0))
    out = tmp_path / "out"
    out.mkdir()
    (out / "collection.json").write_text('{"mine": 1}')
    (out / "height.mosaic.qml").write_text("<mine/>")
    with pytest.raises(OutputExistsError, match=r"height\.mosaic\.qml, collection\.json"):
        predict_many([a, b], (model, meta), out, mc=2, window=32, overlap=0, progress=False)
    assert (out / "collection.json").read_text() == '{"mine": 1}' and not (out / "a").exists()
    (out / "collection.json").unlink()
    (out / "height.mosaic.qml").unlink()
    predict_many([a, b], (model, meta), out, mc=2, window=32, overlap=0, progress=False)
    predict_many([a, b], (model, meta), out, mc=2, window=32, overlap=0, progress=False, skip_existing=True)
    assert json.loads((out / "collection.json").read_text())["type"] == "Collection"
