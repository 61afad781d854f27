"""A tiny numpy rasterizer for ``render_mode="rgb_array"`` (no pygame, no display): anti-aliasing-free
discs, thick segments and polygons drawn by distance tests on the pixel grid."""

from __future__ import annotations

import numpy as np

__all__ = ["Canvas"]


class Canvas:
    """An ``(size, size, 3)`` uint8 image of the world square ``[-extent, extent]²`` (y up)."""

    def __init__(self, size: int = 256, extent: float = 2.5, background=(255, 255, 255)):
        self.size, self.extent = size, extent
        self.img = np.empty((size, size, 3), np.uint8)
        self.img[...] = background
        c = (np.arange(size) + 0.5) / size * 2 * extent - extent
        self.X, self.Y = np.meshgrid(c, -c)  # row 0 is the top of the image

    def _paint(self, mask: np.ndarray, color) -> None:
        self.img[mask] = color

    def disc(self, center, radius: float, color) -> None:
        cx, cy = float(center[0]), float(center[1])
        self._paint((self.X - cx) ** 2 + (self.Y - cy) ** 2 <= radius * radius, color)

    def segment(self, p0, p1, width: float, color) -> None:
        ax, ay, bx, by = float(p0[0]), float(p0[1]), float(p1[0]), float(p1[1])
        dx, dy = bx - ax, by - ay
        L2 = dx * dx + dy * dy
        if L2 == 0:
            t = np.zeros_like(self.X)
        else:
            t = np.clip(((self.X - ax) * dx + (self.Y - ay) * dy) / L2, 0, 1)
        self._paint((self.X - ax - t * dx) ** 2 + (self.Y - ay - t * dy) ** 2 <= (width / 2) ** 2, color)

    def rectangle(self, center, half_w: float, half_h: float, angle: float, color) -> None:
        c, s = np.cos(angle), np.sin(angle)
        u = (self.X - center[0]) * c + (self.Y - center[1]) * s
        v = -(self.X - center[0]) * s + (self.Y - center[1]) * c
        self._paint((np.abs(u) <= half_w) & (np.abs(v) <= half_h), color)

    def hline(self, y: float, color, width: float = 0.02) -> None:
        self._paint(np.abs(self.Y - y) <= width / 2, color)
