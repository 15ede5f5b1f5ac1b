"""A training batch assembled on the CPU in one compiled pass per pixel: :func:`assemble_batch`.

On a GPU the compact patches go to the device and torch finishes them there (:func:`aerialmtl.data.batches.
prepare_batch`). On a CPU the same finishing in torch is a chain of passes over every pixel (a copy to cut the
crop, one per flip/rotation, a widening to float32, the normalisation, the mask, the heights' validity, the
classes widened to int64, a copy into ``channels_last``), each allocating a new batch-sized tensor: ~80 ms per batch
of 32 × 320² on one core, plus the gather's own copy out of the cache, on the same cores as the step.

:func:`kernel` does all of it in one pass, reading each output pixel's source straight from the memory-mapped
patch cache (or from patches already gathered) and writing the finished tensors, in the layout the model takes,
into buffers that can be reused from batch to batch. It applies exactly the arithmetic torch applies —
``(float32(raw) − mean) / std``, 0 where the image is invalid; heights 0 where not finite with their validity;
classes widened — so the batch is the same to the bit (tests/test_assemble.py). The photometric jitter (a
``value``-stage transform, off by default) stays in torch, after this pass.

The kernel is compiled by numba the first time after an install (about 1 s per image dtype) and kept in the
package's ``numba`` store (:mod:`aerialmtl.jit`); importing this module imports numba.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch

from aerialmtl.data.transforms import Move
from aerialmtl.jit import jit

_F = np.float32


@jit
def _normalised(run: Any, ok: Any, m: Any, sd: Any, back: bool, line: Any) -> None:  # pragma: no cover - compiled
    """``line[t] = (float32(run[s]) − m) / sd``, 0 where ``ok[s]`` is 0, with s = t (or n − 1 − t if ``back``)."""
    n, zero = run.shape[0], _F(0.0)
    if back:
        for t in range(n):
            q = np.uint64(n - 1 - t)  # unsigned: no negative-index test, so the loop vectorises
            line[t] = (_F(run[q]) - m) / sd if ok[q] != 0 else zero
    else:
        for t in range(n):
            line[t] = (_F(run[t]) - m) / sd if ok[t] != 0 else zero


@jit
def _references(hrun: Any, crun: Any, back: bool, oh: Any, ov: Any, oc: Any, with_height: bool,
                with_classes: bool) -> None:  # pragma: no cover - compiled
    """Heights (0 where not finite) with their validity, and classes widened, of one run, reversed if ``back``."""
    n, zero = hrun.shape[0] if with_height else crun.shape[0], _F(0.0)
    if with_height:
        for t in range(n):
            x = hrun[np.uint64(n - 1 - t) if back else np.uint64(t)]
            ov[t] = np.isfinite(x)
            oh[t] = x if np.isfinite(x) else zero
    if with_classes:
        for t in range(n):
            oc[t] = crun[np.uint64(n - 1 - t) if back else np.uint64(t)]


@jit
def kernel(image: Any, valid: Any, height: Any, classes: Any, index: Any, rows: Any, cols: Any, moves: Any,
           mean: Any, std: Any, out_image: Any, strides: Any, out_height: Any, out_valid: Any, out_classes: Any,
           h_out: int, w_out: int, with_height: bool, with_classes: bool) -> None:  # pragma: no cover - compiled
    """Finish a batch from source patches in one pass per output pixel.

    Args:
        image: (N, C, H, W) source patches in their stored dtype, C-contiguous (the cache's memory map, or a
            gathered batch).
        valid: (N, H, W) uint8 image validity.
        height: (N, 1, H, W) float32 metres, NaN where unknown (any (1, 1, 1, 1) array when ``with_height`` is
            false).
        classes: (N, H, W) uint8 class indices (any (1, 1, 1) array when ``with_classes`` is false).
        index: (B,) int64 source patch of each sample.
        rows, cols: (B,) int64 top-left corner of each sample's window in its source patch.
        moves: (B, 3) bool per sample: transpose, then flip rows, flip columns (:data:`~aerialmtl.data.transforms.
            Move`); the window is (h_out, w_out) after the move, i.e. (w_out, h_out) before it when transposed.
        mean, std: (C,) float32 normalisation.
        out_image: the (B, C, h_out, w_out) float32 output's memory, flat; ``strides`` (4,) int64 its element
            strides (``channels_last`` or contiguous).
        out_height: (B · h_out · w_out,) float32; out_valid: the same, bool; out_classes: the same, int64.
        h_out, w_out: the output's side.
        with_height, with_classes: whether those layers are written.
    """
    n_src, n_bands, h_src, w_src = image.shape
    plane = h_src * w_src
    img = image.reshape(n_src * n_bands * plane)
    val = valid.reshape(valid.size)
    hgt = height.reshape(height.size)
    cls = classes.reshape(classes.size)
    s_b, s_k, s_i, s_j = strides[0], strides[1], strides[2], strides[3]
    n = w_out
    line = np.empty(n, np.float32)
    # a transposed sample's source column, gathered into contiguous runs
    col_img = np.empty((n_bands, n), image.dtype)
    col_val = np.empty(n, valid.dtype)
    col_h = np.empty(n, height.dtype)
    col_c = np.empty(n, classes.dtype)
    for b in range(index.shape[0]):
        p, r0, c0 = index[b], rows[b], cols[b]
        transpose, flip_r, flip_c = moves[b, 0], moves[b, 1], moves[b, 2]
        for i in range(h_out):
            # Output row i, read from one run of its source (element t, or n − 1 − t when the columns flip):
            # a row (r0 + i', c0 … c0 + n), or, transposed, a column (r0 … r0 + n, c0 + i'), i' = i flipped.
            ii = h_out - 1 - i if flip_r else i
            dst = b * s_b + i * s_i
            ref = (b * h_out + i) * w_out
            oh, ov = out_height[ref:ref + n], out_valid[ref:ref + n]
            oc = out_classes[ref:ref + n]
            if transpose:
                at = p * plane + r0 * w_src + c0 + ii
                for t in range(n):
                    q = at + t * w_src
                    col_val[t] = val[q]
                    if with_height:
                        col_h[t] = hgt[q]
                    if with_classes:
                        col_c[t] = cls[q]
                    for k in range(n_bands):
                        col_img[k, t] = img[q + (p * (n_bands - 1) + k) * plane]
                for k in range(n_bands):
                    _normalised(col_img[k], col_val, mean[k], std[k], flip_c, line)
                    _store(line, out_image, dst + k * s_k, s_j)
                _references(col_h, col_c, flip_c, oh, ov, oc, with_height, with_classes)
            else:
                start = p * plane + (r0 + ii) * w_src + c0
                ok = val[start:start + n]
                for k in range(n_bands):
                    first = start + (p * (n_bands - 1) + k) * plane
                    _normalised(img[first:first + n], ok, mean[k], std[k], flip_c, line)
                    _store(line, out_image, dst + k * s_k, s_j)
                _references(hgt[start:start + n] if with_height else col_h, cls[start:start + n] if with_classes
                            else col_c, flip_c, oh, ov, oc, with_height, with_classes)


@jit
def _store(line: Any, out: Any, dst: int, step: int) -> None:  # pragma: no cover - compiled
    """``out[dst + t · step] = line[t]``."""
    n = line.shape[0]
    if step == 1:
        out[dst:dst + n] = line
    else:
        for t in range(n):
            out[np.uint64(dst) + np.uint64(t) * np.uint64(step)] = line[t]


def move_table(moves: Sequence[Move]) -> np.ndarray:
    """(B, 3) bool rows ``(transpose, flip rows, flip columns)`` of the samples' :data:`Move` s."""
    return np.array([(t, -2 in f, -1 in f) for t, f in moves], dtype=np.bool_).reshape(len(moves), 3)


def empty_batch(batch: int, bands: int, side: tuple[int, int], layers: Sequence[str],
                channels_last: bool = True) -> dict[str, torch.Tensor]:
    """Buffers for :func:`assemble_batch` (reused from batch to batch by a loader).

    Args:
        batch: samples B; bands: C; side: (h, w) after the moves.
        layers: the reference layers (``height``, ``classes``) to hold.
        channels_last: the image's memory layout (the model's); ``False``: contiguous, for a torch transform
            that follows (the jitter reduces over the contiguous layout, as the GPU path does).

    Returns:
        ``image`` float32 (B, C, h, w), ``height`` float32 and ``height_valid`` bool (B, 1, h, w), ``classes``
        int64 (B, h, w), for the layers asked.
    """
    fmt = torch.channels_last if channels_last else torch.contiguous_format
    out = {"image": torch.empty((batch, bands, *side), dtype=torch.float32, memory_format=fmt)}
    if "height" in layers:
        out["height"] = torch.empty((batch, 1, *side), dtype=torch.float32)
        out["height_valid"] = torch.empty((batch, 1, *side), dtype=torch.bool)
    if "classes" in layers:
        out["classes"] = torch.empty((batch, *side), dtype=torch.int64)
    return out


def assemble_batch(source: Mapping[str, np.ndarray], index: Sequence[int] | np.ndarray,
                   rows: Sequence[int] | np.ndarray, cols: Sequence[int] | np.ndarray, moves: Sequence[Move],
                   mean: np.ndarray, std: np.ndarray, out: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Write the finished batch of samples ``index`` into ``out`` (from :func:`empty_batch`) and return it.

    Args:
        source: ``image`` (N, C, H, W) in the stored dtype, ``image_valid`` (N, H, W) uint8, and the reference
            layers ``height`` (N, 1, H, W) float32 / ``classes`` (N, H, W) uint8 that ``out`` holds: the
            cache's memory maps (:meth:`~aerialmtl.data.cache.PatchCache.arrays`) or a gathered batch.
        index: (B,) source patch per sample; rows, cols: (B,) top-left of its window (0 for whole patches).
        moves: per sample, its flips and quarter turns as one :data:`Move`.
        mean, std: (C,) float32 normalisation.
        out: the buffers (their shapes say the window's size after the moves).

    Returns:
        ``out``, filled: ``image`` ``(raw − mean) / std`` (0 where invalid), ``height`` (0 where unknown) with
        ``height_valid``, ``classes`` int64 — equal to the bit to the torch path's batch.
    """
    b = len(index)
    img = out["image"]
    if img.shape[0] != b or len(moves) != b:
        raise ValueError(f"assemble_batch: {b} samples, {len(moves)} moves and buffers for {img.shape[0]}")
    idx, r, c = np.asarray(index, np.int64), np.asarray(rows, np.int64), np.asarray(cols, np.int64)
    n_src, bands, h_src, w_src = source["image"].shape
    _, out_bands, h_out, w_out = img.shape
    turned = np.array([m[0] for m in moves], dtype=np.bool_)
    h_win, w_win = np.where(turned, w_out, h_out), np.where(turned, h_out, w_out)  # each window before its move
    if out_bands != bands or len(mean) != bands or len(std) != bands:
        raise ValueError(f"assemble_batch: {bands} source bands, {out_bands} in the buffers, {len(mean)} means and "
                         f"{len(std)} standard deviations")
    if b and (idx.min() < 0 or idx.max() >= n_src or r.min() < 0 or c.min() < 0 or (r + h_win).max() > h_src
              or (c + w_win).max() > w_src):
        raise IndexError(f"assemble_batch: patches {idx.tolist()} at rows {r.tolist()}, cols {c.tolist()} with "
                         f"{h_out} × {w_out} windows (turned where transposed) do not all lie in the {n_src} source "
                         f"patches of {h_src} × {w_src}")
    dummy_h = np.zeros((1, 1, 1, 1), np.float32)
    dummy_c = np.zeros((1, 1, 1), np.uint8)
    with_h, with_c = "height" in out, "classes" in out

    def flat(t: torch.Tensor) -> np.ndarray:
        """The memory of a dense tensor (contiguous or channels_last) as one flat array."""
        return t.as_strided((t.numel(),), (1,)).numpy()

    kernel(np.ascontiguousarray(source["image"]), np.ascontiguousarray(source["image_valid"]),
           np.ascontiguousarray(source["height"]) if with_h else dummy_h,
           np.ascontiguousarray(source["classes"]) if with_c else dummy_c,
           idx, r, c, move_table(moves),
           np.ascontiguousarray(mean, np.float32), np.ascontiguousarray(std, np.float32), flat(img),
           np.array(img.stride(), np.int64), flat(out["height"]) if with_h else dummy_h.ravel(),
           flat(out["height_valid"]) if with_h else dummy_h.ravel().astype(np.bool_),
           flat(out["classes"]) if with_c else dummy_c.ravel().astype(np.int64), h_out, w_out, with_h, with_c)
    return out


__all__ = ["assemble_batch", "empty_batch", "kernel", "move_table"]
