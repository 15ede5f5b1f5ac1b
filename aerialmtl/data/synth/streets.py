"""Street grids of a synthetic scene: two families of parallel streets, the blocks between them, centre lines.

Streets run along the axes of the scene's frame (:mod:`~aerialmtl.data.synth.canvas`): one family at fixed
``u`` (running along ``v``), one at fixed ``v``. A style says how far apart and how wide its streets are
(:class:`StreetSpacing`); :func:`street_lines` draws one family, :class:`StreetField` tells every pixel how
far it is from the nearest street of each family, and :func:`blocks_between` walks the blocks. All lengths
are metres in the frame.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

#: Dashed centre lines: a dash of 4.5 m every 9 m, on streets at least 8 m wide.
DASH_PERIOD_M, DASH_M, DASHED_MIN_HALF_M = 9.0, 4.5, 4.0


@dataclass(frozen=True)
class StreetSpacing:
    """How a style lays one family of parallel streets (metres; uniform draws in each range).

    Attributes:
        spacing: distance from one street's centre line to the next.
        width: street width.
        lead: the first street lies up to this far before the area.
        tail: streets are laid while their centre line lies less than this far past the area.
    """

    spacing: tuple[float, float]
    width: tuple[float, float]
    lead: float
    tail: float


@dataclass(frozen=True)
class StreetLine:
    """One street (or river, in the city) of a family: its centre line's frame coordinate and its width (m)."""

    centre: float
    width: float
    river: bool = False

    @property
    def low(self) -> float:
        """Frame coordinate of its edge on the low side, metres."""
        return self.centre - self.width / 2

    @property
    def high(self) -> float:
        """Frame coordinate of its edge on the high side, metres."""
        return self.centre + self.width / 2


#: One family of parallel streets, in ascending order of their centre lines.
Family = list[StreetLine]


def street_lines(rng: np.random.Generator, lo: float, hi: float, spacing: StreetSpacing) -> Family:
    """A family of parallel streets covering the frame interval [lo, hi] (metres), in ascending order.

    Draws from ``rng`` in this order: the lead, then each street's width and the gap to the next.
    """
    lines: Family = []
    pos = lo - rng.uniform(0, spacing.lead)
    while pos < hi + spacing.tail:
        lines.append(StreetLine(pos, rng.uniform(*spacing.width)))
        pos += rng.uniform(*spacing.spacing)
    return lines


def nearest_street(coord: np.ndarray, lines: Family) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per pixel: signed offset from the nearest street's centre line (m), its half width (m), its index.

    Args:
        coord: float32 (H, W) the frame coordinate across the family (``u`` for streets at fixed ``u``).
        lines: the family, ascending, at least two.

    Returns:
        float32 (H, W) offset, float32 (H, W) half width, int (H, W) index into ``lines``.
    """
    centres = np.array([ln.centre for ln in lines], np.float32)
    halves = np.array([ln.width / 2 for ln in lines], np.float32)
    k = np.clip(np.searchsorted(centres, coord), 1, len(centres) - 1)
    idx = np.where((centres[k] - coord) < (coord - centres[k - 1]), k, k - 1)
    return coord - centres[idx], halves[idx], idx


@dataclass(frozen=True)
class StreetField:
    """Where every pixel lies against the two street families (arrays (H, W)).

    Attributes:
        off_u, off_v: float32 signed offset from the nearest street centre line of each family, metres.
        half_u, half_v: float32 that street's half width, metres.
        index_u, index_v: int that street's index in its family.
        on_u, on_v: bool, the pixel is on that street.
    """

    off_u: np.ndarray
    half_u: np.ndarray
    index_u: np.ndarray
    on_u: np.ndarray
    off_v: np.ndarray
    half_v: np.ndarray
    index_v: np.ndarray
    on_v: np.ndarray

    @classmethod
    def measure(cls, u: np.ndarray, v: np.ndarray, lines_u: Family, lines_v: Family) -> StreetField:
        """The field of the pixels at frame coordinates ``u``, ``v`` (float32 (H, W), metres)."""
        off_u, half_u, index_u = nearest_street(u, lines_u)
        off_v, half_v, index_v = nearest_street(v, lines_v)
        return cls(off_u, half_u, index_u, np.abs(off_u) <= half_u, off_v, half_v, index_v, np.abs(off_v) <= half_v)

    def centre_dashes(self, u: np.ndarray, v: np.ndarray, gsd: float, road_u: np.ndarray,
                      road_v: np.ndarray) -> np.ndarray:
        """The dashed centre lines of the wide streets, not across junctions: bool (H, W).

        Args:
            u, v: float32 (H, W) frame coordinates of the pixels, metres.
            gsd: pixel size in metres (a line is at least 0.3 m wide, and at least about one pixel).
            road_u, road_v: bool (H, W) the carriageways of each family (``on_u`` / ``on_v`` less any river).
        """
        line_w = max(0.15, 0.55 * gsd)
        dash_u = (road_u & ~self.on_v & (np.abs(self.off_u) < line_w) & (self.half_u >= DASHED_MIN_HALF_M)
                  & (np.mod(v, DASH_PERIOD_M) < DASH_M))
        dash_v = (road_v & ~self.on_u & (np.abs(self.off_v) < line_w) & (self.half_v >= DASHED_MIN_HALF_M)
                  & (np.mod(u, DASH_PERIOD_M) < DASH_M))
        dashes: np.ndarray = dash_u | dash_v
        return dashes


def blocks_between(lines_u: Family, lines_v: Family) -> Iterator[tuple[StreetLine, StreetLine, StreetLine, StreetLine]]:
    """The blocks of the grid, row by row: the streets around each, (low u, high u, low v, high v)."""
    for low_u, high_u in zip(lines_u[:-1], lines_u[1:]):
        for low_v, high_v in zip(lines_v[:-1], lines_v[1:]):
            yield low_u, high_u, low_v, high_v


def positions_along(rng: np.random.Generator, lo: float, hi: float, spacing: float, margin: float) -> Iterator[float]:
    """Evenly spaced positions in [lo + margin, hi − margin) (metres) from a random start: a row of street trees.

    The start is drawn from ``rng`` (uniform in [lo + margin, lo + spacing)) when the first position is asked for.
    """
    pos = lo + rng.uniform(margin, spacing)
    while pos < hi - margin:
        yield pos
        pos += spacing


__all__ = ["Family", "StreetField", "StreetLine", "StreetSpacing", "blocks_between", "nearest_street",
           "positions_along", "street_lines"]
