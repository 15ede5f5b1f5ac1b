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

import math
from collections.abc import Sequence
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np
import rasterio
from rasterio.windows import Window
from tqdm import tqdm

from aerialmtl import __version__
from aerialmtl.classes import IGNORE_INDEX, ClassScheme
from aerialmtl.errors import InputError, OutputExistsError
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
    gaussian_nll_terms,
    sparsification,
    spearman,
)
from aerialmtl.formats.prediction import CLASS_SCHEME_TAG, LAYERS, layer_filename, read_class_scheme_tag
from aerialmtl.io.align import HEIGHT_NODATA, AlignedRaster, Grid, grid_of, open_raster

#: Layer name → file name of a prediction folder (see :mod:`aerialmtl.formats.prediction`).
PREDICTION_FILES = {name: layer_filename(name) for name in LAYERS}


def _read_float(src: rasterio.io.DatasetReader, window: Window, bands: int | list[int] = 1) -> tuple[np.ndarray, np.ndarray]:
    """Read float band(s) as float32 with NaN where nodata/non-finite; returns ``(data, valid)``."""
    data = src.read(bands, window=window).astype(np.float32, copy=False)
    invalid = ~np.isfinite(data)
    nodata = src.nodata if src.nodata is not None else HEIGHT_NODATA
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


def _resolve_scheme(classes: str | Path | ClassScheme | None, classes_tif: Path | None) -> tuple[ClassScheme | None, str]:
    if isinstance(classes, ClassScheme):
        return classes, "argument"
    if classes is not None:
        return ClassScheme.load(classes), str(classes)
    if classes_tif is not None:
        scheme = read_class_scheme_tag(classes_tif)
        if scheme is not None:
            return scheme, f"{classes_tif.name} tag {CLASS_SCHEME_TAG}"
    return None, ""


def evaluate_prediction(
    pred_dir: str | Path,
    height_ref: str | Path | None = None,
    labels_ref: str | Path | None = None,
    classes: str | Path | ClassScheme | None = None,
    out: str | Path | None = "report.json",
    height_threshold: float = 1.0,
    height_bins: Sequence[float] = DEFAULT_HEIGHT_BINS,
    ignore_unknown_codes: bool = False,
    overwrite: bool = False,
    sample_size: int = 2_000_000,
    seed: int = 0,
    steps: int = DEFAULT_STEPS,
    ece_bins: int = DEFAULT_ECE_BINS,
    min_std: float = DEFAULT_MIN_STD,
    block_pixels: int = 1 << 20,
    plots: bool = True,
    progress: bool = False,
    buildings_ref: str | Path | None = None,
    pred_buildings: str | Path | None = None,
) -> dict[str, Any]:
    """Compare a prediction folder with reference heights and/or labels and write a report.

    Args:
        pred_dir: folder written by ``aerialmtl predict`` (``height.tif``, ``classes.tif``, ...).
        height_ref: reference heights above ground (nDSM raster, metres), any CRS/GSD.
        labels_ref: reference label raster with the scheme's raw codes, any CRS/GSD.
        classes: class scheme (YAML path, built-in name or object); default: the scheme in the
            ``AERIALMTL_CLASS_SCHEME`` tag of ``classes.tif``.
        out: report JSON path; ``report.md`` (same stem) and PNG plots are written beside it.
            ``None`` writes nothing and only returns the report.
        height_threshold: δ accuracies count reference heights above this (metres).
        height_bins: reference-height bin edges (metres) for per-bin errors.
        ignore_unknown_codes: label codes missing from the scheme become "no label" instead of raising.
        overwrite: replace an existing report.
        sample_size: max pixels in the seeded subsample for median / sparsification / Spearman.
        seed: seed of that subsample.
        steps: removal fractions of the sparsification curves.
        ece_bins: bins of the expected calibration error.
        min_std: floor of the height standard deviation in the Gaussian NLL (metres).
        block_pixels: pixels per row band read at once (memory bound).
        plots: write PNG plots when matplotlib is installed.
        progress: show a tqdm progress bar.
        buildings_ref: reference building footprints with heights (e.g. ``buildings.geojson`` of
            ``aerialmtl synth``): adds the ``buildings`` section (:mod:`aerialmtl.evaluation.buildings`).
        pred_buildings: footprints written by ``aerialmtl buildings`` to score; default: extracted from
            ``pred_dir`` with the default settings.

    Returns:
        the report dict (also written as JSON, with ``nan`` → ``null``).

    Raises:
        InputError: missing prediction folder/files, grids that differ inside the folder, no reference
            that matches a predicted layer, predicted class indices outside the scheme.
        LabelError: reference label codes not in the scheme (unless ``ignore_unknown_codes``).
        OutputExistsError: ``out`` exists and ``overwrite`` is False.
    """
    pred_dir = Path(pred_dir)
    if not pred_dir.is_dir():
        raise InputError(f"prediction folder '{pred_dir}' does not exist; pass the --out folder of `aerialmtl predict`")
    files = {k: pred_dir / v for k, v in PREDICTION_FILES.items() if (pred_dir / v).is_file()}
    if "height" not in files and "classes" not in files:
        raise InputError(
            f"prediction folder '{pred_dir}' holds neither height.tif nor classes.tif; "
            "pass the --out folder of `aerialmtl predict`"
        )
    if height_ref is None and labels_ref is None and buildings_ref is None:
        raise InputError("no reference given: pass a reference height raster (--height) and/or labels (--labels)")
    if not height_threshold >= 0:
        raise InputError(f"--height-threshold must be ≥ 0 metres, got {height_threshold}")
    if out is not None:
        out = Path(out)
        if out.exists() and not overwrite:
            raise OutputExistsError(f"report '{out}' already exists; pass --overwrite to replace it or choose another --out")

    notes: list[str] = []
    do_height = height_ref is not None and "height" in files
    if height_ref is not None and "height" not in files:
        notes.append("height reference given but the prediction has no height.tif: height metrics skipped")
    scheme, scheme_source = _resolve_scheme(classes, files.get("classes"))
    if labels_ref is not None and scheme is None:
        if "classes" in files:
            raise InputError(
                f"no class scheme for the labels '{labels_ref}': {files['classes']} has no {CLASS_SCHEME_TAG} "
                "tag; pass --classes with the scheme YAML the model was trained with"
            )
        notes.append("labels given without classes.tif or --classes: per-class height errors skipped")
    do_classes = labels_ref is not None and "classes" in files
    if labels_ref is not None and "classes" not in files:
        notes.append("labels given but the prediction has no classes.tif: class metrics skipped")
    if not do_height and not do_classes and buildings_ref is None:
        raise InputError(
            f"nothing to evaluate in '{pred_dir}': the references given ({'--height' if height_ref else ''}"
            f"{' --labels' if labels_ref else ''}) match no predicted layer (found: "
            f"{', '.join(sorted(p.name for p in files.values()))})"
        )
    use_labels = labels_ref is not None and scheme is not None

    # ---- open everything ---------------------------------------------------------------------
    opened: list[Any] = []
    try:
        srcs: dict[str, rasterio.io.DatasetReader] = {}
        needed = (["height", "height_std"] if do_height else []) + (
            ["classes", "class_entropy", "class_mutual_info", "class_probabilities"] if do_classes else []
        )
        for key in needed:
            if key in files:
                srcs[key] = open_raster(files[key], f"prediction {files[key].name}")
                opened.append(srcs[key])
        if not srcs:  # building footprints only: the grid is the prediction's
            key = "height" if "height" in files else "classes"
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
        href = lab = None
        if do_height:
            href = AlignedRaster(height_ref, grid, "height", bands=[1], role="height reference")  # type: ignore[arg-type]
            opened.append(href)
        if use_labels:
            lab = AlignedRaster(labels_ref, grid, "labels", bands=[1], role="label reference")  # type: ignore[arg-type]
            opened.append(lab)
        k = scheme.num_classes if scheme is not None else 0
        names = scheme.names if scheme is not None else []

        hstats = HeightStats(height_threshold, height_bins, k if use_labels else None, names or None,
                             sample_cap=sample_size, seed=seed) if do_height else None
        hsample = Subsample(sample_size, seed + 1) if do_height and "height_std" in srcs else None
        nll_sum, nll_n = 0.0, 0
        cm = np.zeros((k, k), np.int64)
        n_unpredicted = 0
        has_cu = do_classes and ("class_entropy" in srcs or "class_mutual_info" in srcs)
        csample = Subsample(sample_size, seed + 2) if has_cu else None
        calib = CalibrationBins(ece_bins) if do_classes and "class_probabilities" in srcs else None

        windows = _row_bands(grid, block_pixels)
        for win in tqdm(windows, desc="evaluate", unit="band", disable=not progress):
            labels_idx = None
            if lab is not None:
                codes, lvalid = lab.read(win)
                labels_idx = scheme.remap(  # type: ignore[union-attr]
                    codes[0], lvalid, on_unknown="ignore" if ignore_unknown_codes else "error", source=str(labels_ref)
                )
            if hstats is not None and href is not None:
                hp, hp_valid = _read_float(srcs["height"], win)
                ref, ref_valid = href.read(win)
                mask = hstats.update(hp, ref[0], hp_valid & ref_valid, labels_idx)
                if hsample is not None:
                    sd, sd_valid = _read_float(srcs["height_std"], win)
                    sel = mask & sd_valid
                    hsample.add(abs_error=np.abs(hp[sel] - ref[0][sel]), std=sd[sel])
                    terms = gaussian_nll_terms(hp[sel], sd[sel], ref[0][sel], min_std)
                    nll_sum += float(terms.sum())
                    nll_n += int(sel.sum())
            if do_classes and labels_idx is not None:
                cp = srcs["classes"].read(1, window=win)
                bad = (cp != IGNORE_INDEX) & (cp >= k)
                if bad.any():
                    raise InputError(
                        f"'{files['classes']}' holds class index {int(cp[bad].max())} but the class scheme "
                        f"'{scheme.name}' ({scheme_source}) has {k} classes; pass --classes with the scheme "  # type: ignore[union-attr]
                        "the model was trained with"
                    )
                cm += confusion_matrix(labels_idx, cp, k)
                ref_ok = labels_idx != IGNORE_INDEX
                n_unpredicted += int((ref_ok & (cp == IGNORE_INDEX)).sum())
                sel = ref_ok & (cp != IGNORE_INDEX)
                correct = labels_idx == cp
                if csample is not None:
                    cols = {"error": (~correct[sel]).astype(np.uint8)}
                    for key in ("class_entropy", "class_mutual_info"):
                        if key in srcs:
                            cols[key] = _read_float(srcs[key], win)[0][sel]
                        else:
                            cols[key] = np.full(int(sel.sum()), np.nan, np.float32)
                    csample.add(**cols)
                if calib is not None:
                    probs, p_valid = _read_float(srcs["class_probabilities"], win, list(range(1, srcs["class_probabilities"].count + 1)))
                    psel = sel & p_valid
                    calib.update(probs[:, psel].max(axis=0), correct[psel])
    finally:
        for obj in opened:
            obj.close()

    # ---- assemble ------------------------------------------------------------------------------
    report: dict[str, Any] = {
        "aerialmtl_version": __version__,
        "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "prediction": str(pred_dir),
        "references": {"height": str(height_ref) if height_ref else None, "labels": str(labels_ref) if labels_ref else None},
        "grid": {"crs": grid.crs.to_string() if grid.crs else None, "gsd_m": grid.gsd,
                 "width": grid.width, "height": grid.height},
        "class_scheme": {"name": scheme.name, "source": scheme_source, "classes": names} if scheme else None,
        "sampling": {"max_pixels": sample_size, "seed": seed,
                     "note": "median absolute error, sparsification (AUSE/AURG) and Spearman use a seeded "
                             "uniform subsample when more valid pixels than max_pixels exist; all other "
                             "metrics use every valid pixel"},
        "height": None,
        "classes": None,
        "uncertainty": {},
        "notes": notes,
    }
    if hstats is not None:
        report["height"] = hstats.result()
        report["sampling"]["height_pixels"] = hstats.n
        report["sampling"]["height_sampled"] = len(hstats.sample)
        if hstats.n == 0:
            notes.append("no pixel has both a predicted and a reference height: check that the files overlap")
        if hsample is not None:
            ae, sd = hsample.get("abs_error"), hsample.get("std")
            sp = sparsification(ae, sd, steps)
            report["uncertainty"]["height_std"] = {
                "spearman_std_vs_abs_error": spearman(sd, ae),
                "nll": nll_sum / nll_n if nll_n else math.nan,
                "nll_min_std_m": min_std,
                "n_pixels": nll_n,
                "n_sampled": len(hsample),
                "sparsification": sp,
            }
        else:
            notes.append("no height_std.tif (prediction made with T = 1?): height uncertainty metrics skipped")
    if do_classes:
        cls = classification_metrics(cm, names)
        cls["n_reference_without_prediction"] = n_unpredicted
        report["classes"] = cls
        if csample is not None:
            err = csample.get("error").astype(np.float64)
            for key in ("class_entropy", "class_mutual_info"):
                if key in srcs:
                    u = csample.get(key)
                    report["uncertainty"][key] = {
                        "n_sampled": len(csample),
                        "spearman_vs_error": spearman(u, err),
                        "sparsification": sparsification(err, u, steps),
                    }
            report["sampling"]["class_pixels"] = csample.total
            report["sampling"]["class_sampled"] = len(csample)
        else:
            notes.append("no class_entropy.tif / class_mutual_info.tif: class uncertainty metrics skipped")
        if calib is not None:
            report["uncertainty"]["calibration"] = calib.result()
        else:
            notes.append("no class_probabilities.tif: ECE / reliability diagram skipped "
                         "(predict with probabilities saved to get them)")
    if buildings_ref is not None:
        from aerialmtl.evaluation.buildings import evaluate_buildings

        report["references"]["buildings"] = str(buildings_ref)
        report["buildings"] = evaluate_buildings(pred_dir, buildings_ref, grid, pred_buildings, notes=notes)
    if out is not None:
        write_report(report, out, plots=plots)
    return report


__all__ = ["CLASS_SCHEME_TAG", "PREDICTION_FILES", "evaluate_prediction", "read_class_scheme_tag"]
