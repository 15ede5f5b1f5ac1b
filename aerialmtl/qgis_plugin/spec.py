"""The Processing algorithms as data: their parameters, and how values become an ``aerialmtl`` command line.

This module imports neither QGIS nor aerialmtl: the plugin builds its QGIS parameters from
:data:`ALGORITHMS`, and the tests check the command lines (and that every flag is one the installed
command line knows) without QGIS.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Union

#: A parameter's value once QGIS resolved it: a path or text, a number, a flag, or nothing (not given).
Value = Union[str, int, float, bool, None]  # noqa: UP007 - evaluated at run time: QGIS 3.22 may bring Python 3.9

#: Kinds of parameter (the QGIS parameter type each becomes is in ``algorithm.py``).
KINDS = (
    "raster",      # a raster layer or a file/URL GDAL reads → its path
    "vector",      # a polygon layer → a GeoJSON file (converted by QGIS when the layer is not one)
    "file",        # an existing file (``extension`` filters the dialog)
    "folder",      # an existing folder
    "int", "float", "string",
    "enum",        # one of ``choices``
    "bool",        # a flag: given when True
    "folder_out",  # the output folder (created by the command)
    "file_out",    # the output file (``extension``)
)


@dataclass(frozen=True)
class Param:
    """One parameter of an algorithm.

    Attributes:
        name: the QGIS parameter name (upper case).
        flag: the command line's option (``--mc``); ``None`` for the positional argument.
        kind: one of :data:`KINDS`.
        label: what the dialog shows.
        default: the default value (the command line's own default, so that leaving it alone changes nothing).
        optional: may be left empty (the option is then not passed).
        choices: the values of an ``enum``.
        extension: file extension (without the dot) of a ``file`` or ``file_out``.
        advanced: shown under "Advanced parameters".
        minimum: the smallest value of an ``int`` or ``float``.
    """

    name: str
    flag: str | None
    kind: str
    label: str
    default: Value = None
    optional: bool = False
    choices: tuple[str, ...] = ()
    extension: str = ""
    advanced: bool = False
    minimum: float | None = None

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"parameter {self.name}: kind must be one of {', '.join(KINDS)}, got {self.kind!r}")
        if self.kind == "enum" and self.default is not None and self.default not in self.choices:
            raise ValueError(f"parameter {self.name}: default {self.default!r} is not one of {self.choices}")


@dataclass(frozen=True)
class Algorithm:
    """One Processing algorithm: an ``aerialmtl`` sub-command.

    Attributes:
        command: the sub-command (``predict``).
        label: the name shown in the toolbox.
        help: the short help shown beside the dialog.
        params: its parameters, in the order of the dialog.
        loads: what the plugin adds to the project when it ends: ``prediction`` (the layers of the output
            folder, in a group), ``vector`` (the output file) or nothing.
    """

    command: str
    label: str
    help: str
    params: tuple[Param, ...] = field(default_factory=tuple)
    loads: str = ""

    def param(self, name: str) -> Param:
        """The parameter named ``name``."""
        for p in self.params:
            if p.name == name:
                return p
        raise KeyError(f"algorithm {self.command} has no parameter {name}")


_OVERWRITE = Param("OVERWRITE", "--overwrite", "bool", "Replace existing outputs", default=False)
_PRECISION = ("auto", "bf16", "fp32")
_DEVICES = ("auto", "cpu", "cuda")
_Z_UNITS = ("m", "ft", "us-ft")

PREDICT = Algorithm(
    "predict", "Predict height and land cover (with uncertainty)",
    "Height (nDSM, metres) and class maps of an orthophoto with a model trained by aerialmtl, plus the MC-dropout "
    "uncertainty maps when T > 1. The layers are added in a group named after the output folder, styled.",
    (
        Param("INPUT", None, "raster", "Orthophoto"),
        Param("MODEL", "--model", "file", "Model checkpoint (best.pt) [empty: the AERIALMTL_MODEL variable]",
              optional=True, extension="pt"),
        Param("MC", "--mc", "int", "MC-dropout samples T (1 = no uncertainty) [empty: 30 if the model has dropout]",
              optional=True, minimum=1),
        Param("AOI", "--aoi", "vector", "Area of interest (polygons): compute only there", optional=True),
        # a name, not a list: the engines are the registry's (aerialmtl.inference.engines.ENGINES), which this
        # module cannot import; the command refuses a name it does not know, listing them
        Param("ENGINE", "--engine", "string", "Engine: auto, or an engine's name (`aerialmtl predict --help` lists "
              "them)", default="auto"),
        Param("PRECISION", "--precision", "enum", "Precision", default="auto", choices=_PRECISION, advanced=True),
        Param("DEVICE", "--device", "enum", "Device", default="auto", choices=_DEVICES, advanced=True),
        Param("WINDOW", "--window", "int", "Largest window side (pixels, multiple of 32)", default=1024, advanced=True,
              minimum=32),
        Param("OVERLAP", "--overlap", "int", "Minimum overlap between windows (pixels)", default=64, advanced=True,
              minimum=0),
        Param("PROBABILITIES", "--probabilities", "bool", "Also write the class probabilities", default=False,
              advanced=True),
        Param("NO_CALIBRATION", "--no-calibration", "bool", "Do not apply the model's calibration", default=False,
              advanced=True),
        Param("TTA", "--tta", "bool", "Test-time augmentation: 8 flips/rotations per window (8× the work)",
              default=False, advanced=True),
        Param("RESCALE_INPUT", "--rescale-input", "bool",
              "Rescale an orthophoto whose values differ from the training images'", default=False, advanced=True),
        Param("SEED", "--seed", "int", "Base seed of the MC-dropout masks (the same seed gives the same maps)",
              default=0, advanced=True, minimum=0),
        Param("SUN", "--sun", "string", "Sun for the shadow layers: auto, none, or AZIMUTH,ELEVATION (degrees, "
              "azimuth from true north)", default="auto", advanced=True),
        Param("ACQUIRED", "--acquired", "string", "Acquisition time, ISO 8601 (e.g. 2019-06-21T16:45:00Z) "
              "[empty: from a STAC item or the TIFF DateTime]", optional=True, advanced=True),
        Param("SHADOW_FUSION", "--shadow-fusion", "bool",
              "Fuse the heights measured from shadows into the objects' heights", default=False, advanced=True),
        Param("SUN_TUNE", "--sun-tune", "int", "Steps tuning the heights on the orthophoto's own shadows before "
              "predicting (0: off; 30 measured better on the sample area)", default=0, advanced=True, minimum=0),
        _OVERWRITE,
        Param("OUTPUT", "--out", "folder_out", "Prediction folder"),
    ),
    loads="prediction",
)

BUILDINGS = Algorithm(
    "buildings", "Buildings (LoD1 footprints with height)",
    "One polygon per building of a prediction folder, with its height, height uncertainty, area and volume.",
    (
        Param("INPUT", None, "folder", "Prediction folder (written by Predict)"),
        Param("DTM", "--dtm", "raster", "Terrain model (ground elevation per building)", optional=True),
        Param("BUILDING_CLASS", "--building-class", "string",
              "Building class name or index [empty: the classes named 'building(s)']", optional=True),
        Param("MIN_AREA", "--min-area", "float", "Smallest building (m²)", default=10.0, minimum=0),
        Param("MAX_HOLE", "--max-hole", "float", "Fill holes smaller than (m²)", default=10.0, minimum=0),
        Param("HEIGHT_STEP", "--height-step", "float", "Split touching buildings at height jumps of (m)",
              optional=True, advanced=True, minimum=0),
        Param("HEIGHT_PERCENTILE", "--height-percentile", "float", "Percentile of pixel heights for height_m",
              default=50.0, advanced=True, minimum=0),
        Param("NO_ORTHOGONAL", "--no-orthogonal", "bool", "Do not square the outlines", default=False, advanced=True),
        _OVERWRITE,
        Param("OUTPUT", "--out", "file_out", "Buildings (.gpkg, .geojson or .city.json)", extension="gpkg"),
    ),
    loads="vector",
)

EVALUATE = Algorithm(
    "evaluate", "Evaluate a prediction",
    "Accuracy of the heights and classes of a prediction folder against references, and the quality of their "
    "uncertainty: a JSON report with a Markdown summary and plots beside it.",
    (
        Param("PRED", "--pred", "folder", "Prediction folder"),
        Param("HEIGHT", "--height", "raster", "Reference nDSM", optional=True),
        Param("DSM", "--dsm", "raster", "Reference DSM (with DTM)", optional=True),
        Param("DTM", "--dtm", "raster", "Reference DTM (with DSM)", optional=True),
        Param("Z_UNIT", "--z-unit", "enum", "Height unit when a file does not state it", optional=True,
              choices=_Z_UNITS, advanced=True),
        Param("LABELS", "--labels", "raster", "Reference labels (class codes)", optional=True),
        Param("CLASSES", "--classes", "string", "Class scheme of the labels [empty: the prediction's]",
              optional=True, advanced=True),
        Param("BUILDINGS", "--buildings", "vector", "Reference building footprints", optional=True),
        Param("NO_PLOTS", "--no-plots", "bool", "No plots", default=False, advanced=True),
        _OVERWRITE,
        Param("OUTPUT", "--out", "file_out", "Report (.json)", extension="json"),
    ),
)

TILE = Algorithm(
    "tile", "Tile training data",
    "Puts the orthophoto, heights and labels on one grid and cuts aligned training patches with a spatial "
    "train/val/test split.",
    (
        Param("ORTHO", "--ortho", "raster", "Orthophoto"),
        Param("DSM", "--dsm", "raster", "DSM (with DTM)", optional=True),
        Param("DTM", "--dtm", "raster", "DTM (with DSM)", optional=True),
        Param("NDSM", "--ndsm", "raster", "nDSM (instead of DSM and DTM)", optional=True),
        Param("Z_UNIT", "--z-unit", "enum", "Height unit when a file does not state it", optional=True,
              choices=_Z_UNITS, advanced=True),
        Param("LABELS", "--labels", "raster", "Label raster (class codes)", optional=True),
        Param("LABELS_VECTOR", "--labels-vector", "vector", "Label polygons", optional=True),
        Param("CLASS_FIELD", "--class-field", "string", "Field of the label polygons holding the class",
              optional=True),
        Param("CLASSES", "--classes", "string", "Class scheme (YAML or dfc2018, isprs, synthetic)", optional=True),
        Param("SIZE", "--size", "int", "Patch size (pixels)", default=320, minimum=1),
        Param("STRIDE", "--stride", "int", "Step between patches (pixels) [empty: the patch size]", optional=True,
              minimum=1),
        Param("GSD", "--gsd", "float", "Resample to this pixel size (m)", optional=True, minimum=0),
        Param("BANDS", "--bands", "string", "Orthophoto bands, e.g. 1,2,3 [empty: all but alpha]", optional=True,
              advanced=True),
        _OVERWRITE,
        Param("OUTPUT", "--out", "folder_out", "Tile folder"),
    ),
)

TRAIN = Algorithm(
    "train", "Train a model",
    "Trains the multi-task model on a tile folder; the run folder gets best.pt, the checkpoint Predict takes.",
    (
        Param("CONFIG", "--config", "file", "Config (YAML)", optional=True, extension="yaml"),
        Param("DATA", "--data", "folder", "Tile folder (written by Tile)"),
        Param("MAX_STEPS", "--max-steps", "int", "Stop after this many steps", optional=True, minimum=1),
        Param("MAX_TIME", "--max-time", "float", "Stop after this many seconds", optional=True, minimum=0),
        Param("INIT", "--init", "file", "Start from the weights of another checkpoint", optional=True,
              extension="pt", advanced=True),
        Param("RESUME", "--resume", "bool", "Continue the run in the output folder", default=False),
        Param("DEVICE", "--device", "enum", "Device [empty: the config's]", optional=True, choices=_DEVICES,
              advanced=True),
        Param("PRECISION", "--precision", "enum", "Precision [empty: the config's]", optional=True,
              choices=_PRECISION, advanced=True),
        _OVERWRITE,
        Param("OUTPUT", "--out", "folder_out", "Run folder"),
    ),
)

EXPORT = Algorithm(
    "export", "Export a model (ONNX, OpenVINO)",
    "Writes the model of a checkpoint as ONNX (e.g. for the Deepness plugin) or OpenVINO IR.",
    (
        Param("INPUT", None, "file", "Model checkpoint (best.pt)", extension="pt"),
        Param("FORMAT", "--format", "enum", "Format", default="onnx", choices=("onnx", "openvino")),
        Param("TASK", "--task", "enum", "Task", default="all", choices=("all", "height", "height_std", "classes")),
        Param("TILE", "--tile", "int", "Tile size (pixels)", default=512, advanced=True, minimum=32),
        Param("NO_CALIBRATION", "--no-calibration", "bool", "Leave out the height calibration", default=False,
              advanced=True),
        _OVERWRITE,
        Param("OUTPUT", "--out", "file_out", "Model file (.onnx, or .xml for OpenVINO)", extension="onnx"),
    ),
)

#: Every algorithm by sub-command.
ALGORITHMS: dict[str, Algorithm] = {a.command: a for a in (PREDICT, BUILDINGS, EVALUATE, TILE, TRAIN, EXPORT)}


def _text(value: Value) -> str:
    if isinstance(value, float) and value.is_integer():
        return str(int(value)) if abs(value) < 1e15 else repr(value)
    return str(value)


def command_line(executable: Sequence[str] | str, algorithm: Algorithm, values: Mapping[str, Value]) -> list[str]:
    """The ``aerialmtl`` command line that runs ``algorithm`` with ``values``, reporting JSON progress.

    Args:
        executable: the ``aerialmtl`` program (a path, or several words such as ``python -m aerialmtl``).
        algorithm: what to run.
        values: parameter name → value, as QGIS resolved them (paths as strings). A missing or empty value
            passes nothing (the command's default, which a parameter with a default has too); a flag is passed
            when True. Positional values come last, after ``--`` (a path may start with ``-``).

    Raises:
        ValueError: a required parameter has no value, or an ``enum`` value is not one of its choices.
    """
    argv = [executable] if isinstance(executable, str) else list(executable)
    argv += ["--progress", "json", algorithm.command]
    positional: list[str] = []
    for p in algorithm.params:
        value = values.get(p.name)
        if value is None or value == "":
            if not p.optional and p.default is None:
                raise ValueError(f"{algorithm.label}: '{p.label}' needs a value")
            continue
        if p.kind == "bool":
            if value:
                argv.append(str(p.flag))
            continue
        if p.kind == "enum" and value not in p.choices:
            raise ValueError(f"{algorithm.label}: '{p.label}' must be one of {', '.join(p.choices)}, got {value!r}")
        if p.flag is None:
            positional.append(_text(value))
        else:
            argv += [p.flag, _text(value)]
    # positional paths after "--": a file named "-x.tif" or "--help" is a path, never an option
    return argv + (["--", *positional] if positional else [])


#: The layers of a prediction folder the plugin adds, in the order of the group: (file, layer name).
#: The files are those of :mod:`aerialmtl.formats.prediction` (a test keeps the two lists equal); each has a
#: ``.qml`` style of the same name beside it.
PREDICTION_LAYERS: tuple[tuple[str, str], ...] = (
    ("height.tif", "height (m)"),
    ("height_std.tif", "height uncertainty σ (m)"),
    ("classes.tif", "classes"),
    ("class_entropy.tif", "class entropy (nats)"),
    ("class_mutual_info.tif", "class mutual information (nats)"),
    ("class_probabilities.tif", "class probabilities"),
    ("unfamiliarity.tif", "unfamiliarity (0-1)"),
    ("shadow.tif", "cast shadow (0-1)"),
    ("shadow_height.tif", "height from shadows (m)"),
)

#: Name of the provider setting that holds the ``aerialmtl`` program.
EXECUTABLE_SETTING = "AERIALMTL_EXECUTABLE"


def default_executable() -> str:
    """The ``aerialmtl`` program on PATH, else the bare name (the error then says how to set the path)."""
    import shutil

    return shutil.which("aerialmtl") or "aerialmtl"


def not_found_message(executable: str, error: OSError) -> str:
    """What to say when the ``aerialmtl`` program cannot be started."""
    return (f"cannot run aerialmtl at '{executable}' ({error.strerror or error}): install it (from a clone of its "
            "repository: pip install torch==2.13.0 -e . in a virtual environment) and set the path of its "
            "`aerialmtl` program in Settings → Options → Processing → Providers → "
            "aerialmtl → 'aerialmtl executable'")


def dialog_message(algorithm: Algorithm, text: str) -> str:
    """The command's message ``text`` with its options named as the dialog names them.

    The command's errors name its flags (``pass --overwrite to replace them or choose another --out``); in QGIS
    the user sees fields, and scripts (``processing.run``, ``qgis_process``) pass parameter names, so each flag
    of ``algorithm`` becomes its label and name: ``tick 'Replace existing outputs' (OVERWRITE) ... choose
    another 'Prediction folder' (OUTPUT)``. Text that names no flag is returned as it is.
    """
    import re

    for p in sorted((p for p in algorithm.params if p.flag), key=lambda p: -len(str(p.flag))):
        label = p.label.split(" [")[0]  # without the "[empty: ...]" hint
        field_name = f"'{label}' ({p.name})"
        flag = re.escape(str(p.flag))
        if p.kind == "bool":  # "pass --overwrite" → "tick 'Replace existing outputs' (OVERWRITE)"
            text = re.sub(rf"\b(pass|add|use|give) {flag}(?![\w-])", f"tick {field_name}", text)
        text = re.sub(rf"(?<![\w-]){flag}(?![\w-])", field_name, text)
    positional = [p for p in algorithm.params if p.flag is None]
    if len(positional) == 1:  # click names the argument by its metavar: "Invalid value for 'CHECKPOINT'"
        p = positional[0]
        text = re.sub(r"(?<=for )'[A-Z_]+(\.\.\.)?'", f"'{p.label.split(' [')[0]}' ({p.name})", text)
    return text
