"""Cut an orthophoto and its aligned height / label layers into training patches (the tile folder).

:func:`tile_dataset` walks a (size, stride) grid of windows over the reference grid (the ortho, optionally
resampled to ``gsd``), reads every layer window by window through :mod:`aerialmtl.io.align` (no raster is
ever loaded whole), assigns each window to a spatial split, drops windows with too few valid image pixels,
and writes the folder described in ``docs/CONTRACTS.md``::

    OUT/{train,val,test}/image/<id>.tif     ortho bands, source dtype, internal mask where invalid
    OUT/{train,val,test}/height/<id>.tif    float32 metres, nodata -9999
    OUT/{train,val,test}/classes/<id>.tif   uint8 class indices, nodata 255
    OUT/manifest.csv, OUT/dataset.yaml      written last: their absence marks an unfinished run

A run that fails (bad label codes, unreadable file) or is interrupted removes what it wrote; a folder that a
killed run left unfinished (no ``dataset.yaml``, only tile outputs) is replaced by the next run without
``overwrite``.

Every patch's transform is ``rasterio.windows.transform(window, grid.transform)``. Per-band mean/std are
accumulated over valid pixels of the train split only (float64, merged patch by patch).
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import os
import shutil
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import rasterio
from rasterio.windows import Window
from tqdm import tqdm

from aerialmtl import __version__
from aerialmtl.classes import IGNORE_INDEX, ClassScheme
from aerialmtl.errors import InputError, OutputError, OutputExistsError
from aerialmtl.formats.tiles import (
    CACHE_DIR,
    DATASET_YAML,
    MANIFEST_COLUMNS,
    MANIFEST_CSV,
    PART_SUFFIX,
    ManifestWriter,
    TileFolderInfo,
    read_manifest,
)
from aerialmtl.io.align import HEIGHT_NODATA, AlignedRaster, HeightSource, NdsmOptions, reference_grid
from aerialmtl.io.outputs import make_output_dir
from aerialmtl.io.profiles import patch_profile
from aerialmtl.io.vector import VectorLabels
from aerialmtl.tiling.grid import count_windows, tile_windows
from aerialmtl.tiling.splits import SPLITS, SplitAssigner, SplitSpec

#: GDAL block cache while tiling (MB) unless GDAL_CACHEMAX is set: keeps memory flat on huge rasters.
DEFAULT_CACHE_MB = 128


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


#: What a tile run writes into its folder; a folder holding only these but no dataset.yaml is unfinished.
_OWN_ENTRIES = (*SPLITS, MANIFEST_CSV, MANIFEST_CSV + PART_SUFFIX, DATASET_YAML + PART_SUFFIX, CACHE_DIR)


def _unfinished(out_dir: Path) -> bool:
    """True when ``out_dir`` holds only what an interrupted or failed tile run leaves (no dataset.yaml)."""
    names = {p.name for p in out_dir.iterdir()}
    return DATASET_YAML not in names and names <= set(_OWN_ENTRIES)


def _clear(out_dir: Path) -> None:
    """Remove the tile dataset in ``out_dir`` (only the entries a tile run writes)."""
    for name in (DATASET_YAML, MANIFEST_CSV):  # first, so a half-replaced folder reads as unfinished
        (out_dir / name).unlink(missing_ok=True)
    for name in _OWN_ENTRIES:
        path = out_dir / name
        if path.is_dir():
            shutil.rmtree(path)
        else:
            path.unlink(missing_ok=True)


def _prepare_out_dir(out_dir: Path, overwrite: bool) -> bool:
    """Make ``out_dir`` ready for a new tile dataset; returns whether the folder was created here.

    A folder left unfinished by an interrupted or failed run is replaced without ``overwrite``.
    """
    if out_dir.exists() and not out_dir.is_dir():
        raise OutputError(f"--out '{out_dir}' is a file; pass a folder path")
    if out_dir.is_dir() and any(out_dir.iterdir()):
        if not overwrite and not _unfinished(out_dir):
            raise OutputExistsError(
                f"output folder '{out_dir}' is not empty; choose another --out or pass --overwrite to replace "
                "the tile dataset in it"
            )
        _clear(out_dir)
    return make_output_dir(out_dir, "--out folder")


def _band_names(src: rasterio.io.DatasetReader, bands: Sequence[int]) -> list[str]:
    names = []
    for b in bands:
        desc = src.descriptions[b - 1]
        names.append(desc if desc else src.colorinterp[b - 1].name if src.colorinterp else f"band{b}")
    return names


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
    size: int = 320,
    stride: int | None = None,
    gsd: float | None = None,
    min_valid: float = 0.9,
    splits: SplitSpec = SplitSpec(),
    bands: Sequence[int] | None = None,
    ndsm_options: NdsmOptions = NdsmOptions(),
    ignore_unknown_codes: bool = False,
    overwrite: bool = False,
    progress: bool = True,
) -> TileResult:
    """Tile an orthophoto plus aligned height and/or label layers into a training dataset folder.

    Args:
        ortho: orthophoto GeoTIFF; defines the reference grid (CRS, origin, pixel size).
        out_dir: output folder (created; must be empty unless ``overwrite``).
        dsm, dtm: surface and terrain models; height = DSM − DTM in metres (values in the unit the file
            states, else ``ndsm_options.z_unit``, else metres). Mutually exclusive with ``ndsm``.
        ndsm: ready heights above ground (nDSM / CHM; units as for ``dsm``).
        labels: label raster of raw class codes.
        labels_vector: GeoJSON polygons with a class attribute (``class_field``), instead of ``labels``.
        class_field: attribute of ``labels_vector`` with codes or class names.
        classes: :class:`ClassScheme`, a scheme YAML path, or a built-in name; required with labels.
        size: patch side (pixels of the reference grid).
        stride: step between patches (pixels, ``≤ size``; default ``size``).
        gsd: resample everything to this pixel size in metres (whatever the CRS unit) instead of the ortho's.
        min_valid: minimum fraction of valid image pixels for a patch to be kept (0..1).
        splits: spatial split specification.
        bands: 1-based ortho bands to keep (default: all but alpha).
        ndsm_options: negative clipping / maximum height / the heights' unit when a file states none.
        ignore_unknown_codes: map label codes (or vector values) outside the scheme to no-label instead of
            raising :class:`~aerialmtl.errors.LabelError`.
        overwrite: replace an existing tile dataset in ``out_dir``.
        progress: show a tqdm progress bar.

    Returns:
        A :class:`TileResult` (counts per split, manifest path, statistics).

    Raises:
        InputError / AlignmentError / LabelError: unusable inputs (messages name the file and the fix).
        OutputExistsError: ``out_dir`` is not empty and ``overwrite`` is false.
    """
    out_dir = Path(out_dir)
    stride = size if stride is None else stride
    if not 0.0 <= min_valid <= 1.0:
        raise InputError(f"--min-valid must be a fraction in 0..1, got {min_valid}")
    if labels is not None and labels_vector is not None:
        raise InputError("give either a label raster (--labels) or label polygons (--labels-vector), not both")
    if labels_vector is not None and not class_field:
        raise InputError("--labels-vector needs --class-field NAME, the attribute holding the class code or name")
    has_height = any(p is not None for p in (dsm, dtm, ndsm))
    has_labels = labels is not None or labels_vector is not None
    scheme = _load_scheme(classes)
    if has_labels and scheme is None:
        raise InputError(
            "labels were given without a class scheme: pass --classes (a YAML file or dfc2018, isprs, synthetic)"
        )
    if not has_height and not has_labels:
        raise InputError(
            "nothing to learn: give a height layer (--ndsm, or --dsm/--dtm) and/or labels (--labels/--labels-vector)"
        )
    n_windows_check = count_windows(1, 1, size, stride)  # validates size/stride before touching files
    del n_windows_check

    grid = reference_grid(ortho, gsd)
    on_unknown = "ignore" if ignore_unknown_codes else "error"
    height_units: dict[str, dict[str, object]] = {}
    env: dict[str, Any] = {"GDAL_TIFF_INTERNAL_MASK": True}
    if "GDAL_CACHEMAX" not in os.environ:  # a user's own setting wins
        env["GDAL_CACHEMAX"] = DEFAULT_CACHE_MB * 1024 * 1024  # bytes (unambiguous for GDAL and rasterio)
    opened: list[Any] = []
    with rasterio.Env(**env):
        try:
            image = AlignedRaster(ortho, grid, "image", bands=bands, role="orthophoto", bands_from="--bands")
            opened.append(image)
            heights = HeightSource(grid, ndsm=ndsm, dsm=dsm, dtm=dtm, options=ndsm_options) if has_height else None
            if heights is not None:
                opened.append(heights)
                height_units = heights.units()
            label_src: AlignedRaster | VectorLabels | None = None
            if labels is not None:
                label_src = AlignedRaster(labels, grid, "labels", bands=[1], role="labels")
            elif labels_vector is not None:
                label_src = VectorLabels(labels_vector, grid, class_field or "", scheme, on_unknown)  # type: ignore[arg-type]
            if label_src is not None:
                opened.append(label_src)
            assigner = SplitAssigner(splits, grid, stride=stride, size=size)
            created = _prepare_out_dir(out_dir, overwrite)
            try:
                result = _tile_loop(
                    image, heights, label_src, scheme, assigner, grid, out_dir, size, stride, min_valid,
                    on_unknown, progress,
                )
            except BaseException:  # a failed or interrupted run leaves no half dataset behind
                with contextlib.suppress(OSError):
                    _clear(out_dir)
                    if created:
                        out_dir.rmdir()
                raise
            band_names = _band_names(image.src, image.bands)
            dtype = image.src.dtypes[image.bands[0] - 1]
        finally:
            for layer in reversed(opened):
                layer.close()

    tasks = (["height"] if has_height else []) + (["classes"] if has_labels else [])
    result.tasks = tasks
    if assigner.block_size_m is not None:
        result.block_size_m = assigner.block_size_m
        result.block_patches = int(round(assigner.block_px[0] / stride))
    TileFolderInfo(
        root=out_dir,
        crs=grid.crs.to_string(),
        gsd=float(grid.gsd),
        patch_size=int(size),
        stride=int(stride),
        bands=tuple(int(b) for b in image.bands),
        band_names=tuple(band_names),
        dtype=dtype,
        mean=tuple(result.mean or ()),
        std=tuple(result.std or ()),
        tasks=tuple(tasks),
        classes=scheme if has_labels else None,
        height={
            "nodata": HEIGHT_NODATA,
            "clip_negative": bool(ndsm_options.clip_negative),
            "max_height": ndsm_options.max_height,
            "source": "ndsm" if ndsm is not None else "dsm-dtm",
            "units": height_units,
        } if has_height else None,
        splits={**splits.to_dict(), **({"block_size_used_m": assigner.block_size_m}
                                       if assigner.block_size_m is not None else {})},
        counts=dict(result.counts),
        min_valid=float(min_valid),
        provenance={
            "ortho": str(Path(ortho).resolve()),
            "ndsm": str(Path(ndsm).resolve()) if ndsm else None,
            "dsm": str(Path(dsm).resolve()) if dsm else None,
            "dtm": str(Path(dtm).resolve()) if dtm else None,
            "labels": str(Path(labels).resolve()) if labels else None,
            "labels_vector": str(Path(labels_vector).resolve()) if labels_vector else None,
            "class_field": class_field,
            "aerialmtl_version": __version__,
            "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        },
    ).write()
    return result


def _tile_loop(
    image: AlignedRaster,
    heights: HeightSource | None,
    label_src: AlignedRaster | VectorLabels | None,
    scheme: ClassScheme | None,
    assigner: SplitAssigner,
    grid: Any,
    out_dir: Path,
    size: int,
    stride: int,
    min_valid: float,
    on_unknown: str,
    progress: bool,
) -> TileResult:
    counts = {s: 0 for s in SPLITS}
    stats = _BandStats(len(image.bands))
    dropped_invalid = dropped_split = 0
    crs_str = grid.crs.to_string()
    total = count_windows(grid.width, grid.height, size, stride)
    img_dtype = image.src.dtypes[image.bands[0] - 1]
    windows = tile_windows(grid.width, grid.height, size, stride)
    with ManifestWriter(out_dir) as writer:  # streamed row by row, renamed once every patch is written
        for win in tqdm(windows, total=total, desc="tiling", unit="patch", disable=not progress):
            dropped = _tile_one(win, image, heights, label_src, scheme, assigner, grid, out_dir, min_valid,
                                on_unknown, img_dtype, crs_str, writer, counts, stats)
            dropped_invalid += dropped == "invalid"
            dropped_split += dropped == "split"
    manifest = writer.path
    ms = stats.result()
    return TileResult(
        out_dir=out_dir, manifest=manifest, dataset_yaml=out_dir / DATASET_YAML, counts=counts,
        windows=total, dropped_invalid=dropped_invalid, dropped_split=dropped_split,
        mean=ms[0] if ms else None, std=ms[1] if ms else None,
    )


def _tile_one(
    win: Window,
    image: AlignedRaster,
    heights: HeightSource | None,
    label_src: AlignedRaster | VectorLabels | None,
    scheme: ClassScheme | None,
    assigner: SplitAssigner,
    grid: Any,
    out_dir: Path,
    min_valid: float,
    on_unknown: str,
    img_dtype: str,
    crs_str: str,
    writer: ManifestWriter,
    counts: dict[str, int],
    stats: _BandStats,
) -> str | None:
    """Write the patches of one window and its manifest row; returns why it was dropped, if it was."""
    split = assigner.split_of(win)
    if split is None:
        return "split"
    data, valid = image.read(win)
    valid_fraction = float(valid.mean())
    if valid_fraction < min_valid or not valid.any():
        return "invalid"
    pid = f"r{int(win.row_off):06d}_c{int(win.col_off):06d}"
    row: dict[str, Any] = {c: "" for c in MANIFEST_COLUMNS}
    t = grid.window_transform(win)
    left, top = t @ (0, 0)
    right, bottom = t @ (win.width, win.height)
    row.update(patch_id=pid, split=split, col_off=int(win.col_off), row_off=int(win.row_off),
               width=int(win.width), height=int(win.height), left=_fmt(left), bottom=_fmt(bottom),
               right=_fmt(right), top=_fmt(top), crs=crs_str, valid_fraction=f"{valid_fraction:.6f}")

    rel = f"{split}/image/{pid}.tif"
    _write(out_dir / rel, patch_profile(grid, win, data.shape[0], img_dtype, None), data, valid)
    row["image_path"] = rel
    if heights is not None:
        h, hvalid = heights.read(win)
        hvalid = hvalid & valid
        hv = h[hvalid]
        out = np.where(hvalid, h, HEIGHT_NODATA).astype(np.float32)
        rel = f"{split}/height/{pid}.tif"
        _write(out_dir / rel, patch_profile(grid, win, 1, "float32", HEIGHT_NODATA), out[None])
        row["height_path"] = rel
        if hv.size:
            row.update(height_min=_fmt(float(hv.min())), height_mean=_fmt(float(hv.astype(np.float64).mean())),
                       height_max=_fmt(float(hv.max())))
    if label_src is not None and scheme is not None:
        if isinstance(label_src, VectorLabels):
            cls, _ = label_src.read(win)
        else:
            codes, lvalid = label_src.read(win)
            cls = scheme.remap(codes[0], valid=lvalid, on_unknown=on_unknown,  # type: ignore[arg-type]
                               source=f"labels '{label_src.path}'")
        cls = np.where(valid, cls, IGNORE_INDEX).astype(np.uint8)
        rel = f"{split}/classes/{pid}.tif"
        _write(out_dir / rel, patch_profile(grid, win, 1, "uint8", IGNORE_INDEX), cls[None])
        row["classes_path"] = rel
        hist = np.bincount(cls[cls != IGNORE_INDEX].ravel(), minlength=scheme.num_classes)
        row["class_hist"] = ";".join(str(int(v)) for v in hist[: scheme.num_classes])
    if split == "train":
        stats.update(data, valid)
    counts[split] += 1
    writer.writerow(row)
    return None


__all__ = ["MANIFEST_COLUMNS", "TileResult", "read_manifest", "tile_dataset"]
