"""Ground textures cut from the user's own orthophoto, to restyle a synthetic city like the user's area.

A :class:`TexturePool` holds square patches of an orthophoto taken only where the nDSM stays near 0 over
the whole patch (asphalt, gravel, grass, soil of the user's area, never a roof or a tree), so laying them on
synthetic roofs and ground teaches that a roof may look exactly like the user's ground.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import ndimage

from aerialmtl.errors import InputError
from aerialmtl.io.align import AlignedRaster, reference_grid

#: A texture source bound to a GSD: (rng, (h, w), base colour) → float32 (3, h, w) DN, or None (no texture).
Source = Callable[[np.random.Generator, tuple[int, int], tuple[float, float, float]], "np.ndarray | None"]


@dataclass(frozen=True)
class TexturePool:
    """Near-ground texture patches of one orthophoto.

    Attributes:
        patches: uint8 (N, 3, P, P) RGB patches whose every pixel had an nDSM ≤ ``max_height``.
        gsd: their pixel size in metres.
        share: probability that a surface of a synthetic city is drawn with a texture of the pool.
        max_height: the nDSM limit the patches were cut under, metres.
    """

    patches: np.ndarray
    gsd: float
    share: float = 0.5
    max_height: float = 0.5

    def __post_init__(self) -> None:
        p = self.patches
        if p.ndim != 4 or p.shape[1] != 3 or p.shape[2] != p.shape[3] or p.shape[0] == 0 or p.dtype != np.uint8:
            raise InputError(f"TexturePool.patches must be uint8 (N ≥ 1, 3, P, P), got {p.dtype} {p.shape}",
                             param="patches")
        if not self.gsd > 0 or not 0.0 <= self.share <= 1.0:
            raise InputError(f"TexturePool needs gsd > 0 and share in [0, 1], got gsd={self.gsd}, share={self.share}",
                             param="gsd")

    @classmethod
    def from_arrays(cls, image: np.ndarray, ndsm: np.ndarray, gsd: float, patch_px: int = 16,
                    max_height: float = 0.5, max_patches: int = 256, share: float = 0.5,
                    seed: int = 0) -> TexturePool:
        """Cut patches from an orthophoto where its nDSM is near 0.

        Args:
            image: uint8 (3, H, W) RGB orthophoto.
            ndsm: float (H, W) height above ground on the same grid, metres; NaN where unknown (never used).
            gsd: the orthophoto's pixel size in metres.
            patch_px: patch side in pixels.
            max_height: a patch is kept only if every pixel's nDSM is ≤ this (metres) and known.
            max_patches: at most this many patches, chosen at random among the candidates.
            share: see the class.
            seed: seed of the choice of patches.

        Raises:
            InputError: shapes disagree, or no patch of the image is near the ground everywhere.
        """
        image, ndsm = np.asarray(image), np.asarray(ndsm, np.float32)
        if image.ndim != 3 or image.shape[0] != 3 or ndsm.shape != image.shape[1:]:
            raise InputError(f"TexturePool.from_arrays needs image (3, H, W) and ndsm (H, W) on the same grid, got "
                             f"{image.shape} and {ndsm.shape}; align the nDSM onto the orthophoto first",
                             param="ndsm")
        return cls._pick([image], [ndsm], gsd, patch_px, max_height, max_patches, share, seed,
                         "of the orthophoto")

    @classmethod
    def _pick(cls, images: list[np.ndarray], ndsms: list[np.ndarray], gsd: float, patch_px: int, max_height: float,
              max_patches: int, share: float, seed: int, where: str) -> TexturePool:
        """Cut up to ``max_patches`` patches, chosen at random (``seed``) among the low ones of all ``images``."""
        half = patch_px // 2
        step = max(1, half // 2)
        places: list[tuple[int, int, int]] = []
        for k, (image, ndsm) in enumerate(zip(images, ndsms, strict=True)):
            if image.shape[1] < patch_px or image.shape[2] < patch_px:
                continue
            low = np.isfinite(ndsm) & (ndsm <= max_height)
            # a patch qualifies when all of its pixels are low: a box sum of the "not low" mask is 0
            bad = ndimage.uniform_filter((~low).astype(np.float32), size=patch_px, mode="constant", cval=1.0)
            ok = bad[half:image.shape[1] - patch_px + half + 1:step,
                     half:image.shape[2] - patch_px + half + 1:step] < 0.5 / patch_px**2
            places.extend((k, int(r) * step, int(c) * step) for r, c in zip(*np.nonzero(ok), strict=True))
        if not places:
            raise InputError(f"no {patch_px}×{patch_px} px patch {where} has an nDSM ≤ {max_height} m "
                             "everywhere; pass a smaller patch_px or an area with open ground", param="ndsm")
        rng = np.random.default_rng(seed)
        pick = rng.choice(len(places), size=min(max_patches, len(places)), replace=False)
        patches = np.stack([images[k][:3, r:r + patch_px, c:c + patch_px]
                            for k, r, c in (places[int(i)] for i in pick)]).astype(np.uint8)
        return cls(patches=patches, gsd=float(gsd), share=share, max_height=max_height)

    @classmethod
    def from_tile_folder(cls, folder: str | Path, split: str = "train", patch_px: int = 16, max_height: float = 0.5,
                         max_patches: int = 256, share: float = 0.5, seed: int = 0) -> TexturePool:
        """Cut a pool from the ``split`` patches of a tile folder written by ``aerialmtl tile`` (their image and
        nDSM layers; the training split by default, so that no validation or test pixel reaches a start).

        Raises:
            InputError: not a tile folder, patches that are not 8-bit with ≥ 3 bands or have no heights, or
                no patch with open ground.
        """
        from aerialmtl.data.dataset import read_rgb_heights

        images, ndsms, _, gsd = read_rgb_heights(folder, split, "textures", "textures")
        return cls._pick(images, ndsms, gsd, patch_px, max_height, max_patches, share, seed,
                         f"of the {split} split of '{folder}'")

    @classmethod
    def from_files(cls, ortho: str | Path, ndsm: str | Path, gsd: float | None = None, patch_px: int = 16,
                   max_height: float = 0.5, max_patches: int = 256, share: float = 0.5, seed: int = 0) -> TexturePool:
        """Read an orthophoto and an nDSM raster (any grid and CRS; aligned onto the orthophoto's grid, or a
        grid of ``gsd`` metres) and cut a pool from them (the other arguments as :meth:`from_arrays`).
        """
        grid = reference_grid(ortho, gsd)
        with AlignedRaster(ortho, grid, "image", role="orthophoto") as src:
            image, valid = src.read()
        with AlignedRaster(ndsm, grid, "height", role="nDSM") as src:
            height, hvalid = src.read()
        heights = np.where(valid & hvalid, height[0], np.nan).astype(np.float32)
        if image.shape[0] < 3 or image.dtype != np.uint8:
            raise InputError(f"the texture orthophoto '{ortho}' must be 8-bit RGB, got {image.shape[0]} bands of "
                             f"{image.dtype}; pass an 8-bit RGB orthophoto", param="ortho")
        return cls.from_arrays(image[:3], heights, float(grid.res[0] * grid.unit_m), patch_px, max_height,
                               max_patches, share, seed)

    def source(self, gsd: float) -> Source:
        """A texture source for surfaces of a city of ``gsd`` metres (patches resampled to that GSD)."""
        zoom = self.gsd / gsd

        def texture(rng: np.random.Generator, shape: tuple[int, int],
                    rgb: tuple[float, float, float]) -> np.ndarray | None:
            if rng.random() >= self.share:
                return None
            patch = self.patches[int(rng.integers(self.patches.shape[0]))].astype(np.float32)
            if abs(zoom - 1.0) > 0.05:
                patch = ndimage.zoom(patch, (1.0, zoom, zoom), order=1, mode="mirror")
            tile = np.concatenate([patch, patch[:, ::-1]], axis=1)
            tile = np.concatenate([tile, tile[:, :, ::-1]], axis=2)  # mirrored 2×2: seamless when repeated
            reps = (1, shape[0] // tile.shape[1] + 2, shape[1] // tile.shape[2] + 2)
            big = np.tile(tile, reps)
            r0, c0 = int(rng.integers(tile.shape[1])), int(rng.integers(tile.shape[2]))
            return np.ascontiguousarray(big[:, r0:r0 + shape[0], c0:c0 + shape[1]])

        return texture


__all__ = ["Source", "TexturePool"]
