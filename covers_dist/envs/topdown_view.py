"""The square top-down view of the table, and the gripper disc drawn in it.

Pixel ``(i, j)`` of an ``S x S`` view samples the table point ``centre + ((j - c) p, (c - i) p)``
with ``c = (S - 1) / 2`` and pixel pitch ``p = 2 * half_width / S`` (x right, y up, as in
:mod:`covers_dist.symmetry`), so the group acts on the view exactly by rotating and flipping
pixels about its centre.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["TopDownView", "DISC_COLOR", "TABLE_COLOR", "VOID_COLOR", "draw_disc", "disc_pixels"]

#: Colour of the gripper disc (pure blue, as in the paper's real-robot images).
DISC_COLOR = np.array([0, 0, 255], dtype=np.uint8)
#: Uniform colour that replaces the table's wood texture.
TABLE_COLOR = np.array([100, 100, 100], dtype=np.uint8)
#: Colour where no geometry is seen (off the table).
VOID_COLOR = np.array([20, 20, 20], dtype=np.uint8)


@dataclass(frozen=True)
class TopDownView:
    """A square orthographic view of the table plane: ``size`` pixels over ``2 * half_width`` metres."""

    centre: tuple[float, float]
    half_width: float
    size: int

    def __post_init__(self) -> None:
        if not isinstance(self.size, (int, np.integer)) or self.size < 1:
            raise ValueError(f"view size must be a positive integer, got {self.size!r}")
        if not self.half_width > 0:
            raise ValueError(f"view half_width must be > 0, got {self.half_width!r}")

    @property
    def pitch(self) -> float:
        """Metres per pixel."""
        return 2.0 * self.half_width / self.size

    def to_pixels(self, xy: np.ndarray) -> np.ndarray:
        """World (x, y) -> continuous (column, row) pixel coordinates (pixel centres are integers)."""
        xy = np.asarray(xy, dtype=np.float64)
        c = (self.size - 1) / 2.0
        col = (xy[..., 0] - self.centre[0]) / self.pitch + c
        row = c - (xy[..., 1] - self.centre[1]) / self.pitch
        return np.stack([col, row], axis=-1)


def _disc_mask(cx: float, cy: float, radius_px: float, h: int, w: int) -> tuple[int, int, np.ndarray] | None:
    """(first row, first column, mask) of the pixels whose centres lie within ``radius_px`` of
    (``cx``, ``cy``) = (column, row); None when the disc misses the image."""
    r0, r1 = max(math.ceil(cy - radius_px), 0), min(math.floor(cy + radius_px), h - 1)
    c0, c1 = max(math.ceil(cx - radius_px), 0), min(math.floor(cx + radius_px), w - 1)
    if r0 > r1 or c0 > c1:
        return None
    dy = np.arange(r0, r1 + 1, dtype=np.float64) - cy
    dx = np.arange(c0, c1 + 1, dtype=np.float64) - cx
    return r0, c0, np.add.outer(dy * dy, dx * dx) <= radius_px * radius_px


def draw_disc(img: np.ndarray, centre_px: np.ndarray, radius_px: float, color: np.ndarray = DISC_COLOR) -> None:
    """Paint the pixels whose centres lie within ``radius_px`` of ``centre_px`` = (column, row)."""
    found = _disc_mask(float(centre_px[0]), float(centre_px[1]), radius_px, img.shape[0], img.shape[1])
    if found is not None:
        r0, c0, inside = found
        img[r0 : r0 + inside.shape[0], c0 : c0 + inside.shape[1]][inside] = color


def disc_pixels(view: TopDownView, xy: np.ndarray, radius: float) -> np.ndarray:
    """Flat indices (row * size + column) of the pixels that ``draw_disc`` paints for a disc of
    ``radius`` metres at world ``xy`` in ``view`` (the same arithmetic, so the same pixels)."""
    s = view.size
    c = (s - 1) / 2.0
    cx = (float(xy[0]) - view.centre[0]) / view.pitch + c
    cy = c - (float(xy[1]) - view.centre[1]) / view.pitch
    found = _disc_mask(cx, cy, radius / view.pitch, s, s)
    if found is None:
        return np.zeros(0, dtype=np.int64)
    r0, c0, inside = found
    rows, cols = np.nonzero(inside)
    return (rows + r0) * s + (cols + c0)
