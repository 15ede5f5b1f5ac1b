"""STAC metadata of predictions: ``item.json`` per prediction folder, ``collection.json`` per run.

A STAC catalogue, a data cube or a STAC browser indexes aerialmtl outputs through these files
(STAC 1.1, written with :mod:`pystac`):

* **Item** (:func:`build_item`, ``<folder>/item.json``): id = the folder name; geometry and bbox =
  the prediction grid's footprint in WGS 84 (edges densified before reprojection); the projection
  extension (``proj:code`` or ``proj:wkt2``, ``proj:shape``, ``proj:transform``, ``proj:bbox``); one
  asset per layer (role ``data``, plus ``uncertainty`` for the MC-dropout spread layers) with
  ``raster:bands`` (data type, nodata, unit ``m``/``nats``, pixel size in metres, approximate
  statistics); the classification extension on ``classes.tif`` (class index, name, colour hint, and
  the nodata value as a nodata class); the QGIS styles (role ``style``) and ``prediction.json`` (role
  ``metadata``) as assets too. The model is described in plain properties under ``aerialmtl:``
  (architecture, tasks, input bands and normalisation, class names, GSD, MC samples, checkpoint), and every
  predict setting of the run as ``prediction.json`` records it (``aerialmtl:settings``):
  the machine-learning-model extension describes a model *asset*, which a prediction folder does not
  hold. ``datetime`` is when the prediction was made (aerialmtl does not know the orthophoto's
  acquisition time; edit it in if you do), also given as ``created``.
* **Collection** (:func:`build_collection`, ``<out>/collection.json``, runs over several inputs):
  links to every input's item (``./<stem>/item.json``), the spatial and temporal extent of all of
  them, and the VRT mosaics and their styles as collection assets.

Every href is relative, so a folder can be moved or uploaded as a whole; files are written without a
``self`` link for the same reason.
"""

from __future__ import annotations

import json
import os
import warnings
from collections.abc import Mapping, Sequence
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np
import pystac
from pystac.extensions.classification import Classification, ClassificationExtension
from pystac.extensions.projection import ProjectionExtension
from pystac.extensions.raster import DataType, RasterBand, RasterExtension, Sampling, Statistics
from pystac.extensions.view import ViewExtension

from aerialmtl.errors import AlignmentError, InputError
from aerialmtl.filesafety import open_regular
from aerialmtl.formats.prediction import (
    CLASS_ENTROPY,
    CLASS_MUTUAL_INFO,
    CLASSES,
    COLLECTION_FILE,
    HEIGHT_STD,
    INFO_FILE,
    ITEM_FILE,
    UNFAMILIARITY,
    LayerSpec,
    style_filename,
)
from aerialmtl.formats.qgis_style import class_scheme_of
from aerialmtl.io.align import Grid
from aerialmtl.io.outputs import write_text
from aerialmtl.io.place import EDGE_POINTS, NoPlace, wgs84_outline
from aerialmtl.io.stats import BandStats

#: Media types of the assets.
COG_TYPE = pystac.MediaType.COG
VRT_TYPE = "application/xml"
QML_TYPE = "text/xml"
JSON_TYPE = pystac.MediaType.JSON
#: Layers holding uncertainty (role ``uncertainty`` besides ``data``): MC dropout's, and the feature density's.
UNCERTAINTY_LAYERS = (HEIGHT_STD, CLASS_ENTROPY, CLASS_MUTUAL_INFO, UNFAMILIARITY)
#: The STAC item an orthophoto ``NAME.tif`` may have beside it (``NAME.json``, a source of its acquisition time) is
#: read only when it is a regular file of at most this many bytes, nested at most :data:`SOURCE_ITEM_DEPTH` deep.
SOURCE_ITEM_BYTES = 10_000_000
SOURCE_ITEM_DEPTH = 64
#: Prefix of the plain properties describing the model and the run.
PREFIX = "aerialmtl:"


def model_summary(meta: Any) -> dict[str, Any]:
    """What a catalogue needs to know about the model (a :class:`~aerialmtl.formats.checkpoint.ModelMeta`).

    Returns a JSON-able dict: architecture, encoder, tasks, input bands and normalisation, GSD (m),
    class names, MC-dropout rate, and the feature density behind the ``unfamiliarity`` layer (or why there is none).
    """
    cfg = meta.model
    classes = meta.classes if "classes" in cfg.tasks else None
    return {
        "architecture": "D3-Net",
        "encoder": str(getattr(cfg, "encoder", "densenet121")),
        "height_uncertainty": ("MC dropout" if not getattr(cfg, "aleatoric", False) else
                               "MC dropout + height-bin spread" if getattr(cfg, "height_bins", 0) else
                               "MC dropout + aleatoric Laplace scale"),
        "tasks": list(cfg.tasks),
        "in_channels": int(cfg.in_channels),
        "bands": list(meta.bands),
        "band_names": list(meta.band_names),
        "normalization": str(getattr(meta, "normalization", "dataset")),
        "mean": [float(v) for v in meta.mean],
        "std": [float(v) for v in meta.std],
        "gsd_m": float(meta.gsd),
        "dropout": float(cfg.dropout),
        "class_names": list(classes.names) if classes is not None else [],
        "unfamiliarity": (meta.familiarity.summary() if getattr(meta, "familiarity", None) is not None else
                          "none: the checkpoint holds no feature density, so no unfamiliarity layer"),
        # a pretrained start used as it is (trained on synthetic scenes only, not fine-tuned): its name, else None
        "start": getattr(meta, "start", None),
    }


def footprint_wgs84(grid: Grid) -> dict[str, Any]:
    """The grid's outline as a GeoJSON Polygon in WGS 84 (each edge densified to :data:`EDGE_POINTS`).

    Raises:
        AlignmentError: the grid has no place on Earth (a local CRS, coordinates outside its CRS's domain); an
            orthophoto is checked for that when it is opened (:func:`aerialmtl.io.place.check_place`).
    """
    try:
        lon, lat = wgs84_outline(grid.crs, grid.bounds, EDGE_POINTS)
    except NoPlace as exc:
        raise AlignmentError(f"the prediction grid has no STAC footprint: {exc}") from None
    ring = [[round(x, 9), round(y, 9)] for x, y in zip(lon, lat, strict=True)]
    ring.append(ring[0])
    return {"type": "Polygon", "coordinates": [ring]}


def _bbox(geometry: Mapping[str, Any]) -> list[float]:
    ring = np.asarray(geometry["coordinates"][0], dtype=float)
    return [float(ring[:, 0].min()), float(ring[:, 1].min()), float(ring[:, 0].max()), float(ring[:, 1].max())]


def _created(info: Mapping[str, Any]) -> datetime:
    text = info.get("created")
    if isinstance(text, str):
        try:
            return datetime.fromisoformat(text)
        except ValueError:
            pass
    return datetime.now(timezone.utc).replace(microsecond=0)


def _raster_band(spec: LayerSpec, band: int, gsd: float, stats: BandStats | None) -> RasterBand:
    unit = spec.units[band - 1] if len(spec.units) >= band else ""
    statistics = None
    if stats is not None and band == 1 and not spec.categorical:
        statistics = Statistics.create(minimum=stats.minimum, maximum=stats.maximum, mean=stats.mean,
                                       stddev=stats.stddev, valid_percent=stats.valid_percent)
    return RasterBand.create(nodata=spec.nodata, data_type=DataType(spec.dtype), spatial_resolution=gsd,
                             unit=unit or None, statistics=statistics,
                             sampling=Sampling.AREA)


def build_item(folder: str | Path, grid: Grid, specs: Sequence[LayerSpec], info: Mapping[str, Any],
               stats: Mapping[str, BandStats | None] | None = None, styles: bool = True) -> pystac.Item:
    """The STAC Item of a prediction folder (see the module docstring).

    Args:
        folder: the prediction folder (its name is the item id).
        grid: the prediction grid.
        specs: the layers written (``classes`` carries its class scheme in its tags).
        info: the ``prediction.json`` content (``model``, ``mc_samples``, ``checkpoint``, ...).
        stats: band-1 statistics per layer name (``raster:bands`` statistics); missing = none.
        styles: list the layers' ``.qml`` styles as assets.
    """
    folder = Path(folder)
    stats = stats or {}
    geometry = footprint_wgs84(grid)
    created = _created(info)
    props: dict[str, Any] = {"created": created.isoformat().replace("+00:00", "Z")}
    model = info.get("model")
    if model:
        props[PREFIX + "model"] = model
    for key in ("checkpoint", "mc_samples", "orthophoto", "window", "overlap", "aerialmtl_version"):
        value = info.get(key, info.get("tile")) if key == "window" else info.get(key)  # "tile": earlier folders'
        if value is not None:
            props[PREFIX + key] = value
    if info.get("settings"):  # every predict setting, as prediction.json records it
        props[PREFIX + "settings"] = info["settings"]
    item = pystac.Item(id=folder.name, geometry=geometry, bbox=_bbox(geometry), datetime=created,
                       properties=props)
    item.common_metadata.gsd = grid.gsd
    sun = info.get("sun")
    if isinstance(sun, Mapping) and sun.get("azimuth_deg") is not None and sun.get("elevation_deg") is not None:
        view = ViewExtension.ext(item, add_if_missing=True)  # the sun the shadow features used (true north)
        view.sun_azimuth = float(sun["azimuth_deg"])
        view.sun_elevation = float(sun["elevation_deg"])

    proj = ProjectionExtension.ext(item, add_if_missing=True)
    epsg = grid.crs.to_epsg()
    if epsg is not None:
        proj.code = f"EPSG:{epsg}"
    else:
        proj.code = None
        proj.wkt2 = grid.crs.to_wkt()
    proj.shape = [grid.height, grid.width]
    proj.transform = [float(v) for v in list(grid.transform)[:6]]
    proj.bbox = [float(v) for v in grid.bounds]

    RasterExtension.add_to(item)
    for spec in specs:
        roles = ["data", "uncertainty"] if spec.name in UNCERTAINTY_LAYERS else ["data"]
        title = spec.descriptions[0] if spec.count == 1 else f"{spec.name} ({spec.count} bands)"
        asset = pystac.Asset(href=f"./{spec.filename}", title=title, media_type=COG_TYPE, roles=roles)
        item.add_asset(spec.name, asset)
        RasterExtension.ext(asset).apply(
            [_raster_band(spec, b, grid.gsd, stats.get(spec.name)) for b in range(1, spec.count + 1)])
        if spec.name == CLASSES:
            scheme = class_scheme_of(spec)
            if scheme is not None:
                classes = [Classification.create(value=i, name=n, description=n,
                                                 color_hint=f"{r:02X}{g:02X}{b:02X}")
                           for i, (n, (r, g, b)) in enumerate(zip(scheme.names, scheme.colors, strict=True))]
                classes.append(Classification.create(value=int(spec.nodata), name="nodata", nodata=True))
                ClassificationExtension.ext(asset, add_if_missing=True).apply(classes=classes)
        if styles:
            item.add_asset(f"{spec.name}_style", pystac.Asset(
                href=f"./{style_filename(spec.name)}", title=f"QGIS style of {spec.filename}",
                media_type=QML_TYPE, roles=["style", "metadata"]))
    item.add_asset("prediction", pystac.Asset(href=f"./{INFO_FILE}", title="aerialmtl run information",
                                              media_type=JSON_TYPE, roles=["metadata"]))
    return item


def item_dict(item: pystac.Item | pystac.Collection) -> dict[str, Any]:
    """The JSON content of an item or collection as written (relative hrefs, no ``self`` link)."""
    return item.to_dict(include_self_link=False, transform_hrefs=False)


def write_json(path: str | Path, obj: pystac.Item | pystac.Collection, atomic: bool = True) -> Path:
    """Write ``obj`` at ``path`` (replaced atomically unless ``atomic`` is false: ``path`` is then itself a
    staging file that the caller renames).
    """
    return write_text(path, json.dumps(item_dict(obj), indent=2), "a STAC file", atomic)


def read_item(path: str | Path) -> pystac.Item:
    """Read an ``item.json``."""
    try:
        return pystac.Item.from_file(str(path))
    except (OSError, ValueError, KeyError, pystac.STACError) as exc:
        raise InputError(f"'{path}' is not a readable STAC item ({exc}); re-run predict to rewrite it") from exc



def source_item_path(ortho: str | Path) -> Path:
    """Where the STAC item of orthophoto ``ortho`` lies, if it has one: ``NAME.json`` beside ``NAME.tif``."""
    return Path(str(ortho)).with_suffix(".json")


def _json_depth(data: Any) -> int:
    """How deep the arrays and objects of parsed JSON ``data`` nest (a scalar: 0), walked without recursion."""
    best, todo = 0, [(data, 1)]
    while todo:
        node, depth = todo.pop()
        children = node.values() if isinstance(node, dict) else node if isinstance(node, list) else None
        if children is not None:
            best = max(best, depth)
            todo.extend((child, depth + 1) for child in children)
    return best


def read_source_properties(ortho: str | Path) -> dict[str, Any] | None:
    """The ``properties`` of the STAC item beside orthophoto ``ortho`` (:func:`source_item_path`), or ``None``.

    ``None`` without a word when there is no regular file there, or it is JSON but no STAC item (another
    document that shares the name). ``None`` with a :class:`UserWarning` naming the file and what is wrong when it
    cannot be read as one: larger than :data:`SOURCE_ITEM_BYTES`, nested deeper than :data:`SOURCE_ITEM_DEPTH`,
    not UTF-8 JSON, or ``properties`` that are no object. What the properties hold is checked by their reader.
    """
    item = source_item_path(ortho)
    try:
        if not item.is_file():
            return None
        size = item.stat().st_size
        if size > SOURCE_ITEM_BYTES:
            raise ValueError(f"it holds {size:,} bytes, more than the {SOURCE_ITEM_BYTES:,} a STAC item needs")
        with os.fdopen(open_regular(item, follow_links=True), "rb") as fh:
            text = fh.read(SOURCE_ITEM_BYTES + 1).decode("utf-8")
        deep = ValueError(f"it nests arrays and objects more than {SOURCE_ITEM_DEPTH} deep")
        try:
            data = json.loads(text)
        except RecursionError:  # deeper than Python's recursion limit: the decoder stopped before building it
            raise deep from None
        if _json_depth(data) > SOURCE_ITEM_DEPTH:
            raise deep
    except (OSError, ValueError) as exc:
        warnings.warn(f"STAC item '{item}' beside the orthophoto is not read: {exc}; fix or remove it (its "
                      "acquisition time is not used)", UserWarning, stacklevel=2)
        return None
    if not (isinstance(data, dict) and data.get("type") == "Feature"):
        return None
    props = data.get("properties")
    if not isinstance(props, dict):
        warnings.warn(f"STAC item '{item}' beside the orthophoto has no 'properties' object; fix or remove it (no "
                      "acquisition time is read from it)", UserWarning, stacklevel=2)
        return None
    return props


def build_collection(out: str | Path, items: Sequence[str | Path], mosaics: Mapping[str, Path],
                     mosaic_styles: Mapping[str, Path] | None = None, description: str | None = None
                     ) -> pystac.Collection:
    """The STAC Collection of a run over several inputs (see the module docstring).

    Args:
        out: the run's output folder (its name is the collection id; hrefs are relative to it).
        items: the ``item.json`` files of the inputs' prediction folders.
        mosaics: layer name → VRT mosaic.
        mosaic_styles: layer name → the mosaic's QGIS style.
        description: the collection's description.
    """
    out = Path(out)
    loaded = [(Path(p), read_item(p)) for p in items]
    if not loaded:
        raise InputError(f"collection '{out}': no item to link; predict at least one input first")
    boxes = np.asarray([it.bbox for _, it in loaded], dtype=float)
    bbox = [float(boxes[:, 0].min()), float(boxes[:, 1].min()), float(boxes[:, 2].max()), float(boxes[:, 3].max())]
    times = [it.datetime for _, it in loaded if it.datetime is not None]
    interval: list[datetime | None] = [min(times), max(times)] if times else [None, None]
    extent = pystac.Extent(pystac.SpatialExtent([bbox]), pystac.TemporalExtent([interval]))
    collection = pystac.Collection(
        id=out.resolve().name, extent=extent, license="other",
        title=f"aerialmtl predictions: {out.resolve().name}",
        description=description or (f"Height above ground (m), land cover and their MC-dropout uncertainty "
                                    f"predicted by aerialmtl over {len(loaded)} orthophotos, with VRT mosaics."),
    )
    for path, it in loaded:
        href = "./" + os.path.relpath(path.resolve(), out.resolve()).replace(os.sep, "/")
        collection.add_link(pystac.Link(pystac.RelType.ITEM, href, media_type=pystac.MediaType.GEOJSON,
                                        title=it.id))
    for name, path in mosaics.items():
        collection.add_asset(f"{name}_mosaic", pystac.Asset(
            href=f"./{path.name}", title=f"VRT mosaic of {name} over all inputs", media_type=VRT_TYPE,
            roles=["data", "mosaic"]))
    for name, path in (mosaic_styles or {}).items():
        collection.add_asset(f"{name}_mosaic_style", pystac.Asset(
            href=f"./{path.name}", title=f"QGIS style of the {name} mosaic", media_type=QML_TYPE,
            roles=["style", "metadata"]))
    return collection


def write_collection(out: str | Path, folders: Sequence[str | Path], mosaics: Mapping[str, Path],
                     mosaic_styles: Mapping[str, Path] | None = None) -> Path | None:
    """Write ``<out>/collection.json`` over the items of ``folders`` (those that have one); returns its path.

    ``None`` (nothing written) when no folder holds an ``item.json``.
    """
    items = [Path(f) / ITEM_FILE for f in folders if (Path(f) / ITEM_FILE).is_file()]
    if not items:
        return None
    return write_json(Path(out) / COLLECTION_FILE, build_collection(out, items, mosaics, mosaic_styles))



def collection_files(out: str | Path) -> list[str]:
    """The files of ``out`` that an earlier multi-input run wrote, as its ``collection.json`` proves:
    ``collection.json`` itself (an aerialmtl STAC Collection) and the mosaics and styles it lists.

    Empty when there is no such collection (a user's ``collection.json``, or none): then every mosaic file
    in ``out`` is the user's and is replaced only with ``--overwrite``.
    """
    path = Path(out) / COLLECTION_FILE
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return []
    if not (isinstance(data, dict) and data.get("type") == "Collection"
            and str(data.get("title", "")).startswith("aerialmtl predictions:")
            and isinstance(data.get("assets"), dict)):
        return []
    names = [COLLECTION_FILE]
    for asset in data["assets"].values():
        href = asset.get("href") if isinstance(asset, dict) else None
        if isinstance(href, str) and href.startswith("./") and "/" not in href[2:]:
            names.append(href[2:])
    return names


__all__ = ["EDGE_POINTS", "ITEM_FILE", "SOURCE_ITEM_BYTES", "SOURCE_ITEM_DEPTH", "UNCERTAINTY_LAYERS",
           "build_collection", "build_item", "collection_files", "footprint_wgs84", "item_dict", "model_summary",
           "read_item", "read_source_properties", "source_item_path", "write_collection", "write_json"]
