"""Cut an orthophoto and its aligned height / label layers into training patches (the tile folder).

:func:`tile_dataset` walks a (size, stride) grid of windows over the reference grid (the ortho, optionally
resampled to ``gsd``), reads every layer window by window through :mod:`aerialmtl.io.align` (no raster is
ever loaded whole), assigns each window to a spatial split, drops windows with too few valid image pixels,
and writes the folder described in ``docs/CONTRACTS.md``::

    OUT/{train,val,test}/image/<id>.tif     ortho bands, source dtype, internal mask where invalid
    OUT/{train,val,test}/height/<id>.tif    float32 metres, nodata -9999
    OUT/{train,val,test}/classes/<id>.tif   uint8 class indices, nodata 255
    OUT/manifest.csv, OUT/dataset.yaml      written last: their absence marks an unfinished run

The patches, the manifest and ``dataset.yaml`` are written into a hidden staging folder
(``OUT/.patches.partial``) and swapped into place when every patch is written; ``dataset.yaml`` comes
last. A run that fails (bad label codes, unreadable file) or is interrupted (Ctrl-C, SIGTERM, SIGHUP)
before the swap removes its staging folder and leaves an earlier tile dataset in ``OUT`` as it was. The
swap starts by writing a journal into the staging folder (:data:`SWAP_FILE`: the earlier set's files to
remove); from then on it is rolled forward — by the interrupted run itself, or by the next run when the
process was killed — so ``OUT`` holds either the earlier tile dataset or the new one, never half of each
(:mod:`aerialmtl.tiling.swap`; the input layers are opened by :mod:`aerialmtl.tiling.sources`).
``overwrite`` replaces the tile dataset an earlier run wrote (the files its ``dataset.yaml`` and
``manifest.csv`` list, :func:`aerialmtl.formats.tiles.owned_files`), never another file or folder; a
``train``/``val``/``test`` folder that no tile dataset lists is refused. The run holds the folder's lock
(:class:`aerialmtl.io.outputs.OutputFolder`) and refuses an ``OUT`` that is or contains an input.

Every patch's transform is ``rasterio.windows.transform(window, grid.transform)``. Per-band mean/std are
accumulated over valid pixels of the train split only (float64, merged patch by patch).
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import math
import shutil
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import rasterio
from rasterio.windows import Window

from aerialmtl._version import __version__
from aerialmtl.classes import IGNORE_INDEX, ClassScheme
from aerialmtl.errors import AerialMTLError, InputError
from aerialmtl.filesafety import staging_path
from aerialmtl.formats.checkpoint import SURFACE_HEIGHTS_M
from aerialmtl.formats.tiles import (
    DATASET_YAML,
    HEIGHT_NODATA,
    MANIFEST_COLUMNS,
    MANIFEST_CSV,
    STAGING_NAME,
    ManifestWriter,
    TileFolderInfo,
    patch_path,
    read_manifest,
)
from aerialmtl.io.align import Grid, NdsmOptions, reference_grid
from aerialmtl.io.oserrors import kind_of, output_error
from aerialmtl.io.outputs import OutputFolder
from aerialmtl.io.paths import recorded_path
from aerialmtl.io.profiles import patch_profile
from aerialmtl.progress import tqdm
from aerialmtl.runtime import gdal_env
from aerialmtl.tiling.grid import count_windows, tile_windows
from aerialmtl.tiling.height_support import SPLIT_FIX, TALL_M, TallCount, validation_heights_warning
from aerialmtl.tiling.sources import TileSources
from aerialmtl.tiling.splits import SPLITS, SplitAssigner, SplitSpec
from aerialmtl.tiling.swap import SWAP_FILE, claim, commit, finish_interrupted_swap, finish_swap


@dataclass(frozen=True)
class TileOptions:
    """How :func:`tile_dataset` cuts patches and reads the layers (sizes in pixels of the reference grid).

    Attributes:
        size: patch side (pixels).
        stride: step between patches (pixels, ``≤ size``); ``None`` = ``size`` (no overlap).
        gsd: resample everything to this pixel size in metres (whatever the CRS unit) instead of the ortho's.
        min_valid: minimum fraction of valid image pixels for a patch to be kept (0..1).
        splits: spatial split specification.
        bands: 1-based ortho bands to keep (``None``: all but alpha).
        heights: negative clipping / maximum height / the heights' unit when a file states none.
        ignore_unknown_codes: map label codes (or vector values) outside the scheme to no-label instead of
            raising :class:`~aerialmtl.errors.LabelError`.
    """

    size: int = 320
    stride: int | None = None
    gsd: float | None = None
    min_valid: float = 0.9
    splits: SplitSpec = SplitSpec()
    bands: Sequence[int] | None = None
    heights: NdsmOptions = NdsmOptions()
    ignore_unknown_codes: bool = False

    @property
    def step(self) -> int:
        """The stride in pixels (``size`` when ``stride`` is ``None``)."""
        return self.size if self.stride is None else self.stride


@dataclass
class TileResult:
    """What :func:`tile_dataset` wrote.

    Attributes:
        out_dir: the tile folder.
        manifest: path of ``manifest.csv``.
        dataset_yaml: path of ``dataset.yaml``.
        counts: patches written per split.
        windows: windows visited in total.
        dropped_invalid: windows dropped for ``valid_fraction < min_valid``.
        dropped_split: windows dropped because they straddle splits / lie outside every AOI.
        block_size_m: side of the split blocks actually used (metres; snapped to the patch stride), ``None``
            for AOI splits.
        block_patches: patch strides per block side (``None`` for AOI splits).
        mean, std: per-band statistics of the train split (raw units), ``None`` without train patches.
        max_valid_fraction: the largest fraction of valid orthophoto pixels of a window in a split.
    """

    out_dir: Path
    manifest: Path
    dataset_yaml: Path
    counts: dict[str, int]
    windows: int
    dropped_invalid: int
    dropped_split: int
    mean: list[float] | None = None
    std: list[float] | None = None
    tasks: list[str] = field(default_factory=list)
    block_size_m: float | None = None
    block_patches: int | None = None
    max_valid_fraction: float = 0.0
    #: per split with heights: ``mean_m`` (mean reference height of its valid pixels, metres),
    #: ``tall_share`` (share of them ≥ :data:`TALL_M`), as the summary prints them, and ``pixels`` and
    #: ``tall_pixels`` (counts of them)
    height_summary: dict[str, dict[str, float]] = field(default_factory=dict)



class _HeightSummary:
    """Per-split sum, count and tall count of the reference heights written (overlapping patches counted
    as often as they are written).
    """

    def __init__(self) -> None:
        self.acc: dict[str, list[float]] = {}
        self.low, self.high = math.inf, -math.inf
        self.implausible = 0  # pixels outside SURFACE_HEIGHTS_M

    def update(self, split: str, heights: np.ndarray) -> None:
        if heights.size:
            self.low, self.high = min(self.low, float(heights.min())), max(self.high, float(heights.max()))
            lo, hi = SURFACE_HEIGHTS_M
            self.implausible += int(np.count_nonzero((heights < lo) | (heights > hi)))
        a = self.acc.setdefault(split, [0.0, 0.0, 0.0])
        a[0] += float(heights.astype(np.float64).sum())
        a[1] += heights.size
        a[2] += float(np.count_nonzero(heights >= TALL_M))

    def result(self) -> dict[str, dict[str, float]]:
        return {s: {"mean_m": a[0] / a[1], "tall_share": a[2] / a[1], "pixels": a[1], "tall_pixels": a[2]}
                for s, a in sorted(self.acc.items(), key=lambda kv: SPLITS.index(kv[0])) if a[1]}


class _BandStats:
    """Streaming per-band mean/variance in float64 (Chan et al. pairwise merge of per-patch moments)."""

    def __init__(self, bands: int) -> None:
        self.n = 0
        self.mean = np.zeros(bands, np.float64)
        self.m2 = np.zeros(bands, np.float64)

    def update(self, data: np.ndarray, valid: np.ndarray) -> None:
        """``data`` (C, h, w), ``valid`` (h, w) bool."""
        nb = int(valid.sum())
        if nb == 0:
            return
        x = data[:, valid].astype(np.float64)
        mb = x.mean(axis=1)
        m2b = ((x - mb[:, None]) ** 2).sum(axis=1)
        n = self.n + nb
        delta = mb - self.mean
        self.mean = self.mean + delta * (nb / n)
        self.m2 = self.m2 + m2b + delta**2 * (self.n * nb / n)
        self.n = n

    def result(self) -> tuple[list[float], list[float]] | None:
        if self.n == 0:
            return None
        return self.mean.tolist(), np.sqrt(self.m2 / self.n).tolist()


def _fmt(v: float) -> str:
    """Map coordinates and heights for the manifest: exact enough to round-trip float32 and UTM metres."""
    return repr(round(float(v), 9))


def _write(path: Path, profile: dict[str, Any], data: np.ndarray, mask: np.ndarray | None = None) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with rasterio.open(path, "w", **profile) as dst:
        dst.write(data)
        if mask is not None:
            dst.write_mask(np.where(mask, 255, 0).astype(np.uint8))


def _load_scheme(classes: ClassScheme | str | Path | None) -> ClassScheme | None:
    if classes is None or isinstance(classes, ClassScheme):
        return classes
    return ClassScheme.load(classes)


def tile_dataset(
    ortho: str | Path,
    out_dir: str | Path,
    *,
    dsm: str | Path | None = None,
    dtm: str | Path | None = None,
    ndsm: str | Path | None = None,
    labels: str | Path | None = None,
    labels_vector: str | Path | None = None,
    class_field: str | None = None,
    classes: ClassScheme | str | Path | None = None,
    options: TileOptions = TileOptions(),
    overwrite: bool = False,
    progress: bool = True,
) -> TileResult:
    """Tile an orthophoto plus aligned height and/or label layers into a training dataset folder.

    Twelve parameters: every layer a user may give is a keyword of its own (as the command's options are);
    how patches are cut is one :class:`TileOptions`.

    Args:
        ortho: orthophoto GeoTIFF; defines the reference grid (CRS, origin, pixel size).
        out_dir: output folder (created; must not hold a tile dataset unless ``overwrite``; never an input's
            folder).
        dsm, dtm: surface and terrain models; height = DSM − DTM in metres (values in the unit the file
            states, else ``options.heights.z_unit``, else metres). Mutually exclusive with ``ndsm``.
        ndsm: ready heights above ground (nDSM / CHM; units as for ``dsm``).
        labels: label raster of raw class codes.
        labels_vector: GeoJSON polygons with a class attribute (``class_field``), instead of ``labels``.
        class_field: attribute of ``labels_vector`` with codes or class names.
        classes: :class:`ClassScheme`, a scheme YAML path, or a built-in name; required with labels.
        options: patch size, stride, GSD, validity, splits, bands, how heights and labels are read.
        overwrite: replace the tile dataset an earlier run wrote in ``out_dir`` (only its own files).
        progress: show a tqdm progress bar.

    Returns:
        A :class:`TileResult` (counts per split, manifest path, statistics).

    Raises:
        InputError / AlignmentError / LabelError: unusable inputs (messages name the file and the fix).
        OutputExistsError: ``out_dir`` holds a tile dataset and ``overwrite`` is false.
        OutputError: ``out_dir`` holds split folders no tile dataset lists.
        OutputInUseError: another process is writing ``out_dir``.
        InputError: also when no patch at all would be kept (:func:`check_not_empty`); nothing is left.
    """
    out_dir = Path(out_dir)
    size, stride = options.size, options.step
    scheme = _check_arguments(options, dsm, dtm, ndsm, labels, labels_vector, class_field, classes)
    grid = reference_grid(ortho, options.gsd)
    with gdal_env("tile", GDAL_TIFF_INTERNAL_MASK=True), TileSources(
        ortho, grid, bands=options.bands, dsm=dsm, dtm=dtm, ndsm=ndsm, ndsm_options=options.heights, labels=labels,
        labels_vector=labels_vector, class_field=class_field, scheme=scheme,
        ignore_unknown_codes=options.ignore_unknown_codes,
    ) as sources:
        assigner = SplitAssigner(options.splits, grid, stride=stride, size=size)
        inputs = {k: v for k, v in sources.paths.items()}
        with OutputFolder(out_dir, "tile", inputs=inputs, what="tile folder") as folder:
            if finish_interrupted_swap(out_dir):  # a run killed while swapping: its new dataset is finished
                warnings.warn(f"tile folder '{out_dir}': a run was stopped while it replaced the tile dataset; its new "
                              "dataset was put in place first", UserWarning, stacklevel=2)
            folder.remove_leftovers((STAGING_NAME, MANIFEST_CSV, DATASET_YAML))  # of a killed run
            owned = claim(folder, overwrite)
            result = _write_staged(sources, assigner, grid, options, out_dir, owned or [], progress)
    warn_no_tall_pixels(result)
    return result


def warn_no_tall_pixels(result: TileResult) -> None:
    """Warn when validation cannot judge heights (:mod:`aerialmtl.tiling.height_support`: too few pixels ≥
    :data:`TALL_M`, in count or against train's share) or the test split holds none while train does: best.pt
    would be chosen on the ground, the calibration fitted on validation could correct no building or tree (it
    corrects only heights validation holds), and test scores would say nothing about them.
    """
    summary = result.height_summary
    train = summary.get("train")
    if train is None or not int(train["tall_pixels"]):
        return
    train_count = TallCount(int(train["pixels"]), int(train["tall_pixels"]))
    val = summary.get("val")
    if val is not None:
        message = validation_heights_warning(str(result.out_dir), train_count,
                                             TallCount(int(val["pixels"]), int(val["tall_pixels"])),
                                             result.counts.get("val", 0), val["mean_m"])
        if message is not None:
            warnings.warn(message, UserWarning, stacklevel=2)
    test = summary.get("test")
    if test is not None and not int(test["tall_pixels"]):
        warnings.warn(
            f"tile folder '{result.out_dir}': the test split holds no pixel ≥ {TALL_M:g} m (its "
            f"{result.counts.get('test', 0)} patches: {int(test['pixels'])} px, mean {test['mean_m']:.2f} m) while "
            f"train holds {train_count.tall} ({100 * train_count.share:.0f} %): its scores would say nothing of "
            f"buildings or trees; {SPLIT_FIX}", UserWarning, stacklevel=2)


def _write_staged(
    sources: TileSources, assigner: SplitAssigner, grid: Grid, options: TileOptions, out_dir: Path,
    owned: Sequence[str], progress: bool,
) -> TileResult:
    """Write the tile dataset into a staging folder, then swap it into ``out_dir`` in place of ``owned``.

    A failed or interrupted run removes its staging folder (finishing the swap first when it had begun), so
    ``out_dir`` holds the earlier tile dataset or the new one; OS errors become
    :class:`~aerialmtl.errors.OutputError` naming the tile folder.
    """
    stage = staging_path(out_dir / STAGING_NAME)
    stage.mkdir()
    try:
        result = _tile_loop(sources, assigner, grid, stage, options, progress)
        check_not_empty(result, grid, options.size, options.min_valid)
        result.out_dir, result.manifest = out_dir, out_dir / MANIFEST_CSV
        result.dataset_yaml = out_dir / DATASET_YAML
        result.tasks = list(sources.tasks)
        if assigner.block_size_m is not None:
            result.block_size_m = assigner.block_size_m
            result.block_patches = int(round(assigner.block_px[0] / options.step))
        info = _describe(sources, grid, options, assigner, result)
        commit(stage, out_dir, owned, info)
    except BaseException as exc:  # a failed or interrupted run leaves no half dataset behind
        if (stage / SWAP_FILE).is_file():  # stopped inside the swap: finish it, so the new set is whole
            with contextlib.suppress(Exception):
                finish_swap(stage, out_dir)
        shutil.rmtree(stage, ignore_errors=True)
        if not isinstance(exc, AerialMTLError) and (isinstance(exc, OSError)
                                                    or kind_of(exc, out_dir) is not None):
            raise output_error(exc, out_dir, "the tile folder", "‹out_dir›") from exc  # e.g. a full disk
        raise
    return result


def _check_arguments(
    options: TileOptions, dsm: str | Path | None, dtm: str | Path | None, ndsm: str | Path | None,
    labels: str | Path | None, labels_vector: str | Path | None, class_field: str | None,
    classes: ClassScheme | str | Path | None,
) -> ClassScheme | None:
    """Validate :func:`tile_dataset`'s arguments before any file is read; returns the class scheme."""
    min_valid = options.min_valid
    if not 0.0 <= min_valid <= 1.0:
        raise InputError(f"‹min_valid› must be a fraction in 0..1, got {min_valid}", param="min_valid")
    if labels is not None and labels_vector is not None:
        raise InputError("give either a label raster (‹labels›) or label polygons (‹labels_vector›), not both",
                         param="labels_vector")
    if labels_vector is not None and not class_field:
        raise InputError("‹labels_vector› needs ‹class_field=NAME›, the attribute holding the class code or name",
                         param="class_field")
    if ndsm is not None and (dsm is not None or dtm is not None):
        raise InputError("give either an nDSM (‹ndsm›) or a DSM and a DTM (‹dsm›/‹dtm›), not both", param="ndsm")
    if ndsm is None and (dsm is None) != (dtm is None):
        raise InputError("‹dsm› and ‹dtm› go together: pass both, or pass a ready nDSM with ‹ndsm›",
                         param="dtm" if dtm is None else "dsm")
    has_height = any(p is not None for p in (dsm, dtm, ndsm))
    has_labels = labels is not None or labels_vector is not None
    scheme = classes if classes is None or isinstance(classes, ClassScheme) else ClassScheme.load(classes)
    if has_labels and scheme is None:
        raise InputError(
            "labels were given without a class scheme: pass ‹classes› (a YAML file or dfc2018, isprs, synthetic)",
            param="classes",
        )
    if not has_height and not has_labels:
        raise InputError(
            "nothing to learn: give a height layer (‹ndsm›, or ‹dsm›/‹dtm›) and/or labels (‹labels›/‹labels_vector›)"
        )
    count_windows(1, 1, options.size, options.step)  # validates size/stride
    return scheme


def _describe(sources: TileSources, grid: Grid, options: TileOptions, assigner: SplitAssigner,
              result: TileResult) -> TileFolderInfo:
    """The ``dataset.yaml`` of a finished tile run."""
    paths = sources.paths
    return TileFolderInfo(
        root=result.out_dir,
        crs=grid.crs.to_string(),
        gsd=float(grid.gsd),
        patch_size=int(options.size),
        stride=int(options.step),
        bands=tuple(int(b) for b in sources.image.bands),
        band_names=tuple(sources.band_names),
        dtype=sources.dtype,
        mean=tuple(result.mean or ()),
        std=tuple(result.std or ()),
        tasks=tuple(sources.tasks),
        classes=sources.scheme if sources.labels is not None else None,
        height={
            "nodata": HEIGHT_NODATA,
            "clip_negative": bool(options.heights.clip_negative),
            "max_height": options.heights.max_height,
            "source": "ndsm" if paths["ndsm"] is not None else "dsm-dtm",
            "units": sources.height_units,
        } if sources.heights is not None else None,
        splits={**options.splits.to_dict(), **({"block_size_used_m": assigner.block_size_m}
                                       if assigner.block_size_m is not None else {})},
        counts=dict(result.counts),
        min_valid=float(options.min_valid),
        provenance={
            **{k: recorded_path(v) if v else None for k, v in paths.items()},
            "class_field": sources.class_field,
            "aerialmtl_version": __version__,
            "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        },
    )


def _tile_loop(
    sources: TileSources, assigner: SplitAssigner, grid: Grid, out_dir: Path, options: TileOptions, progress: bool,
) -> TileResult:
    """Visit every window of the (size, stride) grid, write its patches and stream the manifest."""
    size, stride, min_valid = options.size, options.step, options.min_valid
    counts = {s: 0 for s in SPLITS}
    stats = _BandStats(len(sources.image.bands))
    dropped_invalid = dropped_split = 0
    max_valid = 0.0
    heights = _HeightSummary()
    total = count_windows(grid.width, grid.height, size, stride)
    windows = tile_windows(grid.width, grid.height, size, stride)
    with ManifestWriter(out_dir) as writer:  # streamed row by row, renamed once every patch is written
        for win in tqdm(windows, total=total, desc="tiling", unit="patch", disable=not progress):
            split = assigner.split_of(win)
            if split is None:
                dropped_split += 1
                continue
            data, valid = sources.image.read(win)
            max_valid = max(max_valid, float(valid.mean()))
            if float(valid.mean()) < min_valid or not valid.any():
                dropped_invalid += 1
                continue
            writer.writerow(_write_patches(sources, grid, win, split, data, valid, out_dir, heights))
            if split == "train":
                stats.update(data, valid)
            counts[split] += 1
    ms = stats.result()
    if heights.implausible:
        lo, hi = SURFACE_HEIGHTS_M
        layers = "nDSM" if sources.paths.get("ndsm") else "DSM − DTM"
        warnings.warn(
            f"the reference heights ({layers}) reach {heights.low:.3g}..{heights.high:.3g} m above ground, beyond "
            f"{lo:g}..{hi:g} m on {heights.implausible} written pixels, which no surface has: probably an undeclared "
            "nodata value (e.g. 3.4e38 or -32768) or a wrong --z-unit; declare it (`gdal_edit.py -a_nodata VALUE "
            "FILE`), pass --max-height, or check the unit; training on these heights would diverge",
            UserWarning, stacklevel=2)
    return TileResult(
        out_dir=out_dir, manifest=writer.path, dataset_yaml=out_dir / DATASET_YAML, counts=counts,
        windows=total, dropped_invalid=dropped_invalid, dropped_split=dropped_split,
        mean=ms[0] if ms else None, std=ms[1] if ms else None, max_valid_fraction=max_valid,
        height_summary=heights.result(),
    )


def check_not_empty(result: TileResult, grid: Grid, size: int, min_valid: float) -> None:
    """Refuse a tile run that kept no patch at all, saying why with the numbers and what to change.

    Raises:
        InputError: the orthophoto is smaller than one patch and too little of it is valid, or every
            window was dropped (too few valid pixels, or outside every split block / AOI).
    """
    if sum(result.counts.values()) > 0:
        return
    w, h = grid.width, grid.height
    pct = f"{100 * result.max_valid_fraction:.0f} %"
    if w < size or h < size:
        fit = (min(w, h) // 32) * 32
        smaller = f"pass ‹size={fit}› (≤ the orthophoto's side, a multiple of 32) or " if fit >= 32 else ""
        raise InputError(
            f"the tile set would be empty: the orthophoto is {w} × {h} pixels (at {grid.gsd:.3g} m), smaller than one "
            f"{size}-pixel patch, and its padded patch is {pct} valid, below ‹min_valid={min_valid:g}›; "
            f"{smaller}lower ‹min_valid› (e.g. {max(0.0, result.max_valid_fraction - 0.01):.2f}), or tile a larger "
            "orthophoto"
        )
    raise InputError(
        f"the tile set would be empty: of {result.windows} windows of {size} pixels, {result.dropped_invalid} have "
        f"fewer valid orthophoto pixels than ‹min_valid={min_valid:g}› (the best has {pct}) and "
        f"{result.dropped_split} straddle split blocks or lie outside every split AOI; lower ‹min_valid›, use a "
        "smaller ‹size› or ‹split_block›, or check the orthophoto's nodata value and alpha band"
    )


def _write_patches(
    sources: TileSources, grid: Grid, win: Window, split: str, data: np.ndarray, valid: np.ndarray, out_dir: Path,
    summary: _HeightSummary | None = None,
) -> dict[str, Any]:
    """Write the image, height and class patches of ``win``; returns its manifest row.

    Args:
        data: (C, h, w) orthophoto bands of the window (source dtype); ``valid``: (h, w) bool.
    """
    pid = f"r{int(win.row_off):06d}_c{int(win.col_off):06d}"
    row: dict[str, Any] = {c: "" for c in MANIFEST_COLUMNS}
    t = grid.window_transform(win)
    left, top = t @ (0, 0)
    right, bottom = t @ (win.width, win.height)
    row.update(patch_id=pid, split=split, col_off=int(win.col_off), row_off=int(win.row_off),
               width=int(win.width), height=int(win.height), left=_fmt(left), bottom=_fmt(bottom),
               right=_fmt(right), top=_fmt(top), crs=grid.crs.to_string(), valid_fraction=f"{float(valid.mean()):.6f}")
    row["image_path"] = rel = patch_path(split, "image", pid)
    _write(out_dir / rel, patch_profile(grid, win, data.shape[0], sources.dtype, None), data, valid)
    if sources.heights is not None:
        h, hvalid = sources.heights.read(win)
        hvalid = hvalid & valid
        hv = h[hvalid]
        row["height_path"] = rel = patch_path(split, "height", pid)
        _write(out_dir / rel, patch_profile(grid, win, 1, "float32", HEIGHT_NODATA),
               np.where(hvalid, h, HEIGHT_NODATA).astype(np.float32)[None])
        if summary is not None:
            summary.update(split, hv)
        if hv.size:
            row.update(height_min=_fmt(float(hv.min())), height_mean=_fmt(float(hv.astype(np.float64).mean())),
                       height_max=_fmt(float(hv.max())))
    if sources.labels is not None and sources.scheme is not None:
        cls = np.where(valid, sources.read_classes(win), IGNORE_INDEX).astype(np.uint8)
        row["classes_path"] = rel = patch_path(split, "classes", pid)
        _write(out_dir / rel, patch_profile(grid, win, 1, "uint8", IGNORE_INDEX), cls[None])
        k = sources.scheme.num_classes
        hist = np.bincount(cls[cls != IGNORE_INDEX].ravel(), minlength=k)
        row["class_hist"] = ";".join(str(int(v)) for v in hist[:k])
    return row


__all__ = ["MANIFEST_COLUMNS", "TileOptions", "TileResult", "read_manifest", "tile_dataset"]
