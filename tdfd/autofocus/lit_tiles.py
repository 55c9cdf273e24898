r"""Which tiles an assist light's pattern covers, and the ambient-subtracted frame.

A sparse pattern (the paper's two bars, stripes tens of pixels wide) on a dark,
texture-less target gives a defocus cue only where its edges are. The depth of such an
ROI must come from those tiles: a tile with no pattern edge has nothing to measure, and
whatever depth the estimator writes there must not vote.

The pattern is found without any model of it: the lit frame minus the ambient (light
off) frame at the **same lens power** is the pattern times the albedo, blurred by the
camera, plus noise. A tile is *lit* when the standard deviation of that difference
inside it stands clear of the noise: ``var_tile - s^2 > (k s)^2`` with ``s`` the noise
of the difference (robust, from its diagonal second differences), and at least
``rel`` of the strongest tile's pattern contrast. A flat tile inside a bright bar has no
contrast and is not counted either: it carries no cue.

Example:
    >>> import numpy as np
    >>> rng = np.random.default_rng(0)
    >>> ambient = 0.3 + 0.005 * rng.standard_normal((128, 160))
    >>> lit = ambient + 0.005 * rng.standard_normal((128, 160))
    >>> lit[:, 40:70] += 0.4                                 # one bright stripe, two edges
    >>> lit_tile_mask(lit, ambient, 64, 32).astype(int)
    array([[1, 1, 1, 0],
           [1, 1, 1, 0],
           [1, 1, 1, 0]])
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..region_fusion import RegionFit, fuse_inverse_depths, fusion_weight
from ..errors import InputError, ShapeError
from .aggregate import DepthAggregate, aggregate_depth

#: a tile confidence the shipped model reaches only where it is right: on held-out planes its
#: tiles above 0.1 have a median error of 1.6 % (tdfd.runtime, models/reference_report.md).
CONFIDENT_TILE = 0.1

__all__ = ["lit_tile_mask", "pair_cue_mask", "pool_lit_tiles", "fuse_with_region", "cue_touches_border", "CONFIDENT_TILE", "pattern_contrast",
           "subtract_ambient", "difference_noise_sigma"]


def difference_noise_sigma(diff: np.ndarray) -> float:
    """Robust white-noise standard deviation of an image (from the MAD of its diagonal
    second difference, whose pass band holds little of a blurred pattern's signal)."""
    x = np.asarray(diff, dtype=np.float64)
    d = x[:-1, :-1] - x[1:, :-1] - x[:-1, 1:] + x[1:, 1:]
    mad = float(np.median(np.abs(d - np.median(d))))
    return mad / 0.6745 / 2.0


def pattern_contrast(lit: np.ndarray, ambient: np.ndarray, tile: int, stride: int) -> tuple[np.ndarray, float]:
    """Per-tile standard deviation of ``lit - ambient`` on the tile grid, and its noise.

    Args:
        lit: ``(H, W)`` frame with the light on.
        ambient: ``(H, W)`` frame with the light off, at the same lens power.
        tile, stride: the estimator's grid (px); tile ``(i, j)`` covers rows
            ``i*stride ... i*stride + tile - 1`` (CONTRACT.md section 2).

    Returns:
        ``(std (h, w), noise sigma)`` in intensity units.
    """
    a, b = np.asarray(lit, dtype=np.float64), np.asarray(ambient, dtype=np.float64)
    if a.shape != b.shape or a.ndim != 2:
        raise ShapeError(f"lit and ambient frames must be (H, W) of one shape, got {a.shape} and {b.shape}")
    diff = a - b
    return _tile_std(diff, tile, stride), difference_noise_sigma(diff)


def _cue_mask(std: np.ndarray, sigma: float, k_noise: float, rel: float) -> np.ndarray:
    """The tiles whose contrast (``std`` less the noise ``sigma``) stands ``k_noise`` sigmas
    clear of the noise and at least ``rel`` of the strongest tile's."""
    signal = np.sqrt(np.clip(std**2 - sigma**2, 0.0, None))
    peak = float(signal.max()) if signal.size else 0.0
    return (signal > k_noise * sigma) & (signal >= rel * peak) & (signal > 0)


def lit_tile_mask(lit: np.ndarray, ambient: np.ndarray, tile: int, stride: int, k_noise: float = 3.0,
                  rel: float = 0.05) -> np.ndarray:
    """Boolean ``(h, w)`` mask of the tiles the pattern's contrast covers (module docs).

    Args:
        lit, ambient: ``(H, W)`` frames with the light on and off at one lens power.
        tile, stride: the estimator's grid (px).
        k_noise: pattern contrast needed, in noise standard deviations.
        rel: pattern contrast needed, as a fraction of the strongest tile's.
    """
    std, sigma = pattern_contrast(lit, ambient, tile, stride)
    return _cue_mask(std, sigma, k_noise, rel)


def _tile_std(image: np.ndarray, tile: int, stride: int) -> np.ndarray:
    """Per-tile standard deviation of an ``(H, W)`` image on the tile grid ``(h, w)``."""
    x = np.asarray(image, dtype=np.float64)
    if x.ndim != 2:
        raise ShapeError(f"frames must be (H, W), got {x.shape}")
    if min(x.shape) < tile:
        raise ShapeError(f"frames {x.shape} are smaller than one {tile} px tile")
    h, w = (x.shape[0] - tile) // stride + 1, (x.shape[1] - tile) // stride + 1  # CONTRACT.md section 2
    return np.lib.stride_tricks.sliding_window_view(x, (tile, tile))[::stride, ::stride][:h, :w].std(axis=(-2, -1))


def pair_cue_mask(image_f1: np.ndarray, image_f2: np.ndarray, tile: int, stride: int, k_noise: float = 3.0,
                  rel: float = 0.05) -> np.ndarray:
    """Boolean ``(h, w)`` mask of the tiles with a cue in a lit DFD pair, without an ambient frame.

    The same test as :func:`lit_tile_mask`, on each lit frame itself: a tile counts when
    its standard deviation stands ``k_noise`` noise sigmas clear of the frame's noise
    (:func:`difference_noise_sigma` of the frame: a texture-less target's ambient image is
    flat, so what a tile shows over the noise is the pattern's edges, or a texture) and is
    at least ``rel`` of the frame's strongest tile; a tile counts if it does in either
    frame (the sharper frame shows the narrow pattern, the blurred one keeps its wide
    edges). A flat tile inside a bright bar has no contrast and does not count.

    Args:
        image_f1, image_f2: ``(H, W)`` lit frames at the two powers.
        tile, stride: the estimator's grid (px).
        k_noise, rel: as :func:`lit_tile_mask`.

    Example:
        >>> rng = np.random.default_rng(0)
        >>> f1 = 0.3 + 0.005 * rng.standard_normal((128, 160))
        >>> f1[:, 40:70] += 0.4                                  # the pattern: one stripe
        >>> f2 = 0.3 + 0.005 * rng.standard_normal((128, 160))   # (no cue in f2 at all)
        >>> pair_cue_mask(f1, f2, 64, 32).astype(int)
        array([[1, 1, 1, 0],
               [1, 1, 1, 0],
               [1, 1, 1, 0]])
    """
    a, b = np.asarray(image_f1, dtype=np.float64), np.asarray(image_f2, dtype=np.float64)
    if a.shape != b.shape:
        raise ShapeError(f"the two frames must have one shape, got {a.shape} and {b.shape}")
    return (_cue_mask(_tile_std(a, tile, stride), difference_noise_sigma(a), k_noise, rel)
            | _cue_mask(_tile_std(b, tile, stride), difference_noise_sigma(b), k_noise, rel))


def pool_lit_tiles(depth_m: np.ndarray, confidence: np.ndarray, lit: np.ndarray,
                   roi: np.ndarray | None = None) -> tuple[DepthAggregate, np.ndarray]:
    """The depth of a lit ROI from the tiles with a cue only: the one pooling of lit tiles.

    The autofocus (:class:`~tdfd.autofocus.assist.AssistedDFDController`) and the paper
    experiment's ROI estimate (``benchmarks/paper_experiment.py``) both pool this way:
    :func:`~tdfd.autofocus.aggregate.aggregate_depth` (confidence-weighted median of
    inverse depth, trimmed weighted mean) over the lit tiles of the ROI; a tile without a
    cue gives no depth, confident or not.

    Args:
        depth_m, confidence: ``(h, w)`` the estimator's tile grid.
        lit: ``(h, w)`` bool, the tiles with a cue (:func:`lit_tile_mask` or :func:`pair_cue_mask`).
        roi: ``(h, w)`` bool, the ROI's tiles (default: all).

    Returns:
        ``(aggregate, pooled mask)``; with no lit tile in the ROI the aggregate has NaN depth,
        zero confidence and no inliers (a caller treats it as no estimate).

    Example:
        >>> depth = np.array([[0.5, 0.5, 2.0]]); conf = np.array([[0.2, 0.3, 0.9]])
        >>> agg, used = pool_lit_tiles(depth, conf, np.array([[True, True, False]]))
        >>> round(agg.depth_m, 3), used.astype(int).tolist()
        (0.5, [[1, 1, 0]])
    """
    lit = np.asarray(lit, dtype=bool)
    mask = lit if roi is None else lit & np.asarray(roi, dtype=bool)
    if mask.shape != np.shape(depth_m) or mask.shape != np.shape(confidence):
        raise ShapeError(f"depth {np.shape(depth_m)}, confidence {np.shape(confidence)} and lit tiles {mask.shape} "
                         "must share the tile grid")
    tiles = int(mask.size if roi is None else np.asarray(roi, dtype=bool).sum())
    if not mask.any():
        return DepthAggregate(depth_m=float("nan"), inverse_depth=float("nan"), confidence=0.0,
                              spread_dpt=float("nan"), tiles=tiles, inliers=0), mask
    return aggregate_depth(depth_m, confidence, mask), mask


def fuse_with_region(pooled: DepthAggregate, tiles_sigma_dpt: float, region: RegionFit,
                     max_discrepancy: float = 3.0) -> tuple[DepthAggregate, float]:
    """The lit ROI's depth from its pooled tiles and one region fit together (:mod:`tdfd.region_fusion`).

    The pooled tiles' inverse depth (standard deviation ``tiles_sigma_dpt``: with a model's
    tiles :attr:`tdfd.autofocus.evidence.FocusUncertainty.std_dpt`, where the model's Laplace
    scale counts sqrt(2) times) and the region's are combined as
    two correlated estimates: the tiles' pixels are the region's, so the region's statistical
    error (:attr:`~tdfd.region_fusion.RegionFit.noise_sigma_dpt`, capped at the tiles' own) is
    their covariance (:mod:`tdfd.region_fusion`); tiles noisier than that add only where the
    region has a systematic term (``mu``, a disk lens). The aggregate keeps the tiles'
    confidence, spread and counts (what the controller's trust rules read), only its depth
    changes. When the two disagree by more than ``max_discrepancy`` standard deviations of
    their difference the region is not used: one fit over an ROI that holds more than one
    depth (an occluder, a slanted or textured background under the pattern) mixes them, where
    the tiles' robust pooling does not.

    Args:
        pooled: :func:`pool_lit_tiles`'s aggregate (a NaN depth: no lit tile, the region alone).
        tiles_sigma_dpt: its standard deviation (dpt; ``inf``: no weight).
        region: :func:`tdfd.dfd.region_fit.fit_region` over the ROI.
        max_discrepancy: the disagreement (in standard deviations of the difference) beyond
            which the region is left out.

    Returns:
        ``(aggregate, region weight)``: the fused aggregate and the region's share of the weight in [0, 1].

    Example:
        >>> pooled = DepthAggregate(0.5, 2.0, 0.3, 0.01, 9, 9)
        >>> fused, w = fuse_with_region(pooled, 0.03, RegionFit(2.04, 0.01, 0.004, 0.9, 512))
        >>> round(fused.inverse_depth, 3), round(w, 2), fused.confidence
        (2.038, 0.96, 0.3)
        >>> fuse_with_region(pooled, 0.03, RegionFit(2.5, 0.01, 0.004, 0.9, 512))[1]   # 16 sigmas apart: left out
        0.0
    """
    q_t = pooled.inverse_depth
    s_t = tiles_sigma_dpt if math.isfinite(q_t) and q_t > 0 else math.inf
    if math.isnan(s_t) or s_t <= 0:
        raise InputError(f"tiles_sigma_dpt must be > 0, got {tiles_sigma_dpt}")
    q_t = q_t if math.isfinite(q_t) else 0.0
    shared = min(region.noise_sigma_dpt, s_t, region.sigma_dpt) ** 2  # the tiles' pixels are the region's
    q, _, chi = fuse_inverse_depths(q_t, s_t, region.inverse_depth, region.sigma_dpt, covariance=shared)
    if chi > max_discrepancy:
        return pooled, 0.0
    w_r = fusion_weight(region.sigma_dpt, s_t, shared)
    depth = 1.0 / q if q > 0 else math.inf
    return dataclasses.replace(pooled, depth_m=depth, inverse_depth=q), w_r


def cue_touches_border(cue: np.ndarray, roi_tiles: np.ndarray) -> bool:
    """Whether a tile with a cue lies on the outer ring of the ROI's tiles: the pattern (or a
    texture) reaches beyond the region, and one fit over the region would cut it (paper sec. 4:
    one region *covering* the pattern). ``cue``, ``roi_tiles``: ``(h, w)`` bool tile masks.

    Example:
        >>> roi = np.ones((5, 6), bool); cue = np.zeros((5, 6), bool); cue[2, 2:4] = True
        >>> cue_touches_border(cue, roi)
        False
        >>> cue[2, 5] = True
        >>> cue_touches_border(cue, roi)
        True
    """
    rows, cols = np.nonzero(roi_tiles)
    if rows.size == 0:
        return True
    r0, r1, c0, c1 = rows.min(), rows.max(), cols.min(), cols.max()
    inner = np.zeros_like(roi_tiles, dtype=bool)
    inner[r0 + 1:r1, c0 + 1:c1] = True
    return bool((cue & roi_tiles & ~inner).any())


def subtract_ambient(lit: np.ndarray, ambient: np.ndarray, pedestal: float = 0.02) -> np.ndarray:
    """``clip(lit - ambient + pedestal, 0, 1)`` as float32: the pattern alone on a small
    pedestal (which keeps the noise of the dark parts from being clipped at zero)."""
    a, b = np.asarray(lit, dtype=np.float32), np.asarray(ambient, dtype=np.float32)
    if a.shape != b.shape:
        raise ShapeError(f"lit and ambient frames must have one shape, got {a.shape} and {b.shape}")
    return np.clip(a - b + np.float32(pedestal), 0.0, 1.0)
