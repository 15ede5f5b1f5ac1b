"""Predict's sanity checks: inputs like the training data's, and model outputs that are numbers.

**Input data type and value range.** A checkpoint records the data type of its training images
(``ModelMeta.input_dtype``) and their value range (``ModelMeta.input_range``): the envelope
``[min_b(mean_b − 3·std_b), max_b(mean_b + 3·std_b)]`` over the bands b of the train split's
statistics, clipped to what the data type can hold (:func:`~aerialmtl.formats.checkpoint.value_envelope`).
Before predicting, the same envelope is computed from a sample of the orthophoto (:func:`sample_input`:
16 windows of 128 × 128 pixels spread over the raster, valid pixels only, so the cost does not grow with
the raster) and compared (:func:`input_mismatch`): the orthophoto does not match when its envelope is
more than :data:`SPREAD_LIMIT` times wider or narrower than the training one (16-bit values on an 8-bit
model, reflectances 0..1 on a model trained on 0..255) or its centre lies more than one training width
away.

A mismatch is refused (:class:`~aerialmtl.errors.InputError` naming both data types and ranges), unless
``rescale_input`` is given: then every value x of every band becomes ``a·x + b``, the one linear map that
sends the orthophoto's envelope onto the training envelope (one map for all bands keeps their balance; it
is computed once per orthophoto, so every window sees the same map). An orthophoto of another data type
whose values lie in the training range (an 8-bit image stored as float32) is predicted as it is, with a
warning. Checkpoints written before these fields existed are not checked (predict is unchanged for them).

**Outputs.** :func:`check_finite_outputs` refuses NaN or ±inf heights or class probabilities at pixels
whose input was valid (a diverged model): predict fails, leaving no prediction folder that looks complete.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from rasterio.errors import RasterioError
from rasterio.io import DatasetReader
from rasterio.windows import Window

from aerialmtl.errors import CheckpointError, InputError, NonFiniteError
from aerialmtl.formats.checkpoint import ModelMeta, plausible_heights, value_envelope
from aerialmtl.io.align import open_raster
from aerialmtl.io.raster_errors import read_error
from aerialmtl.models.mc_dropout import McStatistics

#: windows per side and their side (pixels) of the orthophoto sample.
SAMPLE_GRID, SAMPLE_SIDE = 4, 128
#: an envelope this many times wider or narrower than the training one is a mismatch.
SPREAD_LIMIT = 8.0


def _fmt(v: float) -> str:
    return f"{v:.4g}"


@dataclass(frozen=True)
class InputSample:
    """What a sample of an orthophoto says about its values.

    Attributes:
        dtype: its data type.
        mean, std: per band over the sampled valid pixels (raw units).
        pixels: valid pixels sampled.
    """

    dtype: str
    mean: tuple[float, ...]
    std: tuple[float, ...]
    pixels: int

    @property
    def envelope(self) -> tuple[float, float]:
        """The (low, high) raw values the training images' bands spanned (mean ± 3 std)."""
        return value_envelope(self.mean, self.std, self.dtype)


def sample_input(source: str | Path | DatasetReader, bands: Sequence[int]) -> InputSample | None:
    """Per-band statistics of ``bands`` over a spread of windows of ``source`` (``None`` without valid pixels).

    Reads :data:`SAMPLE_GRID` × :data:`SAMPLE_GRID` windows of :data:`SAMPLE_SIDE` pixels (fewer on a small
    raster); a pixel is valid where every band's mask (nodata, alpha, internal mask) says so and the values
    are finite.

    Args:
        source: the orthophoto's path, or its dataset already open (prediction reads the header and this
            sample in one opening: :meth:`~aerialmtl.inference.ortho.OrthoInput.open`).
        bands: 1-based bands.
    """
    if not isinstance(source, DatasetReader):
        with open_raster(source, "orthophoto") as src:
            return sample_input(src, bands)
    src = source
    dtype = str(src.dtypes[bands[0] - 1])
    w, h = min(SAMPLE_SIDE, src.width), min(SAMPLE_SIDE, src.height)
    cols = sorted({round(k * (src.width - w) / max(1, SAMPLE_GRID - 1)) for k in range(SAMPLE_GRID)})
    rows = sorted({round(k * (src.height - h) / max(1, SAMPLE_GRID - 1)) for k in range(SAMPLE_GRID)})
    values = []
    for r in rows:
        for c in cols:
            win = Window(c, r, w, h)
            try:
                data = src.read(list(bands), window=win)
                ok = np.all(src.read_masks(list(bands), window=win) > 0, axis=0)
            except RasterioError as exc:  # a server that died after the header, a truncated file
                raise read_error("orthophoto", src.name, exc) from exc
            if data.dtype.kind == "f":
                ok &= np.all(np.isfinite(data), axis=0)
            values.append(data[:, ok].astype(np.float64))
    x = np.concatenate(values, axis=1)
    if x.shape[1] == 0:
        return None
    return InputSample(dtype, tuple(x.mean(axis=1).tolist()), tuple(x.std(axis=1).tolist()), int(x.shape[1]))


def input_mismatch(meta: ModelMeta, sample: InputSample) -> str | None:
    """How ``sample``'s value range differs from the training data's, or ``None`` when it fits.

    Data types are not compared here (see :func:`check_input_values`).
    """
    if meta.input_range is None:
        return None
    lo, hi = meta.input_range
    ilo, ihi = sample.envelope
    width, iwidth = hi - lo, ihi - ilo
    if width <= 0:
        return None
    if iwidth > 0 and not (width / SPREAD_LIMIT <= iwidth <= width * SPREAD_LIMIT):
        return f"its values spread over {iwidth / width:.3g} times the training range"
    if abs((ilo + ihi) / 2 - (lo + hi) / 2) > width:
        return "its values are centred far outside the training range"
    return None


def _described(dtype: str | None, rng: tuple[float, float]) -> str:
    return f"{dtype or 'unknown type'} values about {_fmt(rng[0])}..{_fmt(rng[1])}"


def check_input_values(path: str | Path, meta: ModelMeta, rescale: bool = False,
                       dataset: DatasetReader | None = None) -> tuple[float, float] | None:
    """Refuse (or, with ``rescale``, map) an orthophoto whose values do not look like the training data's.

    Args:
        path: the orthophoto (named in the messages).
        meta: the checkpoint metadata (``input_dtype``, ``input_range``, ``bands``).
        rescale: map a mismatching orthophoto onto the training range instead of refusing it.
        dataset: ``path`` already open (its sample is read from it; default: opened here).

    Returns:
        ``(a, b)``: predict with ``a·x + b`` instead of the raw values x; ``None``: use them as they are.

    Raises:
        InputError: the value range does not match and ``rescale`` is false (names both data types and
            ranges, and ‹rescale_input=True›).
    """
    if meta.input_dtype is None or meta.input_range is None:  # written before these were recorded
        return None
    sample = sample_input(path if dataset is None else dataset, meta.bands)
    if sample is None:  # nothing valid to judge by (and nothing to predict)
        return None
    problem = input_mismatch(meta, sample)
    trained, given = _described(meta.input_dtype, meta.input_range), _described(sample.dtype, sample.envelope)
    if problem is None:
        if sample.dtype != meta.input_dtype:
            warnings.warn(f"orthophoto '{path}' holds {sample.dtype} values but the model was trained on "
                          f"{meta.input_dtype}; its values lie in the training range ({given}; trained on "
                          f"{trained}), so it is predicted as it is", stacklevel=3)
        return None
    if not rescale:
        raise InputError(
            f"orthophoto '{path}' holds {given} (mean ± 3 std of a sample of its bands {list(meta.bands)}), but the "
            f"model was trained on {trained}: {problem}, so its heights and classes would be garbage; pass an "
            f"orthophoto like the training data (e.g. `gdal_translate -ot {meta.input_dtype} -scale ...`), or "
            "‹rescale_input=True› to map its values linearly onto the training range"
        )
    (lo, hi), (ilo, ihi) = meta.input_range, sample.envelope
    a = (hi - lo) / (ihi - ilo) if ihi > ilo else 1.0
    b = lo - a * ilo if ihi > ilo else (lo + hi) / 2 - ilo
    warnings.warn(f"orthophoto '{path}': rescaling its values linearly (x · {a:.6g} + {b:.6g}) from {given} onto "
                  f"the training range ({trained}) as ‹rescale_input=True› asks", stacklevel=3)
    return float(a), float(b)


def _all_finite(stats: McStatistics) -> bool:
    """Whether every height and probability is finite, from a min/max reduction of each tensor.

    On the CPU the reductions run in numpy (one thread, no parallel region to wake up: about 2 ms for a
    1024² window with 6 classes, experiments/sanity_cost/run.py); on a GPU in torch with one sync.
    """
    heights, probs = stats.height_mean, stats.probs
    tensors = [t for t in (heights, probs) if t is not None and t.numel()]
    if all(t.device.type == "cpu" and t.dtype in (torch.float32, torch.float64) for t in tensors):
        ends = []
        if heights is not None and heights.numel():
            h = heights.detach().numpy()
            ends += [h.min(), h.max()]
        if probs is not None and probs.numel():  # probabilities are never -inf: the max alone finds NaN/+inf
            ends.append(probs.detach().numpy().max())
        return bool(np.isfinite(ends).all())
    parts = [v for t in tensors for v in torch.aminmax(t.float())]
    return not parts or bool(torch.isfinite(torch.stack(parts)).all())


def check_finite_outputs(stats: McStatistics, valid: torch.Tensor, checkpoint: str) -> None:
    """Refuse NaN or ±inf heights or class probabilities at valid input pixels.

    Cheap on every call: the min and max of the heights and probabilities (NaN propagates through
    both, :func:`_all_finite`); only when one of them is not finite are the pixels compared with ``valid``.

    Args:
        stats: the model's statistics of a batch of windows (B×H×W heights, B×H×W×K probabilities).
        valid: B×H×W bool, the valid input pixels.
        checkpoint: the checkpoint's name, for the message.

    Raises:
        NonFiniteError: naming the checkpoint and what to do.
    """
    if _all_finite(stats):
        return
    bad = torch.zeros((), dtype=torch.bool, device=valid.device)
    for t in (stats.height_mean, stats.probs):
        if t is None:
            continue
        summed = t.sum(dim=-1) if t.dim() == valid.dim() + 1 else t  # NaN/inf survive the sum over K
        bad = bad | (~torch.isfinite(summed) & valid).any()
    if bool(bad):
        raise NonFiniteError(
            f"the model of checkpoint '{checkpoint}' gives NaN or inf for valid orthophoto pixels, so no prediction "
            "was written: its weights or normalisation are broken (a diverged training?); use another checkpoint "
            "(an earlier best.pt / last.pt) or retrain with a lower optim.lr"
        )


def check_height_range(stats: McStatistics, valid: torch.Tensor, checkpoint: str, meta: ModelMeta) -> None:
    """Refuse heights far outside what the checkpoint was trained on (:func:`~aerialmtl.formats.checkpoint.
    plausible_heights` of :attr:`~aerialmtl.formats.checkpoint.ModelMeta.height_range`) at valid pixels: a
    diverged-but-finite model's maps (heights of 1e15 m) are never written.

    Args:
        stats: the model's statistics of a batch of windows (B×H×W heights, metres, before calibration).
        valid: B×H×W bool, the valid input pixels.
        checkpoint: the checkpoint's name, for the message.
        meta: its metadata.

    Raises:
        NonFiniteError: naming the checkpoint, the heights found and allowed, and what to do.
    """
    h = stats.height_mean
    if h is None:
        return
    low, high = plausible_heights(meta.height_range)
    inside = valid.to(h.device)
    if not bool(inside.any()):
        return
    values = h if bool(inside.all()) else h[inside]  # a window inside the raster: no copy of its heights
    ends = torch.aminmax(values)  # one pass
    lo, hi = float(ends.min), float(ends.max)
    if low <= lo and hi <= high:
        return
    trained = (f"the {meta.height_range[0]:.4g}..{meta.height_range[1]:.4g} m it was trained on"
               if meta.height_range is not None else "the heights any surface has")
    raise NonFiniteError(
        f"the model of checkpoint '{checkpoint}' gives heights of {lo:.3g}..{hi:.3g} m, far outside {trained} "
        f"(allowed {low:.4g}..{high:.4g} m), so no prediction was written: the training that wrote it diverged; use "
        "another checkpoint (an earlier best.pt / last.pt) or retrain with a lower optim.lr")


def check_calibration(meta: ModelMeta, checkpoint: str) -> None:
    """Refuse a checkpoint calibration (:attr:`ModelMeta.calibration`) no fit writes: a height map with
    non-finite knots, one that decreases (taller predictions would come out lower), or one that sends every
    height below 0 m, or far outside the heights the model was trained on (an edited or damaged
    checkpoint; applying it silently would give wrong maps that look complete).

    Raises:
        CheckpointError: naming the checkpoint, what is wrong, and the fix (``--no-calibration``).
    """
    cal = meta.calibration
    if cal is None or not cal.height_applied:  # a height map that is not applied changes no height
        return
    x, y = np.asarray(cal.height_x, np.float64), np.asarray(cal.height_y, np.float64)
    problem = None
    if not (np.isfinite(x).all() and np.isfinite(y).all()):
        problem = "its height map has non-finite knots"
    elif (np.diff(y) < 0).any():
        k = int(np.argmax(np.diff(y) < 0))
        problem = (f"its height map decreases ({x[k]:.4g} m → {y[k]:.4g} m but {x[k + 1]:.4g} m → {y[k + 1]:.4g} m), "
                   "so taller predictions would come out lower")
    elif y.max() < 0:  # (all 0 m is what a fit on a flat validation area gives: allowed)
        problem = f"its height map sends every height below 0 m (to {y.max():.4g} m at most: every map would be flat)"
    else:
        low, high = plausible_heights(meta.height_range)
        if y.min() < low or y.max() > high:
            problem = (f"its height map reaches {y.min():.4g}..{y.max():.4g} m, far outside {low:.4g}..{high:.4g} m "
                       "for the heights the model was trained on")
    if problem is not None:
        raise CheckpointError(
            f"checkpoint '{checkpoint}' has an invalid calibration: {problem}; no fit writes one (the file was edited "
            "or damaged): predict without it (--no-calibration, or calibration=False in Python), or use the best.pt / "
            "last.pt as `aerialmtl train` wrote it")


def normalised(raw: torch.Tensor, valid: torch.Tensor, mean: torch.Tensor, std: torch.Tensor) -> torch.Tensor:
    """(B, C, h, w) raw → the model's input: float32 ``(x − mean) / std`` (``mean``, ``std``: (C, 1, 1), the
    checkpoint's), 0 where ``valid`` (B, h, w) is False, channels-last.
    """
    x = (raw.float() - mean) / std
    x = torch.where(valid.unsqueeze(1), x, torch.zeros((), device=x.device))
    return x.contiguous(memory_format=torch.channels_last)


def rescaled(raw: torch.Tensor, rescale: tuple[float, float] | None) -> torch.Tensor:
    """``raw`` (B, C, h, w) as ``a·raw + b`` in float32 when ``rescale`` is ``(a, b)``, else unchanged."""
    if rescale is None:
        return raw
    a, b = rescale
    return raw.float() * a + b if math.isfinite(a) and math.isfinite(b) else raw


__all__ = ["InputSample", "SAMPLE_GRID", "SAMPLE_SIDE", "SPREAD_LIMIT", "check_calibration", "check_finite_outputs",
           "check_height_range", "check_input_values", "input_mismatch", "normalised", "rescaled", "sample_input",
           "value_envelope"]
