"""The shadow heights in numpy as first written (aerialmtl 0.1, before the compiled kernels of
:mod:`aerialmtl.sun.kernels`): the oracle the kernels are held to, to the bit (tests/test_sun_kernels.py).
"""

from __future__ import annotations

import math

import numpy as np

from aerialmtl.sun.cast import line_offsets, sun_steps
from aerialmtl.sun.heights import MAD_TO_SD, ShadowHeights, ShadowObject, majority
from aerialmtl.sun.position import Sun


def shadow_runs_numpy(shadow: np.ndarray, known: np.ndarray, objects: np.ndarray, sun: Sun, max_steps: int,
                      gap_px: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`aerialmtl.sun.heights.shadow_runs` as first written: one numpy pass per step over the runs."""
    h, w = objects.shape
    rows_dom, step, slope = sun_steps(sun.azimuth_deg)
    step, slope = -step, -slope  # away from the sun
    cross = line_offsets(max_steps + 2, slope)

    def offset(k: int) -> tuple[int, int]:
        return (step * k, int(cross[k])) if rows_dom else (int(cross[k]), step * k)

    dr, dc = offset(1)
    r, c = np.nonzero(objects)
    lab = objects[r, c]
    rr, cc = r + dr, c + dc
    inside = (rr >= 0) & (rr < h) & (cc >= 0) & (cc < w)
    nxt = np.zeros(len(r), objects.dtype)
    nxt[inside] = objects[rr[inside], cc[inside]]
    edge = nxt != lab
    r, c, lab = r[edge], c[edge], lab[edge]
    n = len(r)
    length = np.zeros(n, np.int64)
    lit = np.zeros(n, np.int64)  # lit pixels since the last shadow pixel
    state = np.zeros(n, np.int8)  # 0 running, 1 ended (a measurement if length > 0), 2 not a measurement
    for k in range(1, max_steps + 1):
        run = np.nonzero(state == 0)[0]
        if len(run) == 0:
            break
        dr, dc = offset(k)
        rr, cc = r[run] + dr, c[run] + dc
        inside = (rr >= 0) & (rr < h) & (cc >= 0) & (cc < w)
        # leaving the raster, unknown pixels or an object: clipped, unless a lit pixel already ended the shadow
        bad = ~inside
        bad[inside] = ~known[rr[inside], cc[inside]] | (objects[rr[inside], cc[inside]] != 0)
        state[run[bad]] = np.where(lit[run[bad]] > 0, 1, 2)
        run, rr, cc = run[~bad], rr[~bad], cc[~bad]
        dark = shadow[rr, cc]
        length[run[dark]] = k
        lit[run[dark]] = 0
        lit[run[~dark]] += 1
        state[run[lit[run] > gap_px]] = 1
    ok = (state == 1) & (length > 0)
    return lab, length, ok, np.stack([r, c], axis=1)


def occluder_steps_numpy(height: np.ndarray, objects: np.ndarray, rc: np.ndarray, lab: np.ndarray, sun: Sun,
                         q: float, max_steps: int) -> np.ndarray:
    """:func:`aerialmtl.sun.heights.occluder_steps` as first written: one numpy pass per step."""
    h, w = objects.shape
    rows_dom, step, slope = sun_steps(sun.azimuth_deg)
    cross = line_offsets(max_steps + 2, slope)
    r, c = rc[:, 0], rc[:, 1]
    best = np.nan_to_num(height[r, c].astype(np.float64), nan=-np.inf)
    arg = np.zeros(len(r), np.int64)
    alive = np.ones(len(r), bool)
    for j in range(1, max_steps + 1):
        idx = np.nonzero(alive)[0]
        if len(idx) == 0:
            break
        dr, dc = (step * j, int(cross[j])) if rows_dom else (int(cross[j]), step * j)
        rr, cc = r[idx] + dr, c[idx] + dc
        inside = (rr >= 0) & (rr < h) & (cc >= 0) & (cc < w)
        same = np.zeros(len(idx), bool)
        same[inside] = objects[rr[inside], cc[inside]] == lab[idx[inside]]
        alive[idx[~same]] = False
        idx, rr, cc = idx[same], rr[same], cc[same]
        val = np.nan_to_num(height[rr, cc].astype(np.float64), nan=-np.inf) - j * q
        better = val > best[idx]
        best[idx[better]] = val[better]
        arg[idx[better]] = j
    return arg


def shadow_heights_numpy(shadow_prob: np.ndarray, gsd_m: float, sun: Sun, objects: np.ndarray, *,
                         height: np.ndarray | None = None, threshold: float = 0.5, smooth_px: int = 3,
                         gap_px: int = 1, min_runs: int = 3, max_height_m: float = 150.0,
                         elevation_sd_deg: float = 3.0) -> ShadowHeights:
    """:func:`aerialmtl.sun.shadow_heights` as first written (a loop over the objects for the medians)."""
    # the inputs as the tests give them (float probabilities, integer labels): no checks, no bool masks
    labels = np.asarray(objects)
    p = np.asarray(shadow_prob, dtype=np.float32)
    known = np.isfinite(p)
    shadow = majority(known & (p >= threshold), int(smooth_px)) & known if smooth_px > 1 else known & (p >= threshold)
    q = gsd_m * math.hypot(1.0, sun_steps(sun.azimuth_deg)[2]) * sun.tan_elevation
    max_steps = max(1, int(math.ceil(max_height_m / q)))
    lab, length, ok, rc = shadow_runs_numpy(shadow, known, labels, sun, max_steps, gap_px)
    if height is not None:
        steps = occluder_steps_numpy(np.asarray(height, dtype=np.float32), labels, rc, lab, sun, q, max_steps)
        length = length + np.where(ok, steps, 0)
    e = math.tan(math.radians(min(sun.elevation_deg + elevation_sd_deg, 89.9))) / sun.tan_elevation - 1.0
    all_labels = np.unique(labels[labels != 0])
    n_edges = dict(zip(*np.unique(lab, return_counts=True)))
    heights = length[ok] * q
    lab_ok = lab[ok]
    order = np.argsort(lab_ok, kind="stable")
    lab_ok, heights = lab_ok[order], heights[order]
    starts = np.searchsorted(lab_ok, all_labels, side="left")
    ends = np.searchsorted(lab_ok, all_labels, side="right")
    records: list[ShadowObject] = []
    value = {}
    for label, a, b in zip(all_labels.tolist(), starts.tolist(), ends.tolist()):
        runs = heights[a:b]
        n = len(runs)
        hm = sd = math.nan
        if n >= min_runs:
            hm = float(np.median(runs))
            mad = MAD_TO_SD * float(np.median(np.abs(runs - hm)))
            sd = math.sqrt(max(mad, q / 2) ** 2 * (1.0 + 10.0 / n) + (hm * e) ** 2)
            value[label] = (hm, sd)
        records.append(ShadowObject(int(label), int(n_edges.get(label, 0)), n, hm, sd))
    height = np.full(labels.shape, np.nan, np.float32)
    std = np.full(labels.shape, np.nan, np.float32)
    if value:
        lut_h = np.full(int(labels.max()) + 1, np.nan, np.float32)
        lut_s = np.full(int(labels.max()) + 1, np.nan, np.float32)
        for label, (hm, sd) in value.items():
            lut_h[label], lut_s[label] = hm, sd
        inside = labels > 0
        height[inside] = lut_h[labels[inside]]
        std[inside] = lut_s[labels[inside]]
    return ShadowHeights(height, std, records)


def shadow_surface_numpy(surface: np.ndarray, gsd: float, azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    """:func:`aerialmtl.sun.cast.shadow_surface_sweep` as first written: one numpy pass per column."""
    z = np.asarray(surface, dtype=np.float32)
    flat = z.ndim == 2
    z3 = z[None] if flat else z
    az = math.radians(azimuth_deg)
    d_row, d_col = -math.cos(az), math.sin(az)
    transposed = abs(d_row) > abs(d_col)
    if transposed:
        z3 = z3.transpose(0, 2, 1)
        d_row, d_col = d_col, d_row
    zt = np.ascontiguousarray(z3.transpose(2, 0, 1))
    n_cols, _, n_rows = zt.shape
    step_c = 1 if d_col > 0 else -1
    slope = d_row / abs(d_col)
    drop = np.float32(gsd * math.tan(math.radians(elevation_deg)) * math.hypot(1.0, slope))
    offsets = line_offsets(n_cols, slope * step_c)
    surf = np.empty_like(zt)
    order = range(n_cols - 1, -1, -1) if step_c > 0 else range(n_cols)
    prev: np.ndarray | None = None
    prev_c = -1
    neg = np.float32(-np.inf)
    shifted = np.empty(zt.shape[1:], dtype=np.float32)
    for c in order:
        if prev is None:
            surf[c] = zt[c]
        else:
            delta = int(offsets[prev_c] - offsets[c])
            if delta == 0:
                shifted[:] = prev
            elif delta > 0:
                shifted[:, : n_rows - delta] = prev[:, delta:]
                shifted[:, n_rows - delta:] = neg
            else:
                shifted[:, -delta:] = prev[:, : n_rows + delta]
                shifted[:, : -delta] = neg
            np.maximum(zt[c], shifted - drop, out=surf[c])
        prev = surf[c]
        prev_c = c
    out = surf.transpose(1, 2, 0)
    if transposed:
        out = out.transpose(0, 2, 1)
    out = np.ascontiguousarray(out)
    return out[0] if flat else out
