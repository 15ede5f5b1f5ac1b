"""The pixel grid a synthetic scene is drawn on, its street frame, and the "highest surface wins" rule.

A scene is planned in metres in a frame (u, v) rotated by the scene's street angle θ from the image axes and
rasterised onto an (N, N) grid of ``gsd`` metres, north-up. A pixel centre (row, col) lies at
x = (col + 0.5)·gsd east and y = (row + 0.5)·gsd south of the canvas's upper-left corner, and
u = x·cosθ + y·sinθ, v = −x·sinθ + y·cosθ. Objects are drawn with a "highest surface wins" rule
(:meth:`Canvas.raise_top`), so each pixel's label and nDSM are those of the surface a lidar sees from above
at the true footprint.

Both styles draw on a :class:`Canvas`: the town rasterises polygons (:meth:`Canvas.fill`), the city masks
rectangles of pixels (:meth:`Canvas.window`); each adds the colour arrays it needs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from skimage.draw import polygon


@dataclass
class Window:
    """A rectangle of canvas pixels and the frame coordinates of their centres.

    Attributes:
        rows, cols: the pixel rectangle (slices of the canvas arrays).
        u, v: float32 (h, w) frame coordinates of its pixel centres, metres.
    """

    rows: slice
    cols: slice
    u: np.ndarray
    v: np.ndarray


class Canvas:
    """An (N, N) grid of ``gsd`` metres with the street frame rotated by ``theta`` radians.

    Attributes:
        n: side in pixels.
        gsd: pixel size in metres.
        cos, sin: of the frame angle θ.
        shape: (N, N).
        ndsm: float32 (N, N) height above ground of the top surface, metres (0 everywhere at first).
        labels: uint8 (N, N) raw class codes (``label`` everywhere at first).
        u, v: float32 (N, N) frame coordinates of the pixel centres, metres.
    """

    def __init__(self, size: int, gsd: float, theta: float, label: int = 0) -> None:
        self.n, self.gsd = size, gsd
        self.cos, self.sin = math.cos(theta), math.sin(theta)
        self.shape = (size, size)
        self.ndsm = np.zeros(self.shape, np.float32)
        self.labels = np.full(self.shape, label, np.uint8)
        xs = self.centres()
        self.u, self.v = self.to_frame(xs[None, :], xs[:, None])

    def centres(self) -> np.ndarray:
        """float32 (N,) distances of the pixel centres from the upper-left corner along a row or column, metres."""
        xs: np.ndarray = (np.arange(self.n, dtype=np.float32) + 0.5) * np.float32(self.gsd)
        return xs

    def to_frame(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Frame coordinates (u, v) of points x metres east and y metres south of the upper-left corner."""
        return x * self.cos + y * self.sin, -x * self.sin + y * self.cos

    def from_frame(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(x east, y south) metres from the upper-left corner of frame points (u, v)."""
        return u * self.cos - v * self.sin, u * self.sin + v * self.cos

    def to_px(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Fractional (row, col) pixel coordinates of frame points (integers at pixel centres)."""
        x, y = self.from_frame(u, v)
        return y / self.gsd - 0.5, x / self.gsd - 0.5

    def uv_of(self, rr: np.ndarray, cc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """float32 frame coordinates (u, v) of the centres of pixels (``rr``, ``cc``)."""
        x = (cc.astype(np.float32) + 0.5) * self.gsd
        y = (rr.astype(np.float32) + 0.5) * self.gsd
        return self.to_frame(x, y)

    def fill(self, u: list[float] | np.ndarray, v: list[float] | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(rows, cols) of the pixels whose centres lie inside the frame polygon (``u``, ``v``) (metres)."""
        r, c = self.to_px(np.asarray(u, np.float64), np.asarray(v, np.float64))
        result: tuple[np.ndarray, np.ndarray] = polygon(r, c, self.shape)
        return result

    def fill_rect(self, u0: float, u1: float, v0: float, v1: float) -> tuple[np.ndarray, np.ndarray]:
        """(rows, cols) of the pixels inside the frame rectangle [u0, u1] × [v0, v1] (metres)."""
        return self.fill([u0, u1, u1, u0], [v0, v0, v1, v1])

    def window(self, u0: float, u1: float, v0: float, v1: float) -> Window | None:
        """Canvas pixels around the frame rectangle [u0, u1] × [v0, v1] (metres), or None if off the canvas."""
        x, y = self.from_frame(np.array([u0, u1, u1, u0]), np.array([v0, v0, v1, v1]))
        c0, c1 = int(math.floor(x.min() / self.gsd)), int(math.ceil(x.max() / self.gsd)) + 1
        r0, r1 = int(math.floor(y.min() / self.gsd)), int(math.ceil(y.max() / self.gsd)) + 1
        r0, c0, r1, c1 = max(r0, 0), max(c0, 0), min(r1, self.n), min(c1, self.n)
        if r0 >= r1 or c0 >= c1:
            return None
        rows, cols = slice(r0, r1), slice(c0, c1)
        return Window(rows, cols, self.u[rows, cols], self.v[rows, cols])

    def rect(self, u0: float, u1: float, v0: float, v1: float) -> tuple[Window, np.ndarray] | None:
        """The window of a frame rectangle and its bool (h, w) inside mask, or None if none of it is on the canvas."""
        win = self.window(u0, u1, v0, v1)
        if win is None:
            return None
        inside = (win.u >= u0) & (win.u < u1) & (win.v >= v0) & (win.v < v1)
        return (win, inside) if inside.any() else None

    def raise_top(self, rr: np.ndarray, cc: np.ndarray, height: np.ndarray,
                  label: int | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Make an object the top surface of pixels (``rr``, ``cc``) where it is higher than what is there.

        Args:
            rr, cc: int (K,) pixel rows and columns (each pixel once).
            height: float32 (K,) the object's height above ground at those pixels, metres.
            label: its class code, or None to keep the label underneath (a car on a road).

        Returns:
            bool (K,) where the object became the top, and the rows and columns of those pixels; the caller
            draws its colours there.
        """
        top = height > self.ndsm[rr, cc]
        rt, ct = rr[top], cc[top]
        self.ndsm[rt, ct] = height[top]
        if label is not None:
            self.labels[rt, ct] = label
        return top, rt, ct


__all__ = ["Canvas", "Window"]
