"""The shadow step's compiled kernels (numba, :func:`aerialmtl.jit.jit`; imported only when a run needs them).

Inside ``predict`` the shadow layers are computed for every window the model computes, on the CPU threads the
model also uses: in numpy their per-pixel arithmetic (a dozen passes over every pixel for the classifier's
features) and their per-step walks (a hundred and fifty passes over a shrinking index array for the shadow runs)
cost a fifth of the small-area recipe's model stage. Each kernel here does the same work in one pass:

* :func:`logistic_rows` — the shadow classifier's features and logistic per pixel (:mod:`aerialmtl.sun.colour`);
* :func:`max_filter_reflect` — the maximum over a square window (``scipy.ndimage.maximum_filter`` with
  ``mode="reflect"``; the maximum is exact, so the result is the same to the bit);
* :func:`edge_pixels`, :func:`run_lengths` and :func:`occluder_offsets` — the edges and the walks of
  :func:`aerialmtl.sun.shadow_heights` (integers: the same to the bit as the numpy walks they replace,
  tests/test_sun_kernels.py);
* :func:`sweep_surface` — the shadow surface of :func:`aerialmtl.sun.cast.shadow_surface_sweep`, which the sun
  fit after training casts ~740 times (every sun of its grid) over the whole training area: a numpy pass per
  column of the raster, between two transposed copies, held the GIL and took 7.5 ms per sun on 1024² (7 s of a
  fit); one pass here in the raster's own layout (the same float32 maxima and differences, the same surface to
  the bit);
* :func:`shadow_sums` — the fit's score of one sun from that surface: how many ground pixels it shades and the sum
  of their shadow scores, in one pass instead of the mask's six numpy passes and a boolean gather (three quarters
  of a sun's time after the sweep was compiled).

Every kernel releases the GIL (``nogil``), so bands of rows run on threads. numba compiles them the first time
after an install (about 2 s together) and keeps their machine code in the package's ``numba`` store.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from aerialmtl.jit import jit

_F = np.float32


@jit
def logistic_rows(x: Any, lum: Any, l0: Any, l1: Any, l2: Any, l3: Any, l4: Any, l5: Any, a: Any, bias: Any,
                  eps: Any, r0: int, r1: int, out: Any) -> None:  # pragma: no cover - runs compiled
    """Rows ``r0:r1`` of ``out`` (H, W) float32 = ``1 / (1 + exp(−clip(bias + a · f, ±40)))`` with ``f`` the 12
    features of :func:`aerialmtl.sun.colour.colour_features` per pixel: unit RGB ``x`` (3, H, W) float32, its
    log-brightness ``lum`` (H, W) and the six neighbourhood filters of it ``l0`` … ``l5`` (H, W) in
    :data:`aerialmtl.sun.colour._CONTEXTS` order; ``a`` (12,) float32 standardised weights, ``bias`` float32,
    ``eps`` the chromaticity's float32 guard. float32 arithmetic throughout (within 2e-7 of the numpy planes).
    """
    third = _F(1.0 / 3.0)
    c02 = _F(0.02)
    one = _F(1.0)
    lo, hi = _F(-40.0), _F(40.0)
    width = lum.shape[1]
    for y in range(r0, r1):
        for i in range(width):
            red, green, blue = x[0, y, i], x[1, y, i], x[2, y, i]
            lv = lum[y, i]
            total = (red + green) + blue + eps
            cb = blue / total - third
            cr = red / total - third
            top = max(max(red, green), blue)
            sat = (top - min(min(red, green), blue)) / (top + c02)
            z = bias + a[0] * lv
            z += a[1] * cb
            z += a[2] * cr
            z += a[3] * sat
            z += a[4] * (lv * lv)
            z += a[5] * (lv * cb)
            z += a[6] * (lv - l0[y, i])
            z += a[7] * (lv - l1[y, i])
            z += a[8] * (lv - l2[y, i])
            z += a[9] * (lv - l3[y, i])
            z += a[10] * (lv - l4[y, i])
            z += a[11] * (lv - l5[y, i])
            z = min(max(z, lo), hi)
            out[y, i] = one / (one + np.exp(-z))


@jit
def _reflect(i: int, n: int) -> int:  # pragma: no cover - runs compiled
    """The index of scipy's ``mode="reflect"`` (``d c b a | a b c d | d c b a``) of position ``i`` in ``0..n-1``."""
    period = 2 * n
    i = i % period
    return i if i < n else period - 1 - i


@jit
def max_filter_reflect(img: Any, size: int, tmp: Any, out: Any) -> None:  # pragma: no cover - runs compiled
    """``out`` (H, W) = the maximum of ``img`` (H, W) over the ``size`` × ``size`` window centred on each pixel
    (``size`` odd), edges by reflection: ``scipy.ndimage.maximum_filter(img, size, mode="reflect")`` to the bit
    (NaN-free input). ``tmp`` (H, W) scratch of ``img``'s dtype.
    """
    h, w = img.shape
    r = size // 2
    pad = np.empty(w + 2 * r, img.dtype)
    for y in range(h):  # along rows: the window's columns, from the row padded by reflection
        for i in range(-r, w + r):
            pad[i + r] = img[y, _reflect(i, w)]
        for i in range(w):
            tmp[y, i] = pad[i]
        for d in range(1, 2 * r + 1):
            for i in range(w):
                v = pad[i + d]
                if v > tmp[y, i]:
                    tmp[y, i] = v
    for y in range(h):  # along columns: the window's rows
        for i in range(w):
            out[y, i] = tmp[y, i]
        for d in range(1, r + 1):
            up = _reflect(y - d, h)
            down = _reflect(y + d, h)
            for i in range(w):
                v = tmp[up, i] if tmp[up, i] > tmp[down, i] else tmp[down, i]
                if v > out[y, i]:
                    out[y, i] = v


@jit
def edge_pixels(objects: Any, dr: int, dc: int) -> Any:  # pragma: no cover - runs compiled
    """``(r, c)`` int64 (n,) each, in row-major order: the object pixels (``objects`` int (H, W), 0 = none) whose
    neighbour at ``(+dr, +dc)`` is outside the raster or not of their object (their shadow-casting edge).
    """
    h, w = objects.shape
    n = 0
    for pas in range(2):  # count, then fill
        if pas == 1:
            r = np.empty(n, np.int64)
            c = np.empty(n, np.int64)
            n = 0
        for y in range(h):
            for x in range(w):
                lab = objects[y, x]
                if lab == 0:
                    continue
                yy, xx = y + dr, x + dc
                if 0 <= yy < h and 0 <= xx < w and objects[yy, xx] == lab:
                    continue
                if pas == 1:
                    r[n] = y
                    c[n] = x
                n += 1
    return r, c


@jit
def run_lengths(shadow: Any, known: Any, objects: Any, r: Any, c: Any, off_r: Any, off_c: Any, max_steps: int,
                gap_px: int, length: Any, ok: Any) -> None:  # pragma: no cover - runs compiled
    """The shadow run from each edge pixel ``(r[n], c[n])``, walked at offsets ``(off_r[k], off_c[k])`` for
    ``k = 1 … max_steps`` (away from the sun): ``length[n]`` the last step that was shadow (0: none), ``ok[n]``
    whether the run is a measurement, as :func:`aerialmtl.sun.heights.shadow_runs` defines them: leaving the
    raster, an unknown pixel or an object ends the run clipped (not a measurement) unless a lit pixel already
    ended the shadow; more than ``gap_px`` lit pixels in a row end it (a measurement if it had shadow); a run
    still going after ``max_steps`` is not one. ``shadow``/``known`` bool (H, W), ``objects`` int (H, W).
    """
    h, w = objects.shape
    for n in range(r.shape[0]):
        last = 0
        lit = 0
        state = 0  # 0 running, 1 ended, 2 clipped
        for k in range(1, max_steps + 1):
            rr = r[n] + off_r[k]
            cc = c[n] + off_c[k]
            if rr < 0 or rr >= h or cc < 0 or cc >= w or not known[rr, cc] or objects[rr, cc] != 0:
                state = 1 if lit > 0 else 2
                break
            if shadow[rr, cc]:
                last = k
                lit = 0
            else:
                lit += 1
            if lit > gap_px:
                state = 1
                break
        length[n] = last
        ok[n] = state == 1 and last > 0


@jit
def occluder_offsets(height: Any, objects: Any, r: Any, c: Any, lab: Any, off_r: Any, off_c: Any, q: float,
                     max_steps: int, arg: Any) -> None:  # pragma: no cover - runs compiled
    """``arg[n]`` = the step ``j`` (0 … ``max_steps``, towards the sun at offsets ``(off_r[j], off_c[j])``,
    inside object ``lab[n]``) maximising ``height − j·q`` from edge pixel ``(r[n], c[n])``, the first such step
    on ties (:func:`aerialmtl.sun.heights.occluder_steps`); NaN heights never win. ``height`` float32 (H, W)
    metres, ``objects`` int (H, W), ``q`` metres of height per step (float64 arithmetic).
    """
    h, w = objects.shape
    for n in range(r.shape[0]):
        v0 = height[r[n], c[n]]
        best = -np.inf if np.isnan(v0) else np.float64(v0)
        found = 0
        for j in range(1, max_steps + 1):
            rr = r[n] + off_r[j]
            cc = c[n] + off_c[j]
            if rr < 0 or rr >= h or cc < 0 or cc >= w or objects[rr, cc] != lab[n]:
                break
            v = height[rr, cc]
            val = (-np.inf if np.isnan(v) else np.float64(v)) - j * q
            if val > best:
                best = val
                found = j
        arg[n] = found


@jit
def sweep_surface(z: Any, rows: bool, step: int, deltas: Any, drop: Any,
                  surf: Any) -> None:  # pragma: no cover - runs compiled
    """The shadow surface of ``z`` (float32 (N, H, W), metres) into ``surf`` (the same), swept from the sun-side
    edge (:func:`aerialmtl.sun.cast.shadow_surface_sweep`), in the rasters' own layout.

    The sweep moves one row per step (``rows``) or one column, ``step`` (+1/−1) being the way towards the sun;
    ``deltas[p]`` (int64, one per position along that axis) is the shift across it from position ``p`` to the one
    before it (``p + step``, its upstream neighbour on the sun's digital line). Then ``surf`` at ``p`` =
    ``max(z, surf at p + step shifted by deltas[p] − drop)``, ``z`` where the shifted pixel leaves the raster
    (−∞ there); the first position is ``z``'s. ``drop``: float32 metres per step. NaN propagates as in
    ``numpy.maximum``. Along rows each step is a contiguous pass over a row; along columns each row is swept whole,
    rows in the order the shifts point to (a row reads the row it shifts to, already swept).
    """
    n, h, w = z.shape
    length = h if rows else w
    first = length - 1 if step > 0 else 0
    for i in range(n):
        if rows:
            for x in range(w):
                surf[i, first, x] = z[i, first, x]
            for k in range(1, length):
                y = first - k if step > 0 else k
                d = deltas[y]
                prev = y + step
                for x in range(w):
                    zz = z[i, y, x]
                    if 0 <= x + d < w:
                        v = surf[i, prev, x + d] - drop
                        surf[i, y, x] = zz if (zz >= v or zz != zz) else v
                    else:
                        surf[i, y, x] = zz
        else:
            down = False  # rows whose shift is positive read the row below: sweep the rows bottom up
            for c in range(w):
                if deltas[c] > 0:
                    down = True
            for j in range(h):
                y = h - 1 - j if down else j
                surf[i, y, first] = z[i, y, first]
                for k in range(1, length):
                    c = first - k if step > 0 else k
                    yy = y + deltas[c]
                    zz = z[i, y, c]
                    if 0 <= yy < h:
                        v = surf[i, yy, c + step] - drop
                        surf[i, y, c] = zz if (zz >= v or zz != zz) else v
                    else:
                        surf[i, y, c] = zz


@jit
def shadow_sums(z: Any, surf: Any, ground: Any, score: Any, tol: Any) -> Any:  # pragma: no cover - runs compiled
    """``(count, total)``: how many ``ground`` pixels lie in cast shadow, and the sum of their ``score``, in one pass.

    A pixel is in cast shadow where its shadow surface rises more than ``tol`` above it, ``surf − z > tol`` in
    float32 (:func:`aerialmtl.sun.cast.cast_shadow_mask`). ``z``, ``surf`` float32 (N, H, W) metres; ``ground``
    bool (N, H, W); ``score`` float64 (N, H, W); ``tol`` float32 metres. ``count`` is exact; ``total`` adds each
    row's float64 sum in turn (within ~1e-15 relative of numpy's pairwise sum of the same values).
    """
    n, h, w = z.shape
    count = 0
    total = 0.0
    for i in range(n):
        for y in range(h):
            row = 0.0
            for x in range(w):
                if ground[i, y, x] and surf[i, y, x] - z[i, y, x] > tol:
                    count += 1
                    row += score[i, y, x]
            total += row
    return count, total


@jit
def scaled_shadow_sums(z: Any, inside: Any, scales: Any, rows: bool, step: int, deltas: Any, drop: Any, known: Any,
                       score: Any, tol: Any, zs: Any, surf: Any, out: Any) -> None:  # pragma: no cover - compiled
    """For each multiplier ``scales[k]`` (float32) of the heights inside the objects: the sum of ``score`` over the
    ``known`` pixels that the heights so scaled shade, into ``out[k]`` (float64) — :func:`sweep_surface` then
    :func:`shadow_sums` of ``where(inside, z · scale, z)``, the same float32 products and the same sums, with no
    array made per multiplier (:func:`aerialmtl.sun.render.rendered_heights`' common multiplier).

    ``z`` float32 (1, H, W) metres (−inf unknown); ``inside`` and ``known`` bool (1, H, W); ``score`` float64
    (1, H, W); ``zs`` and ``surf`` float32 (1, H, W) work arrays; the sweep's arguments as :func:`sweep_surface`.
    """
    _, h, w = z.shape
    for k in range(scales.shape[0]):
        s = scales[k]
        for y in range(h):
            for x in range(w):
                zs[0, y, x] = z[0, y, x] * s if inside[0, y, x] else z[0, y, x]
        sweep_surface(zs, rows, step, deltas, drop, surf)
        _, out[k] = shadow_sums(zs, surf, known, score, tol)


__all__ = ["edge_pixels", "logistic_rows", "max_filter_reflect", "occluder_offsets", "run_lengths",
           "scaled_shadow_sums", "shadow_sums", "sweep_surface"]


@jit
def shade_thresholds(shape: Any, footprint: Any, receive: Any, start: Any, off_r: Any, off_c: Any, drop: float,
                     tol: float, top: float, out: Any) -> None:  # pragma: no cover - runs compiled
    """``out[p]`` = the least height ``H`` at which an object of shape ``H · shape`` over ``footprint`` casts
    its shadow on ``p``: ``min_k (receive[p] + tol + k·drop) / shape[p + step_k]`` over the footprint pixels met
    walking towards the sun at offsets ``(off_r[k], off_c[k])``, ``k ≥ 1`` (:mod:`aerialmtl.sun.render`); +inf
    on the footprint itself, where no footprint pixel lies up-sun, and where ``H`` would exceed ``top``.
    ``shape`` float32 (H, W) in (0, 1] on the footprint, ``footprint`` bool (H, W), ``receive`` float32 (H, W)
    metres (−inf: unknown: out is +inf), ``drop`` metres of sun ray per step (float64 arithmetic). ``start``
    int32 (H, W): the first step worth walking (no footprint pixel lies nearer up-sun), −1 where none lies
    up-sun at all (out is +inf).
    """
    h, w = footprint.shape
    n_steps = off_r.shape[0]
    for y in range(h):
        for x in range(w):
            best = np.inf
            base = np.float64(receive[y, x])
            k0 = start[y, x]
            if footprint[y, x] or k0 < 0 or not np.isfinite(base):
                out[y, x] = best
                continue
            base += tol
            for k in range(max(k0, 1), n_steps):
                need = base + k * drop
                if need > top or need >= best:
                    break
                rr = y + off_r[k]
                cc = x + off_c[k]
                if rr < 0 or rr >= h or cc < 0 or cc >= w:
                    break
                if footprint[rr, cc]:
                    g = np.float64(shape[rr, cc])
                    if g > 0.0:
                        t = need / g
                        if t < best:
                            best = t
            out[y, x] = best
