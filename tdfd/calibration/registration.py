r"""Focus breathing from image registration: magnification between frames versus lens power.

Two frames of one scene at ECVFL powers ``P_a`` and ``P_b`` differ by the magnification
``rho = (1 + m P_a) / (1 + m P_b)`` about the optical centre (:mod:`tdfd.breathing`), so a
region centred at ``x`` (relative to the centre) appears shifted by ``(rho - 1) x``. Each
region's shift (Hann window) is the weighted least-squares slope of the cross spectrum's
phase at low frequencies (:func:`region_shift`) (a symmetric defocus PSF has a real transfer
function, so blur adds no phase); ``rho - 1`` is the least-squares slope of shift against position over the regions;
``m`` is the least-squares fit of ``log rho`` against the power differences.

Example:
    >>> import numpy as np
    >>> from tdfd.breathing import magnify
    >>> x = np.random.default_rng(0).random((192, 192))
    >>> rho, n = relative_magnification(x, magnify(x, 1.01), region=64)
    >>> abs(rho - 1.01) < 5e-4, n
    (True, 9)
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from ..breathing import magnify
from ..errors import InputError
from .focus import region_grid

__all__ = ["relative_magnification", "region_shift", "fit_magnification_per_dpt", "MIN_RESPONSE"]

#: Gaussian pre-smoothing (px) of both frames against sensor noise before the Laplacian.
NOISE_SMOOTHING_PX = 1.0
#: regions whose mean coherence between the frames is below this are not used.
MIN_RESPONSE = 0.3


def _gauss(x: np.ndarray, sigma: float) -> np.ndarray:
    import cv2

    if sigma < 0.05:
        return x
    k = 2 * int(math.ceil(4 * sigma)) + 1
    return cv2.GaussianBlur(x, (k, k), sigma, borderType=cv2.BORDER_REFLECT)


def _whiten(x: np.ndarray) -> np.ndarray:
    """Pre-whitening (gradient magnitude is not linear; a Laplacian is): large flat areas and
    the window's edges then weigh little against the texture's detail."""
    y = np.zeros_like(x)
    y[1:-1, 1:-1] = 4 * x[1:-1, 1:-1] - x[:-2, 1:-1] - x[2:, 1:-1] - x[1:-1, :-2] - x[1:-1, 2:]
    return y


def relative_magnification(reference: np.ndarray, moving: np.ndarray, region: int = 64,
                           square_difference: np.ndarray | None = None, iterations: int = 4) -> tuple[float, int]:
    """Magnification of ``moving`` relative to ``reference`` about the image centre, refined
    by warping ``moving`` with the estimate and measuring what remains (``iterations`` times):
    the Hann window pulls each measured shift towards zero by a texture-dependent fraction,
    a bias that vanishes as the remaining shift does.

    Returns:
        ``(rho, regions used)``; ``rho`` is NaN when fewer than 3 regions correlate.
    """
    b = np.asarray(moving, dtype=np.float64)
    rho, used = 1.0, 0
    for it in range(max(int(iterations), 1)):
        warped = b if rho == 1.0 else magnify(b, 1.0 / rho)
        r, used = _magnification_once(reference, warped, region, square_difference)
        if not math.isfinite(r):
            return (math.nan, used) if it == 0 else (rho, used)
        rho *= r
        if abs(r - 1.0) < 1e-6:
            break
    return rho, used


def _magnification_once(reference: np.ndarray, moving: np.ndarray, region: int,
                        square_difference: np.ndarray | None) -> tuple[float, int]:
    """One registration pass: magnification of ``moving`` relative to ``reference`` about the image centre.

    ``square_difference`` (``(rows, cols)``, ``sigma_ref^2 - sigma_moving^2`` in px^2, e.g.
    from :func:`tdfd.calibration.measure.measure_pair`) equalises the blur first: the
    sharper frame of each region is blurred by a Gaussian of ``sqrt(|D|)``, so that window
    edges weigh both frames' content alike (unequal blur would otherwise move the phase).

    Returns:
        ``(rho, regions used)``; ``rho`` is NaN when fewer than 3 regions correlate.
    """
    a = np.asarray(reference, dtype=np.float64)
    b = np.asarray(moving, dtype=np.float64)
    if a.shape != b.shape or a.ndim != 2:
        raise InputError(f"frames to register must be (H, W) of one size, got {a.shape} and {b.shape}")
    rows, cols = region_grid(a.shape, region)
    cy, cx = (a.shape[0] - 1) / 2.0, (a.shape[1] - 1) / 2.0
    win = np.outer(np.hanning(region), np.hanning(region))
    pos, shifts = [], []
    for i in range(rows):
        for j in range(cols):
            sl = (slice(i * region, (i + 1) * region), slice(j * region, (j + 1) * region))
            aa, bb = a, b
            if square_difference is not None and np.isfinite(square_difference[i, j]):
                dd = float(square_difference[i, j])
                aa, bb = (a, _gauss(b, math.sqrt(dd))) if dd > 0 else (_gauss(a, math.sqrt(-dd)), b)
            ra, rb = _whiten(_gauss(aa, NOISE_SMOOTHING_PX)[sl]), _whiten(_gauss(bb, NOISE_SMOOTHING_PX)[sl])
            shift = region_shift(ra, rb, win)
            if shift is None:
                continue
            dx, dy = shift
            pos.append((j * region + (region - 1) / 2.0 - cx, i * region + (region - 1) / 2.0 - cy))
            shifts.append((dx, dy))
    if len(pos) < 3:
        return math.nan, len(pos)
    r, d = np.asarray(pos), np.asarray(shifts)
    keep = np.ones(len(r), bool)
    for _ in range(3):  # least squares, then drop regions far off the fitted magnification
        den = float(np.sum(r[keep] ** 2))
        if den <= 0:
            return math.nan, int(keep.sum())
        slope = float(np.sum(r[keep] * d[keep]) / den)
        err = np.hypot(*(d - slope * r).T)
        scale = max(1.4826 * float(np.median(err[keep])), 0.05)
        new = err <= 3 * scale
        if new.sum() < 3 or np.array_equal(new, keep):
            break
        keep = new
    return 1.0 + slope, int(keep.sum())


def region_shift(a: np.ndarray, b: np.ndarray, window: np.ndarray) -> tuple[float, float] | None:
    """Sub-pixel shift ``(dx, dy)`` of ``b`` relative to ``a`` (same square size, shifts of
    up to about 2 px), or ``None`` when the regions do not correlate.

    The phase of the cross spectrum, ``-(kx dx + ky dy)``, is fitted by weighted least
    squares over ``0.05 pi < |k| < 0.35 pi`` rad/px (no phase wrap below ~2.8 px); each
    frequency is weighted by its phase information ``gamma^2 / (1 - gamma^2)``, ``gamma^2``
    the magnitude-squared coherence over 3x3 neighbouring frequencies, so noise-dominated
    frequencies (random phase, which would dilute the slope) get no weight. Regions whose
    mean coherence in the band is below :data:`MIN_RESPONSE` are refused.
    """
    n = a.shape[0]
    fa, fb = np.fft.fft2(a * window), np.fft.fft2(b * window)
    cross = fb * np.conj(fa)
    k = np.fft.fftfreq(n) * 2 * np.pi
    ky, kx = np.meshgrid(k, k, indexing="ij")
    radius = np.hypot(kx, ky)

    def box(z: np.ndarray) -> np.ndarray:
        return sum(np.roll(np.roll(z, u, 0), v, 1) for u in (-1, 0, 1) for v in (-1, 0, 1))

    g2 = np.abs(box(cross)) ** 2 / np.maximum(box(np.abs(fa) ** 2) * box(np.abs(fb) ** 2), 1e-300)
    g2 = np.clip(g2, 0.0, 0.999)
    sel = (radius < 0.35 * np.pi) & (radius > 0.05 * np.pi)
    if float(np.mean(g2[sel])) < MIN_RESPONSE:
        return None
    w = (g2 / (1.0 - g2))[sel]
    design = -np.stack([kx[sel], ky[sel]], 1)
    lhs = design.T @ (design * w[:, None])
    rhs = design.T @ (w * np.angle(cross)[sel])
    try:
        dx, dy = np.linalg.solve(lhs, rhs)
    except np.linalg.LinAlgError:
        return None
    if not (abs(dx) <= 2.5 and abs(dy) <= 2.5):
        return None
    return float(dx), float(dy)


def fit_magnification_per_dpt(powers_a: Sequence[float], powers_b: Sequence[float], rhos: Sequence[float],
                              weights: Sequence[float] | None = None) -> tuple[float, np.ndarray]:
    """Least-squares ``m`` from magnifications ``rho_k`` of frames at ``P_b`` relative to ``P_a``.

    Model ``log rho = log(1 + m P_b) - log(1 + m P_a)`` (solved by Gauss-Newton from the
    linearised ``m = sum(dP log rho) / sum(dP^2)``).

    Starts from the median of ``log rho / dP``; measurements more than 3 robust standard
    deviations (at least 2e-4) off the fit are dropped (frames too blurred or too bare to
    register) before each least-squares refit.

    Returns:
        ``(m, residuals of log rho)``.

    Raises:
        InputError: no usable measurement (all power differences zero or no finite rho).
    """
    pa, pb, r = (np.asarray(v, dtype=np.float64) for v in (powers_a, powers_b, rhos))
    w = np.ones_like(r) if weights is None else np.asarray(weights, dtype=np.float64)
    ok = np.isfinite(r) & (r > 0) & (pa != pb)
    if ok.sum() < 1:
        raise InputError("no frame pair registers: breathing cannot be measured (too little texture or too few frames)")
    pa, pb, y, w = pa[ok], pb[ok], np.log(r[ok]), w[ok]
    dp = pb - pa
    m = float(np.median(y / dp))  # robust start: frames that failed to register are far off
    keep = np.ones(len(y), bool)
    for _ in range(4):  # drop measurements beyond 3 robust standard deviations, then refit
        res = y - (np.log1p(m * pb) - np.log1p(m * pa))
        spread = max(1.4826 * float(np.median(np.abs(res[keep]))), 2e-4)
        new = np.abs(res) <= 3 * spread
        if new.sum() < 1:
            break
        keep = new
        m = float(np.sum((w * dp * y)[keep]) / np.sum((w * dp * dp)[keep]))
        for _ in range(10):
            model = np.log1p(m * pb) - np.log1p(m * pa)
            jac = pb / (1 + m * pb) - pa / (1 + m * pa)
            m += float(np.sum((w * jac * (y - model))[keep]) / np.sum((w * jac * jac)[keep]))
    res = y - (np.log1p(m * pb) - np.log1p(m * pa))
    return m, res
