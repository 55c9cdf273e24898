r"""The region of interest and its tiles: which tiles of the estimator's grid an ROI covers.

The tile grid is CONTRACT.md section 2's (:mod:`tdfd.grid`): tile ``(i, j)`` covers rows
``i*stride … i*stride + tile - 1`` of the frame (columns likewise).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import InputError

__all__ = ["Roi", "roi_tile_mask", "roi_crop_box"]


@dataclass(frozen=True)
class Roi:
    """A rectangular region of interest in frame pixels.

    Args:
        x: left column (px).
        y: top row (px).
        w: width (px).
        h: height (px).
    """

    x: int
    y: int
    w: int
    h: int

    def __post_init__(self) -> None:
        if self.w <= 0 or self.h <= 0 or self.x < 0 or self.y < 0:
            raise InputError(f"ROI must have x, y >= 0 and w, h > 0, got {self}")

    @classmethod
    def parse(cls, text: str) -> "Roi":
        """Parse ``"x,y,w,h"`` (pixels)."""
        try:
            x, y, w, h = (int(round(float(v))) for v in text.split(","))
        except ValueError:
            raise InputError(f"ROI must be 'x,y,w,h' in pixels, got {text!r}") from None
        return cls(x, y, w, h)

    @classmethod
    def centre(cls, frame_hw: tuple[int, int], fraction: float = 0.5) -> "Roi":
        """The centred ROI covering ``fraction`` of each side of a ``(H, W)`` frame."""
        hh, ww = frame_hw
        h, w = max(1, int(round(hh * fraction))), max(1, int(round(ww * fraction)))
        return cls((ww - w) // 2, (hh - h) // 2, w, h)

    def clip(self, frame_hw: tuple[int, int]) -> "Roi":
        """The ROI clipped to a ``(H, W)`` frame.

        Raises:
            InputError: if the ROI lies entirely outside the frame.
        """
        hh, ww = frame_hw
        x0, y0 = min(self.x, ww), min(self.y, hh)
        x1, y1 = min(self.x + self.w, ww), min(self.y + self.h, hh)
        if x1 <= x0 or y1 <= y0:
            raise InputError(f"ROI {self} lies outside the {hh}x{ww} frame")
        return Roi(x0, y0, x1 - x0, y1 - y0)

    def crop(self, image: np.ndarray) -> np.ndarray:
        """``image[..., y:y+h, x:x+w]`` (clipped to the image)."""
        r = self.clip(image.shape[-2:])
        return image[..., r.y : r.y + r.h, r.x : r.x + r.w]

    def __str__(self) -> str:
        return f"{self.x},{self.y},{self.w},{self.h}"


def _tile_range(start: int, length: int, n: int, tile: int, stride: int) -> tuple[int, int]:
    """First and last tile index (inclusive) whose centre lies in the pixels ``start … start + length - 1``.

    Pixel ``k`` spans ``[k - 0.5, k + 0.5)``; tile ``i``'s centre is ``i*stride + (tile-1)/2``.
    """
    c0 = (tile - 1) / 2.0
    lo = max(0, math.ceil((start - 0.5 - c0) / stride))
    hi = min(n - 1, math.ceil((start + length - 0.5 - c0) / stride) - 1)
    if hi < lo:  # no centre inside: the tile nearest to the middle
        k = min(max(int(round((start + (length - 1) / 2.0 - c0) / stride)), 0), n - 1)
        return k, k
    return lo, hi


def roi_tile_mask(roi: Roi | None, grid_hw: tuple[int, int], tile: int, stride: int,
                  offset: tuple[int, int] = (0, 0)) -> np.ndarray:
    """Boolean ``(h, w)`` mask of the tiles whose centre lies inside ``roi``.

    Tile ``(i, j)`` covers rows ``offset[0] + i*stride … + tile - 1`` of the frame
    (CONTRACT.md section 2; ``offset`` is the origin of a crop the grid was computed on).
    If no tile centre falls inside a small ROI, the tile whose centre is nearest to the
    ROI centre is used. ``roi=None`` selects every tile.

    Example:
        >>> int(roi_tile_mask(Roi(64, 64, 64, 64), (5, 5), 64, 32).sum())
        4
    """
    gh, gw = grid_hw
    if roi is None:
        return np.ones((gh, gw), bool)
    r0, r1 = _tile_range(roi.y - offset[0], roi.h, gh, tile, stride)
    c0, c1 = _tile_range(roi.x - offset[1], roi.w, gw, tile, stride)
    mask = np.zeros((gh, gw), bool)
    mask[r0 : r1 + 1, c0 : c1 + 1] = True
    return mask


def roi_crop_box(roi: Roi, frame_hw: tuple[int, int], tile: int, stride: int) -> tuple[int, int, int, int]:
    """The smallest grid-aligned crop ``(y0, y1, x0, x1)`` holding every tile of :func:`roi_tile_mask`.

    Running the estimator on ``frame[y0:y1, x0:x1]`` gives exactly those tiles (the crop
    starts on a multiple of ``stride``), at a fraction of the full frame's cost.

    Example:
        >>> roi_crop_box(Roi(80, 64, 160, 128), (256, 320), 64, 32)
        (32, 192, 64, 256)
    """
    from ..grid import grid_shape  # tdfd.grid imports torch: only where needed (the hardware loop runs without it)

    gh, gw = grid_shape(frame_hw[0], frame_hw[1], tile, stride)
    r0, r1 = _tile_range(roi.y, roi.h, gh, tile, stride)
    c0, c1 = _tile_range(roi.x, roi.w, gw, tile, stride)
    return r0 * stride, r1 * stride + tile, c0 * stride, c1 * stride + tile
