"""Training batches cut from synthetic scenes generated on the fly (no disk): the data of ``aerialmtl pretrain``.

:func:`synthetic_scene` is the one place that asks a generator for a scene; today it is the synthetic city of
:func:`aerialmtl.data.synth.city.sample_city` (towers and halls with ground-like roofs, stands, trees, cars; its own
sun, lean and sensor style per scene).
:class:`SyntheticBatches` is a map-style dataset whose item ``step`` is the whole batch of that optimisation
step: its patches are cut at random places, quarter turns and flips out of a few scenes, each scene reused
for ``scene_reuse`` consecutive steps (a scene costs about as much as a training step). Everything is a pure
function of ``(seed, step)``: scene ``j`` is generated from ``(seed, j)``, a patch from ``(seed, step, i)``, so
a resumed run sees the batches an uninterrupted one sees, with any number of DataLoader workers (each keeps a
few scenes in memory; a scene it lacks it generates again, identically).
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from aerialmtl.classes import IGNORE_INDEX, ClassScheme
from aerialmtl.data.dataset import normalise_batch
from aerialmtl.data.synth.city import sample_city
from aerialmtl.data.synth.city_canvas import GROUND_ROOFS
from aerialmtl.data.synth.style import CityStyle
from aerialmtl.data.synth.textures import TexturePool
from aerialmtl.errors import ConfigError

#: The class scheme of the synthetic scenes (:mod:`aerialmtl.resources.classes`).
SCHEME_NAME = "synthetic"
#: The name and version of the scene generator (recorded in a start's model card).
GENERATOR = ("aerialmtl.data.synth.city.sample_city (synthetic cities: towers, halls, stands, trees, cars; per-scene "
             "sun, lean and sensor style)")


@dataclass(frozen=True)
class SyntheticScene:
    """One synthetic scene with its references.

    ``image`` uint8 (3, H, W) RGB, ``height`` float32 (H, W) metres above ground, ``classes`` uint8 (H, W) class
    indices of the ``synthetic`` scheme (255 unlabelled), ``gsd`` metres per pixel.
    """

    image: np.ndarray
    height: np.ndarray
    classes: np.ndarray
    gsd: float


def city_seed(seed: int, index: int) -> int:
    """The city seed of scene ``index`` of the stream ``seed`` (a 63-bit int, well mixed)."""
    return int(np.random.SeedSequence([int(seed) & 0xFFFFFFFF, int(index)]).generate_state(2, np.uint64)[0] >> 1)


def synthetic_scene(seed: int, index: int, size: int, gsd: float,
                    textures: TexturePool | None = None, ground_roofs: float = GROUND_ROOFS) -> SyntheticScene:
    """Scene ``index`` of the stream seeded ``seed`` (``size`` × ``size`` pixels of ``gsd`` metres).

    Its surfaces are drawn in part with ``textures`` (the user's own ground) when given, ``ground_roofs`` of its
    flat roofs in a ground material (:attr:`~aerialmtl.data.synth.style.CityStyle.ground_roofs`).

    The one function that asks the generator for a scene: switching generators changes only this body.
    """
    city = sample_city(city_seed(seed, index), size, gsd, CityStyle(ground_roofs=ground_roofs), textures=textures)
    classes = ClassScheme.load(SCHEME_NAME).remap(city.classes, on_unknown="ignore").astype(np.uint8)
    return SyntheticScene(city.image, city.height.astype(np.float32), classes, gsd)


@dataclass(frozen=True)
class RealPatches:
    """The training patches of a tile folder, whole, for mixing into synthetic batches.

    ``images`` uint8 (3, S, S) RGB each, ``heights`` float32 (S, S) metres with NaN where invalid (the image's
    nodata too), ``valid`` bool (S, S) where the image is valid.
    """

    images: list[np.ndarray]
    heights: list[np.ndarray]
    valid: list[np.ndarray]

    @classmethod
    def from_tile_folder(cls, folder: str | Path, patch_size: int, split: str = "train") -> RealPatches:
        """Read ``split``'s patches (8-bit RGB with heights; at least ``patch_size`` pixels a side).

        Raises:
            InputError: not such a tile folder, or no such patch.
        """
        from aerialmtl.data.dataset import read_rgb_heights

        images, heights, valid, _ = read_rgb_heights(folder, split, "real patches for pretraining", "real",
                                                     min_side=patch_size)
        return cls(images, heights, valid)


@dataclass(frozen=True)
class SyntheticStream:
    """What :class:`SyntheticBatches` cuts: scene size and GSD range, patches per step, scene reuse.

    Attributes:
        seed: the stream's seed.
        batch_size: patches per step.
        patch_size: patch side (pixels, a multiple of 32).
        scene_size: scene side (pixels, ≥ ``patch_size``).
        gsd_range: ``(low, high)`` metres per pixel; each scene draws its GSD uniformly from it.
        scenes_per_step: scenes a step's patches come from (patch i from scene i mod this).
        scene_reuse: consecutive steps that cut from the same scenes.
        textures: a tile folder (``aerialmtl tile``) whose training patches lend their open ground's look to
            the scenes' surfaces (:meth:`TexturePool.from_tile_folder`); ``None``: the generator's own materials.
        texture_share: probability that a surface is drawn with one of those textures.
        ground_roofs: probability that a flat roof is drawn in a ground material (the generator's default
            :data:`~aerialmtl.data.synth.city_canvas.GROUND_ROOFS`).
        real: a tile folder whose training patches (orthophoto and nDSM; no labels: their classes are another
            scheme's) fill ``real_share`` of every batch, cropped at random places, quarter turns and flips;
            ``None``: synthetic scenes only.
        real_share: share of a batch's patches taken from ``real`` (rounded; at least one when > 0).
    """

    seed: int = 0
    batch_size: int = 8
    patch_size: int = 128
    scene_size: int = 256
    gsd_range: tuple[float, float] = (0.5, 1.0)
    scenes_per_step: int = 4
    scene_reuse: int = 4
    textures: str | None = None
    texture_share: float = 0.5
    ground_roofs: float = GROUND_ROOFS
    real: str | None = None
    real_share: float = 0.25

    def __post_init__(self) -> None:
        if self.patch_size < 32 or self.patch_size % 32:
            raise ConfigError(f"patch_size: must be a multiple of 32 (the network's stride), got {self.patch_size}")
        if self.scene_size < self.patch_size:
            raise ConfigError(f"scene_size: must be ≥ patch_size {self.patch_size}, got {self.scene_size}")
        lo, hi = self.gsd_range
        if not 0 < lo <= hi:
            raise ConfigError(f"gsd_range: must be two pixel sizes 0 < low ≤ high (metres), got {list(self.gsd_range)}")
        for name in ("batch_size", "scenes_per_step", "scene_reuse"):
            if getattr(self, name) < 1:
                raise ConfigError(f"{name}: must be ≥ 1, got {getattr(self, name)}")
        for name in ("texture_share", "ground_roofs", "real_share"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ConfigError(f"{name}: must be a probability in [0, 1], got {getattr(self, name)}")

    def real_count(self) -> int:
        """Patches of a batch taken from :attr:`real` (0 without it)."""
        if self.real is None or self.real_share == 0:
            return 0
        return min(self.batch_size, max(1, round(self.real_share * self.batch_size)))

    def texture_pool(self) -> TexturePool | None:
        """The pool of :attr:`textures` (``None`` without one)."""
        if self.textures is None:
            return None
        return TexturePool.from_tile_folder(self.textures, share=self.texture_share, seed=self.seed)

    def scene_of(self, step: int, i: int) -> int:
        """The index of the scene patch ``i`` of ``step`` is cut from."""
        return (step // self.scene_reuse) * self.scenes_per_step + i % self.scenes_per_step

    def scene_gsd(self, index: int) -> float:
        """The GSD (metres) of scene ``index``."""
        lo, hi = self.gsd_range
        return float(np.random.default_rng([self.seed, 0x65D, index]).uniform(lo, hi)) if hi > lo else float(lo)


class SyntheticBatches(torch.utils.data.Dataset[dict[str, torch.Tensor]]):
    """Item ``step``: the normalised batch of that step (use with ``batch_size=None`` and a sampler of steps).

    Args:
        stream: what is cut (:class:`SyntheticStream`).
        mean, std: (3,) per-band normalisation in raw 8-bit units.
        length: the number of steps (``len``).
        keep: scenes kept in memory per process.

    Items are :class:`~aerialmtl.data.types.Sample` batches: ``image`` float32 (B, 3, P, P), ``height``
    float32 (B, 1, P, P) metres with ``height_valid``, ``classes`` int64 (B, P, P).
    """

    def __init__(self, stream: SyntheticStream, mean: tuple[float, ...], std: tuple[float, ...], length: int,
                 keep: int = 4) -> None:
        self.stream, self.length, self.keep = stream, length, max(keep, stream.scenes_per_step)
        self.textures = stream.texture_pool()
        self.real = (RealPatches.from_tile_folder(stream.real, stream.patch_size)
                     if stream.real is not None and stream.real_count() else None)
        self.mean = torch.tensor(mean, dtype=torch.float32)
        self.std = torch.tensor(std, dtype=torch.float32)
        self._scenes: OrderedDict[int, SyntheticScene] = OrderedDict()

    def __len__(self) -> int:
        return self.length

    def __getstate__(self) -> dict[str, object]:
        return {**self.__dict__, "_scenes": OrderedDict()}

    def scene(self, index: int) -> SyntheticScene:
        """Scene ``index`` (generated, or kept from an earlier step)."""
        if index in self._scenes:
            self._scenes.move_to_end(index)
            return self._scenes[index]
        s = self.stream
        scene = synthetic_scene(s.seed, index, s.scene_size, s.scene_gsd(index), self.textures, s.ground_roofs)
        self._scenes[index] = scene
        while len(self._scenes) > self.keep:
            self._scenes.popitem(last=False)
        return scene

    def raw(self, step: int) -> dict[str, torch.Tensor]:
        """The compact batch of ``step``.

        ``image`` uint8 (B, 3, P, P), ``height`` float32 (B, 1, P, P) (NaN where unknown), ``classes`` uint8
        (B, P, P), ``valid`` bool (B, P, P) where the image is valid; the first
        :meth:`SyntheticStream.real_count` patches are real ones.
        """
        s, p = self.stream, self.stream.patch_size
        images, heights, classes, valids = [], [], [], []
        n_real = s.real_count()
        for i in range(s.batch_size):
            if i < n_real:
                assert self.real is not None
                rng = np.random.default_rng([s.seed, 0x4EA1, step, i])
                j = int(rng.integers(len(self.real.images)))
                shape = self.real.heights[j].shape
                src = (self.real.images[j], self.real.heights[j], np.full(shape, IGNORE_INDEX, np.uint8),
                       self.real.valid[j])
            else:
                scene = self.scene(s.scene_of(step, i))
                src = (scene.image, scene.height, scene.classes, np.ones(scene.height.shape, bool))
                rng = np.random.default_rng([s.seed, 0xBA7C, step, i])
            side = src[1].shape[0]
            r, c = (int(v) for v in rng.integers(0, side - p + 1, 2))
            k, flip = int(rng.integers(0, 4)), bool(rng.integers(0, 2))

            def cut(a: np.ndarray, r: int = r, c: int = c, k: int = k, flip: bool = flip) -> np.ndarray:
                out = np.rot90(a[..., r:r + p, c:c + p], k, axes=(-2, -1))
                return np.ascontiguousarray(out[..., ::-1] if flip else out)

            images.append(cut(src[0]))
            heights.append(cut(src[1])[None])
            classes.append(cut(src[2]))
            valids.append(cut(src[3]))
        return {"image": torch.from_numpy(np.stack(images)), "height": torch.from_numpy(np.stack(heights)),
                "classes": torch.from_numpy(np.stack(classes)), "valid": torch.from_numpy(np.stack(valids))}

    def __getitem__(self, step: int) -> dict[str, torch.Tensor]:
        raw = self.raw(step)
        return normalise_batch(raw["image"], raw["valid"], self.mean, self.std, raw["height"], raw["classes"])


__all__ = ["GENERATOR", "SCHEME_NAME", "SyntheticBatches", "SyntheticScene", "SyntheticStream", "city_seed",
           "synthetic_scene"]
