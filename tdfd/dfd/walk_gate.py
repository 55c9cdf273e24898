r"""The walking window's check against the depth structure: a walked minimum that leads a tile away
from its fitted neighbours is a drift, not a rescue.

A seeded fit whose minimum lies on its window's edge may walk its window downhill
(:func:`tdfd.dfd.seeded_fit.seeded_tile_fit` with ``walk``), and the walked minimum counts only
when its likelihood gains :data:`~tdfd.dfd.seeded_fit.WALK_GAIN` nats. On the structure
benchmark's smooth surfaces that gate still let through walks that moved a tile 10-17 % away
from a good seed (``docs/BENCHMARKS.md``, section ``psf_structure``'s notes): a slanted or curved
tile's likelihood, fitted as a fronto-parallel one, can keep falling past the truth. A surface
is continuous almost everywhere, so the tile's neighbours whose own first windows held a
minimum say where it should be: the median of their inverse depths within :data:`WALK_RADIUS`
tiles (at least :data:`WALK_NEIGHBOURS` of them), the *consensus*. A walk is kept only when it
ends no farther from the consensus than the seed it left (:func:`walk_rejected`); where no
consensus exists (an occlusion layout's lone tile, a weak texture's sparse fits) the likelihood
gain alone decides.

Example:
    >>> import torch
    >>> q = torch.tensor([2.0, 2.0, 2.0, 2.0, 2.6])
    >>> rows, cols = torch.tensor([0, 0, 1, 1, 2]), torch.tensor([0, 1, 0, 1, 1])
    >>> c = neighbour_consensus(q, torch.tensor([True, True, True, False, False]), rows, cols, (3, 2))
    >>> c.tolist()[3:]
    [2.0, 2.0]
    >>> seed = torch.tensor([2.0, 2.0, 2.0, 2.1, 2.1])  # tile 3 walked towards 2.0, tile 4 away from it
    >>> walk_rejected(q, seed, c, torch.tensor([False, False, False, True, True])).tolist()
    [False, False, False, False, True]
"""

from __future__ import annotations

import math

import torch

from ..errors import InputError

__all__ = ["WALK_RADIUS", "WALK_NEIGHBOURS", "neighbour_consensus", "walk_rejected"]

#: How far, in tiles (each way), a tile's neighbours are taken from.
WALK_RADIUS = 2
#: How many neighbours with a first-window minimum make a consensus.
WALK_NEIGHBOURS = 3


def neighbour_consensus(q: torch.Tensor, usable: torch.Tensor, rows: torch.Tensor, cols: torch.Tensor,
                        grid: tuple[int, int], radius: int = WALK_RADIUS, least: int = WALK_NEIGHBOURS
                        ) -> torch.Tensor:
    """``(T,)`` the median ``q`` of each tile's ``usable`` neighbours within ``radius`` tiles on the
    ``grid`` (the tile itself left out), ``nan`` where fewer than ``least`` are usable.

    Args:
        q: ``(T,)`` the tiles' inverse depths (1/m).
        usable: ``(T,)`` bool, the tiles whose ``q`` may speak for their neighbours (e.g. a first
            window's minimum with a finite sigma).
        rows, cols: ``(T,)`` the tiles' cells on the ``(h, w)`` ``grid``.
        radius, least: the neighbourhood's half-width in tiles and the least count.

    Raises:
        InputError: tensors not ``(T,)``, cells off the grid or shared by two tiles, ``radius`` < 1
            or ``least`` < 1.
    """
    n = q.shape[0] if q.ndim == 1 else -1
    if n < 0 or any(t.shape != (n,) for t in (usable, rows, cols)) or usable.dtype != torch.bool:
        raise InputError(f"q, usable (bool), rows and cols must be (T,) alike, got {tuple(q.shape)}, "
                         f"{tuple(usable.shape)} {usable.dtype}, {tuple(rows.shape)}, {tuple(cols.shape)}")
    if radius < 1 or least < 1:
        raise InputError(f"radius and least must be >= 1, got {radius} and {least}")
    h, w = grid
    if n and (int(rows.min()) < 0 or int(cols.min()) < 0 or int(rows.max()) >= h or int(cols.max()) >= w):
        raise InputError(f"tile cells must lie on the {h}x{w} grid")
    cells = rows * w + cols
    if cells.unique().numel() != n:
        raise InputError("each tile must have a cell of its own on the grid")
    # each tile's (2 radius + 1)^2 window on the grid, its own cell left out: O(T) memory, not O(T^2)
    side = 2 * radius + 1
    on_grid = torch.full((h * w,), math.nan, dtype=torch.float64)
    on_grid[cells[usable]] = q.to(torch.float64)[usable]
    counted = torch.zeros(h * w, dtype=torch.float64)
    counted[cells[usable]] = 1.0

    def windows(x: torch.Tensor, fill: float) -> torch.Tensor:
        padded = torch.nn.functional.pad(x.reshape(1, 1, h, w), (radius,) * 4, value=fill)
        out = torch.nn.functional.unfold(padded, side)[0].T[cells]  # (T, side^2)
        out[:, side * side // 2] = fill
        return out

    values = windows(on_grid, math.nan)
    out = values.nanmedian(1).values if n else values.new_zeros(0)
    return torch.where(windows(counted, 0.0).sum(1) >= least, out, torch.full_like(out, math.nan))


def walk_rejected(q_walked: torch.Tensor, q_seed: torch.Tensor, consensus: torch.Tensor, walked: torch.Tensor
                  ) -> torch.Tensor:
    """``(T,)`` bool: the ``walked`` tiles whose walked ``q`` lies farther from their neighbours'
    ``consensus`` (:func:`neighbour_consensus`) than the seed they left; a tile without a
    consensus (``nan``) is never rejected."""
    far = (q_walked.to(torch.float64) - consensus).abs() > (q_seed.to(torch.float64) - consensus).abs()
    return walked & torch.isfinite(consensus) & far
