"""Streaming prediction of one orthophoto into a prediction folder of Cloud-Optimized GeoTIFFs.

The orthophoto is read window by window on the reference grid at the model's GSD
(:func:`~aerialmtl.io.align.reference_grid` + :class:`~aerialmtl.io.align.AlignedRaster`), normalised
with the checkpoint's per-band mean/std, batched through the model (plain forward for T = 1,
:func:`~aerialmtl.models.mc_dropout.mc_predict` for T > 1: encoder once, T decoder samples), blended
with :class:`~aerialmtl.inference.stitch.BandStitcher` following the plan of
:func:`~aerialmtl.inference.windows.plan_bands`, and written row band by row band
(:class:`~aerialmtl.inference.writer.PredictionWriter`). Memory holds one window row of accumulators
(``tile × width`` pixels), independent of the raster height; windows with no valid input pixel (nodata,
outside the AOI) are not computed.
"""

from __future__ import annotations

import contextlib
import json
import os
import time
import warnings
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import rasterio
import torch
from rasterio.features import geometry_mask
from rasterio.windows import Window
from shapely.geometry import box
from shapely.strtree import STRtree
from tqdm.auto import tqdm

from aerialmtl import __version__
from aerialmtl.classes import IGNORE_INDEX
from aerialmtl.errors import InputError
from aerialmtl.formats.checkpoint import ModelMeta
from aerialmtl.formats.prediction import CLASS_SCHEME_TAG
from aerialmtl.inference.stitch import FLOAT_NODATA, BandStitcher
from aerialmtl.inference.windows import check_tiling, plan_bands
from aerialmtl.inference.writer import LayerSpec, PredictionWriter, check_outputs_free
from aerialmtl.io.align import AlignedRaster, Grid, reference_grid

#: MC-dropout samples when neither the caller nor the checkpoint says otherwise.
DEFAULT_MC_SAMPLES = 30
#: Relative GSD difference above which the orthophoto is resampled to the model's GSD.
GSD_TOLERANCE = 0.01
#: Largest number of image pixels (windows × MC samples × h × w) decoded in one call, per device type.
#: The full D3-Net decoder needs about 1.2 GiB of activations per decoded megapixel in fp32, so a batch
#: of 4 windows of 512² with T = 30 decoded at once would need ~36 GiB; the MC samples are split into
#: chunks that fit instead (the result is the same, only the dropout masks are drawn in another order).
DECODE_PIXELS = {"cpu": 2**21, "cuda": 2**23}

Precision = Literal["auto", "bf16", "fp32"]


@dataclass(frozen=True)
class PredictResult:
    """What :func:`predict_raster` wrote and how long it took.

    Attributes:
        out_dir: the prediction folder.
        files: layer name → final path (``"prediction"`` is ``prediction.json``).
        mc: MC-dropout samples T.
        windows_total, windows_computed: windows in the plan / actually run through the model.
        overlap_factor: pixels computed / output pixels (computed windows only).
        plan_overlap_factor: the same if every window were computed.
        megapixels_per_s: output megapixels per second of total time.
        timings: seconds per stage (``read``, ``model``, ``stitch_write``, ``cog``, ``total``).
    """

    out_dir: Path
    files: dict[str, Path]
    grid: Grid
    mc: int
    windows_total: int
    windows_computed: int
    overlap_factor: float
    plan_overlap_factor: float
    megapixels_per_s: float
    timings: dict[str, float] = field(default_factory=dict)


# ---- inputs ------------------------------------------------------------------------------------
class _Aoi:
    """AOI polygons on the grid; ``mask(window)`` → (h, w) bool inside."""

    def __init__(self, path: str | Path, grid: Grid) -> None:
        from aerialmtl.io.vector import load_geometries

        self.geoms = [g for g, _ in load_geometries(path, grid.crs, role="AOI (--aoi)")]
        if not self.geoms:
            raise InputError(f"AOI (--aoi) '{path}' holds no polygon; pass a GeoJSON with polygons")
        self.tree = STRtree(self.geoms)
        self.grid = grid

    def mask(self, window: Window) -> np.ndarray:
        h, w = int(window.height), int(window.width)
        tr = self.grid.window_transform(window)
        x0, y0 = tr @ (0, 0)
        x1, y1 = tr @ (w, h)
        hits = [self.geoms[k] for k in self.tree.query(box(min(x0, x1), min(y0, y1), max(x0, x1), max(y0, y1)))]
        if not hits:
            return np.zeros((h, w), bool)
        return geometry_mask(hits, out_shape=(h, w), transform=tr, invert=True)


def _load(checkpoint: str | Path | tuple[torch.nn.Module, ModelMeta]) -> tuple[torch.nn.Module, ModelMeta, str]:
    if isinstance(checkpoint, tuple):
        model, meta = checkpoint
        return model, meta, "<in-memory model>"
    from aerialmtl.formats.checkpoint import load_model

    model, meta = load_model(checkpoint)
    return model, meta, str(checkpoint)


def _device(device: str) -> torch.device:
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise InputError(f"device={device!r} but no CUDA GPU is available; pass --device cpu or --device auto")
    if device not in ("cpu",) and not device.startswith("cuda"):
        raise InputError(f"device={device!r} is not supported; use auto, cpu or cuda")
    return torch.device(device)


# ---- model -------------------------------------------------------------------------------------
def resolve_precision(precision: str, device: torch.device) -> Literal["bf16", "fp32"]:
    """``auto`` → bf16 autocast on CUDA, fp32 on CPU.

    CPUs without native bf16 matrix instructions (AVX-512-BF16/AMX; e.g. the AMD Zen 3 this package is
    developed on) emulate bf16 convolutions more than 10× slower than fp32 (bench/RESULTS.md, predict).
    """
    if precision == "auto":
        return "bf16" if device.type == "cuda" else "fp32"
    if precision not in ("bf16", "fp32"):
        raise InputError(f"precision={precision!r} is not supported; use auto, bf16 or fp32 (--precision)")
    return precision  # type: ignore[return-value]


def mc_sample_batch(batch: int, height: int, width: int, device: torch.device, max_pixels: int | None = None) -> int:
    """MC samples decoded per call so that ``batch × samples × height × width ≤ max_pixels`` (at least 1)."""
    budget = DECODE_PIXELS.get(device.type, DECODE_PIXELS["cpu"]) if max_pixels is None else max_pixels
    return max(1, int(budget) // max(1, batch * height * width))


def _run_model(
    model: torch.nn.Module, x: torch.Tensor, mc: int, tasks: tuple[str, ...], precision: Literal["bf16", "fp32"],
    max_decode_pixels: int | None = None,
) -> dict[str, np.ndarray]:
    """B×C×h×w normalised batch → blended quantities, each (B, C, h, w) float32 numpy."""
    amp = (torch.autocast(x.device.type, dtype=torch.bfloat16) if precision == "bf16"
           else contextlib.nullcontext())
    out: dict[str, torch.Tensor] = {}
    with torch.inference_mode(), amp:
        if mc == 1:
            model.eval()
            raw = model(x)
            if "height" in tasks:
                out["height"] = raw["height"].float()
            if "classes" in tasks:
                out["probs"] = torch.softmax(raw["classes"].float(), dim=1)
        else:
            from aerialmtl.models.mc_dropout import mc_predict

            b, _, h, w = x.shape
            res = mc_predict(model, x, mc, sample_batch=mc_sample_batch(b, h, w, x.device, max_decode_pixels))
            if "height" in tasks:
                out["height"] = res["height"]["mean"].float().reshape(b, 1, h, w)
                out["height_std"] = res["height"]["std"].float().reshape(b, 1, h, w)
            if "classes" in tasks:
                c = res["classes"]
                out["probs"] = c["probs"].float()
                ent = c["entropy"].float().reshape(b, 1, h, w)
                out["expected_entropy"] = ent - c["mutual_info"].float().reshape(b, 1, h, w)
    return {k: v.cpu().numpy() for k, v in out.items()}


# ---- outputs -----------------------------------------------------------------------------------
def _layer_specs(meta: ModelMeta, mc: int, probabilities: bool) -> list[LayerSpec]:
    tasks = tuple(meta.model.tasks)
    specs: list[LayerSpec] = []
    unc = mc > 1
    if "height" in tasks:
        specs.append(LayerSpec("height", 1, "float32", FLOAT_NODATA, ("height above ground (MC mean)",), ("m",)))
        if unc:
            specs.append(LayerSpec("height_std", 1, "float32", FLOAT_NODATA,
                                   ("height standard deviation (MC dropout)",), ("m",)))
    if "classes" in tasks:
        scheme = meta.classes
        assert scheme is not None
        names = {str(i): n for i, n in enumerate(scheme.names)}
        specs.append(LayerSpec(
            "classes", 1, "uint8", IGNORE_INDEX, ("land-cover class index",), ("",), categorical=True,
            colormap=scheme.colormap(), tags={CLASS_SCHEME_TAG: json.dumps(scheme.to_dict())},
            band_tags={1: {"class_names": json.dumps(names), **{f"CLASS_{i}": n for i, n in names.items()}}},
        ))
        if unc:
            specs.append(LayerSpec("class_entropy", 1, "float32", FLOAT_NODATA,
                                   ("predictive entropy of the class probabilities",), ("nats",)))
            specs.append(LayerSpec("class_mutual_info", 1, "float32", FLOAT_NODATA,
                                   ("mutual information (epistemic part of the entropy)",), ("nats",)))
        if probabilities:
            specs.append(LayerSpec("class_probabilities", scheme.num_classes, "float32", FLOAT_NODATA,
                                   tuple(f"P({n})" for n in scheme.names), ("",) * scheme.num_classes))
    return specs


def _batches(items: Iterator[Any], size: int) -> Iterator[list[Any]]:
    batch: list[Any] = []
    for it in items:
        batch.append(it)
        if len(batch) == size:
            yield batch
            batch = []
    if batch:
        yield batch


def _record_timings(path: Path, timings: dict[str, float]) -> None:
    """Add the final timings to ``prediction.json`` (atomic replace)."""
    info = json.loads(path.read_text(encoding="utf-8"))
    info["timings_s"] = dict(timings)
    tmp = path.with_name(f".{path.name}.partial")
    tmp.write_text(json.dumps(info, indent=2, default=str), encoding="utf-8")
    os.replace(tmp, path)


# ---- the tool ----------------------------------------------------------------------------------
def predict_raster(
    ortho: str | Path,
    checkpoint: str | Path | tuple[torch.nn.Module, ModelMeta],
    out_dir: str | Path,
    *,
    mc: int | None = None,
    tile: int = 1024,
    overlap: int = 64,
    batch_size: int = 2,
    precision: Precision = "auto",
    device: str = "auto",
    aoi: str | Path | None = None,
    probabilities: bool = False,
    overwrite: bool = False,
    progress: bool = True,
    checkpoint_name: str | None = None,
    max_decode_pixels: int | None = None,
) -> PredictResult:
    """Predict height and land cover (with MC-dropout uncertainty) over a whole orthophoto.

    Args:
        ortho: orthophoto GeoTIFF (any size; read window by window).
        checkpoint: checkpoint path, or ``(model, meta)`` already loaded.
        out_dir: prediction folder (see docs/CONTRACTS.md, "Prediction folder").
        mc: MC-dropout samples T (1 = single deterministic pass, no uncertainty files); default
            :data:`DEFAULT_MC_SAMPLES` when the model has dropout, else 1.
        tile: largest window side in pixels (multiple of 32). 1024 with ``overlap`` 64 computes ≈ 1.14×
            the output pixels (512 → 1.31×); the row-band accumulators grow with ``tile × raster width``.
        overlap: minimum overlap between neighbouring windows in pixels (blended; see
            :mod:`aerialmtl.inference.windows`).
        batch_size: windows per model call.
        precision: ``"auto"`` (bf16 on CUDA, fp32 on CPU; see :func:`resolve_precision`), ``"bf16"``
            (autocast) or ``"fp32"``.
        device: ``"auto"``, ``"cpu"`` or ``"cuda"``.
        aoi: optional GeoJSON of polygons; only windows intersecting them are computed, pixels outside
            are nodata.
        probabilities: also write ``class_probabilities.tif`` (K float32 bands).
        overwrite: replace existing outputs instead of raising.
        progress: show a tqdm progress bar.
        checkpoint_name: name recorded in ``prediction.json`` when ``checkpoint`` is a loaded model.
        max_decode_pixels: bound on the pixels decoded per model call with MC dropout (windows ×
            samples × h × w); default :data:`DECODE_PIXELS` of the device. Bounds memory, not results.

    Returns:
        A :class:`PredictResult`.

    Raises:
        OutputExistsError: outputs exist and ``overwrite`` is false.
        InputError / AlignmentError / CheckpointError: unusable inputs (messages name the fix).
    """
    t_start = time.perf_counter()
    check_tiling(tile, overlap)
    if mc is not None and (not isinstance(mc, int) or mc < 1):
        raise InputError(f"mc must be a positive number of MC-dropout samples, got {mc!r}; pass e.g. --mc 30 (or 1)")
    if not isinstance(batch_size, int) or batch_size < 1:
        raise InputError(f"batch_size must be ≥ 1, got {batch_size!r}; pass e.g. --batch-size 4")
    dev = _device(device)
    precision = resolve_precision(precision, dev)
    out_dir = Path(out_dir)
    check_outputs_free(out_dir, ["height.tif", "classes.tif", "prediction.json"], overwrite)  # fail early
    model, meta, ckpt_name = _load(checkpoint)
    ckpt_name = checkpoint_name or ckpt_name
    if mc is None:
        mc = DEFAULT_MC_SAMPLES if meta.model.dropout > 0 else 1
    model = model.to(dev).to(memory_format=torch.channels_last)
    tasks = tuple(meta.model.tasks)

    native = reference_grid(ortho)
    resample = abs(native.gsd - meta.gsd) > GSD_TOLERANCE * meta.gsd
    if resample:
        warnings.warn(
            f"orthophoto '{ortho}' has a GSD of {native.gsd:.4g} m but the model was trained at {meta.gsd:.4g} m; "
            f"resampling the orthophoto to {meta.gsd:.4g} m (outputs are on the {meta.gsd:.4g} m grid)",
            stacklevel=2,
        )
    grid = reference_grid(ortho, gsd=meta.gsd) if resample else native
    plan = plan_bands(grid.height, grid.width, tile, overlap)
    k = meta.classes.num_classes if meta.classes is not None and "classes" in tasks else 0
    channels: dict[str, int] = {}
    if "height" in tasks:
        channels["height"] = 1
        if mc > 1:
            channels["height_std"] = 1
    if "classes" in tasks:
        channels["probs"] = k
        if mc > 1:
            channels["expected_entropy"] = 1
    specs = _layer_specs(meta, mc, probabilities)
    stitcher = BandStitcher(plan, channels, tuple(s.name for s in specs))
    mean = np.asarray(meta.mean, np.float32)[:, None, None]
    std = np.asarray(meta.std, np.float32)[:, None, None]
    timings = {"read": 0.0, "model": 0.0, "stitch_write": 0.0}
    computed = 0

    env = rasterio.Env(GDAL_CACHEMAX=128)  # MB: bounded block cache, whatever the raster size
    with env, AlignedRaster(ortho, grid, "image", bands=list(meta.bands), role="orthophoto") as src:
        unused = [b for b in range(1, src.src.count + 1) if b not in meta.bands and b != src.alpha_band]
        if unused:
            trained = f"bands {list(meta.bands)}" + (f" ({', '.join(meta.band_names)})" if meta.band_names else "")
            warnings.warn(f"orthophoto '{ortho}' has {src.src.count} bands; the model reads {trained} as recorded "
                          f"in its checkpoint and ignores band(s) {unused}", stacklevel=2)
        aoi_mask = _Aoi(aoi, grid) if aoi is not None else None
        writer = PredictionWriter(out_dir, grid, specs, overwrite=overwrite)
        bar = tqdm(total=plan.num_windows, unit="win", desc=Path(ortho).name, disable=not progress,
                   dynamic_ncols=True)
        try:
            for band in plan.bands:
                stitcher.start_band(band.index)

                def windows() -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
                    nonlocal computed
                    for j, win in enumerate(band.windows):
                        t0 = time.perf_counter()
                        data, valid = src.read(win)
                        if aoi_mask is not None:
                            valid &= aoi_mask.mask(win)
                        timings["read"] += time.perf_counter() - t0
                        if not valid.any():
                            bar.update(1)
                            continue
                        x = (data.astype(np.float32) - mean) / std
                        x[:, ~valid] = 0.0
                        computed += 1
                        yield j, x, valid

                for batch in _batches(windows(), batch_size):
                    t0 = time.perf_counter()
                    xb = torch.from_numpy(np.stack([b[1] for b in batch])).to(dev)
                    xb = xb.contiguous(memory_format=torch.channels_last)
                    res = _run_model(model, xb, mc, tasks, precision, max_decode_pixels)
                    t1 = time.perf_counter()
                    timings["model"] += t1 - t0
                    for n, (j, _, valid) in enumerate(batch):
                        stitcher.add(j, {key: v[n] for key, v in res.items()}, valid)
                    timings["stitch_write"] += time.perf_counter() - t1
                    bar.update(len(batch))
                t0 = time.perf_counter()
                writer.write(stitcher.flush())
                timings["stitch_write"] += time.perf_counter() - t0
            bar.close()
            t0 = time.perf_counter()
            out_px = grid.width * grid.height
            factor = computed * plan.rows.size * plan.cols.size / out_px
            total_so_far = time.perf_counter() - t_start
            info = {
                "aerialmtl_version": __version__,
                "orthophoto": str(ortho),
                "checkpoint": ckpt_name,
                "mc_samples": mc,
                "tile": tile,
                "overlap": overlap,
                "window_size": [plan.rows.size, plan.cols.size],
                "batch_size": batch_size,
                "precision": precision,
                "device": str(dev),
                "aoi": None if aoi is None else str(aoi),
                "grid": {"crs": grid.crs.to_string(), "transform": list(grid.transform)[:6],
                         "width": grid.width, "height": grid.height, "gsd": grid.gsd},
                "resampled_from_gsd": native.gsd if resample else None,
                "windows_total": plan.num_windows,
                "windows_computed": computed,
                "overlap_factor": factor,
                "plan_overlap_factor": plan.overlap_factor,
                "timings_s": {**timings, "before_cog": total_so_far},
            }
            files = writer.commit(info)
            timings["cog"] = time.perf_counter() - t0
        except BaseException:
            bar.close()
            writer.abort()
            raise
    timings["total"] = time.perf_counter() - t_start
    _record_timings(files["prediction"], timings)
    return PredictResult(out_dir, files, grid, mc, plan.num_windows, computed, factor, plan.overlap_factor,
                         out_px / 1e6 / max(timings["total"], 1e-9), timings)


__all__ = ["DEFAULT_MC_SAMPLES", "PredictResult", "predict_raster"]
