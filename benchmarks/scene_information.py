r"""The structure scenes split by the information their tiles hold, and the bound for one plane.

Issue 19's structure target is a median over every tile of every scene. Some scenes hold too
little per-tile information for any tile-wise estimator to reach it: a weak, low-contrast texture
under noise leaves the tile's Cramér-Rao standard deviation (section ``structure``'s per-tile
reference, the PSF shared by the image) at many percent. :func:`information_groups` splits the
scenes at :data:`POOR_SCENE_STD`: a scene whose median per-tile reference lies above it is
*information-poor*, because an unbiased estimator at the bound would have a median error there
above the 2 % target (``0.6745 sigma > 2 %``). :func:`information_rows` scores each group: its
share of the tiles, the score at the bound, each estimator's median error and confident share, and
the part of the error the scene's tiles share (the median over the scenes of the scene's median
signed error), which tells a scene-wide offset from per-tile noise.

:func:`plane_pooled_std` is the reference for an estimator told that the scene is one plane (a
slanted plane's inverse depth is affine in the image coordinates, ``data_synth.scenes``): the
per-tile information pooled under that model. It treats the tiles' errors as independent, with
the information of overlapping tiles divided by their overlap, and leaves the coupling through
the shared PSF out: a rough limit of what pooling along the structure could give, not a bound
any estimator here is held to.
"""

from __future__ import annotations

import math

import torch

from benchmarks.bench_bound import median_at_bound
from tdfd.dfd.inverse_variance import MEDIAN_ABS_NORMAL

__all__ = ["POOR_SCENE_STD", "scene_medians", "information_groups", "plane_pooled_std", "information_rows"]

#: the median per-tile Cramér-Rao standard deviation (relative) above which a scene is
#: information-poor: at the bound its median error would exceed issue 19's 2 % (2 % / 0.6745)
POOR_SCENE_STD = 0.02 / MEDIAN_ABS_NORMAL


def scene_medians(values: torch.Tensor, scene: torch.Tensor) -> dict[int, float]:
    """Each scene's median of ``values`` (finite ones; scenes with none are left out)."""
    out = {}
    for s in scene.unique().tolist():
        v = values[(scene == s) & torch.isfinite(values)]
        if v.numel():
            out[int(s)] = float(v.median())
    return out


def information_groups(bound: torch.Tensor, scene: torch.Tensor, limit: float = POOR_SCENE_STD
                       ) -> dict[str, torch.Tensor]:
    """Tile masks of the ``"informative"`` and ``"information-poor"`` scenes: a scene is poor when
    the median of its tiles' finite ``bound`` (relative standard deviations) exceeds ``limit``; a
    scene without a finite bound is in neither.

    Example:
        >>> g = information_groups(torch.tensor([0.01, 0.01, 0.2, 0.3]), torch.tensor([0, 0, 1, 1]))
        >>> g["informative"].tolist(), g["information-poor"].tolist()
        ([True, True, False, False], [False, False, True, True])

    Raises:
        ValueError: ``bound`` and ``scene`` of different shapes, or a ``limit`` not > 0.
    """
    if bound.shape != scene.shape:
        raise ValueError(f"bound {tuple(bound.shape)} and scene {tuple(scene.shape)} differ in shape")
    if not limit > 0:
        raise ValueError(f"the limit must be > 0, got {limit}")
    medians = scene_medians(bound, scene)
    poor = torch.tensor([medians.get(int(s), math.nan) > limit for s in scene.tolist()], dtype=torch.bool)
    known = torch.tensor([int(s) in medians for s in scene.tolist()], dtype=torch.bool)
    return {"informative": known & ~poor, "information-poor": poor}


def plane_pooled_std(std: torch.Tensor, q: torch.Tensor, rows: torch.Tensor, cols: torch.Tensor,
                     overlap: float) -> torch.Tensor:
    """Each tile's relative standard deviation of ``q`` when one plane ``q = a + b col + c row``
    is fitted to all the scene's tiles by their per-tile information.

    Args:
        std: ``(T,)`` each tile's relative standard deviation of ``q`` (``nan``/``inf``: no information).
        q: ``(T,)`` the tiles' true inverse depths (1/m).
        rows, cols: ``(T,)`` the tiles' grid positions.
        overlap: how many tiles cover a pixel, ``(tile / stride)^2``; each tile's information is
            divided by it.

    Returns:
        ``(T,)`` the pooled relative standard deviation (``inf`` with fewer than three informative
        tiles or tiles on one line).

    Example:
        >>> s = plane_pooled_std(torch.full((9,), 0.03), torch.ones(9), torch.arange(9) // 3, torch.arange(9) % 3, 1.0)
        >>> round(float(s[4]), 4)  # the centre of nine equal tiles: 0.03 / 3
        0.01

    Raises:
        ValueError: tensors of different shapes, or an overlap not >= 1.
    """
    if not (std.shape == q.shape == rows.shape == cols.shape) or std.ndim != 1:
        raise ValueError("std, q, rows and cols must be (T,) of one shape")
    if not overlap >= 1:
        raise ValueError(f"the overlap must be >= 1, got {overlap}")
    q = q.double()
    ok = torch.isfinite(std) & (std > 0)
    jac = torch.stack([torch.ones_like(q), cols.double(), rows.double()], 1)
    info = torch.where(ok, 1.0 / (std.double().clamp_min(1e-300) * q) ** 2, torch.zeros_like(q)) / overlap
    fisher = (jac * info[:, None]).T @ jac
    if int(ok.sum()) < 3 or torch.linalg.matrix_rank(fisher) < 3:
        return torch.full_like(q, math.inf)
    var = ((jac @ torch.linalg.inv(fisher)) * jac).sum(1)
    return var.clamp_min(0).sqrt() / q


def information_rows(groups: list[tuple[str, dict[str, torch.Tensor]]], estimators: tuple[str, ...],
                     confident: float, limit: float = POOR_SCENE_STD, target: float = 0.02) -> list[list[object]]:
    """Per layout (``groups``: name, flat tiles with ``true``, ``edge``, ``scene``, ``bound_shared``,
    each estimator and its ``_conf``, and ``plane_pooled`` where computed) and information group, the
    tiles away from edges: scenes, tiles and their share, the score at the bound (and at the
    pooled one-plane reference where every tile has one), then per estimator the median error, the
    share at confidence >= ``confident`` and the median over the scenes of ``|scene median signed
    error|``."""
    out = []
    for name, t in groups:
        away = ~t["edge"]
        split = information_groups(torch.where(away, t["bound_shared"], torch.full_like(t["bound_shared"], math.nan)),
                                   t["scene"], limit)
        total = int(away.sum())
        for label, mask in split.items():
            sel = mask & away & torch.isfinite(t["bound_shared"])
            if not bool(sel.any()):
                continue
            pooled = t.get("plane_pooled")
            plane = (f"{100 * median_at_bound(pooled[sel]):.2f} %"
                     if pooled is not None and bool(torch.isfinite(pooled[sel]).all()) else "-")
            count = int(sel.sum())
            cells = [name, label, len(t["scene"][sel].unique()), f"{count} ({100 * count / total:.0f} %)",
                     f"{100 * median_at_bound(t['bound_shared'][sel]):.2f} %", plane]
            for k in estimators:
                signed = t[k][sel] / t["true"][sel] - 1
                shared = torch.tensor(list(scene_medians(signed, t["scene"][sel]).values())).abs().median()
                share = float((t[f"{k}_conf"][sel] >= confident).double().mean())
                within = float((signed.abs() <= target).double().mean())
                cells.append(f"{100 * float(signed.abs().median()):.2f} %; {100 * within:.0f} %; {100 * share:.0f} %; "
                             f"{100 * float(shared):.2f} %")
            out.append(cells)
    return out
