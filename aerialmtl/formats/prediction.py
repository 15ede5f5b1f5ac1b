"""The prediction folder: what ``aerialmtl predict`` writes.

``evaluate``, the maps notebook and ``buildings`` read it.

One folder per orthophoto, all layers Cloud-Optimized GeoTIFFs on one grid (the orthophoto's, at the
model's GSD)::

    height.tif               float32, metres above ground (MC mean), nodata FLOAT_NODATA
    height_std.tif           float32, metres, predictive standard deviation: MC dropout (T > 1),
                             plus the aleatoric Laplace scale of a model with model.aleatoric (any T)
    classes.tif              uint8 class index, nodata CLASS_NODATA, colour table,
                             tag CLASS_SCHEME_TAG = the class scheme as JSON
    class_entropy.tif        float32, predictive entropy (nats)                       (T > 1)
    class_mutual_info.tif    float32, mutual information (nats), the epistemic part   (T > 1)
    class_probabilities.tif  K × float32, MC mean class probabilities                 (optional)
    unfamiliarity.tif        float32 0–1, share of the training feature pixels the model found more
                             familiar than this pixel's encoder features (a checkpoint with a
                             feature density, :mod:`aerialmtl.models.familiarity`; any T)
    <layer>.qml              QGIS style of each layer (:func:`style_filename`; QGIS applies a .qml
                             named like the raster when it opens it; :mod:`aerialmtl.formats.qgis_style`)
    item.json                STAC 1.1 Item describing the folder (:mod:`aerialmtl.formats.stac`)
    prediction.json          run information (checkpoint, T, tile, overlap, grid, timings)

Layers exist only for the tasks the model has. This module owns the names, tags and nodata values
and the output schema (:func:`prediction_layers`: one :class:`LayerSpec` per layer, which the
stitcher fills and the writer writes); every reader and writer imports them from here.

A run over several orthophotos writes one such folder per input (named after the file stem) and one
GDAL VRT mosaic per layer beside them, ``<layer>.mosaic.vrt`` (:func:`mosaic_filename`) with its QGIS
style ``<layer>.mosaic.qml``, so that a GIS opens one layer over all inputs, and a STAC Collection
``collection.json`` (:data:`COLLECTION_FILE`) linking the items of the inputs and the mosaics.

A folder is complete for a run (:meth:`PredictionFolder.check`, :meth:`PredictionFolder.is_complete`) when
``prediction.json`` exists (the writer renames it into place last, so a run that stopped earlier leaves
no complete-looking folder), every file it lists exists, each layer with the size it records
(``file_sizes``; the styles and ``item.json`` may be edited) and as a raster of the recorded grid, its
``provenance`` matches the run at hand, and each layer's bytes still have the SHA-256 recorded at commit
(``file_sha256``: a disk error that zeroes a block keeps the size, not the checksum):

    provenance.checkpoint   SHA-256 of the checkpoint bytes that were loaded
                            (:func:`aerialmtl.formats.checkpoint.read_checkpoint`; of the weights and
                            metadata for a model given in memory)
    provenance.settings     what changes the maps: MC samples T, seed, precision, engine, the class
                            probabilities layer, the AOI (:func:`~aerialmtl.io.fingerprint.file_fingerprint` of
                            the GeoJSON), whether the checkpoint's calibration was applied, the linear map of
                            ``rescale_input`` (``input_rescale``, :mod:`aerialmtl.inference.sanity`)
    provenance.input        :func:`~aerialmtl.io.fingerprint.input_fingerprint` of the orthophoto, taken when
                            the run opens it and checked again before it commits (a file changed under the run
                            is refused): the file, the sidecars GDAL reads beside it (world file, ``.prj``,
                            ``.aux.xml``, ``.ovr``, ``.msk``), a VRT's sources, a server's or archive's
                            validators, and the raster as GDAL presents it (size, geotransform, CRS, nodata),
                            which ``--skip-existing`` compares with the input as it opens now

Window size, overlap, batch size and device are not part of it: they change speed and memory, and the
maps only within the blending of window seams. ``prediction.json`` is also the proof of what a run owns:
``overwrite`` removes a stale layer of an earlier run only when that run's ``prediction.json`` lists it
(:meth:`PredictionFolder.owned_files`).

``prediction.json`` is read through one schema (:class:`PredictionInfo`, pydantic): any other shape (a
list, ``null``, wrong types) is "not a prediction folder of aerialmtl" (:class:`NotAPredictionFolder`).
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, ValidationError

from aerialmtl.classes import IGNORE_INDEX, ClassScheme
from aerialmtl.errors import InputError, cause
from aerialmtl.filesafety import special_kind
from aerialmtl.io.fingerprint import blocking_file, changed, content_sha256

#: Layer names, in the order a prediction folder lists them (file ``<name>.tif``).
HEIGHT = "height"
HEIGHT_STD = "height_std"
CLASSES = "classes"
CLASS_ENTROPY = "class_entropy"
CLASS_MUTUAL_INFO = "class_mutual_info"
CLASS_PROBABILITIES = "class_probabilities"
UNFAMILIARITY = "unfamiliarity"
SHADOW = "shadow"
SHADOW_HEIGHT = "shadow_height"
LAYERS = (HEIGHT, HEIGHT_STD, CLASSES, CLASS_ENTROPY, CLASS_MUTUAL_INFO, CLASS_PROBABILITIES, UNFAMILIARITY, SHADOW,
          SHADOW_HEIGHT)

#: Unit of each float layer (``class_probabilities``: none; ``unfamiliarity`` and ``shadow``: 0–1, no unit).
LAYER_UNITS = {HEIGHT: "m", HEIGHT_STD: "m", CLASS_ENTROPY: "nats", CLASS_MUTUAL_INFO: "nats", UNFAMILIARITY: "",
               SHADOW: "", SHADOW_HEIGHT: "m"}

#: The run-information file.
INFO_FILE = "prediction.json"
#: The STAC Item of a prediction folder.
ITEM_FILE = "item.json"
#: The STAC Collection a run over several inputs writes beside their folders and the mosaics.
COLLECTION_FILE = "collection.json"

#: nodata of every float layer.
FLOAT_NODATA = -9999.0
#: nodata of ``classes.tif`` (the ignore index of the class scheme).
CLASS_NODATA = IGNORE_INDEX
#: Dataset tag of ``classes.tif`` holding the class scheme as JSON.
CLASS_SCHEME_TAG = "AERIALMTL_CLASS_SCHEME"


def layer_filename(name: str) -> str:
    """File name of layer ``name`` (``"height"`` → ``"height.tif"``)."""
    return f"{name}.tif"


def style_filename(name: str) -> str:
    """File name of the QGIS style of layer ``name`` (``"height"`` → ``"height.qml"``).

    QGIS applies ``<raster name without its extension>.qml`` when it opens a raster.
    """
    return f"{name}.qml"


#: Every file name a prediction folder can hold (``prediction.json`` last).
ALL_FILES = (tuple(layer_filename(n) for n in LAYERS) + tuple(style_filename(n) for n in LAYERS)
             + (ITEM_FILE, INFO_FILE))


def folder_files(names: Iterable[str]) -> list[str]:
    """Every file a prediction folder with layers ``names`` holds.

    The layers, their QGIS styles, the STAC item and ``prediction.json`` (last). A run claims all of them before
    writing, so that a user's own ``height.qml`` or ``item.json`` in ``--out`` is never replaced without
    ``--overwrite``.
    """
    names = list(names)
    return ([layer_filename(n) for n in names] + [style_filename(n) for n in names] + [ITEM_FILE, INFO_FILE])


def mosaic_filename(name: str) -> str:
    """File name of the VRT mosaic of layer ``name`` over all inputs of a run (``"height.mosaic.vrt"``)."""
    return f"{name}.mosaic.vrt"


def mosaic_style_filename(name: str) -> str:
    """File name of the QGIS style of the mosaic of layer ``name`` (``"height.mosaic.qml"``)."""
    return f"{name}.mosaic.qml"


def mosaic_files(names: Iterable[str]) -> list[str]:
    """Every file a run over several inputs writes beside their folders for layers ``names``.

    Each layer's VRT mosaic and its QGIS style, and the STAC ``collection.json``.
    """
    names = list(names)
    return [mosaic_filename(n) for n in names] + [mosaic_style_filename(n) for n in names] + [COLLECTION_FILE]


# ---- the output schema -------------------------------------------------------------------------
@dataclass(frozen=True)
class LayerSpec:
    """One output raster of a prediction folder.

    Attributes:
        name: layer name (file :func:`layer_filename`).
        count, dtype, nodata: bands, numpy dtype name, nodata value.
        descriptions: one description per band.
        units: unit per band (``"m"``, ``"nats"``, ...; empty for none).
        categorical: class indices (``mode`` overviews) rather than continuous values.
        colormap: optional GDAL colour table of band 1.
        tags: dataset tags; ``band_tags``: tags per band (1-based index → mapping).
    """

    name: str
    count: int
    dtype: str
    nodata: float | int
    descriptions: tuple[str, ...]
    units: tuple[str, ...] = ()
    categorical: bool = False
    colormap: dict[int, tuple[int, int, int, int]] | None = None
    tags: dict[str, str] = field(default_factory=dict)
    band_tags: dict[int, dict[str, str]] = field(default_factory=dict)

    @property
    def filename(self) -> str:
        """The layer's file name in the prediction folder."""
        return layer_filename(self.name)


def prediction_layers(
    tasks: Sequence[str], classes: ClassScheme | None, mc: int, probabilities: bool = False, aleatoric: bool = False,
    tta: bool = False, unfamiliarity: bool = False, shadows: bool = False,
) -> tuple[LayerSpec, ...]:
    """The layers a prediction writes, in :data:`LAYERS` order.

    Args:
        tasks: the model's tasks (``"height"``, ``"classes"``).
        classes: the class scheme (required with the ``classes`` task).
        mc: MC-dropout samples T; uncertainty layers only for T > 1 (``height_std`` at T = 1 too with
            ``aleatoric``).
        probabilities: also the K-band ``class_probabilities`` layer.
        aleatoric: the model's height head predicts a Laplace scale: ``height_std`` is the predictive
            spread (MC dropout and the aleatoric scale).
        tta: test-time augmentation (8 views): uncertainty layers at any T.
        unfamiliarity: the checkpoint holds a feature density: the ``unfamiliarity`` layer (any T).
        shadows: the shadow features run (a sun and the checkpoint's shadow classifier): the ``shadow`` and
            ``shadow_height`` layers (:mod:`aerialmtl.inference.shadows`).
    """
    specs: list[LayerSpec] = []
    unc = mc > 1 or tta
    if HEIGHT in tasks:
        specs.append(LayerSpec(HEIGHT, 1, "float32", FLOAT_NODATA, ("height above ground (MC mean)",),
                               (LAYER_UNITS[HEIGHT],)))
        if unc or aleatoric:
            parts = (["MC dropout"] if mc > 1 else []) + (["test-time augmentation"] if tta else []) + (
                ["aleatoric scale"] if aleatoric else [])
            what = ", ".join(parts)
            specs.append(LayerSpec(HEIGHT_STD, 1, "float32", FLOAT_NODATA,
                                   (f"height standard deviation ({what})",), (LAYER_UNITS[HEIGHT_STD],)))
    if CLASSES in tasks:
        if classes is None:
            raise InputError("the classes task needs a class scheme; pass the checkpoint's ModelMeta.classes")
        names = {str(i): n for i, n in enumerate(classes.names)}
        specs.append(LayerSpec(
            CLASSES, 1, "uint8", CLASS_NODATA, ("land-cover class index",), ("",), categorical=True,
            colormap=classes.colormap(), tags={CLASS_SCHEME_TAG: json.dumps(classes.to_dict())},
            band_tags={1: {"class_names": json.dumps(names), **{f"CLASS_{i}": n for i, n in names.items()}}},
        ))
        if unc:
            specs.append(LayerSpec(CLASS_ENTROPY, 1, "float32", FLOAT_NODATA,
                                   ("predictive entropy of the class probabilities",),
                                   (LAYER_UNITS[CLASS_ENTROPY],)))
            specs.append(LayerSpec(CLASS_MUTUAL_INFO, 1, "float32", FLOAT_NODATA,
                                   ("mutual information (epistemic part of the entropy)",),
                                   (LAYER_UNITS[CLASS_MUTUAL_INFO],)))
        if probabilities:
            specs.append(LayerSpec(CLASS_PROBABILITIES, classes.num_classes, "float32", FLOAT_NODATA,
                                   tuple(f"P({n})" for n in classes.names), ("",) * classes.num_classes))
    if unfamiliarity:
        specs.append(LayerSpec(UNFAMILIARITY, 1, "float32", FLOAT_NODATA,
                               ("unfamiliarity: share of training pixels more familiar to the model (0-1)",),
                               (LAYER_UNITS[UNFAMILIARITY],)))
    if shadows and HEIGHT in tasks:
        specs.append(LayerSpec(SHADOW, 1, "float32", FLOAT_NODATA, ("probability of cast shadow (0-1)",),
                               (LAYER_UNITS[SHADOW],)))
        specs.append(LayerSpec(SHADOW_HEIGHT, 1, "float32", FLOAT_NODATA,
                               ("height of the object measured from its shadow (nodata: not measurable)",),
                               (LAYER_UNITS[SHADOW_HEIGHT],)))
    return tuple(specs)


def read_class_scheme_tag(path: str | Path) -> ClassScheme | None:
    """The :class:`ClassScheme` stored in the :data:`CLASS_SCHEME_TAG` tag of ``path``, or ``None``."""
    from aerialmtl.io.align import open_raster  # rasterio (GDAL): see _layer_problem

    with open_raster(path, "predicted classes") as src:
        text = src.tags().get(CLASS_SCHEME_TAG) or src.tags(1).get(CLASS_SCHEME_TAG)
    if not text:
        return None
    try:
        return ClassScheme.from_dict(json.loads(text))
    except (ValueError, TypeError) as exc:
        raise InputError(
            f"'{path}': tag {CLASS_SCHEME_TAG} is not a valid class scheme ({exc}); pass ‹classes› with "
            "the scheme the model was trained with"
        ) from exc


class NotAPredictionFolder(InputError):
    """A ``prediction.json`` that is not one aerialmtl wrote (unreadable JSON, another shape, wrong types)."""


class GridInfo(BaseModel):
    """``prediction.json``'s ``grid``: the output grid (CRS, geotransform, pixels, GSD in metres)."""

    model_config = ConfigDict(extra="allow")
    crs: str | None = None
    transform: list[float] | None = None
    width: int
    height: int
    gsd: float | None = None


class Provenance(BaseModel):
    """``prediction.json``'s ``provenance`` (module docstring).

    The checkpoint's fingerprint, the settings that change the maps, the input's fingerprint
    (:func:`aerialmtl.io.fingerprint.input_fingerprint`).
    """

    model_config = ConfigDict(extra="allow")
    checkpoint: str | None = None
    settings: dict[str, Any] = {}
    input: dict[str, Any] | None = None


class PredictionInfo(BaseModel):
    """The schema of ``prediction.json`` (the fields readers rely on; the rest are kept as they are).

    Attributes:
        files: layer or file key → file name in the folder.
        file_sizes: file name → size in bytes when the run committed.
        file_sha256: layer file name → SHA-256 (hex) of its bytes when the run committed.
        grid: the output grid.
        calibration: what calibration was applied (:meth:`Predictor.calibration_info
            <aerialmtl.inference.predict.Predictor.calibration_info>`).
        provenance: checkpoint, settings and input fingerprints (module docstring).
    """

    model_config = ConfigDict(extra="allow")
    files: dict[str, str]
    file_sizes: dict[str, int] = {}
    file_sha256: dict[str, str] = {}
    grid: GridInfo | None = None
    calibration: dict[str, Any] | None = None
    provenance: Provenance | None = None


#: The settings ``prediction.json`` also holds at its top level, as it did before its ``settings`` mapping (readers
#: rely on them; ``mc_samples`` is the setting ``mc``). A new setting is recorded in ``settings`` only.
RECORD_KEYS = ("tta", "seed", "window", "overlap", "batch_size", "precision", "engine", "threads", "device", "compile",
               "shadow_fusion")


class PredictionRecord(BaseModel):
    """What a run writes to ``prediction.json``, once, when it commits (field order = the file's key order).

    Readers go through :class:`PredictionInfo` (the fields they rely on, any others kept); this is the
    writing side, every field typed. Units: seconds for ``timings_s``, metres for GSDs.

    Attributes:
        aerialmtl_version: the package version that wrote it.
        orthophoto: the input as given; ``checkpoint``: the checkpoint's name; ``model``: its summary
            (:func:`aerialmtl.formats.stac.model_summary`).
        mc_samples, tta, seed: MC-dropout samples T, test-time augmentation, base seed of the masks.
        window, overlap, window_size, batch_size: the largest window side and overlap asked for (pixels), the
            window size used (rows, columns), windows per model call (earlier files say ``tile`` for ``window``).
        precision, engine, threads, device, compile, processes: how it ran (``threads``: CPU threads and
            streams, ``None`` on a GPU; ``processes``: torchrun ranks that computed it); engine_choice: the engine
            and precision chosen and why (:class:`aerialmtl.inference.engine_choice.EngineChoice`).
        aoi: the AOI file, if any; ``grid``: the output grid; ``resampled_from_gsd``: the input's GSD when it
            was resampled; ``input_rescale``: ``(a, b)`` of ``rescale_input``.
        windows_total, windows_computed, overlap_factor, plan_overlap_factor: the window plan and the work.
        timings_s: seconds per stage (``read``, ``model``, ``stitch_write``, ``write``, ``strip_total``,
            ``cog``, ``total``).
        settings: every setting of the run (the fields of :class:`~aerialmtl.inference.settings.PredictSettings`),
            with what ``auto`` and the defaults resolved to.
        calibration: what calibration was applied; provenance: :data:`PROVENANCE_KEY` (module docstring).
        sun_setting, shadow_fusion: ``--sun`` and ``--shadow-fusion`` as given; ``sun``: the sun the shadow
            layers used and its source (:meth:`aerialmtl.inference.sun_choice.SunChoice.record`), ``None`` when
            the run had no shadow features.
        fusion: whether ``--shadow-fusion`` moved this input's heights, and why (or why not): ``{"applied",
            "reason"}`` (:func:`aerialmtl.inference.settings.fusion_record`); ``shadow_fusion`` is what was asked.
        sun_tune: what ``--sun-tune`` did before predicting (:meth:`aerialmtl.inference.self_tune.TuneReport.record`:
            steps, crops, the shadow match before and after), ``None`` when the run did not tune.
        created: UTC time of the commit (ISO 8601); files: key → file name; file_sizes: layer file → bytes;
        file_sha256: layer file → SHA-256 (hex) of its bytes.
    """

    model_config = ConfigDict(extra="forbid")
    aerialmtl_version: str
    orthophoto: str
    checkpoint: str
    model: dict[str, Any]
    mc_samples: int
    tta: bool
    seed: int
    window: int
    overlap: int
    window_size: list[int]
    batch_size: int
    precision: str
    engine: str
    threads: dict[str, Any] | None
    engine_choice: dict[str, Any] | None = None
    device: str
    compile: bool
    processes: int
    settings: dict[str, Any] = {}
    aoi: str | None
    grid: GridInfo
    resampled_from_gsd: float | None
    input_rescale: list[float] | None
    windows_total: int
    windows_computed: int
    overlap_factor: float
    plan_overlap_factor: float
    timings_s: dict[str, float]
    calibration: dict[str, Any]
    sun_setting: str = "auto"
    shadow_fusion: bool = False
    sun: dict[str, Any] | None = None
    fusion: dict[str, Any] | None = None
    sun_tune: dict[str, Any] | None = None
    provenance: dict[str, Any]
    created: str | None = None
    files: dict[str, str] = {}
    file_sizes: dict[str, int] = {}
    file_sha256: dict[str, str] = {}

    def to_json(self) -> str:
        """The file's text (2-space indented JSON, as every earlier version wrote it)."""
        return json.dumps(self.model_dump(), indent=2, default=str)


def parse_info(text: str | bytes, path: str | Path) -> dict[str, Any]:
    """``prediction.json``'s content, validated by :class:`PredictionInfo` (as a dict, every field kept).

    Raises:
        NotAPredictionFolder: not JSON, or not of the schema (the message names the file, the first problem
            and the fix).
    """
    try:
        info = PredictionInfo.model_validate_json(text)
    except ValidationError as exc:
        err = exc.errors()[0]
        where = ".".join(str(p) for p in err.get("loc", ())) or "the file"
        raise NotAPredictionFolder(
            f"'{path}' is not a prediction folder's {INFO_FILE} of aerialmtl ({where}: {err.get('msg', 'invalid')}); "
            f"pass a folder written by `aerialmtl predict`, or predict again there with --overwrite") from exc
    return info.model_dump()


@dataclass(frozen=True)
class PredictionFolder:
    """A prediction folder on disk (reading side).

    Attributes:
        path: the folder.
    """

    path: Path

    def __init__(self, path: str | Path) -> None:
        object.__setattr__(self, "path", Path(path))

    def layer_path(self, name: str) -> Path:
        """Path of layer ``name`` (whether or not it exists)."""
        return self.path / layer_filename(name)

    def layers(self) -> dict[str, Path]:
        """Layer name → path, for the layers present, in :data:`LAYERS` order."""
        return {n: self.layer_path(n) for n in LAYERS if self.layer_path(n).is_file()}

    @property
    def info_path(self) -> Path:
        """The folder's ``prediction.json``."""
        return self.path / INFO_FILE

    def info(self) -> dict[str, Any]:
        """The parsed and validated ``prediction.json`` (:class:`PredictionInfo`; empty when the folder has none).

        Raises:
            NotAPredictionFolder: it is not one aerialmtl wrote (a ``ValueError`` too).
            OSError: it cannot be read.
        """
        if not self.info_path.is_file():
            return {}
        return parse_info(self.info_path.read_bytes(), self.info_path)

    def class_scheme(self) -> ClassScheme | None:
        """The class scheme tagged on ``classes.tif`` (``None`` without classes or tag)."""
        path = self.layer_path(CLASSES)
        return read_class_scheme_tag(path) if path.is_file() else None

    def owned_files(self) -> list[str]:
        """Files an earlier run here wrote, as its ``prediction.json`` lists them (with itself); [] without one."""
        try:
            files = self.info().get("files")
        except (OSError, ValueError):
            return []
        if not isinstance(files, dict):
            return []
        names = [str(n) for n in files.values() if str(n) in ALL_FILES]
        return [*names, INFO_FILE] if names else []

    def check(self, expected: Mapping[str, Any] | None = None, content: bool = True) -> str | None:
        """Why this folder is not a finished prediction of the run ``expected`` describes (``None``: it is).

        Args:
            expected: the ``provenance`` of the run at hand (:meth:`Predictor.provenance
                <aerialmtl.inference.predict.Predictor.provenance>`); ``None`` checks only that a run finished
                here and its files are whole.
            content: also check each layer's bytes against the SHA-256 recorded at commit (``file_sha256``; about
                1 s per GB read: bench/RESULTS.md); done last, once everything cheaper holds.

        Returns:
            ``None`` when complete, else a short reason for a summary (``"height.tif is truncated ..."``,
            ``"made with another model"``, ...).
        """
        try:
            info = self.info()
        except NotAPredictionFolder as exc:
            return f"its {INFO_FILE} is not aerialmtl's ({str(exc).split('(', 1)[-1].split(');', 1)[0]})"
        except (OSError, ValueError):
            return f"its {INFO_FILE} is unreadable"
        files = info.get("files")
        if not info:
            return f"it has no {INFO_FILE} (no run finished there)"
        if not files:
            return f"its {INFO_FILE} lists no layer"
        sizes = info.get("file_sizes") or {}
        grid = info.get("grid") or {}
        for key, name in files.items():
            path = self.path / str(name)
            if not path.is_file():
                if path.exists():  # a FIFO or a folder at a layer's name: never opened
                    return f"{name} is {special_kind(path.stat().st_mode)}, not a regular file"
                return f"{name} is missing"
            size = sizes.get(str(name))
            if size is not None and path.stat().st_size != size:
                return f"{name} is truncated or was changed ({path.stat().st_size} bytes, {INFO_FILE} says {size})"
            problem = _layer_problem(path, grid) if key in LAYERS else None  # layers, not styles or STAC
            if problem:
                return problem
        if expected is not None:
            problem = _provenance_problem(info.get(PROVENANCE_KEY), expected)
            if problem:
                return problem
        return self._content_problem(info) if content else None

    def _content_problem(self, info: Mapping[str, Any]) -> str | None:
        """Which layer's bytes differ from the SHA-256 recorded at commit.

        ``None``: all match, or none recorded (folders of earlier versions are checked by size only).
        """
        listed = {str(n) for n in (info.get("files") or {}).values()}
        for name, digest in (info.get("file_sha256") or {}).items():
            if str(name) not in listed:  # only its own layers: never a path elsewhere ('../x', '/dev/zero')
                return f"its {INFO_FILE} lists a checksum of '{name}', which is none of its files"
            try:
                now = content_sha256(self.path / str(name))  # a FIFO there: an OSError, not a wait
            except OSError as exc:
                return f"{name} cannot be read ({exc.strerror or exc})"
            if now != digest:
                return (f"{name} was damaged or changed after the run wrote it (its content does not match the "
                        f"checksum in {INFO_FILE})")
        return None

    def is_complete(self, expected: Mapping[str, Any] | None = None) -> bool:
        """Whether a finished prediction of the run ``expected`` describes is here (see :meth:`check`)."""
        return self.check(expected) is None


def _layer_problem(path: Path, grid: Mapping[str, Any]) -> str | None:
    """Why layer ``path`` does not open as a raster of ``grid`` (``None`` when it does)."""
    import rasterio  # GDAL only when a layer is opened: reading prediction.json stays numpy-only
    from rasterio.errors import RasterioError

    found = blocking_file(path)  # a FIFO among its sidecars: GDAL would wait on it forever
    if found is not None:
        return f"'{found[0].name}' beside {path.name} is {found[1]}, not a regular file"
    try:
        with rasterio.open(path) as src:
            shape = (src.width, src.height)
    except (RasterioError, OSError) as exc:
        return f"{path.name} does not open ({cause(exc)})"
    want = (grid.get("width"), grid.get("height"))
    if None not in want and shape != want:
        return f"{path.name} is {shape[0]}×{shape[1]} px, {INFO_FILE} says {want[0]}×{want[1]}"
    return None


# ---- provenance ---------------------------------------------------------------------------------
#: The ``prediction.json`` key of a run's provenance (see the module docstring).
PROVENANCE_KEY = "provenance"


def _provenance_problem(recorded: Any, expected: Mapping[str, Any]) -> str | None:
    """Why the ``provenance`` recorded differs from the run's ``expected`` one, in a few words (``None``: same)."""
    if not isinstance(recorded, dict):
        return f"its {INFO_FILE} records no provenance (made by an older version)"
    if recorded.get("checkpoint") != expected.get("checkpoint"):
        return "it was made with another model"
    old_input, new_input = recorded.get("input"), expected.get("input")
    if old_input != new_input:
        what = changed(old_input, new_input) if isinstance(old_input, dict) and isinstance(new_input, dict) else None
        return "it was made with another or a changed orthophoto" + (f" ({what})" if what else "")
    old, new = recorded.get("settings") or {}, expected.get("settings") or {}
    diff = [f"{k} {old.get(k)!r} → {new.get(k)!r}" for k in sorted(set(old) | set(new)) if old.get(k) != new.get(k)]
    if diff:
        return f"it was made with other settings ({', '.join(diff)})"
    return None


__all__ = [
    "ALL_FILES", "CLASSES", "CLASS_ENTROPY", "CLASS_MUTUAL_INFO", "CLASS_NODATA", "CLASS_PROBABILITIES",
    "CLASS_SCHEME_TAG", "COLLECTION_FILE", "FLOAT_NODATA", "HEIGHT", "HEIGHT_STD", "INFO_FILE", "ITEM_FILE", "LAYERS",
    "SHADOW",
    "SHADOW_HEIGHT",
    "UNFAMILIARITY",
    "LAYER_UNITS",
    "LayerSpec", "PredictionFolder", "folder_files", "layer_filename", "mosaic_files", "mosaic_filename",
    "mosaic_style_filename",
    "prediction_layers", "read_class_scheme_tag", "style_filename",
    "PROVENANCE_KEY", "RECORD_KEYS", "GridInfo", "NotAPredictionFolder", "PredictionInfo", "PredictionRecord",
    "Provenance",
    "parse_info",
]
