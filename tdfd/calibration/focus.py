r"""Depth from focus for calibration: each region's sharpness peak along a focus sweep.

The focus measure of a region is the energy of the image Laplacian over the region,
divided by the squared region mean (gain invariant). For a symmetric PSF whose size grows
with ``|P - P*|`` (paper eq. 3: ``r_b`` is linear in the lens power) the measure is an
even function of ``P - P*``, so its peak ``P*`` is the in-focus power. The peak is found to
a fraction of the sweep step by **mirror symmetry**: ``P*`` minimises the mismatch between
the log focus curve and its reflection about ``P*`` (linear interpolation), over the points
within a few steps of the maximum; no curve shape is assumed.

Example:
    >>> import numpy as np
    >>> p = np.arange(0.0, 3.01, 0.25)
    >>> curve = np.log1p(5 * np.exp(-((p - 1.37) / 0.4) ** 2))
    >>> round(symmetric_peak(p, curve, half_width=0.8), 3)
    1.37
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError, ShapeError

__all__ = ["region_grid", "focus_measure", "symmetric_peak"]


def region_grid(shape: tuple[int, int], region: int) -> tuple[int, int]:
    """Number of ``region``-px square regions ``(rows, cols)`` (the DFD tile grid at stride = tile)."""
    h, w = shape
    if region < 16 or h < region or w < region:
        raise ShapeError(f"regions of {region} px need frames of at least that size (and region >= 16), got {h}x{w}")
    return h // region, w // region


def focus_measure(image: np.ndarray, region: int) -> np.ndarray:
    """Normalised Laplacian energy per region, ``(rows, cols)``, for an ``(H, W)`` frame in [0, 1]."""
    x = np.asarray(image, dtype=np.float64)
    if x.ndim != 2:
        raise ShapeError(f"focus_measure takes one (H, W) frame, got {x.shape}")
    rows, cols = region_grid(x.shape, region)
    lap = np.zeros_like(x)
    lap[1:-1, 1:-1] = 4 * x[1:-1, 1:-1] - x[:-2, 1:-1] - x[2:, 1:-1] - x[1:-1, :-2] - x[1:-1, 2:]
    lap[0, :] = lap[-1, :] = lap[:, 0] = lap[:, -1] = 0.0
    h, w = rows * region, cols * region
    e = (lap[:h, :w] ** 2).reshape(rows, region, cols, region).mean((1, 3))
    m = x[:h, :w].reshape(rows, region, cols, region).mean((1, 3))
    return e / np.maximum(m, 1e-3) ** 2


def symmetric_peak(powers: np.ndarray, log_measure: np.ndarray, half_width: float) -> float:
    """The power about which ``log_measure`` is most nearly symmetric, near its maximum.

    Args:
        powers: sweep powers ``(N,)``, strictly increasing, dioptres.
        log_measure: log focus measure ``(N,)``.
        half_width: points within this distance of the candidate peak are compared, dpt.

    Returns:
        The peak power, dioptres (within one sweep step of the maximum sample).

    Raises:
        InputError: fewer than 3 points or unsorted powers.
    """
    p = np.asarray(powers, dtype=np.float64)
    v = np.asarray(log_measure, dtype=np.float64)
    if p.ndim != 1 or p.shape != v.shape or len(p) < 3 or np.any(np.diff(p) <= 0):
        raise InputError("symmetric_peak needs >= 3 strictly increasing powers and one value each")
    k = int(np.argmax(v))
    step = float(np.median(np.diff(p)))
    cands = np.linspace(p[k] - step, p[k] + step, 81)

    def cost(c: float) -> float:
        sel = (np.abs(p - c) <= half_width) & (2 * c - p >= p[0]) & (2 * c - p <= p[-1])
        if sel.sum() < 3:
            return np.inf
        mirrored = np.interp(2 * c - p[sel], p, v)
        return float(np.mean((v[sel] - mirrored) ** 2))

    costs = np.array([cost(c) for c in cands])
    if not np.isfinite(costs).any():
        return float(p[k])
    j = int(np.nanargmin(np.where(np.isfinite(costs), costs, np.nan)))
    if 0 < j < len(cands) - 1 and np.all(np.isfinite(costs[j - 1 : j + 2])):
        c0, c1, c2 = costs[j - 1 : j + 2]
        den = c0 - 2 * c1 + c2
        if den > 0:
            return float(cands[j] + 0.5 * (c0 - c2) / den * (cands[1] - cands[0]))
    return float(cands[j])
