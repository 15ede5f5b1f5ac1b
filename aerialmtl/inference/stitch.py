"""Blend window statistics on the model's device and hand back finished blocks in their output dtypes.

:class:`Stitcher` follows the window plan of :mod:`aerialmtl.inference.windows`: windows arrive row by
row, left to right. Each one is added, weighted by its dyadic blending weights times its input
validity, into accumulators on the model's device; after window ``(i, j)`` the output rows of window row ``i`` and the
columns before :meth:`~aerialmtl.inference.windows.AxisPlan.final_until` ``(j)`` get no more weight, so
that block is finalised on the device (weighted means, argmax, entropy, mutual information; on a CPU the
class map by a compiled kernel, :mod:`aerialmtl.inference.stitch_kernel`, to the same bits) and handed back as a
:class:`Block` of host arrays in the output dtypes of the schema (:func:`aerialmtl.formats.prediction.
prediction_layers`), nodata filled in. Only finished pixels cross to the host.

Memory: accumulators for one window (shifted in place as the window moves right) plus the rows of a
window row that still get weight from the next one (about ``overlap − 2·margin`` rows over the raster
width, the "carry", read as columns enter the window and rewritten as they are finished). Nothing grows
with the raster height. The carry (~(K + 2) · 4 B per carried row and column) is kept in memory up to
:data:`CARRY_IN_MEMORY` bytes and in an anonymous temporary file beyond (wide rasters: 138 MiB at
32768 px wide with 20 classes), so memory does not grow with the width either.

Blended statistics (:class:`~aerialmtl.models.mc_dropout.McStatistics` of each window):

* ``height_mean`` → ``height``; ``height_std`` → ``height_std`` (weighted mean of the window stds);
  with a ``calibration`` (:class:`~aerialmtl.models.calibration.Calibration`, from the checkpoint) the
  finished values go through its height map and its spread map (by range of the predicted height), each
  where the checkpoint says it is applied;
* ``probs`` (K, channels last) → ``classes`` (argmax), ``class_entropy`` (entropy of the blended
  probabilities), ``class_probabilities``;
* ``mean_entropy`` (mean per-sample entropy) → ``class_mutual_info = clip(entropy − blended mean
  entropy, 0, entropy)``, so ``0 ≤ MI ≤ entropy ≤ log K`` holds exactly in the blended result;
* ``unfamiliarity`` (0–1) → ``unfamiliarity`` (weighted mean, so it stays in 0–1);
* ``shadow`` → ``shadow`` (weighted mean over the windows that knew the sun, ``shadow_on``; nodata where none
  did) and ``shadow_height`` (weighted mean over the windows that measured it, ``shadow_weight``; nodata where
  none did), from :mod:`aerialmtl.inference.shadows`.

Every sum is formed in window order with one rounding per product and per addition, so any
implementation that adds the same products in the same order (e.g. a whole-raster reference in numpy)
gets the same bits; the result does not depend on batching or on where a strip of window rows starts.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from aerialmtl.formats.prediction import (
    CLASS_ENTROPY,
    CLASS_MUTUAL_INFO,
    CLASS_PROBABILITIES,
    CLASSES,
    HEIGHT,
    HEIGHT_STD,
    SHADOW,
    SHADOW_HEIGHT,
    UNFAMILIARITY,
    LayerSpec,
)
from aerialmtl.inference import stitch_kernel
from aerialmtl.inference.windows import Plan
from aerialmtl.models.calibration import Calibration
from aerialmtl.models.mc_dropout import McStatistics

#: Elements per temporary on CPU (~4 MiB of float32): the blending loops stay in the caches.
CHUNK_ELEMENTS = 1 << 20
#: Largest carry held in memory (bytes); a larger one goes to a temporary file (see the module docstring).
CARRY_IN_MEMORY = 32 << 20

_QUANTITIES = ("height_mean", "height_std", "probs", "mean_entropy", "unfamiliarity", "shadow", "shadow_on",
               "shadow_height", "shadow_weight")


@dataclass
class Block:
    """Finished output pixels: grid rows ``[row_off, row_off + height)`` × columns ``[col_off, col_off + width)``.

    Attributes:
        layers: layer name → (bands, height, width) host array in the layer's dtype, nodata filled in.
    """

    row_off: int
    col_off: int
    height: int
    width: int
    layers: dict[str, np.ndarray]


def _quantities(names: set[str]) -> tuple[str, ...]:
    """The blended statistics the output layers ``names`` need."""
    need = []
    if HEIGHT in names:
        need.append("height_mean")
    if HEIGHT_STD in names:
        need.append("height_std")
    if names & {CLASSES, CLASS_ENTROPY, CLASS_MUTUAL_INFO, CLASS_PROBABILITIES}:
        need.append("probs")
    if CLASS_MUTUAL_INFO in names:
        need.append("mean_entropy")
    if UNFAMILIARITY in names:
        need.append("unfamiliarity")
    if SHADOW in names:
        need.extend(("shadow", "shadow_on"))
    if SHADOW_HEIGHT in names:
        need.extend(("shadow_height", "shadow_weight"))
    return tuple(need)


class Stitcher:
    """Blend the windows of window rows ``[start, stop)`` of ``plan`` into finished blocks.

    Args:
        plan: the window plan.
        layers: the output schema (:func:`~aerialmtl.formats.prediction.prediction_layers`).
        num_classes: K (0 without the classes task).
        device: where the accumulators live (the model's device).
        start, stop: the window rows whose output rows to hand back (a strip of the raster); default
            all. The stitcher then expects the windows of window rows :attr:`first_row` … ``stop − 1``:
            window rows before ``start`` are only accumulated (they reach into the strip), nothing of
            them is handed back.
    """

    def __init__(
        self,
        plan: Plan,
        layers: Sequence[LayerSpec],
        num_classes: int,
        device: torch.device | str = "cpu",
        start: int = 0,
        stop: int | None = None,
        calibration: Calibration | None = None,
    ) -> None:
        self.plan = plan
        self.calibration = calibration
        self.specs = {s.name: s for s in layers}
        self.quantities = _quantities(set(self.specs))
        self.k = int(num_classes)
        if "probs" in self.quantities and self.k < 1:
            raise ValueError("Stitcher: class layers need num_classes ≥ 1")
        self.device = torch.device(device)
        n_rows = len(plan.window_rows)
        self.start = start
        self.stop = n_rows if stop is None else stop
        if not 0 <= start < self.stop <= n_rows:
            raise ValueError(f"Stitcher: window rows [{start}, {stop}) outside the plan's {n_rows} window rows")
        #: The first window row the stitcher needs (the first source of ``start``).
        self.first_row = plan.window_rows[start].sources[0]
        rows, cols = plan.rows, plan.cols
        self.height, self.width = rows.length, cols.length
        self._rw = torch.from_numpy(rows.weights).to(self.device)
        self._cw = torch.from_numpy(cols.weights).to(self.device)
        sr, sc = rows.size, cols.size
        # carry: output rows still reached by window row k after its own rows are final (from its
        # out_stop), over the raster width (see the module docstring)
        self._pending = [max(0, min(self.height, rows.reach(k)) - b.out_stop)
                         for k, b in enumerate(plan.window_rows)]
        self._ring = self._alloc(sr, sc)
        carry_rows = max(self._pending + [0])
        per_column = carry_rows * (1 + sum(self.k if q == "probs" else 1 for q in self.quantities)) * 4
        self._carry = _Carry(self._alloc(carry_rows, self.width) if per_column * self.width <= CARRY_IN_MEMORY
                             else None, carry_rows, {n: t.shape[2:] for n, t in self._ring.items()}, self.width,
                             self.device)
        self._carry_rows = 0  # rows of _carry in use (from the current window row's out_start)
        self._expect = (self.first_row, 0)
        self._a0 = 0  # grid column of ring column 0
        self._done = 0  # first grid column of the current window row not yet handed back
        self.chunk = CHUNK_ELEMENTS
        self._tmp = torch.empty(0, device=self.device)
        #: the classes layer by the compiled kernel (:mod:`aerialmtl.inference.stitch_kernel`) on a CPU
        self.compiled_classes = self.device.type == "cpu" and CLASSES in self.specs

    # ---- storage ----------------------------------------------------------------------------------
    def _alloc(self, h: int, w: int) -> dict[str, torch.Tensor]:
        acc = {"weight": torch.zeros((h, w), dtype=torch.float32, device=self.device)}
        for q in self.quantities:
            shape = (h, w, self.k) if q == "probs" else (h, w)
            acc[q] = torch.zeros(shape, dtype=torch.float32, device=self.device)
        return acc

    def _row_chunks(self, rows: int, per_row: int) -> list[tuple[int, int]]:
        if self.device.type != "cpu":
            return [(0, rows)]
        step = max(1, self.chunk // max(1, per_row))
        return [(r, min(rows, r + step)) for r in range(0, rows, step)]

    def _combine(self, dst: torch.Tensor, src: torch.Tensor | None, mult: torch.Tensor | None,
                 base: torch.Tensor | None, accumulate: bool = False) -> None:
        """``dst = base + src·mult`` (``accumulate``: ``base`` is ``dst`` itself).

        ``src`` None: no contribution (``dst = base``, or 0 without a base); ``mult`` None: the
        contribution is ``src`` itself. Shapes (h, w[, K]), ``mult`` (h, w). One rounding for the product
        and one for the sum, in this order, like ``acc += value * weight`` in numpy.
        """
        if dst.numel() == 0:
            return
        if src is None:
            if accumulate:
                return
            if base is None:
                dst.zero_()
            else:
                dst.copy_(base)
            return
        per_row = int(np.prod(dst.shape[1:]))
        for r0, r1 in self._row_chunks(dst.shape[0], per_row):
            s, d = src[r0:r1], dst[r0:r1]
            if mult is None:
                prod = s
            else:
                m = mult[r0:r1]
                if s.dim() == 3:
                    m = m.unsqueeze(-1)
                if base is None and not accumulate:
                    torch.mul(s, m, out=d)
                    continue
                if self.device.type == "cpu":  # a reused scratch buffer: no page faults, stays in cache
                    if self._tmp.numel() < s.numel():
                        self._tmp = torch.empty(max(s.numel(), self.chunk), device=self.device)
                    prod = self._tmp[: s.numel()].view(s.shape)
                    torch.mul(s, m, out=prod)
                else:
                    prod = s * m
            if accumulate:
                d.add_(prod)
            elif base is None:
                d.copy_(prod)
            else:
                torch.add(base[r0:r1], prod, out=d)

    # ---- windows ----------------------------------------------------------------------------------
    def add(self, i: int, j: int, stats: McStatistics | None, valid: torch.Tensor | None) -> list[Block]:
        """Add window (row ``i``, column ``j``); returns the blocks it finished (possibly none).

        Args:
            i, j: the window; windows must come in plan order from row :attr:`first_row` on.
            stats: the window's statistics (tensors of one window, on the device: (h, w) and (h, w, K)),
                or ``None`` for a window that was not computed (no valid input pixel).
            valid: (h, w) bool input validity (ignored when ``stats`` is None).
        """
        if (i, j) != self._expect:
            raise ValueError(f"Stitcher: expected window {self._expect}, got {(i, j)}")
        plan = self.plan
        cols = plan.cols
        wrow = plan.window_rows[i]
        sc = cols.size
        n_cols = len(cols.starts)
        a0 = cols.starts[j]
        top = wrow.out_start - wrow.row_off  # ring rows above are final already
        ring = self._ring
        keep = max(0, self._a0 + sc - a0) if j > 0 else 0
        shift = a0 - self._a0
        # carry columns entering the ring with this window
        c_lo, c_hi = min(self.width, a0 + keep), min(self.width, a0 + sc)
        nc = self._carry_rows
        w = None
        if stats is not None:
            assert valid is not None
            w = torch.outer(self._rw[i], self._cw[j]) * valid
        n = max(0, c_hi - c_lo)  # new columns that have a carry
        for name, dst in ring.items():
            if stats is None:
                src, mult = None, None
            elif name == "weight":
                src, mult = w, None
            else:
                src, mult = getattr(stats, name), w
                if src is None:
                    raise ValueError(f"Stitcher: window statistics lack '{name}'")

            def part(t: torch.Tensor | None, r: slice, c: slice) -> torch.Tensor | None:
                return None if t is None else t[r, c]

            if keep:  # columns shared with the previous window: previous sums + this window
                moved = dst[top:, shift:shift + keep]
                dst[top:, :keep] = moved.clone() if shift < keep else moved  # overlapping copy: via a temporary
                k_ = (slice(top, None), slice(0, keep))
                self._combine(dst[k_], part(src, *k_), part(mult, *k_), None, accumulate=True)
            if keep < sc:  # new columns: carried rows (+ this window), then fresh rows (= this window)
                carried = (slice(top, top + nc), slice(keep, keep + n))
                if nc and n:
                    self._combine(dst[carried], part(src, *carried), part(mult, *carried),
                                  self._carry.read(name, nc, c_lo, c_hi))
                    rest = (slice(top, top + nc), slice(keep + n, None))
                    self._combine(dst[rest], part(src, *rest), part(mult, *rest), None)
                fresh = (slice(top + (nc if n else 0), None), slice(keep, None))
                self._combine(dst[fresh], part(src, *fresh), part(mult, *fresh), None)
        self._a0 = a0
        # finished columns of this window row
        stop = cols.final_until(j)
        blocks: list[Block] = []
        if stop > self._done:
            lo, hi = self._done - a0, stop - a0
            r_lo, r_hi = top, wrow.out_stop - wrow.row_off
            if i >= self.start and r_hi > r_lo:
                blocks.append(self._finalise(ring, wrow.out_start, self._done, r_lo, r_hi, lo, hi))
            pending = self._pending[i] if i + 1 < len(plan.window_rows) else 0
            if pending:  # rows still reached after this window row → the carry (these columns were read already)
                p_lo = wrow.out_stop - wrow.row_off
                for name, acc in ring.items():
                    self._carry.write(name, self._done, acc[p_lo:p_lo + pending, lo:hi])
            self._done = stop
        # move on
        if j + 1 < n_cols:
            self._expect = (i, j + 1)
        else:
            self._carry_rows = self._pending[i] if i + 1 < len(plan.window_rows) else 0
            self._expect = (i + 1, 0)
            self._done = 0
            self._a0 = 0
        return blocks

    @property
    def finished(self) -> bool:
        """Whether every window up to window row ``stop`` has been added."""
        return self._expect[0] >= self.stop

    # ---- finalising -------------------------------------------------------------------------------
    def _finalise(self, acc: dict[str, torch.Tensor], row_off: int, col_off: int, r_lo: int, r_hi: int,
                  c_lo: int, c_hi: int) -> Block:
        h, w = r_hi - r_lo, c_hi - c_lo
        specs = self.specs
        out: dict[str, torch.Tensor] = {
            n: torch.empty((s.count, h, w), dtype=getattr(torch, s.dtype), device=self.device)
            for n, s in specs.items()
        }
        per_row = w * max(1, self.k)
        for r0, r1 in self._row_chunks(h, per_row):
            rs, cs = slice(r_lo + r0, r_lo + r1), slice(c_lo, c_hi)
            invalid = acc["weight"][rs, cs] <= 0
            for name, value in self._layer_values(acc, rs, cs, invalid).items():
                nodata = torch.as_tensor(specs[name].nodata, dtype=value.dtype, device=self.device)
                value = value if value.dim() == 3 else value.unsqueeze(0)
                torch.where(invalid, nodata, value, out=out[name][:, r0:r1])
            if self.compiled_classes:  # the same classes as _layer_values' argmax, in one pass
                stitch_kernel.finished_classes(acc["probs"][rs, cs], acc["weight"][rs, cs],
                                               int(specs[CLASSES].nodata), out[CLASSES][0, r0:r1])
        return Block(row_off, col_off, h, w, {n: _to_host(t) for n, t in out.items()})

    def _layer_values(self, acc: dict[str, torch.Tensor], rs: slice, cs: slice,
                      invalid: torch.Tensor) -> dict[str, torch.Tensor]:
        """Output layer values (before nodata) of accumulator rows ``rs`` × columns ``cs``."""
        specs = self.specs
        wsum = acc["weight"][rs, cs]
        safe = torch.where(invalid, torch.ones_like(wsum), wsum)
        values: dict[str, torch.Tensor] = {}
        if HEIGHT in specs:
            values[HEIGHT] = acc["height_mean"][rs, cs] / safe
        if HEIGHT_STD in specs:
            values[HEIGHT_STD] = (acc["height_std"][rs, cs] / safe).clamp_min_(0.0)
        if self.calibration is not None:  # the one place the checkpoint's calibration is applied
            raw_height = values.get(HEIGHT)
            if HEIGHT_STD in values:  # the spread's range is that of the predicted (uncalibrated) height
                values[HEIGHT_STD] = self.calibration.std_torch(values[HEIGHT_STD], raw_height)
            if raw_height is not None:
                values[HEIGHT] = self.calibration.height_torch(raw_height)
        if UNFAMILIARITY in specs:
            values[UNFAMILIARITY] = (acc["unfamiliarity"][rs, cs] / safe).clamp_(0.0, 1.0)
        for layer, value, weight in ((SHADOW, "shadow", "shadow_on"),
                                     (SHADOW_HEIGHT, "shadow_height", "shadow_weight")):
            if layer in specs:  # its own weight: nodata where no window knew the sun / measured the object
                part = acc[weight][rs, cs]
                none = part <= 0
                ratio = acc[value][rs, cs] / torch.where(none, torch.ones_like(part), part)
                values[layer] = torch.where(none, torch.full_like(ratio, specs[layer].nodata), ratio)
        if "probs" not in acc or (self.compiled_classes and not specs.keys() & {CLASS_ENTROPY, CLASS_MUTUAL_INFO,
                                                                                 CLASS_PROBABILITIES}):
            return values
        probs = acc["probs"][rs, cs] / safe.unsqueeze(-1)
        if CLASSES in specs and not self.compiled_classes:
            values[CLASSES] = probs.argmax(-1).to(torch.uint8)
        if CLASS_ENTROPY in specs or CLASS_MUTUAL_INFO in specs:
            ent = (probs * torch.log(probs.clamp(1e-12, 1.0))).sum(-1).neg_().clamp_min_(0.0)
            if CLASS_MUTUAL_INFO in specs:
                values[CLASS_MUTUAL_INFO] = torch.minimum((ent - acc["mean_entropy"][rs, cs] / safe).clamp_min_(0.0),
                                                          ent)
            if CLASS_ENTROPY in specs:
                values[CLASS_ENTROPY] = ent
        if CLASS_PROBABILITIES in specs:
            values[CLASS_PROBABILITIES] = probs.permute(2, 0, 1)
        return values


class _Carry:
    """The carried rows of every accumulator over the raster width: in memory, or in a temporary file.

    In the file each accumulator is stored column by column (``rows × channels`` floats per column), so
    a range of columns is one contiguous read or write.
    """

    def __init__(self, tensors: dict[str, torch.Tensor] | None, rows: int, channels: dict[str, torch.Size],
                 width: int, device: torch.device) -> None:
        self.tensors = tensors
        self.rows, self.width, self.device = rows, width, device
        self.shapes = {n: tuple(c) for n, c in channels.items()}
        self.file = None
        if tensors is None:
            import tempfile

            self.file = tempfile.TemporaryFile(prefix="aerialmtl-carry-")
            self.offsets: dict[str, int] = {}
            off = 0
            for n, shape in self.shapes.items():
                self.offsets[n] = off
                off += width * self._column_bytes(shape)

    def _column_bytes(self, shape: tuple[int, ...]) -> int:
        return self.rows * int(np.prod(shape, dtype=np.int64)) * 4

    def read(self, name: str, rows: int, c0: int, c1: int) -> torch.Tensor:
        """(rows, c1 − c0[, K]) carried sums of columns ``[c0, c1)``."""
        if self.tensors is not None:
            return self.tensors[name][:rows, c0:c1]
        assert self.file is not None
        shape = self.shapes[name]
        size = self._column_bytes(shape)
        raw = os.pread(self.file.fileno(), (c1 - c0) * size, self.offsets[name] + c0 * size)
        cols = torch.from_numpy(np.frombuffer(raw, np.float32).reshape(c1 - c0, self.rows, *shape).copy())
        return cols[:, :rows].transpose(0, 1).to(self.device)

    def write(self, name: str, c0: int, values: torch.Tensor) -> None:
        """Store ``values`` (rows, columns[, K]) as the carried sums of columns ``[c0, c0 + columns)``."""
        if self.tensors is not None:
            self.tensors[name][:values.shape[0], c0:c0 + values.shape[1]] = values
            return
        assert self.file is not None
        shape = self.shapes[name]
        block = torch.zeros((values.shape[1], self.rows, *shape), dtype=torch.float32)
        block[:, :values.shape[0]] = values.transpose(0, 1).cpu()
        os.pwrite(self.file.fileno(), block.numpy().tobytes(), self.offsets[name] + c0 * self._column_bytes(shape))


def _to_host(t: torch.Tensor) -> np.ndarray:
    """A finished layer block on the host (synchronous copy on CUDA; a view on CPU)."""
    return t.numpy() if t.device.type == "cpu" else t.cpu().numpy()


__all__ = ["CHUNK_ELEMENTS", "Block", "Stitcher"]
