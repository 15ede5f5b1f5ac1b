"""Training augmentations on :class:`~aerialmtl.data.types.Sample` dicts, per sample or per batch.

Geometric transforms (flips, 90° rotations, crops) move every spatial layer of a sample identically
(``image`` (C, H, W), ``height`` and ``height_valid`` (1, H, W), ``classes`` (H, W)), so the image
stays aligned with its references. Photometric jitter changes the image only, in normalised space
(after ``(raw - mean) / std``): contrast scales each band around its patch mean and brightness adds a
shift in units of the band's standard deviation, so one setting fits 8-bit, 16-bit and reflectance
imagery alike. Invalid image pixels are 0 in normalised space and are not jittered.

Every transform is split in two so that a batch can be augmented on the training device:

* ``draw(generator, shape)`` draws one sample's random parameters on the CPU (small tensors) from the
  sample's own ``torch.Generator``, given the sample's (C, H, W) before the transform;
* ``apply(batch, params)`` applies them to a batch (every tensor with a leading B dimension, on any
  device), ``params`` being the per-sample parameters stacked along B (:func:`stack_params`).

``transform(sample, generator)`` does both for one sample. A :class:`Compose` draws its transforms'
parameters in order from one generator, so the per-sample and the batched path draw the same numbers and
give the same result. Each transform belongs to a stage, and a pipeline lists them in stage order:

* ``"load"`` (crops): may be applied while patches are read (the cached data path cuts the crop window out
  of the memory-mapped patch);
* ``"permute"`` (flips, rotations): only move pixels, so they may run on the compact stored arrays (uint8
  image, validity, heights with NaN, uint8 classes) before normalisation — fewer bytes to move;
* ``"value"`` (jitter, and anything that changes values): run on the normalised Sample.

A batch is augmented sample by sample on its device (B small kernels per transform): the same arithmetic
as the per-sample path, hence the same numbers.

Randomness comes from torch: without a generator a transform uses torch's global RNG, which DataLoader
seeds per worker. The training loop passes a generator seeded per (seed, epoch, position) so that results
depend neither on the number of workers nor on resuming.

Adding an augmentation: subclass :class:`BatchTransform`, implement ``draw`` and ``apply`` (and
``out_shape`` if it changes the patch size), and add it in :func:`build_train_transform`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import torch

from aerialmtl.data.types import Sample, as_sample
from aerialmtl.errors import ConfigError

#: The layers a geometric transform moves (``shadow``: the shadow head's labels, :mod:`aerialmtl.data.shadow_labels`).
SPATIAL_KEYS = ("image", "height", "height_valid", "classes", "image_valid", "shadow")

#: The stages of a pipeline, in the order transforms must come (see the module docstring).
STAGES = ("load", "permute", "value")

#: One sample's parameters (``draw``), or a batch's (stacked along a leading B dimension).
Params = dict[str, torch.Tensor]
Batch = dict[str, Any]


def _rand(generator: torch.Generator | None) -> float:
    return float(torch.rand((), generator=generator))


def stack_params(per_sample: Sequence[Params]) -> Params:
    """Stack the parameters of B samples along a new leading dimension."""
    if not per_sample or not per_sample[0]:
        return {}
    return {k: torch.stack([p[k] for p in per_sample]) for k in per_sample[0]}


class BatchTransform:
    """Base class: ``draw`` one sample's parameters, ``apply`` a batch's; ``__call__`` does both for one sample."""

    #: ``"load"`` (crops), ``"permute"`` (moves pixels only, any dtype) or ``"value"`` (changes values).
    stage = "value"

    def out_shape(self, shape: tuple[int, int, int]) -> tuple[int, int, int]:
        """(C, H, W) of a sample after this transform, given (C, H, W) before."""
        return shape

    def draw(self, generator: torch.Generator | None, shape: tuple[int, int, int]) -> Params:
        """Random parameters of one sample of (C, H, W) ``shape`` (CPU tensors)."""
        return {}

    def apply(self, batch: Batch, params: Params) -> Batch:
        """Apply stacked parameters to a batch; returns a new dict (inputs are not modified)."""
        raise NotImplementedError

    def __call__(self, sample: Sample, generator: torch.Generator | None = None) -> Sample:
        """Apply the transform to one sample with parameters drawn from ``generator``."""
        c, h, w = sample["image"].shape
        params = stack_params([self.draw(generator, (c, h, w))])
        out: dict[str, Any] = dict(sample)
        batch = {k: out[k][None] for k in SPATIAL_KEYS if k in out}
        for k, v in self.apply(batch, params).items():
            out[k] = v[0].contiguous()
        return as_sample(out)


def _map_spatial(batch: Batch, fn: Callable[[torch.Tensor], torch.Tensor]) -> Batch:
    out = dict(batch)
    for key in SPATIAL_KEYS:
        if key in out:
            out[key] = fn(out[key])
    return out


def _per_sample(batch: Batch, ops: list[Callable[[torch.Tensor], torch.Tensor] | None]) -> Batch:
    """Apply ``ops[i]`` (``None`` = unchanged) to sample i of every spatial layer."""
    if all(op is None for op in ops):
        return batch
    return _map_spatial(batch, lambda t: torch.stack([t[i] if op is None else op(t[i]) for i, op in enumerate(ops)]))


#: A flip/rotation of the last two axes as ``(transpose, flipped axes)``: ``x.transpose(-2, -1)`` if ``transpose``,
#: then ``flip`` of those axes. Every combination of flips and quarter turns is one such move.
Move = tuple[bool, frozenset[int]]
_ROT90_MOVES: dict[int, Move] = {0: (False, frozenset()), 1: (True, frozenset({-2})), 2: (False, frozenset({-2, -1})),
                                 3: (True, frozenset({-1}))}


def _then(first: Move, second: Move) -> Move:
    """The move ``second ∘ first`` (a transpose turns the flips before it into flips of the other axis)."""
    flips = frozenset(-3 - d for d in first[1]) if second[0] else first[1]
    return first[0] != second[0], flips ^ second[1]


def move_op(move: Move) -> Callable[[torch.Tensor], torch.Tensor] | None:
    """The function of ``move`` on one sample's (…, H, W) tensor; ``None`` for the identity."""
    transpose, flips = move
    if not transpose and not flips:
        return None
    dims = tuple(sorted(flips))

    def op(x: torch.Tensor) -> torch.Tensor:
        y = x.transpose(-2, -1) if transpose else x
        return torch.flip(y, dims=dims) if dims else y

    return op


class RandomFlip(BatchTransform):
    """Flip left-right and/or up-down, each with probability ``p``.

    Parameters: ``h``, ``v`` bool.
    """

    stage = "permute"

    def __init__(self, p: float = 0.5, horizontal: bool = True, vertical: bool = True) -> None:
        self.p, self.horizontal, self.vertical = p, horizontal, vertical

    def draw(self, generator: torch.Generator | None, shape: tuple[int, int, int]) -> Params:
        """Whether to flip horizontally and vertically (each with probability ``p``)."""
        h = self.horizontal and _rand(generator) < self.p
        v = self.vertical and _rand(generator) < self.p
        return {"h": torch.tensor(h), "v": torch.tensor(v)}

    def apply(self, batch: Batch, params: Params) -> Batch:
        """Flip every image of the batch as its parameters say."""
        def op(h: bool, v: bool) -> Callable[[torch.Tensor], torch.Tensor] | None:
            dims = (-2,) * v + (-1,) * h
            return (lambda x: torch.flip(x, dims=dims)) if dims else None

        return _per_sample(batch, [op(h, v) for h, v in zip(params["h"].tolist(), params["v"].tolist())])

    def moves(self, params: Params) -> list[Move]:
        """Each sample's flip as a :data:`Move`."""
        return [(False, frozenset((-2,) * v + (-1,) * h)) for h, v in zip(params["h"].tolist(), params["v"].tolist())]


class RandomRot90(BatchTransform):
    """Rotate by k·90° counter-clockwise, k uniform in {0, 1, 2, 3}.

    Non-square patches only get k in {0, 2} so that every sample of a batch keeps its shape.
    Parameters: ``k`` int64.
    """

    stage = "permute"

    def draw(self, generator: torch.Generator | None, shape: tuple[int, int, int]) -> Params:
        """A number of quarter turns (any on square patches, 0 or 2 otherwise)."""
        h, w = shape[-2:]
        k = int(torch.randint(0, 4, (), generator=generator)) if h == w else 2 * int(
            torch.randint(0, 2, (), generator=generator))
        return {"k": torch.tensor(k, dtype=torch.int64)}

    def apply(self, batch: Batch, params: Params) -> Batch:
        """Rotate every image of the batch by its quarter turns."""
        def op(k: int) -> Callable[[torch.Tensor], torch.Tensor] | None:
            return (lambda x: torch.rot90(x, k, dims=(-2, -1))) if k else None

        return _per_sample(batch, [op(k) for k in params["k"].tolist()])

    def moves(self, params: Params) -> list[Move]:
        """Each sample's quarter turns as a :data:`Move` (as ``torch.rot90``: k = 1 flips the columns, then
        transposes).
        """
        return [_ROT90_MOVES[k % 4] for k in params["k"].tolist()]


class _Crop(BatchTransform):
    stage = "load"

    def __init__(self, size: int) -> None:
        self.size = size

    def _check(self, shape: tuple[int, int, int]) -> tuple[int, int]:
        h, w = shape[-2:]
        if h < self.size or w < self.size:
            raise ConfigError(
                f"data.crop_size: {self.size} is larger than the {h}×{w} patches; use a crop ≤ the tile size"
            )
        return h, w

    def out_shape(self, shape: tuple[int, int, int]) -> tuple[int, int, int]:
        return (shape[0], self.size, self.size)

    def apply(self, batch: Batch, params: Params) -> Batch:
        s = self.size
        rows, cols = params["row"].tolist(), params["col"].tolist()

        def cut(t: torch.Tensor) -> torch.Tensor:
            if t.shape[-2:] == (s, s):
                return t
            return torch.stack([t[i, ..., r:r + s, c:c + s] for i, (r, c) in enumerate(zip(rows, cols))])

        return _map_spatial(batch, cut)


class RandomCrop(_Crop):
    """Cut a random ``size`` × ``size`` window (all layers); patches already that size are kept.

    Parameters: ``row``, ``col`` int64, the window's top-left corner.
    """

    def __init__(self, size: int) -> None:
        if size < 1:
            raise ConfigError(f"data.crop_size: must be ≥ 1, got {size}")
        super().__init__(size)

    def draw(self, generator: torch.Generator | None, shape: tuple[int, int, int]) -> Params:
        """A random top-left corner of the crop."""
        h, w = self._check(shape)
        r = c = 0
        if (h, w) != (self.size, self.size):
            r = int(torch.randint(0, h - self.size + 1, (), generator=generator))
            c = int(torch.randint(0, w - self.size + 1, (), generator=generator))
        return {"row": torch.tensor(r, dtype=torch.int64), "col": torch.tensor(c, dtype=torch.int64)}


class CenterCrop(_Crop):
    """Cut the central ``size`` × ``size`` window (validation counterpart of :class:`RandomCrop`)."""

    def draw(self, generator: torch.Generator | None, shape: tuple[int, int, int]) -> Params:
        """The top-left corner of the central crop."""
        h, w = self._check(shape)
        return {"row": torch.tensor((h - self.size) // 2, dtype=torch.int64),
                "col": torch.tensor((w - self.size) // 2, dtype=torch.int64)}


class PhotometricJitter(BatchTransform):
    """Random contrast and brightness of the (normalised) image, per band.

    ``image' = (image - m) · c + m + b`` with ``m`` the band's mean over valid (non-zero) pixels,
    ``c ~ U(1 - contrast, 1 + contrast)`` and ``b ~ U(-brightness, brightness)`` (in std units).
    Applied with probability ``p``. Parameters: ``on`` bool, ``contrast`` and ``brightness`` (C,) float32.
    """

    def __init__(self, brightness: float = 0.2, contrast: float = 0.2, p: float = 0.8) -> None:
        if brightness < 0 or not 0 <= contrast < 1:
            raise ConfigError(
                f"data.jitter: brightness must be ≥ 0 and contrast in [0, 1), got {brightness}, {contrast}"
            )
        self.brightness, self.contrast, self.p = brightness, contrast, p

    def draw(self, generator: torch.Generator | None, shape: tuple[int, int, int]) -> Params:
        """Whether to jitter and, if so, the per-band brightness and contrast factors."""
        n = shape[0]
        if _rand(generator) >= self.p:
            return {"on": torch.tensor(False), "contrast": torch.ones(n), "brightness": torch.zeros(n)}
        c = 1.0 + (torch.rand(n, generator=generator) * 2 - 1) * self.contrast
        b = (torch.rand(n, generator=generator) * 2 - 1) * self.brightness
        return {"on": torch.tensor(True), "contrast": c, "brightness": b}

    def apply(self, batch: Batch, params: Params) -> Batch:
        """Scale and shift the bands of the chosen images."""
        on = params["on"].tolist()
        if not any(on):
            return batch
        img = batch["image"]
        c = params["contrast"].to(img.device, img.dtype)[:, :, None, None]
        b = params["brightness"].to(img.device, img.dtype)[:, :, None, None]

        def jitter(x: torch.Tensor, c: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
            valid = (x != 0).any(dim=0, keepdim=True)
            m = (x * valid).sum(dim=(-2, -1), keepdim=True) / valid.sum().clamp(min=1)
            return torch.where(valid, (x - m) * c + m + b, x)

        out = dict(batch)
        out["image"] = torch.stack([jitter(img[i], c[i], b[i]) if on[i] else img[i] for i in range(len(on))])
        return out


class Compose(BatchTransform):
    """Apply transforms in order, drawing each one's parameters from the same generator."""

    def __init__(self, transforms: Sequence[BatchTransform]) -> None:
        self.transforms = list(transforms)
        order = [STAGES.index(t.stage) for t in self.transforms]
        if order != sorted(order):
            raise ValueError(f"Compose: transforms must come in stage order {STAGES}, got "
                             f"{[t.stage for t in self.transforms]}")

    def out_shape(self, shape: tuple[int, int, int]) -> tuple[int, int, int]:
        """(C, H, W) of a sample after every transform."""
        for t in self.transforms:
            shape = t.out_shape(shape)
        return shape

    def draw(self, generator: torch.Generator | None, shape: tuple[int, int, int]) -> Params:
        """Parameters of every transform, keyed ``"<i>.<name>"`` (i = position in the pipeline)."""
        out: Params = {}
        for i, t in enumerate(self.transforms):
            out.update({f"{i}.{k}": v for k, v in t.draw(generator, shape).items()})
            shape = t.out_shape(shape)
        return out

    def _params(self, params: Params, i: int) -> Params:
        prefix = f"{i}."
        return {k[len(prefix):]: v for k, v in params.items() if k.startswith(prefix)}

    def load_window(self, params: Params) -> tuple[int, torch.Tensor, torch.Tensor] | None:
        """``(size, rows, cols)`` of the leading crop (stacked parameters), or ``None`` without one."""
        if self.transforms and isinstance(self.transforms[0], _Crop):
            p = self._params(params, 0)
            return self.transforms[0].size, p["row"], p["col"]
        return None

    def apply(self, batch: Batch, params: Params, stages: Sequence[str] = ("load", "permute", "value")) -> Batch:
        """Apply the transforms of ``stages`` (e.g. without ``"load"`` when crops were cut while reading).

        Consecutive flips and rotations move each sample once (their composition, :data:`Move`): one copy of
        each layer instead of one per transform, and the same pixels.
        """
        moving: list[int] = []
        for i, t in enumerate(self.transforms):
            if t.stage not in stages:
                continue
            if isinstance(t, (RandomFlip, RandomRot90)):
                moving.append(i)
                continue
            batch = self._move(batch, params, moving)
            moving = []
            batch = t.apply(batch, self._params(params, i))
        return self._move(batch, params, moving)

    def _move(self, batch: Batch, params: Params, indices: list[int]) -> Batch:
        """Apply the flips/rotations at ``indices`` (consecutive in the pipeline) as one move per sample."""
        if len(indices) < 2:
            return self.transforms[indices[0]].apply(batch, self._params(params, indices[0])) if indices else batch
        return _per_sample(batch, [move_op(m) for m in self._moves(params, indices)])

    def _moves(self, params: Params, indices: list[int]) -> list[Move]:
        moves: list[Move] | None = None
        for i in indices:
            t = self.transforms[i]
            assert isinstance(t, (RandomFlip, RandomRot90))
            step = t.moves(self._params(params, i))
            moves = step if moves is None else [_then(a, b) for a, b in zip(moves, step)]
        assert moves is not None
        return moves

    def sample_moves(self, params: Params, batch: int) -> list[Move]:
        """Each sample's flips and quarter turns (the ``permute`` stage) composed into one :data:`Move`.

        Args:
            params: stacked parameters of ``batch`` samples.
            batch: the number of samples (the identity for each when the pipeline has no flip or rotation).
        """
        indices = [i for i, t in enumerate(self.transforms) if isinstance(t, (RandomFlip, RandomRot90))]
        return self._moves(params, indices) if indices else [(False, frozenset())] * batch

    def has_stage(self, stage: str) -> bool:
        """Whether a transform of ``stage`` is in the pipeline."""
        return any(t.stage == stage for t in self.transforms)

    def __call__(self, sample: Sample, generator: torch.Generator | None = None) -> Sample:
        """Apply every transform to one sample, in order."""
        for t in self.transforms:
            sample = t(sample, generator)
        return sample


def build_train_transform(
    flips: bool = True,
    rot90: bool = True,
    jitter: bool = False,
    crop_size: int | None = None,
    brightness: float = 0.2,
    contrast: float = 0.2,
) -> Compose:
    """The training augmentation pipeline: crop → flips → rot90 → jitter (each optional)."""
    ts: list[BatchTransform] = []
    if crop_size:
        ts.append(RandomCrop(crop_size))
    if flips:
        ts.append(RandomFlip())
    if rot90:
        ts.append(RandomRot90())
    if jitter:
        ts.append(PhotometricJitter(brightness, contrast))
    return Compose(ts)


def build_eval_transform(crop_size: int | None = None) -> Compose:
    """Validation transform: a centre crop when training crops, otherwise the identity."""
    return Compose([CenterCrop(crop_size)] if crop_size else [])


__all__ = ["BatchTransform", "RandomFlip", "RandomRot90", "RandomCrop", "CenterCrop", "PhotometricJitter",
           "Compose", "stack_params", "build_train_transform", "build_eval_transform", "SPATIAL_KEYS", "STAGES",
           "Params", "Move", "move_op"]
