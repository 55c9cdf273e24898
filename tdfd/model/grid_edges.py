"""Where a tile lies in its grid: distances to the grid's four edges as feature maps.

The refinement CNN pads its 3x3 convolutions by replicating the border tiles, and the
pooled-context fits (:func:`tdfd.model.combined.pool_measurements`) average fewer tiles
near the frame's edge. Neither tells the network that a tile *is* near an edge: a border
tile of a 7x7 grid and an inner tile of a 14x19 grid look alike to it, although the first
has fewer real neighbours and errs more (2.42 % against 2.0-2.1 % on the refinement
benchmark's planes, 2026-11-26). :func:`edge_distance_maps` gives the network that
knowledge as four constant-per-tile channels, one per side, so it can weigh its padded
neighbourhood accordingly.

Both functions build the distances from cumulative sums of ones, with no shape arithmetic,
so an exported ONNX graph computes them for any grid size.

Example:
    >>> import torch
    >>> edge_distance_maps(torch.zeros(1, 1, 2, 3), limit=2)[0, :, 0]
    tensor([[0.0000, 0.0000, 0.0000],
            [0.5000, 0.5000, 0.5000],
            [0.0000, 0.5000, 1.0000],
            [1.0000, 0.5000, 0.0000]])
"""

from __future__ import annotations

import torch

from ..errors import InputError

__all__ = ["NUM_EDGE_CHANNELS", "edge_distance_maps", "append_edge_maps", "tile_border_distance"]

#: channels that :func:`append_edge_maps` adds: distance to the top, bottom, left and right edge
NUM_EDGE_CHANNELS = 4


def _side_distances(grid: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(from_top, from_bottom, from_left, from_right)``, each ``(1, 1, h, w)``, in cells."""
    if grid.dim() != 4:
        raise InputError(f"grid must be (B, C, h, w), got shape {tuple(grid.shape)}")
    ones = torch.ones_like(grid[:1, :1])
    row = ones.cumsum(2)  # 1 .. h down the rows
    col = ones.cumsum(3)
    return row - 1, ones.sum(2, keepdim=True) - row, col - 1, ones.sum(3, keepdim=True) - col


def tile_border_distance(grid: torch.Tensor) -> torch.Tensor:
    """Each cell's distance, in cells, to the nearest edge of a ``(B, C, h, w)`` grid.

    Args:
        grid: ``(B, C, h, w)``; only its shape, dtype and device are used.

    Returns:
        ``(1, 1, h, w)`` of ``grid``'s dtype: ``min(i, h - 1 - i, j, w - 1 - j)``.

    Example:
        >>> tile_border_distance(torch.zeros(1, 1, 3, 4))[0, 0]
        tensor([[0., 0., 0., 0.],
                [0., 1., 1., 0.],
                [0., 0., 0., 0.]])
    """
    top, bottom, left, right = _side_distances(grid)
    return torch.minimum(torch.minimum(top, bottom), torch.minimum(left, right))


def edge_distance_maps(grid: torch.Tensor, limit: int) -> torch.Tensor:
    """Each cell's distance to each edge of its grid, in cells, held at ``limit`` and divided by it.

    Args:
        grid: ``(B, C, h, w)``; only its shape, dtype and device are used.
        limit: distance (cells, >= 1) beyond which a cell counts as inner on that side.

    Returns:
        ``(1, 4, h, w)`` in [0, 1]: ``min(d, limit) / limit`` for the distance ``d`` to the
        top, bottom, left and right edge (0 on that edge, 1 at ``limit`` cells or more).

    Raises:
        InputError: ``grid`` not 4-D, or ``limit`` not a positive integer.
    """
    if isinstance(limit, bool) or not isinstance(limit, int) or limit < 1:
        raise InputError(f"edge limit must be a positive integer (cells), got {limit!r}")
    return torch.cat([d.clamp(max=float(limit)) for d in _side_distances(grid)], 1) / float(limit)


def append_edge_maps(features: torch.Tensor, limit: int) -> torch.Tensor:
    """``features`` ``(B, C, h, w)`` with :func:`edge_distance_maps` appended: ``(B, C + 4, h, w)``.

    Example:
        >>> append_edge_maps(torch.zeros(2, 5, 3, 4), limit=3).shape
        torch.Size([2, 9, 3, 4])
    """
    maps = edge_distance_maps(features, limit)
    return torch.cat([features, maps.expand(features.shape[0], -1, -1, -1)], 1)
