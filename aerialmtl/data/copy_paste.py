"""Copy-paste of real tall objects between training patches (simple copy-paste, Ghiasi et al., CVPR 2021).

A small area shows the model few tall structures. Copy-paste shows it more: the crops of the tall objects
of the train split are pasted at other places, quarter turns and flips of other training patches, every
layer together: the orthophoto's pixels, their reference heights (nDSM) and their land-cover labels, so a
pasted roof is a roof of its true height, with its label.

The object bank (:func:`build_object_bank`) is built once from the train split's patch cache: the 8-connected
components of ``nDSM ≥ min_height_m`` (at least ``min_pixels`` pixels), each cut with a margin of
``margin_m + margin_ratio × its highest pixel`` metres, which carries its cast shadow and the lean of a
non-true orthophoto's roofs. What is pasted is the object dilated by that margin (a square dilation), not
its whole box, so the target keeps its own ground away from the object. An object whose margin box leaves
its patch (cut by the patch border: its shadow or part of it is missing) is not banked; an object seen in
several overlapping patches is banked once (same place on the tile grid). Objects are banked in manifest
order, and a bank larger than ``bank_size`` keeps a random subset drawn with the run's seed.

Pasting (:meth:`CopyPaster.paste`) runs on the compact arrays a batch is gathered as (raw image dtype,
uint8 validity and classes, float32 heights with NaN where invalid), after the crop and before flips and
rotations, in the DataLoader workers. Each sample's placements are drawn from its own generator seeded with
the sample's augmentation seed (another stream than the other augmentations), so a run is the same whatever
the number of workers and across a resume, and with ``prob: 0`` (the default) nothing is drawn and batches
are bit-identical to a run without copy-paste.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from scipy import ndimage

from aerialmtl.errors import ConfigError

#: Added to a sample's augmentation seed for its copy-paste stream (independent of the other draws).
SEED_SALT = 0x5EED_C0BE


@dataclass(frozen=True)
class CopyPaste:
    """The ``data.copy_paste`` section of a training config (off unless ``prob > 0``).

    Attributes:
        prob: probability that a training patch receives pasted objects (0: off).
        max_objects: a patch that receives objects gets 1 … ``max_objects`` of them (uniform).
        min_height_m: an object is a connected region of reference heights ≥ this (metres above ground).
        min_pixels: smallest object kept (pixels of the region).
        margin_m, margin_ratio: the margin cut around an object is ``margin_m + margin_ratio × h_max``
            metres (``h_max`` its highest pixel): room for its shadow and the lean of its roof.
        bank_size: most objects kept in the bank (a random subset, seeded by the run's seed, beyond it).
    """

    prob: float = 0.0
    max_objects: int = 3
    min_height_m: float = 2.5
    min_pixels: int = 16
    margin_m: float = 2.0
    margin_ratio: float = 0.5
    bank_size: int = 1000

    def __post_init__(self) -> None:
        if not (isinstance(self.prob, (int, float)) and 0.0 <= float(self.prob) <= 1.0):
            raise ConfigError(f"data.copy_paste.prob: must be a probability in [0, 1], got {self.prob!r}; "
                              "0 switches copy-paste off, e.g. 0.5 pastes into half the patches")
        for name in ("max_objects", "min_pixels", "bank_size"):
            if getattr(self, name) < 1:
                raise ConfigError(f"data.copy_paste.{name}: must be ≥ 1, got {getattr(self, name)}")
        for name in ("min_height_m", "margin_m", "margin_ratio"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ConfigError(f"data.copy_paste.{name}: must be a finite number ≥ 0, got {value!r}")
        if self.min_height_m <= 0:
            raise ConfigError(f"data.copy_paste.min_height_m: must be > 0 m (0 would make the ground an object), "
                              f"got {self.min_height_m}; e.g. 2.5")

    @property
    def enabled(self) -> bool:
        """Whether anything is pasted."""
        return self.prob > 0


@dataclass(frozen=True)
class BankedObject:
    """One tall object with its margin, cut out of a training patch (arrays of its margin box, h × w).

    Attributes:
        source: the patch it was cut from (index in the split's manifest order).
        mask: bool (h, w), the object dilated by its margin: the pixels that are pasted.
        image: (C, h, w) raw image values (the cache's dtype); ``image_valid``: bool (h, w).
        height: float32 (h, w) metres, NaN where invalid.
        classes: uint8 (h, w) class indices (255 unlabelled), ``None`` without classes.
        height_max: its highest reference height (m).
    """

    source: int
    mask: np.ndarray
    image: np.ndarray
    image_valid: np.ndarray
    height: np.ndarray
    classes: np.ndarray | None
    height_max: float

    @property
    def shape(self) -> tuple[int, int]:
        """(h, w) of its margin box."""
        return (int(self.mask.shape[0]), int(self.mask.shape[1]))


def find_objects(height: np.ndarray, spec: CopyPaste, gsd: float) -> list[tuple[slice, slice, np.ndarray, float]]:
    """The objects of one patch: ``(rows, cols, mask, h_max)`` of each margin box inside the patch.

    Args:
        height: float32 (H, W) reference heights in metres, NaN where invalid.
        spec: the copy-paste settings (height threshold, smallest object, margin).
        gsd: metres per pixel.

    Returns:
        For every 8-connected region of ``height ≥ spec.min_height_m`` of at least ``spec.min_pixels`` pixels
        whose margin box lies inside the patch: the box's slices, the region dilated by the margin (bool, box
        shape) and the region's highest height.
    """
    tall = np.nan_to_num(height, nan=-np.inf) >= spec.min_height_m
    labels, n = ndimage.label(tall, structure=np.ones((3, 3), bool))
    if n == 0:
        return []
    rows_n, cols_n = height.shape
    out = []
    for i, box in enumerate(ndimage.find_objects(labels), start=1):
        if box is None:
            continue
        region = labels[box] == i
        if int(region.sum()) < spec.min_pixels:
            continue
        hmax = float(np.nanmax(np.where(region, height[box], np.nan)))
        m = int(math.ceil((spec.margin_m + spec.margin_ratio * hmax) / gsd))
        r0, r1, c0, c1 = box[0].start - m, box[0].stop + m, box[1].start - m, box[1].stop + m
        if r0 < 0 or c0 < 0 or r1 > rows_n or c1 > cols_n:
            continue  # cut by the patch border: part of the object or of its shadow is missing
        rows, cols = slice(r0, r1), slice(c0, c1)
        core = np.zeros((r1 - r0, c1 - c0), bool)
        core[m:m + region.shape[0], m:m + region.shape[1]] = region
        mask = ndimage.maximum_filter(core, size=2 * m + 1, mode="constant") if m else core
        out.append((rows, cols, mask, hmax))
    return out


@dataclass(frozen=True)
class ObjectBank:
    """The tall objects of a split (:func:`build_object_bank`), pasted by :class:`CopyPaster`."""

    objects: tuple[BankedObject, ...]
    patches: int

    def __len__(self) -> int:
        return len(self.objects)

    def summary(self) -> str:
        """One line: how many objects from how many patches, and their heights."""
        if not self.objects:
            return f"no object in {self.patches} patches"
        h = np.array([o.height_max for o in self.objects])
        return (f"{len(self.objects)} objects from {self.patches} patches, highest pixel {h.min():.1f}–{h.max():.1f} m "
                f"(median {np.median(h):.1f} m)")


def build_object_bank(arrays: dict[str, np.ndarray], spec: CopyPaste, gsd: float, seed: int,
                      offsets: Sequence[tuple[int, int]] | None = None) -> ObjectBank:
    """Cut every tall object (:func:`find_objects`) out of a split's cached arrays.

    Args:
        arrays: the patch cache's arrays (:meth:`~aerialmtl.data.cache.PatchCache.arrays`): ``image``
            (N, C, H, W), ``image_valid`` (N, H, W), ``height`` (N, 1, H, W) float32 NaN invalid, optionally
            ``classes`` (N, H, W).
        spec: the copy-paste settings.
        gsd: metres per pixel.
        seed: the run's seed (the subset kept beyond ``spec.bank_size``).
        offsets: each patch's ``(row_off, col_off)`` on the tile grid (the manifest's): an object found in
            several overlapping patches is banked once. ``None``: no de-duplication.

    Raises:
        ConfigError: the split has no heights (copy-paste finds objects by height).
    """
    if "height" not in arrays:
        raise ConfigError("data.copy_paste: finds tall objects by their reference heights, and this tile folder has "
                          "none; set data.copy_paste.prob: 0 or tile with --dsm/--dtm (or --ndsm)")
    heights = arrays["height"]
    objects: list[BankedObject] = []
    seen: set[tuple[int, int, int, int]] = set()
    for n in range(len(heights)):
        height = np.asarray(heights[n, 0], np.float32)
        for rows, cols, mask, hmax in find_objects(height, spec, gsd):
            if offsets is not None:
                key = (offsets[n][0] + rows.start, offsets[n][1] + cols.start, rows.stop - rows.start,
                       cols.stop - cols.start)
                if key in seen:
                    continue
                seen.add(key)
            classes = arrays.get("classes")
            objects.append(BankedObject(
                source=n, mask=mask, image=np.array(arrays["image"][n, :, rows, cols]),
                image_valid=np.asarray(arrays["image_valid"][n, rows, cols]).astype(bool),
                height=height[rows, cols].copy(),
                classes=None if classes is None else np.array(classes[n, rows, cols]), height_max=hmax))
    if len(objects) > spec.bank_size:
        keep = np.sort(np.random.default_rng(seed).choice(len(objects), spec.bank_size, replace=False))
        objects = [objects[i] for i in keep]
    return ObjectBank(tuple(objects), len(heights))


@dataclass(frozen=True)
class Placement:
    """Where one banked object goes: its index, quarter turns ``k`` (counter-clockwise), a left-right flip
    (after the turns) and the top-left corner ``(row, col)`` of its margin box in the target patch.
    """

    index: int
    k: int
    flip: bool
    row: int
    col: int


def _turned(a: np.ndarray, k: int, flip: bool) -> np.ndarray:
    """``a`` (…, h, w) turned ``k`` quarter turns counter-clockwise, then flipped left-right if ``flip``."""
    out = np.rot90(a, k, axes=(-2, -1))
    return out[..., ::-1] if flip else out


class CopyPaster:
    """Pastes objects of an :class:`ObjectBank` into batches gathered from the same split.

    Args:
        bank: the objects.
        spec: the settings (``prob``, ``max_objects``).
    """

    def __init__(self, bank: ObjectBank, spec: CopyPaste) -> None:
        self.bank, self.spec = bank, spec

    def draw(self, generator: torch.Generator, target: int, shape: tuple[int, int]) -> list[Placement]:
        """The placements of one patch (index ``target``, ``shape`` = (H, W) after the crop).

        Objects cut from the target patch itself, or larger than the patch once turned, are skipped (so a
        patch may get fewer than drawn).
        """
        if not len(self.bank) or float(torch.rand((), generator=generator)) >= self.spec.prob:
            return []
        count = int(torch.randint(1, self.spec.max_objects + 1, (), generator=generator))
        out = []
        for _ in range(count):
            i = int(torch.randint(0, len(self.bank), (), generator=generator))
            k = int(torch.randint(0, 4, (), generator=generator))
            flip = bool(torch.rand((), generator=generator) < 0.5)
            h, w = self.bank.objects[i].shape
            if k % 2:
                h, w = w, h
            if self.bank.objects[i].source == target or h > shape[0] or w > shape[1]:
                continue
            row = int(torch.randint(0, shape[0] - h + 1, (), generator=generator))
            col = int(torch.randint(0, shape[1] - w + 1, (), generator=generator))
            out.append(Placement(i, k, flip, row, col))
        return out

    def paste(self, data: dict[str, torch.Tensor], spec: Sequence[tuple[int, int]]) -> dict[str, torch.Tensor]:
        """Paste into a gathered batch (:meth:`~aerialmtl.data.cache.PatchCache.gather`; changed in place).

        Args:
            data: CPU tensors ``image`` (B, C, H, W), ``image_valid`` (B, H, W), ``height`` (B, 1, H, W),
                ``classes`` (B, H, W) (the layers present are pasted).
            spec: per sample, ``(patch index, augmentation seed)``.

        Returns:
            ``data``.
        """
        shape = (int(data["image"].shape[-2]), int(data["image"].shape[-1]))
        for b, (target, seed) in enumerate(spec):
            gen = torch.Generator().manual_seed((seed + SEED_SALT) % 2**63)
            for p in self.draw(gen, target, shape):
                self._paste_one(data, b, p)
        return data

    def _paste_one(self, data: dict[str, torch.Tensor], b: int, p: Placement) -> None:
        obj = self.bank.objects[p.index]
        mask = np.ascontiguousarray(_turned(obj.mask, p.k, p.flip))
        h, w = mask.shape
        m = torch.from_numpy(mask)
        rows, cols = slice(p.row, p.row + h), slice(p.col, p.col + w)

        def put(target: torch.Tensor, source: np.ndarray) -> None:
            src = torch.from_numpy(np.ascontiguousarray(_turned(source, p.k, p.flip))).to(target.dtype)
            region = target[..., rows, cols]
            region[..., m] = src[..., m]

        put(data["image"][b], obj.image)
        put(data["image_valid"][b], obj.image_valid)
        if "height" in data:
            put(data["height"][b, 0], obj.height)
        if "classes" in data and obj.classes is not None:
            put(data["classes"][b], obj.classes)


__all__ = ["CopyPaste", "BankedObject", "ObjectBank", "CopyPaster", "Placement", "build_object_bank",
           "find_objects", "SEED_SALT"]
