"""`aerialmtl buildings`: footprints from a prediction folder, streamed in blocks, in metres whatever the CRS."""

from __future__ import annotations

import json
import math
import warnings
from pathlib import Path

import numpy as np
import pytest
import rasterio
import shapely
from affine import Affine
from helpers.cli import run_cli
from helpers.rasters import write_prediction_layers, write_raster
from rasterio.crs import CRS
from rasterio.features import rasterize
from scipy import ndimage
from shapely import affinity
from shapely.geometry import Polygon, box

from aerialmtl.buildings import (
    BuildingOptions,
    ExtractionStats,
    building_class_indices,
    iter_buildings,
    write_buildings,
)
from aerialmtl.buildings.clean import clean_footprint
from aerialmtl.classes import IGNORE_INDEX, ClassScheme
from aerialmtl.errors import InputError, OutputExistsError
from aerialmtl.formats.buildings import LAYER, PREDICTED_FIELDS, read_footprints

pyogrio = pytest.importorskip("pyogrio")

BUILDING, SOIL = 2, 0  # indices of the built-in "synthetic" scheme
T = Affine(0.5, 0, 500000.0, 0, -0.5, 5000000.0)  # the conftest default grid: 0.5 m pixels


def _layers(shape: tuple[int, int], rects: list[tuple[int, int, int, int, float]], rng: np.random.Generator,
            nodata_cols: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """classes / height / std / entropy with building rectangles (row0, row1, col0, col1, height m)."""
    cls = np.full(shape, SOIL, np.uint8)
    height = rng.uniform(0.0, 0.3, shape).astype(np.float32)
    for r0, r1, c0, c1, h in rects:
        cls[r0:r1, c0:c1] = BUILDING
        height[r0:r1, c0:c1] = h + rng.normal(0, 0.2, (r1 - r0, c1 - c0))
    std = rng.uniform(0.1, 1.0, shape).astype(np.float32)
    entropy = rng.uniform(0.0, 1.0, shape).astype(np.float32)
    if nodata_cols:
        cls[:, :nodata_cols] = IGNORE_INDEX
        for arr in (height, std, entropy):
            arr[:, :nodata_cols] = -9999.0
    return cls, height, std, entropy


def _by_position(buildings: list) -> list:
    return sorted(buildings, key=lambda b: (round(b.geometry.centroid.x, 6), round(b.geometry.centroid.y, 6)))


# ---- geometry and attributes -----------------------------------------------------------------
def test_polygon_on_map_coordinates_with_attributes(tmp_path: Path, rng: np.random.Generator) -> None:
    cls, height, std, ent = _layers((64, 64), [(10, 30, 5, 45, 12.0)], rng)
    pred = write_prediction_layers(tmp_path / "pred", cls, height, std, ent)
    found = list(iter_buildings(pred))
    assert len(found) == 1
    b = found[0]
    # rows 10..29, cols 5..44 of 0.5 m pixels from (500000, 5000000)
    assert b.geometry.equals(box(500002.5, 4999985.0, 500022.5, 4999995.0))
    inside = (slice(10, 30), slice(5, 45))
    a = b.attributes
    assert a["n_pixels"] == 800 and a["ground_area_m2"] == pytest.approx(200.0)
    assert a["height_m"] == pytest.approx(np.median(height[inside]), abs=1e-5)
    assert a["height_std_m"] == pytest.approx(np.median(std[inside]), abs=1e-6)
    assert a["volume_m3"] == pytest.approx(np.maximum(height[inside], 0).mean() * 200.0, rel=1e-5)
    assert a["class_confidence"] == pytest.approx(np.mean(1 - ent[inside] / math.log(6)), abs=1e-5)
    assert a["class_name"] == "building"
    high = list(iter_buildings(pred, BuildingOptions(height_percentile=90)))[0].attributes["height_m"]
    assert high == pytest.approx(np.percentile(height[inside], 90), abs=1e-5) and high > a["height_m"]


def test_without_uncertainty_layers_the_attributes_are_undefined(tmp_path: Path, rng: np.random.Generator) -> None:
    cls, height, _, _ = _layers((40, 40), [(5, 30, 5, 30, 6.0)], rng)
    pred = write_prediction_layers(tmp_path / "pred", cls, height)
    (b,) = list(iter_buildings(pred))
    assert math.isnan(b.attributes["height_std_m"]) and math.isnan(b.attributes["class_confidence"])
    out = write_buildings(pred, [tmp_path / "b.gpkg"])
    _, fields, _ = read_footprints(tmp_path / "b.gpkg")
    assert out.count == 1 and np.isnan(fields["height_std_m"][0])


def test_small_buildings_dropped_holes_filled_courtyards_kept(tmp_path: Path, rng: np.random.Generator) -> None:
    cls, height, std, ent = _layers((80, 80), [(2, 6, 2, 6, 3.0), (10, 70, 10, 70, 9.0)], rng)
    cls[20:22, 20:22] = SOIL   # a 1 m² hole: filled
    cls[35:55, 35:55] = SOIL   # a 100 m² courtyard: kept
    pred = write_prediction_layers(tmp_path / "pred", cls, height, std, ent)
    stats = ExtractionStats()
    (b,) = list(iter_buildings(pred, stats=stats))  # the 4 m² shed is below min_area_m2 = 10
    assert stats.too_small == 1 and stats.components == 2
    assert len(b.geometry.interiors) == 1
    assert Polygon(b.geometry.interiors[0]).area == pytest.approx(100.0)
    assert b.attributes["ground_area_m2"] == pytest.approx(900.0 - 100.0)
    assert b.attributes["n_pixels"] == 3600 - 400 - 4
    assert len(list(iter_buildings(pred, BuildingOptions(min_area_m2=1.0)))) == 2


def test_rotated_outlines_are_squared(rng: np.random.Generator) -> None:
    """A rasterised rotated rectangle / L comes back with 4 / 6 right-angled corners, closer to the truth."""
    for shape_, corners in ((box(20, 20, 80, 50), 4),
                            (Polygon([(20, 20), (90, 20), (90, 40), (50, 40), (50, 75), (20, 75)]), 6)):
        for angle in (0.0, 12.0, 27.0, 45.0, 71.0):
            truth = affinity.rotate(shape_, angle, origin=(50.3, 50.1))
            mask = rasterize([truth], out_shape=(100, 100)).astype(np.uint8)
            (raw,) = [shapely.geometry.shape(g) for g, _ in rasterio.features.shapes(mask, mask=mask > 0)]
            clean = clean_footprint(raw, max_hole_area=4.0, tolerance=1.5)
            assert clean is not None and len(clean.exterior.coords) - 1 == corners, (angle, corners)
            xy = np.asarray(clean.exterior.coords)
            d = np.diff(np.vstack([xy, xy[1:2]]), axis=0)
            cos = [abs(np.dot(u, v)) / np.linalg.norm(u) / np.linalg.norm(v) for u, v in zip(d[:-1], d[1:])]
            assert max(cos) < math.sin(math.radians(1.0))
            iou = clean.intersection(truth).area / clean.union(truth).area
            assert iou > 0.96 and iou >= raw.intersection(truth).area / raw.union(truth).area - 0.005


def test_fast_supports_and_principal_axis_match_the_plain_versions(rng: np.random.Generator) -> None:
    """The vectorised vertex lookup and the closed-form principal axis give what a dict lookup and an SVD give."""
    from aerialmtl.buildings.clean import _supports

    truth = affinity.rotate(box(20, 20, 80, 50), 23.0, origin=(50.3, 50.1))
    mask = rasterize([truth], out_shape=(100, 100)).astype(np.uint8)
    (raw,) = [shapely.geometry.shape(g) for g, _ in rasterio.features.shapes(mask, mask=mask > 0)]
    original = np.asarray(raw.exterior.coords)[:-1]
    simple = np.asarray(raw.simplify(1.5).exterior.coords)[:-1]
    spans = _supports(simple, original)
    pos = {tuple(p): i for i, p in enumerate(original.tolist())}
    idx = [pos[tuple(p)] for p in simple.tolist()]
    n = len(original)
    assert spans is not None and len(spans) == len(simple)
    for a, b, span in zip(idx, idx[1:] + idx[:1], spans):
        assert np.array_equal(span, original[[k % n for k in range(a, (b if b > a else b + n) + 1)]])
    assert _supports(simple + 0.25, original) is None  # vertices not in the original ring
    for _ in range(20):
        pts = rng.normal(size=(30, 2)) * [5.0, 1.0] @ np.array([[0.6, 0.8], [-0.8, 0.6]])
        c = pts - pts.mean(axis=0)
        axis = 0.5 * math.atan2(2 * c[:, 0] @ c[:, 1], c[:, 0] @ c[:, 0] - c[:, 1] @ c[:, 1])
        vt = np.linalg.svd(c, full_matrices=False)[2][0]
        assert abs(math.sin(axis - math.atan2(vt[1], vt[0]))) < 1e-9


# ---- streaming ----------------------------------------------------------------------------------
def test_buildings_across_block_edges_come_out_once(tmp_path: Path, rng: np.random.Generator) -> None:
    shape_ = (90, 110)
    rects = [(3, 40, 3, 20, 5.0), (50, 85, 30, 100, 9.0), (5, 30, 40, 100, 7.0)]
    cls, height, std, ent = _layers(shape_, rects, rng)
    cls[12:30, 50:90] = SOIL  # U shape: its two legs meet only in rows 5..11, across several block edges
    cls[60:80, 60:70] = SOIL  # courtyard
    cls[20:45, 70:74] = BUILDING  # joins nothing
    pred = write_prediction_layers(tmp_path / "pred", cls, height, std, ent)
    options = BuildingOptions(min_area_m2=0.0, max_hole_m2=0.0)
    whole = _by_position(list(iter_buildings(pred, BuildingOptions(min_area_m2=0.0, max_hole_m2=0.0,
                                                                    block_size=512))))
    n_components = ndimage.label(cls == BUILDING)[1]  # default structure: 4-connectivity
    assert len(whole) == n_components == 4
    for block in (7, 16, 33, 50):
        stats = ExtractionStats()
        blocks = _by_position(list(iter_buildings(pred, BuildingOptions(**{**options.__dict__, "block_size": block}),
                                                  stats=stats)))
        assert stats.components > n_components  # the pieces were really cut by block edges ...
        assert len(blocks) == len(whole)        # ... and merged back: each building once
        for a, b in zip(whole, blocks):
            assert a.geometry.equals_exact(b.geometry, 1e-9), block
            for key, value in a.attributes.items():
                if isinstance(value, float):
                    assert b.attributes[key] == pytest.approx(value, rel=1e-6, nan_ok=True), (block, key)
                else:
                    assert b.attributes[key] == value, (block, key)


def test_random_layouts_give_the_same_buildings_for_any_block_size(tmp_path: Path) -> None:
    rng = np.random.default_rng(7)
    for trial in range(3):
        mask = ndimage.binary_opening(rng.random((70, 90)) < 0.55, iterations=1)
        cls = np.where(mask, BUILDING, SOIL).astype(np.uint8)
        height = rng.uniform(2, 20, mask.shape).astype(np.float32)
        pred = write_prediction_layers(tmp_path / f"pred{trial}", cls, height)
        ref = None
        for block in (9, 32, 128):
            got = _by_position(list(iter_buildings(pred, BuildingOptions(min_area_m2=0.0, block_size=block))))
            areas = sorted(b.attributes["n_pixels"] for b in got)
            if ref is None:
                ref = areas
                assert sum(areas) == int(mask.sum())
                assert len(areas) == ndimage.label(mask)[1]
            assert areas == ref, (trial, block)


def test_height_steps_split_touching_buildings(tmp_path: Path, rng: np.random.Generator) -> None:
    cls, height, std, ent = _layers((60, 60), [(10, 50, 5, 30, 4.0), (10, 50, 30, 55, 12.0)], rng)
    pred = write_prediction_layers(tmp_path / "pred", cls, height, std, ent)
    assert len(list(iter_buildings(pred))) == 1
    for block in (30, 31, 64):  # the step on a block edge, beside one, inside one block
        found = _by_position(list(iter_buildings(pred, BuildingOptions(height_step_m=3.0, block_size=block))))
        assert [round(b.attributes["height_m"]) for b in found] == [4, 12], block
        assert [b.attributes["n_pixels"] for b in found] == [1000, 1000], block


# ---- class scheme, CRS units, inputs ---------------------------------------------------------------
def test_building_classes_recognised_by_name_or_given() -> None:
    assert building_class_indices(ClassScheme.load("synthetic")) == [2]
    assert building_class_indices(ClassScheme.load("isprs")) == [1]
    assert building_class_indices(ClassScheme.load("dfc2018")) == [7, 8]
    assert building_class_indices(ClassScheme.load("dfc2018"), ["residential buildings", 8]) == [7, 8]
    assert building_class_indices(None, ["3"]) == [3]
    with pytest.raises(InputError, match="no class named 'building"):
        building_class_indices(ClassScheme.from_dict({"name": "veg", "classes": [{"code": 1, "name": "tree"}]}))
    with pytest.raises(InputError, match="'roof' is not a class of scheme 'synthetic'"):
        building_class_indices(ClassScheme.load("synthetic"), ["roof"])
    with pytest.raises(InputError, match="class index 9 is not in 0..5"):
        building_class_indices(ClassScheme.load("synthetic"), [9])
    with pytest.raises(InputError, match="no AERIALMTL_CLASS_SCHEME tag"):
        building_class_indices(None)


def test_areas_in_square_metres_for_a_crs_in_feet(tmp_path: Path, rng: np.random.Generator) -> None:
    cls, height, std, ent = _layers((64, 64), [(10, 50, 10, 30, 10.0)], rng)
    feet = Affine(1.0, 0, 635615.0, 0, -1.0, 853362.0)  # 1 international foot pixels, EPSG:2994 (Oregon, ft)
    pred = write_prediction_layers(tmp_path / "ft", cls, height, std, ent, crs="EPSG:2994", transform=feet)
    (b,) = list(iter_buildings(pred))
    assert b.attributes["ground_area_m2"] == pytest.approx(800 * 0.3048**2)
    assert b.attributes["volume_m3"] == pytest.approx(b.attributes["height_m"] * 800 * 0.3048**2, rel=0.05)
    assert b.geometry.equals(box(635625.0, 853312.0, 635645.0, 853352.0))  # coordinates stay in feet
    # min_area_m2 is in m² too: 800 ft² = 74.3 m²
    assert not list(iter_buildings(pred, BuildingOptions(min_area_m2=75.0)))
    out = write_buildings(pred, [tmp_path / "ft.city.json"])
    doc = json.loads((tmp_path / "ft.city.json").read_text())
    z = np.asarray(doc["vertices"])[:, 2] * doc["transform"]["scale"][2]
    assert z.max() == pytest.approx(b.attributes["height_m"] / 0.3048, abs=0.002)  # z in the CRS unit (ft)
    assert out.count == 1


def test_geographic_or_missing_crs_is_refused(tmp_path: Path, rng: np.random.Generator) -> None:
    cls, height, _, _ = _layers((40, 40), [(5, 30, 5, 30, 6.0)], rng)
    geo = write_prediction_layers(tmp_path / "geo", cls, height, crs="EPSG:4326",
                                  transform=Affine(1e-5, 0, 2.0, 0, -1e-5, 48.0))
    with pytest.raises(InputError, match="geographic CRS.*reproject"):
        list(iter_buildings(geo))


def test_nodata_and_empty_predictions_give_clear_messages(tmp_path: Path, rng: np.random.Generator) -> None:
    cls, height, std, ent = _layers((40, 40), [], rng)
    nodata = np.full_like(cls, IGNORE_INDEX)
    pred = write_prediction_layers(tmp_path / "nodata", nodata, np.full_like(height, -9999.0))
    with pytest.raises(InputError, match=r"classes\.tif' is nodata everywhere"):
        write_buildings(pred, [tmp_path / "n.gpkg"])
    assert not list(tmp_path.glob("*n.gpkg*"))  # nothing left behind

    empty = write_prediction_layers(tmp_path / "empty", cls, height, std, ent)
    with pytest.warns(UserWarning, match="no building pixel .*1600 valid pixels"):
        result = write_buildings(empty, [tmp_path / "e.gpkg", tmp_path / "e.city.json"])
    assert result.count == 0
    assert pyogrio.read_info(tmp_path / "e.gpkg", layer=LAYER)["features"] == 0
    assert json.loads((tmp_path / "e.city.json").read_text())["CityObjects"] == {}

    # buildings beside nodata: only the valid pixels count
    cls2, height2, std2, ent2 = _layers((40, 40), [(5, 30, 0, 30, 6.0)], rng, nodata_cols=10)
    part = write_prediction_layers(tmp_path / "part", cls2, height2, std2, ent2)
    (b,) = list(iter_buildings(part))
    assert b.attributes["n_pixels"] == 25 * 20

    (tmp_path / "noheight").mkdir()
    write_prediction_layers(tmp_path / "noheight", cls, height)
    (tmp_path / "noheight" / "height.tif").unlink()
    with pytest.raises(InputError, match="has no height.tif"):
        list(iter_buildings(tmp_path / "noheight"))
    with pytest.raises(InputError, match="does not exist"):
        list(iter_buildings(tmp_path / "missing"))


# ---- outputs --------------------------------------------------------------------------------------
def test_geopackage_and_geojson_open_with_the_prediction_crs(tmp_path: Path, rng: np.random.Generator) -> None:
    cls, height, std, ent = _layers((64, 64), [(5, 25, 5, 25, 6.0), (35, 60, 10, 60, 15.0)], rng)
    pred = write_prediction_layers(tmp_path / "pred", cls, height, std, ent)
    outs = [tmp_path / "out" / "b.gpkg", tmp_path / "out" / "b.geojson"]
    result = write_buildings(pred, outs, batch_size=1)  # one append per building
    assert result.count == 2
    with rasterio.open(pred / "classes.tif") as src:
        crs = src.crs
    expected = list(iter_buildings(pred))
    for path in outs:
        info = pyogrio.read_info(path, layer=LAYER)
        assert CRS.from_user_input(info["crs"]) == crs
        assert info["geometry_type"] == "Polygon" and info["features"] == 2
        assert list(info["fields"]) == list(PREDICTED_FIELDS)
        geoms, fields, file_crs = read_footprints(path)
        assert file_crs == crs
        assert list(fields["building_id"]) == [1, 2]
        for g, b in zip(geoms, expected):
            assert g.equals_exact(b.geometry, 1e-6)
            assert fields["height_m"][b.id - 1] == pytest.approx(b.attributes["height_m"])
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["b.geojson", "b.gpkg"]  # no leftovers


def test_outputs_are_refused_when_present_and_written_all_or_nothing(tmp_path: Path, rng: np.random.Generator,
                                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    cls, height, std, ent = _layers((40, 40), [(5, 30, 5, 30, 6.0)], rng)
    pred = write_prediction_layers(tmp_path / "pred", cls, height, std, ent)
    write_buildings(pred, [tmp_path / "b.gpkg"])
    with pytest.raises(OutputExistsError, match="b.gpkg already exist.*overwrite=True"):
        write_buildings(pred, [tmp_path / "b.gpkg"])
    with pytest.raises(InputError, match=r"\.gpkg .*\.geojson .*\.city\.json"):
        write_buildings(pred, [tmp_path / "b.shp"])

    import aerialmtl.buildings.export as export

    original = export.extract_buildings

    def broken(*args: object, **kwargs: object):
        yield from original(*args, **kwargs)  # type: ignore[arg-type]
        raise RuntimeError("disk on fire")

    monkeypatch.setattr(export, "extract_buildings", broken)
    with pytest.raises(RuntimeError, match="disk on fire"):
        write_buildings(pred, [tmp_path / "new.gpkg", tmp_path / "new.city.json"])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b.gpkg", "pred"]


def check_cityjson(doc: dict) -> None:
    """Structural checks of a CityJSON 2.0 document with LoD1 solids (schema structure, closed solids)."""
    assert doc["type"] == "CityJSON" and doc["version"] == "2.0"
    assert set(doc) <= {"type", "version", "transform", "metadata", "CityObjects", "vertices", "extensions",
                        "appearance", "geometry-templates"}
    tr = doc["transform"]
    assert len(tr["scale"]) == 3 and len(tr["translate"]) == 3 and all(s > 0 for s in tr["scale"])
    vertices = doc["vertices"]
    assert isinstance(vertices, list) and all(len(v) == 3 and all(isinstance(c, int) for c in v) for v in vertices)
    assert isinstance(doc["CityObjects"], dict)
    used = set()
    for oid, obj in doc["CityObjects"].items():
        assert isinstance(oid, str) and obj["type"] == "Building"
        assert isinstance(obj.get("attributes", {}), dict)
        for geom in obj.get("geometry", []):
            assert geom["type"] == "Solid" and isinstance(geom["lod"], str)
            assert geom["lod"].replace(".", "").isdigit()
            shells = geom["boundaries"]
            assert len(shells) == 1  # exterior shell only
            edges: dict[tuple[int, int], int] = {}
            for surface in shells[0]:
                assert isinstance(surface, list) and surface  # [exterior ring, interior rings...]
                for ring in surface:
                    assert len(ring) >= 3 and all(isinstance(i, int) and 0 <= i < len(vertices) for i in ring)
                    used.update(ring)
                    for a, b in zip(ring, ring[1:] + ring[:1]):
                        edges[(a, b)] = edges.get((a, b), 0) + 1
            # closed and consistently oriented: every directed edge once, and its reverse once
            assert all(n == 1 and edges.get((b, a)) == 1 for (a, b), n in edges.items()), oid
    assert used == set(range(len(vertices)))


def _signed_volume(doc: dict, oid: str) -> float:
    """Volume enclosed by an object's solid (divergence theorem; > 0 when its surfaces face outwards)."""
    scale, tr = np.asarray(doc["transform"]["scale"]), np.asarray(doc["transform"]["translate"])
    v = np.asarray(doc["vertices"], np.float64) * scale + tr - tr  # translation does not change the volume
    total = 0.0
    for surface in doc["CityObjects"][oid]["geometry"][0]["boundaries"][0]:
        for ring in surface:
            p = v[ring]
            for i in range(1, len(p) - 1):  # fan triangulation; interior rings run the other way
                total += np.dot(p[0], np.cross(p[i], p[i + 1])) / 6.0
    return total


def test_cityjson_lod1_solids(tmp_path: Path, rng: np.random.Generator) -> None:
    cls, height, std, ent = _layers((80, 80), [(5, 30, 5, 30, 6.0), (40, 75, 10, 70, 15.0)], rng)
    cls[50:65, 30:50] = SOIL  # a courtyard: walls inside too
    pred = write_prediction_layers(tmp_path / "pred", cls, height, std, ent)
    write_buildings(pred, [tmp_path / "b.city.json", tmp_path / "b.gpkg"])
    doc = json.loads((tmp_path / "b.city.json").read_text())
    check_cityjson(doc)
    assert doc["metadata"]["referenceSystem"] == "https://www.opengis.net/def/crs/EPSG/0/32631"
    geoms, fields, _ = read_footprints(tmp_path / "b.gpkg")
    assert len(doc["CityObjects"]) == 2
    for i, (g, h) in enumerate(zip(geoms, fields["height_m"])):
        oid = f"building-{fields['building_id'][i]}"
        attrs = doc["CityObjects"][oid]["attributes"]
        assert attrs["height_m"] == pytest.approx(h) and attrs["n_pixels"] == fields["n_pixels"][i]
        assert _signed_volume(doc, oid) == pytest.approx(g.area * h, rel=1e-3)  # outward, closed, right size
        z = {doc["vertices"][j][2] for s in doc["CityObjects"][oid]["geometry"][0]["boundaries"][0]
             for r in s for j in r}
        assert z == {0, round(h / 0.001)}  # ground at z = 0 without a DTM
    lo = np.asarray(doc["metadata"]["geographicalExtent"][:2])
    assert lo == pytest.approx([min(g.bounds[0] for g in geoms), min(g.bounds[1] for g in geoms)], abs=1e-3)


def test_dtm_gives_ground_elevation(tmp_path: Path, rng: np.random.Generator) -> None:
    cls, height, std, ent = _layers((40, 40), [(5, 30, 5, 30, 6.0)], rng)
    pred = write_prediction_layers(tmp_path / "pred", cls, height, std, ent)
    # a 1 m DTM in another grid: elevation 100 m + 0.1 m per metre east
    dtm = np.tile(100.0 + 0.1 * (np.arange(30) + 0.5), (30, 1)).astype(np.float32)
    write_raster(tmp_path / "dtm.tif", dtm, transform=Affine(1.0, 0, 500000.0, 0, -1.0, 5000000.0), nodata=-9999.0)
    write_buildings(pred, [tmp_path / "b.gpkg", tmp_path / "b.city.json"], dtm=tmp_path / "dtm.tif")
    _, fields, _ = read_footprints(tmp_path / "b.gpkg")
    assert fields["ground_z_m"][0] == pytest.approx(100.0 + 0.1 * 8.75, abs=0.01)  # median x: 8.75 m east
    doc = json.loads((tmp_path / "b.city.json").read_text())
    check_cityjson(doc)
    z = sorted({v[2] * 0.001 for v in doc["vertices"]})
    assert z == pytest.approx([fields["ground_z_m"][0], fields["ground_z_m"][0] + fields["height_m"][0]], abs=1e-3)


# ---- command line ----------------------------------------------------------------------------------
def test_cli(tmp_path: Path, rng: np.random.Generator, capsys: pytest.CaptureFixture) -> None:
    cls, height, std, ent = _layers((64, 64), [(5, 25, 5, 25, 6.0), (35, 60, 10, 60, 15.0)], rng)
    pred = write_prediction_layers(tmp_path / "pred", cls, height, std, ent)
    code, out, err = run_cli(capsys, "buildings", pred, "--out", tmp_path / "b.gpkg", "--out", tmp_path / "b.city.json",
                          "--quiet")
    assert code == 0, err
    assert "2 buildings (classes: building)" in out and "GPKG:" in out and "CityJSON:" in out and "EPSG:32631" in out
    code, _, err = run_cli(capsys, "buildings", pred, "--out", tmp_path / "b.gpkg", "--quiet")
    assert code == 1 and "already exist" in err and "--overwrite" in err and "Traceback" not in err
    code, _, err = run_cli(capsys, "buildings", pred, "--out", tmp_path / "x.gpkg", "--building-class", "roof")
    assert code == 2 and "--building-class" in err and "'roof' is not a class" in err
    code, _, err = run_cli(capsys, "buildings", pred, "--out", tmp_path / "x.shp")
    assert code == 2 and "--out" in err and ".city.json" in err
    other = write_prediction_layers(tmp_path / "veg", cls, height, scheme=None)
    code, _, err = run_cli(capsys, "buildings", other, "--out", tmp_path / "y.gpkg")
    assert code == 2 and "pass --building-class with the class index" in err
    code, out, err = run_cli(capsys, "buildings", other, "--out", tmp_path / "y.gpkg", "--building-class", "2",
                             "--quiet", "--min-area", "150")
    assert code == 0 and "1 buildings" in out and "1 smaller than 150 m² dropped" in out


def test_no_building_warning_reaches_the_cli(tmp_path: Path, rng: np.random.Generator,
                                             capsys: pytest.CaptureFixture) -> None:
    cls, height, _, _ = _layers((40, 40), [], rng)
    pred = write_prediction_layers(tmp_path / "pred", cls, height)
    with warnings.catch_warnings():
        warnings.simplefilter("default")
        code, out, err = run_cli(capsys, "buildings", pred, "--out", tmp_path / "b.gpkg", "--quiet")
    assert code == 0 and "warning: no building pixel" in err and "0 buildings" in out


def test_plot_and_table_of_the_most_uncertain_buildings(tmp_path: Path, rng: np.random.Generator) -> None:
    pytest.importorskip("matplotlib")
    from aerialmtl.evaluation.building_maps import format_buildings, most_uncertain_buildings, plot_buildings

    cls, height, std, ent = _layers((80, 80), [(5, 30, 5, 30, 6.0), (40, 75, 10, 70, 15.0)], rng)
    std[40:75, 10:70] += 3.0  # the big building is the uncertain one
    cls[50:65, 30:50] = SOIL
    pred = write_prediction_layers(tmp_path / "pred", cls, height, std, ent)
    write_buildings(pred, [tmp_path / "b.gpkg"])
    geoms, fields, _ = read_footprints(tmp_path / "b.gpkg")
    rows = most_uncertain_buildings(fields, geoms, top_k=1)
    big = int(np.argmax(fields["ground_area_m2"]))
    assert rows[0]["building_id"] == fields["building_id"][big]
    assert (rows[0]["x"], rows[0]["y"]) == pytest.approx((geoms[big].centroid.x, geoms[big].centroid.y))
    assert str(rows[0]["building_id"]) in format_buildings(rows)
    fig, axes = plot_buildings(geoms, fields)
    assert len(axes) == 2 and len(axes[0].collections) == 1
    left, right = axes[0].get_xlim()
    assert left <= min(g.bounds[0] for g in geoms) and right >= max(g.bounds[2] for g in geoms)
    fig.savefig(tmp_path / "b.png")
    assert (tmp_path / "b.png").stat().st_size > 1000
