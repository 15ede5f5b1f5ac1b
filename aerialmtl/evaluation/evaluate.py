"""Evaluate a prediction folder against reference rasters: the library behind ``aerialmtl evaluate``.

The prediction folder (see ``docs/CONTRACTS.md``) defines the grid. References in any CRS/GSD are
reprojected onto it lazily with :class:`~aerialmtl.io.align.AlignedRaster` (heights bilinear; labels
nearest, or mode when the reference is finer) and read in row bands of about ``block_pixels`` pixels,
so memory stays bounded whatever the raster size: confusion matrices, error sums, calibration bins and
NLL sums are accumulated exactly; the rank-based metrics (median absolute error, sparsification/AUSE/
AURG, Spearman) use a seeded uniform subsample of at most ``sample_size`` pixels (all pixels when
there are fewer), which the report states.
"""

from __future__ import annotations

import contextlib
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np
import rasterio
from rasterio.windows import Window

from aerialmtl._version import __version__
from aerialmtl.classes import IGNORE_INDEX, ClassScheme, OnUnknown
from aerialmtl.errors import InputError, OutputError, OutputExistsError
from aerialmtl.evaluation.buildings import evaluate_buildings
from aerialmtl.evaluation.metrics import (
    DEFAULT_HEIGHT_BINS,
    HeightStats,
    Subsample,
    classification_metrics,
    confusion_matrix,
)
from aerialmtl.evaluation.report import write_report
from aerialmtl.evaluation.uncertainty import (
    DEFAULT_ECE_BINS,
    DEFAULT_MIN_STD,
    DEFAULT_STEPS,
    CalibrationBins,
    SpreadStrata,
    gaussian_nll_terms,
    sparsification,
    spearman,
)
from aerialmtl.evaluation.unfamiliarity import UnfamiliarityScores
from aerialmtl.formats.prediction import (
    ALL_FILES,
    CLASS_ENTROPY,
    CLASS_MUTUAL_INFO,
    CLASS_PROBABILITIES,
    CLASS_SCHEME_TAG,
    CLASSES,
    FLOAT_NODATA,
    HEIGHT,
    HEIGHT_STD,
    LAYERS,
    UNFAMILIARITY,
    PredictionFolder,
    layer_filename,
    read_class_scheme_tag,
)
from aerialmtl.formats.report import report_files
from aerialmtl.io.align import AlignedRaster, Grid, HeightSource, NdsmOptions, grid_of, open_raster
from aerialmtl.io.outputs import OutputFolder, check_files_not_input
from aerialmtl.progress import tqdm

#: Layer name → file name of a prediction folder (see :mod:`aerialmtl.formats.prediction`).
PREDICTION_FILES = {name: layer_filename(name) for name in LAYERS}


def _read_float(
    src: rasterio.io.DatasetReader, window: Window, bands: int | list[int] = 1
) -> tuple[np.ndarray, np.ndarray]:
    """Read float band(s) as float32 with NaN where nodata/non-finite; returns ``(data, valid)``."""
    data = src.read(bands, window=window).astype(np.float32, copy=False)
    invalid = ~np.isfinite(data)
    nodata = src.nodata if src.nodata is not None else FLOAT_NODATA
    invalid |= data == np.float32(nodata)
    if data.ndim == 3:
        invalid = invalid.any(axis=0)
        data[:, invalid] = np.nan
    else:
        data[invalid] = np.nan
    return data, ~invalid


def _row_bands(grid: Grid, block_pixels: int) -> list[Window]:
    rows = max(1, int(block_pixels) // max(1, grid.width))
    return [Window(0, r, grid.width, min(rows, grid.height - r)) for r in range(0, grid.height, rows)]


def _resolve_scheme(
    classes: str | Path | ClassScheme | None, classes_tif: Path | None
) -> tuple[ClassScheme | None, str]:
    if classes is not None:
        given, source = (classes, "argument") if isinstance(classes, ClassScheme) else \
            (ClassScheme.load(classes), str(classes))
        stored = read_class_scheme_tag(classes_tif) if classes_tif is not None else None
        if stored is not None and given.names != stored.names:  # class index k would mean another class
            raise InputError(
                f"class scheme ‹classes› '{source}' ({', '.join(given.names)}) is not the one the prediction was made "
                f"with ({', '.join(stored.names)}, stored in '{classes_tif}'), so predicted class k would be scored "
                "as another class; drop ‹classes› to use the stored scheme, or pass one with the same classes in the "
                "same order (its codes may differ)", param="classes")
        return given, source
    if classes_tif is not None:
        scheme = read_class_scheme_tag(classes_tif)
        if scheme is not None:
            return scheme, f"{classes_tif.name} tag {CLASS_SCHEME_TAG}"
    return None, ""


@dataclass(frozen=True)
class EvaluateOptions:
    """How :func:`evaluate_prediction` scores a prediction (what it is scored against are its arguments).

    Attributes:
        z_unit: unit of the reference heights when a file does not state one (``"m"``, ``"ft"``,
            ``"us-ft"``; default metres); see :mod:`aerialmtl.io.units`.
        height_threshold: δ accuracies count reference heights above this (metres).
        height_bins: reference-height bin edges (metres) for per-bin errors.
        ignore_unknown_codes: label codes missing from the scheme become "no label" instead of raising.
        sample_size: max pixels in the seeded subsample for median / sparsification / Spearman.
        seed: seed of that subsample (0 … 2³² − 1).
        steps: removal fractions of the sparsification curves.
        ece_bins: bins of the expected calibration error.
        min_std: floor of the height standard deviation in the Gaussian NLL (metres).
        block_pixels: pixels per row of windows read at once (memory bound).
        plots: write PNG plots beside the report when matplotlib is installed.
    """

    z_unit: str | None = None
    height_threshold: float = 1.0
    height_bins: Sequence[float] = DEFAULT_HEIGHT_BINS
    ignore_unknown_codes: bool = False
    sample_size: int = 2_000_000
    seed: int = 0
    steps: int = DEFAULT_STEPS
    ece_bins: int = DEFAULT_ECE_BINS
    min_std: float = DEFAULT_MIN_STD
    block_pixels: int = 1 << 20
    plots: bool = True


@dataclass(frozen=True)
class _References:
    """What a prediction is compared with (see :func:`evaluate_prediction`'s arguments)."""

    height: str | Path | None
    labels: str | Path | None
    dsm: str | Path | None
    dtm: str | Path | None
    buildings: str | Path | None
    pred_buildings: str | Path | None

    @property
    def height_given(self) -> str | Path | None:
        """The height reference, an nDSM or the DSM of a DSM/DTM pair."""
        return self.height if self.height is not None else self.dsm


def evaluate_prediction(
    pred_dir: str | Path,
    height_ref: str | Path | None = None,
    labels_ref: str | Path | None = None,
    *,
    dsm_ref: str | Path | None = None,
    dtm_ref: str | Path | None = None,
    buildings_ref: str | Path | None = None,
    pred_buildings: str | Path | None = None,
    classes: str | Path | ClassScheme | None = None,
    out: str | Path | None = "report.json",
    options: EvaluateOptions = EvaluateOptions(),
    overwrite: bool = False,
    progress: bool = False,
) -> dict[str, Any]:
    """Compare a prediction folder with reference heights and/or labels and write a report.

    Twelve parameters: every reference a user may give is a keyword of its own (as the command's options
    are); how the prediction is scored is one :class:`EvaluateOptions`.

    Args:
        pred_dir: folder written by ``aerialmtl predict`` (``height.tif``, ``classes.tif``, ...).
        height_ref: reference heights above ground (nDSM raster), any CRS/GSD, taken as given.
        labels_ref: reference label raster with the scheme's raw codes, any CRS/GSD.
        dsm_ref, dtm_ref: instead of ``height_ref``, a DSM and a DTM: the reference is DSM − DTM on the
            prediction grid, negatives clipped to 0, exactly as ``tile`` derives its training heights.
        buildings_ref: reference building footprints with heights (e.g. ``buildings.geojson`` of
            ``aerialmtl synth``): adds the ``buildings`` section (:mod:`aerialmtl.evaluation.buildings`).
        pred_buildings: footprints written by ``aerialmtl buildings`` to score; default: extracted from
            ``pred_dir`` with the default settings.
        classes: class scheme (YAML path, built-in name or object); default: the scheme in the
            ``AERIALMTL_CLASS_SCHEME`` tag of ``classes.tif``.
        out: report JSON path; ``report.md`` (same stem) and PNG plots are written beside it.
            ``None`` writes nothing and only returns the report.
        options: thresholds, bins, sampling, units, plots (:class:`EvaluateOptions`).
        overwrite: replace an existing report.
        progress: show a tqdm progress bar.

    Returns:
        the report dict (also written as JSON, with ``nan`` → ``null``).

    Raises:
        InputError: missing prediction folder/files, grids that differ inside the folder, no reference
            that matches a predicted layer, predicted class indices outside the scheme.
        LabelError: reference label codes not in the scheme (unless ``ignore_unknown_codes``).
        OutputExistsError: the report's files exist and ``overwrite`` is False.
        OutputInUseError: another process is writing into the report's folder.
    """
    if not 0 <= options.seed < 2**32:
        raise InputError(f"‹seed› must be an integer in 0..2**32-1, got {options.seed}", param="seed")
    refs = _References(height_ref, labels_ref, dsm_ref, dtm_ref, buildings_ref, pred_buildings)
    with contextlib.ExitStack() as stack:
        if out is not None:  # the report's folder is this run's until the report is written
            report_files(out, options.plots)  # a .json path
            stack.enter_context(OutputFolder(Path(out).parent, "evaluate", option="out", what="report folder"))
        return _evaluate(Path(pred_dir), refs, classes, out, options, overwrite, progress)


def _evaluate(pred_dir: Path, refs: _References, classes: str | Path | ClassScheme | None, out: str | Path | None,
              options: EvaluateOptions, overwrite: bool, progress: bool) -> dict[str, Any]:
    """:func:`evaluate_prediction` once the report's folder is held."""
    files = _check_arguments(pred_dir, refs, options, out, overwrite)
    notes: list[str] = []
    scheme, scheme_source = _resolve_scheme(classes, files.get("classes"))
    do_height, do_classes = _what_to_evaluate(pred_dir, refs, files, scheme, notes)
    k = scheme.num_classes if scheme is not None else 0
    names = scheme.names if scheme is not None else []

    opened: list[Any] = []
    try:
        needed = ([HEIGHT, HEIGHT_STD, UNFAMILIARITY] if do_height else []) + (
            [CLASSES, CLASS_ENTROPY, CLASS_MUTUAL_INFO, CLASS_PROBABILITIES] if do_classes else []
        )
        srcs, grid = _open_prediction(files, needed, opened)
        labels = None
        if refs.labels is not None and scheme is not None:
            labels = LabelReference(refs.labels, grid, scheme, options.ignore_unknown_codes)
            opened.append(labels)
        heights = None
        if do_height:
            reference = HeightSource(grid, ndsm=refs.height, dsm=refs.dsm, dtm=refs.dtm,
                                     options=NdsmOptions(clip_negative=refs.height is None, z_unit=options.z_unit))
            opened.append(reference)
            heights = HeightEvaluation(
                srcs[HEIGHT], srcs.get(HEIGHT_STD), reference,
                HeightStats(options.height_threshold, options.height_bins, k if labels is not None else None,
                            names or None, sample_cap=options.sample_size, seed=options.seed),
                options.sample_size, options.seed, options.min_std, srcs.get(UNFAMILIARITY),
            )
        classes_eval = None
        if do_classes:
            classes_eval = ClassEvaluation(srcs, files[CLASSES], scheme, scheme_source, options.sample_size,
                                           options.seed, options.ece_bins)
        for win in tqdm(_row_bands(grid, options.block_pixels), desc="evaluate", unit="band", disable=not progress):
            labels_idx = labels.read(win) if labels is not None else None
            if heights is not None:
                heights.update(win, labels_idx)
            if classes_eval is not None and labels_idx is not None:
                classes_eval.update(win, labels_idx)
    finally:
        for obj in opened:
            obj.close()
    report = _report(pred_dir, refs, grid, scheme, scheme_source, heights, options, notes)
    if heights is not None:
        heights.report_into(report, options.steps)
        try:  # whether predict applied the checkpoint's calibration (height map, spread factor)
            pinfo = PredictionFolder(pred_dir).info()
        except (OSError, ValueError):
            pinfo = {}
        report["calibration"] = {k: v for k, v in dict(pinfo.get("calibration") or {"applied": False}).items()
                                 if k != "height_knots_m"}
    if classes_eval is not None:
        classes_eval.report_into(report, names, options.steps)
    if refs.buildings is not None:
        report["references"]["buildings"] = str(refs.buildings)
        report["buildings"] = evaluate_buildings(pred_dir, refs.buildings, grid, refs.pred_buildings, notes=notes)
    if out is not None:
        write_report(report, Path(out), plots=options.plots)
    return report


def _what_to_evaluate(pred_dir: Path, refs: _References, files: dict[str, Path], scheme: ClassScheme | None,
                      notes: list[str]) -> tuple[bool, bool]:
    """Whether heights and classes are scored (a reference and its predicted layer both given); what is
    skipped is said in ``notes``.

    Raises:
        InputError: labels without a class scheme although ``classes.tif`` exists; nothing to evaluate.
    """
    height_given = refs.height_given
    do_height = height_given is not None and "height" in files
    if height_given is not None and "height" not in files:
        notes.append("height reference given but the prediction has no height.tif: height metrics skipped")
    if refs.labels is not None and scheme is None:
        if "classes" in files:
            raise InputError(
                f"no class scheme for the labels '{refs.labels}': {files['classes']} has no {CLASS_SCHEME_TAG} "
                "tag; pass ‹classes› with the scheme YAML the model was trained with"
            )
        notes.append("labels given without classes.tif or ‹classes›: per-class height errors skipped")
    do_classes = refs.labels is not None and "classes" in files
    if refs.labels is not None and "classes" not in files:
        notes.append("labels given but the prediction has no classes.tif: class metrics skipped")
    if not do_height and not do_classes and refs.buildings is None:
        raise InputError(
            f"nothing to evaluate in '{pred_dir}': the references given ({'‹height_ref›' if height_given else ''}"
            f"{' ‹labels_ref›' if refs.labels else ''}) match no predicted layer (found: "
            f"{', '.join(sorted(p.name for p in files.values()))})"
        )
    return do_height, do_classes


def _report(pred_dir: Path, refs: _References, grid: Grid, scheme: ClassScheme | None, scheme_source: str,
            heights: HeightEvaluation | None, options: EvaluateOptions, notes: list[str]) -> dict[str, Any]:
    """The report's header: versions, the references, the grid, the class scheme and the sampling."""
    return {
        "aerialmtl_version": __version__,
        "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "prediction": str(pred_dir),
        "references": {"height": str(refs.height) if refs.height else None,
                       "labels": str(refs.labels) if refs.labels else None,
                       **({"dsm": str(refs.dsm), "dtm": str(refs.dtm)} if refs.dsm else {}),
                       **({"height_units": heights.units} if heights is not None and heights.units else {})},
        "grid": {"crs": grid.crs.to_string() if grid.crs else None, "gsd_m": grid.gsd,
                 "width": grid.width, "height": grid.height},
        "class_scheme": {"name": scheme.name, "source": scheme_source, "classes": scheme.names} if scheme else None,
        "sampling": {"max_pixels": options.sample_size, "seed": options.seed,
                     "note": "median absolute error, sparsification (AUSE/AURG) and Spearman use a seeded "
                             "uniform subsample when more valid pixels than max_pixels exist; all other "
                             "metrics use every valid pixel"},
        "height": None,
        "classes": None,
        "uncertainty": {},
        "notes": notes,
    }


def _check_arguments(pred_dir: Path, refs: _References, options: EvaluateOptions, out: str | Path | None,
                     overwrite: bool) -> dict[str, Path]:
    """Validate the arguments of :func:`evaluate_prediction`; returns the predicted layers present."""
    height_ref, dsm_ref, dtm_ref = refs.height, refs.dsm, refs.dtm
    labels_ref, buildings_ref = refs.labels, refs.buildings
    sample_size, height_threshold = options.sample_size, options.height_threshold
    if height_ref is not None and (dsm_ref is not None or dtm_ref is not None):
        raise InputError(
            "give either a reference nDSM (‹height_ref›) or a DSM and a DTM (‹dsm_ref›/‹dtm_ref›), not both",
            param="height_ref",
        )
    if (dsm_ref is None) != (dtm_ref is None):
        raise InputError("‹dsm_ref› and ‹dtm_ref› go together: pass both, or pass a reference nDSM with ‹height_ref›",
                         param="dtm_ref" if dtm_ref is None else "dsm_ref")
    if height_ref is None and dsm_ref is None and labels_ref is None and buildings_ref is None:
        raise InputError(
            "no reference given: pass a reference height raster (‹height_ref›) and/or labels (‹labels_ref›)"
        )
    if sample_size < 1:
        raise InputError(f"‹sample_size› must be a positive number of pixels, got {sample_size}", param="sample_size")
    if not (height_threshold >= 0 and math.isfinite(height_threshold)):
        raise InputError(f"‹height_threshold› must be ≥ 0 metres, got {height_threshold}", param="height_threshold")
    if not pred_dir.is_dir():
        raise InputError(f"prediction folder '{pred_dir}' does not exist; pass the --out folder of `aerialmtl predict`",
                         param="pred_dir")
    files = PredictionFolder(pred_dir).layers()
    if HEIGHT not in files and CLASSES not in files:
        raise InputError(
            f"prediction folder '{pred_dir}' holds neither height.tif nor classes.tif; "
            "pass the --out folder of `aerialmtl predict`"
        )
    if out is not None:
        outputs = report_files(out, options.plots)
        inputs = [("height_ref", height_ref), ("labels_ref", labels_ref), ("dsm_ref", dsm_ref), ("dtm_ref", dtm_ref),
                  ("buildings_ref", buildings_ref),
                  *(("pred_dir", pred_dir / name) for name in ALL_FILES)]  # prediction.json, item.json too
        check_files_not_input(outputs, inputs, option="out")
        existing = [str(p) for p in outputs if os.path.lexists(p)]
        if existing and not overwrite:
            raise OutputExistsError(
                f"report '{out}': {', '.join(existing)} already exist(s); pass ‹overwrite=True› to replace the "
                "report or choose another ‹out›"
            )
        folders = [p for p in existing if Path(p).is_dir()]
        if folders:
            raise OutputError(f"report '{out}': '{folders[0]}' is a folder where the report writes a file; choose "
                              "another ‹out›")
    return files


def _open_prediction(
    files: dict[str, Path], needed: list[str], opened: list[Any]
) -> tuple[dict[str, rasterio.io.DatasetReader], Grid]:
    """Open the ``needed`` layers present in ``files`` (appended to ``opened``); check they share one grid."""
    srcs: dict[str, rasterio.io.DatasetReader] = {}
    if not any(key in files for key in needed):  # building footprints only: the grid is the prediction's
        needed = [HEIGHT if HEIGHT in files else CLASSES]
    for key in needed:
        if key in files:
            srcs[key] = open_raster(files[key], f"prediction {files[key].name}")
            opened.append(srcs[key])
    first = next(iter(srcs.values()))
    grid = grid_of(first)
    for key, src in srcs.items():
        if (src.width, src.height) != (grid.width, grid.height) or not src.transform.almost_equals(grid.transform):
            raise InputError(
                f"'{files[key]}' is not on the grid of '{first.name}' ({src.width}×{src.height} vs "
                f"{grid.width}×{grid.height}); all files of a prediction folder must share one grid"
            )
    return srcs, grid


class LabelReference:
    """Reference labels on the prediction grid, as class indices of ``scheme``.

    Args:
        path: label raster of raw codes (any CRS/GSD).
        grid: the prediction grid.
        scheme: the class scheme mapping codes to indices.
        ignore_unknown_codes: codes outside the scheme become no-label instead of raising.
    """

    def __init__(self, path: str | Path, grid: Grid, scheme: ClassScheme, ignore_unknown_codes: bool) -> None:
        self.path = path
        self.scheme = scheme
        self.on_unknown: OnUnknown = "ignore" if ignore_unknown_codes else "error"
        self.raster = AlignedRaster(path, grid, "labels", bands=[1], role="label reference")

    def read(self, win: Window) -> np.ndarray:
        """(h, w) uint8 class indices of ``win``, ``IGNORE_INDEX`` where unlabelled."""
        codes, valid = self.raster.read(win)
        return self.scheme.remap(codes[0], valid, on_unknown=self.on_unknown, source=str(self.path))

    def close(self) -> None:
        """Close the label raster."""
        self.raster.close()


class HeightEvaluation:
    """Height errors (and the quality of ``height_std``) accumulated row band by row band.

    Args:
        pred, std: the predicted ``height`` and (optional) ``height_std`` layers.
        reference: reference heights on the prediction grid (metres).
        stats: the error accumulator (:class:`~aerialmtl.evaluation.metrics.HeightStats`).
        sample_size, seed: cap and seed of the subsample for the rank-based uncertainty metrics.
        min_std: floor of the standard deviation in the Gaussian NLL (metres).
        unfamiliarity: the optional ``unfamiliarity`` layer (scored by :class:`UnfamiliarityScores`).
    """

    def __init__(self, pred: rasterio.io.DatasetReader, std: rasterio.io.DatasetReader | None,
                 reference: HeightSource, stats: HeightStats, sample_size: int, seed: int, min_std: float,
                 unfamiliarity: rasterio.io.DatasetReader | None = None) -> None:
        self.pred, self.std, self.reference, self.stats = pred, std, reference, stats
        self.unfam = unfamiliarity
        self.unfam_scores = (UnfamiliarityScores(stats.edges, sample_size, seed + 3) if unfamiliarity is not None
                             else None)
        self.sample = Subsample(sample_size, seed + 1) if std is not None else None
        self.min_std = min_std
        names = getattr(stats, "class_names", None) if stats.num_classes is not None else None
        self.strata = SpreadStrata(stats.edges, names, sample_size, seed + 2, min_std) if std is not None else None
        self.nll_sum, self.nll_n = 0.0, 0
        self.within = np.zeros(2, dtype=np.int64)  # |error| ≤ 1 σ, ≤ 2 σ
        #: the unit each reference layer was read in (see :meth:`HeightSource.units`)
        self.units = reference.units()

    def update(self, win: Window, labels_idx: np.ndarray | None) -> None:
        """Add the pixels of ``win`` (per-class errors when ``labels_idx`` is given)."""
        hp, hp_valid = _read_float(self.pred, win)
        ref, ref_valid = self.reference.read(win)
        mask = self.stats.update(hp, ref, hp_valid & ref_valid, labels_idx)
        if self.unfam is not None and self.unfam_scores is not None:
            u, u_valid = _read_float(self.unfam, win)
            sel = mask & u_valid
            self.unfam_scores.update(u[sel], hp[sel], ref[sel])
        if self.sample is not None and self.std is not None:
            sd, sd_valid = _read_float(self.std, win)
            sel = mask & sd_valid
            self.sample.add(abs_error=np.abs(hp[sel] - ref[sel]), std=sd[sel])
            self.nll_sum += float(gaussian_nll_terms(hp[sel], sd[sel], ref[sel], self.min_std).sum())
            self.nll_n += int(sel.sum())
            err, s = np.abs(hp[sel] - ref[sel]), sd[sel]
            self.within += (int(np.count_nonzero(err <= s)), int(np.count_nonzero(err <= 2 * s)))
            if self.strata is not None:
                self.strata.update(hp[sel], sd[sel], ref[sel], None if labels_idx is None else labels_idx[sel])

    def report_into(self, report: dict[str, Any], steps: int) -> None:
        """Fill ``report["height"]``, ``report["uncertainty"]["height_std"]``, sampling counts and notes."""
        notes = report["notes"]
        report["height"] = self.stats.result()
        report["sampling"]["height_pixels"] = self.stats.n
        report["sampling"]["height_sampled"] = len(self.stats.sample)
        if self.stats.n == 0:
            notes.append("no pixel has both a predicted and a reference height: check that the files overlap")
        if self.unfam_scores is not None:  # does the unfamiliarity layer flag the misses within a height bin
            report["uncertainty"][UNFAMILIARITY] = self.unfam_scores.result()
        if self.sample is None:
            notes.append("no height_std.tif (prediction made with T = 1?): height uncertainty metrics skipped")
            return
        ae, sd = self.sample.get("abs_error"), self.sample.get("std")
        report["uncertainty"]["height_std"] = {
            "spearman_std_vs_abs_error": spearman(sd, ae),
            "nll": self.nll_sum / self.nll_n if self.nll_n else math.nan,
            "nll_min_std_m": self.min_std,
            "n_pixels": self.nll_n,
            "n_sampled": len(self.sample),
            "sparsification": sparsification(ae, sd, steps),
            # calibrated Gaussian spreads: 0.683 and 0.954
            "coverage_1sigma": float(self.within[0] / self.nll_n) if self.nll_n else math.nan,
            "coverage_2sigma": float(self.within[1] / self.nll_n) if self.nll_n else math.nan,
        }
        if self.strata is not None:  # per reference-height bin and class: is the spread right where users look
            report["uncertainty"]["height_std"]["strata"] = self.strata.result()


class ClassEvaluation:
    """Confusion matrix, class-uncertainty samples and calibration, accumulated row band by row band.

    Args:
        srcs: the open prediction layers (``classes`` and any of ``class_entropy``,
            ``class_mutual_info``, ``class_probabilities``).
        classes_path: path of ``classes.tif`` (named in messages).
        scheme, scheme_source: the class scheme and where it came from (named in messages).
        sample_size, seed: cap and seed of the subsample for the rank-based uncertainty metrics.
        ece_bins: bins of the expected calibration error.
    """

    def __init__(self, srcs: dict[str, rasterio.io.DatasetReader], classes_path: Path, scheme: ClassScheme | None,
                 scheme_source: str, sample_size: int, seed: int, ece_bins: int) -> None:
        self.srcs, self.classes_path = srcs, classes_path
        self.scheme, self.scheme_source = scheme, scheme_source
        self.k = scheme.num_classes if scheme is not None else 0
        self.cm = np.zeros((self.k, self.k), np.int64)
        self.n_unpredicted = 0
        has_u = CLASS_ENTROPY in srcs or CLASS_MUTUAL_INFO in srcs
        self.sample = Subsample(sample_size, seed + 2) if has_u else None
        self.calib = CalibrationBins(ece_bins) if CLASS_PROBABILITIES in srcs else None

    def update(self, win: Window, labels_idx: np.ndarray) -> None:
        """Add the labelled pixels of ``win``."""
        cp = self.srcs[CLASSES].read(1, window=win)
        bad = (cp != IGNORE_INDEX) & (cp >= self.k)
        if bad.any():
            name = self.scheme.name if self.scheme is not None else ""
            raise InputError(
                f"'{self.classes_path}' holds class index {int(cp[bad].max())} but the class scheme "
                f"'{name}' ({self.scheme_source}) has {self.k} classes; pass ‹classes› with the scheme "
                "the model was trained with"
            )
        self.cm += confusion_matrix(labels_idx, cp, self.k)
        ref_ok = labels_idx != IGNORE_INDEX
        self.n_unpredicted += int((ref_ok & (cp == IGNORE_INDEX)).sum())
        sel = ref_ok & (cp != IGNORE_INDEX)
        correct = labels_idx == cp
        if self.sample is not None:
            cols = {"error": (~correct[sel]).astype(np.uint8)}
            for key in (CLASS_ENTROPY, CLASS_MUTUAL_INFO):
                if key in self.srcs:
                    cols[key] = _read_float(self.srcs[key], win)[0][sel]
                else:
                    cols[key] = np.full(int(sel.sum()), np.nan, np.float32)
            self.sample.add(**cols)
        if self.calib is not None:
            src = self.srcs[CLASS_PROBABILITIES]
            probs, p_valid = _read_float(src, win, list(range(1, src.count + 1)))
            psel = sel & p_valid
            self.calib.update(probs[:, psel].max(axis=0), correct[psel])

    def report_into(self, report: dict[str, Any], names: Sequence[str], steps: int) -> None:
        """Fill ``report["classes"]``, the class entries of ``report["uncertainty"]``, counts and notes."""
        notes = report["notes"]
        cls = classification_metrics(self.cm, list(names))
        cls["n_reference_without_prediction"] = self.n_unpredicted
        report["classes"] = cls
        if self.sample is not None:
            err = self.sample.get("error").astype(np.float64)
            for key in (CLASS_ENTROPY, CLASS_MUTUAL_INFO):
                if key in self.srcs:
                    u = self.sample.get(key)
                    report["uncertainty"][key] = {
                        "n_sampled": len(self.sample),
                        "spearman_vs_error": spearman(u, err),
                        "sparsification": sparsification(err, u, steps),
                    }
            report["sampling"]["class_pixels"] = self.sample.total
            report["sampling"]["class_sampled"] = len(self.sample)
        else:
            notes.append("no class_entropy.tif / class_mutual_info.tif: class uncertainty metrics skipped")
        if self.calib is not None:
            report["uncertainty"]["calibration"] = self.calib.result()
        else:
            notes.append("no class_probabilities.tif: ECE / reliability diagram skipped "
                         "(predict with probabilities saved to get them)")


__all__ = ["CLASS_SCHEME_TAG", "PREDICTION_FILES", "ClassEvaluation", "EvaluateOptions", "HeightEvaluation",
           "LabelReference", "evaluate_prediction", "read_class_scheme_tag"]
