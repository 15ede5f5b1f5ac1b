"""Whether an orthophoto is the flight the model was trained on: chips of the training orthophoto, kept with the
training fit of the sun, and how closely an orthophoto's pixels at the same places match them.

The training fit's sun holds for the training flight only. Place alone cannot tell a later flight of the same town
from the training flight; where an orthophoto covers part of the training area, its pixels can.

Both sides are box-smoothed over a few pixels and correlated (Pearson's r, median over the chips an orthophoto
covers). Measured with ``experiments/heights_from_the_sun/flight_chips.py`` on the four real orthophotos of
``../shared/data`` (0.1–0.3 m):

- the same flight gives the same pixels, whatever was done to the file since: regridded by 0.4 px and saved as
  JPEG (quality 60), r = 0.992–0.999; averaged to a 2× or 3× coarser product, 0.995–0.999;
- another flight does not: its orthorectification registers it differently, by a metre or more, and its shadows,
  cars and leaves have moved. The same orthophoto registered 1 m off alone gave r = 0.23–0.86 (0.32–0.90 at 2×
  coarser). On synthetic towns at one place (``tests/test_time_and_place.py``): another town, r = 0.00; the
  training town under a sun 14° away and registered 1 m off, 0.43.

So a median under :data:`SAME_FLIGHT_R` over at least :data:`MIN_CHIPS` chips says "another flight". What the
pixels cannot tell: a later flight registered to the pixel with the training one, its houses, cars and leaves
unchanged, only its sun moved (the synthetic town so, 14° away: r = 0.99). Its own shadows are then the only
witness, and with a network's heights they refute only a sun far off
(:data:`aerialmtl.inference.shadows.CHECK_RATIO`); a time (``--acquired``) is needed for the rest.
Numpy only (the chips are read from a raster by :mod:`aerialmtl.inference.sun_choice`).
"""

from __future__ import annotations

import base64
import binascii
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from aerialmtl.errors import CheckpointError

#: A chip's side in pixels of the training grid (64 px at 0.3 m: 20 m of town).
CHIP_PX = 64
#: Chips kept with the training fit (16 × 4 KiB of grey levels in the checkpoint).
N_CHIPS = 16
#: Least standard deviation (grey levels of 0–255) of a chip worth keeping: a flat roof or a lawn correlates with
#: anything by its noise.
MIN_STD = 8.0
#: Least share of a chip's pixels an orthophoto must hold for the chip to be compared.
MIN_COVER = 0.9
#: Chips an orthophoto must hold before its pixels decide whether it is the training flight.
MIN_CHIPS = 3
#: The median correlation with the training chips below which an orthophoto is another flight (see the module
#: docstring for what the same flight and another one gave).
SAME_FLIGHT_R = 0.95
#: The box (pixels of the orthophoto read) both sides are smoothed over before they are compared: the same flight
#: regridded by 0.4 px and saved as JPEG (quality 60) matched its chips at r = 0.908 unsmoothed on NEON's 0.1 m
#: orthophoto, 0.992 so. A box of chip pixels coarser than that blurs away a registration 1 m off: on chips of
#: ``autzen_west``'s tiles at 1 m, r = 0.917 unsmoothed against 0.947 over 3 chip pixels.
SMOOTH_PX = 3


@dataclass(frozen=True)
class FlightChip:
    """A square of the training orthophoto, in grey levels, where it lies.

    Attributes:
        left, top: the chip's upper-left corner in the training area's CRS (its units).
        pixel: the chip's pixel size in those units (north-up, square pixels).
        size: its side in pixels.
        grey: base64 of its ``size × size`` uint8 grey levels (the mean of the patch's first three bands: the
            orthophoto bands :attr:`aerialmtl.sun.record.TrainingSun.chip_bands`), row-major.
    """

    left: float
    top: float
    pixel: float
    size: int
    grey: str

    def __post_init__(self) -> None:
        if not (math.isfinite(self.left) and math.isfinite(self.top) and math.isfinite(self.pixel)
                and self.pixel > 0):
            raise CheckpointError("checkpoint meta is invalid: a flight chip (sun.chips) needs a finite corner and a "
                                  f"pixel size > 0, got ({self.left}, {self.top}) and {self.pixel}")
        if not 8 <= self.size <= 512:
            raise CheckpointError(f"checkpoint meta is invalid: a flight chip's size must be 8–512 px, got {self.size}")
        try:
            n = len(base64.b64decode(self.grey, validate=True))
        except (binascii.Error, ValueError):
            n = -1
        if n != self.size * self.size:
            raise CheckpointError(f"checkpoint meta is invalid: a flight chip's grey levels must be base64 of "
                                  f"{self.size}² bytes; refit the sun (aerialmtl.training.sun.sun_checkpoint)")

    def pixels(self) -> np.ndarray:
        """float32 ``(size, size)`` grey levels, 0–255."""
        raw = np.frombuffer(base64.b64decode(self.grey), np.uint8)
        return raw.reshape(self.size, self.size).astype(np.float32)

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """``(left, bottom, right, top)`` in the training area's CRS."""
        side = self.size * self.pixel
        return self.left, self.top - side, self.left + side, self.top


def grey_levels(rgb: np.ndarray) -> np.ndarray:
    """float32 ``(h, w)``: the mean of the first three bands of ``rgb`` ``(bands, h, w)``."""
    grey: np.ndarray = np.asarray(rgb[:3], np.float32).mean(axis=0)
    return grey


def cut_chip(rgb: np.ndarray, valid: np.ndarray, left: float, top: float, pixel: float,
             size: int = CHIP_PX) -> FlightChip | None:
    """The centre chip of a patch ``rgb`` uint8 ``(bands, h, w)`` whose upper-left corner is ``(left, top)`` with
    pixels of ``pixel`` CRS units, or ``None`` where the patch is smaller than ``size``, the chip has an invalid
    pixel (``valid`` bool ``(h, w)``) or too little texture (:data:`MIN_STD`).
    """
    h, w = rgb.shape[1:]
    if h < size or w < size:
        return None
    r, c = (h - size) // 2, (w - size) // 2
    if not valid[r:r + size, c:c + size].all():
        return None
    grey = grey_levels(rgb[:, r:r + size, c:c + size])
    if float(grey.std()) < MIN_STD:
        return None
    data = np.clip(np.rint(grey), 0, 255).astype(np.uint8).tobytes()
    return FlightChip(left=float(left + c * pixel), top=float(top - r * pixel), pixel=float(pixel), size=size,
                      grey=base64.b64encode(data).decode("ascii"))


def pick_chips(candidates: Sequence[FlightChip], n: int = N_CHIPS, seed: int = 0) -> tuple[FlightChip, ...]:
    """``n`` of ``candidates`` drawn with a seeded generator (all of them where there are fewer), spread over the
    area as the patches are.
    """
    order = np.random.default_rng(seed).permutation(len(candidates))[:n]
    return tuple(candidates[i] for i in sorted(order))


def correlation(chip: np.ndarray, seen: np.ndarray) -> float | None:
    """Pearson's r of two ``(size, size)`` grey chips over the pixels both hold (NaN where ``seen`` has none), or
    ``None`` when fewer than :data:`MIN_COVER` of them do or either is flat there.
    """
    both = np.isfinite(seen) & np.isfinite(chip)
    if both.mean() < MIN_COVER:
        return None
    a = chip[both] - chip[both].mean()
    b = seen[both] - seen[both].mean()
    norm = float(np.sqrt((a * a).sum() * (b * b).sum()))
    return float((a * b).sum() / norm) if norm > 0 else None


def _box(grey: np.ndarray, k: int) -> np.ndarray:
    """``grey`` averaged over ``k × k`` pixels; NaN where the box holds a NaN."""
    from scipy.ndimage import uniform_filter

    held = np.isfinite(grey)
    total = uniform_filter(np.where(held, grey, 0.0).astype(np.float64), size=k, mode="nearest")
    share = uniform_filter(held.astype(np.float64), size=k, mode="nearest")
    return np.where(share > 1.0 - 1e-9, total, np.nan).astype(np.float32)


@dataclass(frozen=True)
class FlightMatch:
    """How an orthophoto's pixels match the training chips it covers.

    Attributes:
        r: the median correlation over the chips compared, or ``None`` when fewer than :data:`MIN_CHIPS` were.
        chips: how many chips were compared.
    """

    r: float | None
    chips: int

    @property
    def other_flight(self) -> bool:
        """The orthophoto covers the training area and is not its flight (r under :data:`SAME_FLIGHT_R`)."""
        return self.r is not None and self.r < SAME_FLIGHT_R


def match_chips(chips: Sequence[FlightChip], read: Callable[[FlightChip], np.ndarray | None],
                coarser: float = 1.0) -> FlightMatch:
    """Compare each chip with what ``read`` gives of the orthophoto on its grid (float32 ``(size, size)`` grey
    levels, NaN where it has none; ``None`` where it does not reach the chip).

    Both are box-smoothed over :data:`SMOOTH_PX` pixels of the orthophoto first (``coarser``: its pixel over the
    chips'; at least one chip pixel): resampling and recompression blur its single pixels, and a coarser product
    of the same flight lacks them. Chips coarser than the orthophoto (tiles at the lidar's 1 m from a 0.3 m
    orthophoto) are compared unsmoothed, read with the averaging the tiles were made with.
    """
    k = max(1, int(round(SMOOTH_PX * coarser)))
    rs = []
    for chip in chips:
        seen = read(chip)
        r = None if seen is None else correlation(_box(chip.pixels(), k), _box(seen, k))
        if r is not None:
            rs.append(r)
    return FlightMatch(float(np.median(rs)) if len(rs) >= MIN_CHIPS else None, len(rs))


__all__ = ["CHIP_PX", "MIN_CHIPS", "N_CHIPS", "SAME_FLIGHT_R", "FlightChip", "FlightMatch", "correlation",
           "cut_chip", "grey_levels", "match_chips", "pick_chips"]
