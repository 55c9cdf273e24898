"""Occlusion edges of a true depth map, and the tiles near them.

A tile of the grid whose footprint straddles a depth discontinuity has no single true depth
(its two surfaces blur differently), so the structure benchmark reports the tiles within
``reach`` tiles of an occlusion edge apart from the others. Away from edges, a tile of a
slanted or curved surface still spans a range of depths (:func:`tile_depth_spread`).

A *discontinuity* is a step between two neighbouring pixels (along a row or a column) in
inverse depth ``q = 1/d``: relatively larger than ``jump`` and at least ``ratio`` times the
larger of the steps two pixels before and after it on the same line. The second condition
tells a step from a steep but smooth slope (a tilted plane or a curved relief changes by about
as much from pixel to pixel as two pixels away), whatever the slope; ``data_synth``'s
piecewise-planar layouts give one-pixel steps (each pixel belongs to one surface).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from tdfd.errors import InputError

__all__ = ["depth_discontinuities", "edge_tiles", "tile_depth_spread", "EDGE_JUMP", "EDGE_RATIO"]

#: smallest relative step of inverse depth between neighbouring pixels that counts as an edge
EDGE_JUMP = 0.01
#: a step must be this many times the steps two pixels before and after it on its line
EDGE_RATIO = 3.0


def _steps(q: torch.Tensor, dim: int, jump: float, ratio: float) -> torch.Tensor:
    """Boolean map of the steps along ``dim`` (-1 or -2), one shorter along it."""
    n = q.shape[dim]
    a, b = q.narrow(dim, 0, n - 1), q.narrow(dim, 1, n - 1)
    d = (b - a).abs()
    rel = d / torch.minimum(a, b)
    pad = [0, 0, 0, 0]
    pad[0 if dim == -1 else 2] = 2  # left / top
    pad[1 if dim == -1 else 3] = 2
    dp = F.pad(d[None], pad)[0]  # zeros beyond the border
    m = d.shape[dim]
    around = torch.maximum(dp.narrow(dim, 0, m), dp.narrow(dim, 4, m))
    return (rel > jump) & (d > ratio * around)


def depth_discontinuities(depth_m: torch.Tensor, jump: float = EDGE_JUMP, ratio: float = EDGE_RATIO) -> torch.Tensor:
    """Pixels next to a depth discontinuity (both pixels of each step).

    Args:
        depth_m: ``(H, W)`` true depth in metres (finite, > 0).
        jump: smallest relative step of inverse depth that counts.
        ratio: how much larger than the steps two pixels away it must be.

    Returns:
        ``(H, W)`` bool.

    Raises:
        InputError: not 2-D (at least 2x2 px), or a depth that is not finite and positive.

    Example:
        >>> d = torch.ones(4, 6); d[:, 3:] = 0.5  # a near surface from column 3 on
        >>> depth_discontinuities(d)[0].tolist()
        [False, False, True, True, False, False]
    """
    if depth_m.dim() != 2 or min(depth_m.shape) < 2:
        raise InputError(f"depth_m must be (H, W) with H, W >= 2, got {tuple(depth_m.shape)}")
    if not bool(torch.isfinite(depth_m).all()) or not bool((depth_m > 0).all()):
        raise InputError("depth_m must be finite and > 0")
    if not (jump > 0 and ratio >= 1):
        raise InputError(f"need jump > 0 and ratio >= 1, got {jump}, {ratio}")
    q = 1.0 / depth_m.double()
    out = torch.zeros_like(q, dtype=torch.bool)
    sx = _steps(q, -1, jump, ratio)
    sy = _steps(q, -2, jump, ratio)
    out[:, :-1] |= sx
    out[:, 1:] |= sx
    out[:-1, :] |= sy
    out[1:, :] |= sy
    return out


def edge_tiles(depth_m: torch.Tensor, tile: int, stride: int, reach: int = 1, jump: float = EDGE_JUMP,
               ratio: float = EDGE_RATIO) -> torch.Tensor:
    """Tiles within ``reach`` tiles of an occlusion edge: those whose ``(2 reach + 1)^2``
    neighbourhood of tiles covers a pixel of :func:`depth_discontinuities`.

    Args:
        depth_m: ``(H, W)`` true depth in metres.
        tile, stride: the tile grid (px); tile ``(i, j)`` covers rows ``i stride ... i stride + tile - 1``.
        reach: neighbourhood half-width in tiles (0: the tile's own footprint).

    Returns:
        ``(h, w)`` bool on the grid ``h = (H - tile) // stride + 1`` (likewise ``w``).

    Example:
        >>> d = torch.ones(64, 256); d[:, 200:] = 0.5
        >>> edge_tiles(d, 64, 32, reach=0).tolist(), edge_tiles(d, 64, 32).tolist()
        ([[False, False, False, False, False, True, True]], [[False, False, False, False, True, True, True]])
    """
    if tile < 1 or not 1 <= stride <= tile or reach < 0:
        raise InputError(f"need tile >= 1, 1 <= stride <= tile and reach >= 0, got {tile}, {stride}, {reach}")
    if depth_m.dim() != 2 or depth_m.shape[0] < tile or depth_m.shape[1] < tile:
        raise InputError(f"depth_m must be (H, W) of at least one tile ({tile} px), got {tuple(depth_m.shape)}")
    disc = depth_discontinuities(depth_m, jump, ratio).float()[None, None]
    own = F.max_pool2d(disc, tile, stride)
    if reach:
        own = F.max_pool2d(own, 2 * reach + 1, 1, reach)
    return own[0, 0] > 0


def tile_depth_spread(depth_m: torch.Tensor, tile: int, stride: int) -> torch.Tensor:
    """How much the inverse depth varies over each tile: ``(max q - min q) / q_tile``.

    ``q = 1/d``; ``q_tile`` is the tile's mean inverse depth (:func:`tdfd.grid.tile_true_depth`
    unweighted). 0 for a fronto-parallel face; a slanted tile's blur changes across it by this
    fraction of its mean.

    Args:
        depth_m: ``(H, W)`` true depth (m), finite and positive.
        tile, stride: the tile grid (px).

    Returns:
        ``(h, w)`` float64 relative spread per tile.

    Raises:
        InputError: a depth map that is not 2-D, finite and positive, or smaller than a tile.

    Example:
        >>> q = torch.linspace(2.0, 3.0, 128, dtype=torch.float64).expand(64, 128)  # a ramp in 1/d
        >>> tile_depth_spread(1.0 / q, 64, 64)  # each half spans 0.496 1/m, means 2.248 and 2.752 1/m
        tensor([[0.2207, 0.1803]], dtype=torch.float64)
    """
    d = torch.as_tensor(depth_m, dtype=torch.float64)
    if d.dim() != 2 or not bool(torch.isfinite(d).all()) or bool((d <= 0).any()):
        raise InputError("depth_m must be a finite, positive (H, W) map")
    if min(d.shape) < tile:
        raise InputError(f"depth map {tuple(d.shape)} is smaller than a {tile}-px tile")
    q = (1.0 / d)[None, None]
    q_max = F.max_pool2d(q, tile, stride)
    q_min = -F.max_pool2d(-q, tile, stride)
    return ((q_max - q_min) / F.avg_pool2d(q, tile, stride))[0, 0]
