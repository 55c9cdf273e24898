r"""One robust depth for an ROI from the estimator's per-tile depth and confidence."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import InputError

__all__ = ["DepthAggregate", "aggregate_depth"]


@dataclass(frozen=True)
class DepthAggregate:
    """A robust depth for a region of the tile grid.

    Attributes:
        depth_m: aggregated object distance (m); ``inf`` if the inverse depth is <= 0.
        inverse_depth: aggregated ``1/d_o`` (1/m, i.e. dioptres of defocus).
        confidence: mean tile confidence over the region, in [0, 1].
        spread_dpt: confidence-weighted standard deviation of the inliers' inverse depth (1/m).
        tiles: tiles in the region.
        inliers: tiles kept after trimming.
    """

    depth_m: float
    inverse_depth: float
    confidence: float
    spread_dpt: float
    tiles: int
    inliers: int


def _weighted_median(values: np.ndarray, weights: np.ndarray) -> float:
    order = np.argsort(values, kind="stable")
    v, w = values[order], weights[order]
    cum = np.cumsum(w)
    half = 0.5 * cum[-1]
    k = int(np.searchsorted(cum, half))
    # average the two middle values when the half-weight falls exactly on a boundary
    if k + 1 < len(v) and math.isclose(cum[k], half, rel_tol=1e-12, abs_tol=0.0):
        return float(0.5 * (v[k] + v[k + 1]))
    return float(v[min(k, len(v) - 1)])


def aggregate_depth(depth_m: np.ndarray, confidence: np.ndarray, mask: np.ndarray | None = None, *,
                    trim_sigmas: float = 3.0, min_trim_dpt: float = 0.05) -> DepthAggregate:
    r"""Confidence-weighted, outlier-robust depth of a region of the tile grid.

    Works in inverse depth ``q = 1/d_o``, where blur and the in-focus power are linear
    (paper eq. 4). First the confidence-weighted median ``q_med`` and the weighted median
    absolute deviation ``MAD``; tiles with ``|q - q_med| > max(trim_sigmas * 1.4826 MAD,
    min_trim_dpt)`` are dropped; the result is the confidence-weighted mean of the rest.

    Args:
        depth_m: ``(h, w)`` depth per tile in metres (> 0; non-finite tiles are ignored).
        confidence: ``(h, w)`` confidence per tile in [0, 1].
        mask: ``(h, w)`` boolean region (default: every tile).
        trim_sigmas: inlier half-width in robust standard deviations.
        min_trim_dpt: lower bound of the inlier half-width in 1/m.

    Returns:
        A :class:`DepthAggregate`. With zero total confidence the unweighted median is used
        and ``confidence`` is 0.

    Raises:
        InputError: shapes disagree or the region holds no finite tile.

    Example:
        >>> d = np.full((3, 3), 0.5); d[0, 0] = 5.0          # one wild outlier
        >>> c = np.full((3, 3), 0.8); c[1, 1] = 0.0
        >>> a = aggregate_depth(d, c)
        >>> round(a.depth_m, 6), a.inliers, a.tiles
        (0.5, 8, 9)
    """
    depth_m = np.asarray(depth_m, dtype=np.float64)
    confidence = np.asarray(confidence, dtype=np.float64)
    if depth_m.shape != confidence.shape or depth_m.ndim != 2:
        raise InputError(f"depth and confidence must be (h, w) of one shape, got {depth_m.shape} and {confidence.shape}")
    if mask is None:
        mask = np.ones(depth_m.shape, bool)
    elif mask.shape != depth_m.shape:
        raise InputError(f"mask shape {mask.shape} differs from the grid {depth_m.shape}")
    sel = mask & np.isfinite(depth_m) & (depth_m > 0) & np.isfinite(confidence)
    n = int(mask.sum())
    if not sel.any():
        raise InputError("the region holds no tile with a finite, positive depth")
    q = 1.0 / depth_m[sel]
    w = np.clip(confidence[sel], 0.0, 1.0)
    mean_conf = float(np.clip(np.where(np.isfinite(confidence[mask]), confidence[mask], 0.0), 0, 1).mean())
    if w.sum() <= 0:
        w = np.ones_like(q)
        mean_conf = 0.0
    med = _weighted_median(q, w)
    mad = _weighted_median(np.abs(q - med), w)
    half = max(trim_sigmas * 1.4826 * mad, min_trim_dpt)
    keep = np.abs(q - med) <= half
    wk, qk = w[keep], q[keep]
    qa = float(np.sum(wk * qk) / np.sum(wk)) if wk.sum() > 0 else med
    spread = float(np.sqrt(np.sum(wk * (qk - qa) ** 2) / np.sum(wk))) if wk.sum() > 0 else 0.0
    return DepthAggregate(depth_m=1.0 / qa if qa > 0 else math.inf, inverse_depth=qa, confidence=mean_conf,
                          spread_dpt=spread, tiles=n, inliers=int(keep.sum()))
