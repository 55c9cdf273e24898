"""The tile grid shared by the analytic DFD, the CNN, the ONNX contract and the datasets.

A ``(H, W)`` image with tile size ``T`` and stride ``S`` has ``h = floor((H - T) / S) + 1``
rows of tiles (likewise ``w``); cell ``(i, j)`` covers rows ``i*S … i*S + T - 1`` and the
same for columns (``CONTRACT.md`` section 2).

Example:
    >>> grid_shape(480, 640, tile=64, stride=32)
    (14, 19)
    >>> import torch
    >>> tile_mean(torch.ones(1, 1, 96, 96), 64, 32).shape
    torch.Size([1, 1, 2, 2])
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from .errors import InputError, ShapeError

__all__ = ["grid_shape", "check_grid", "tile_mean", "tile_true_depth", "tile_centres"]


def check_grid(tile: int, stride: int) -> None:
    """Raise :class:`~tdfd.errors.InputError` unless ``tile`` and ``stride`` are valid."""
    if int(tile) != tile or int(stride) != stride or tile < 8 or stride < 1 or stride > tile:
        raise InputError(f"tile must be an integer >= 8 and stride an integer in [1, tile], got tile={tile}, stride={stride}")


def grid_shape(height: int, width: int, tile: int, stride: int) -> tuple[int, int]:
    """Tile-grid shape ``(h, w)`` for an image of ``height`` x ``width`` pixels.

    Raises:
        ShapeError: if the image is smaller than one tile.
    """
    check_grid(tile, stride)
    if height < tile or width < tile:
        raise ShapeError(f"image {height}x{width} is smaller than one {tile}x{tile} tile")
    return (height - tile) // stride + 1, (width - tile) // stride + 1


def tile_mean(x: torch.Tensor, tile: int, stride: int, weight: torch.Tensor | None = None) -> torch.Tensor:
    """Mean of ``x`` ``(B, C, H, W)`` over each tile, optionally weighted by a ``(T, T)`` window.

    Returns:
        ``(B, C, h, w)`` on the contract grid.
    """
    if x.ndim != 4:
        raise ShapeError(f"expected (B, C, H, W), got {tuple(x.shape)}")
    grid_shape(x.shape[-2], x.shape[-1], tile, stride)
    b, c, h, w = x.shape
    if weight is None:
        return F.avg_pool2d(x, tile, stride)
    if weight.shape != (tile, tile):
        raise ShapeError(f"weight must be ({tile}, {tile}), got {tuple(weight.shape)}")
    k = (weight / weight.sum()).to(x)[None, None]
    return F.conv2d(x.reshape(b * c, 1, h, w), k, stride=stride).reshape(b, c, *grid_shape(h, w, tile, stride))


def tile_true_depth(depth_m: torch.Tensor, tile: int, stride: int, weight: torch.Tensor | None = None) -> torch.Tensor:
    """Ground-truth depth per tile: the (window-weighted) mean of **inverse** depth, inverted.

    Blur is linear in inverse depth (paper eq. 4), so this is the depth whose blur the tile
    shows on average.
    """
    if not torch.isfinite(depth_m).all() or bool((depth_m <= 0).any()):
        raise InputError("depth_m must be finite and > 0")
    return 1.0 / tile_mean(1.0 / depth_m, tile, stride, weight)


def tile_centres(height: int, width: int, tile: int, stride: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixel coordinates (row, column) of tile centres, each 1-D, in pixels."""
    h, w = grid_shape(height, width, tile, stride)
    return (torch.arange(h) * stride + (tile - 1) / 2.0, torch.arange(w) * stride + (tile - 1) / 2.0)
