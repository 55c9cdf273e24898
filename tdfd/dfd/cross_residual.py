r"""The texture-free cross-residual likelihood of a defocus pair, over a whole frame or per tile.

The estimator behind the likelihood stage (:mod:`tdfd.dfd.likelihood_stage`) and the oracle
benchmarks (``benchmarks/bench_plane_oracle.py``, ``benchmarks/bench_tile_oracle.py``). Both frames are the same sharp texture ``s`` blurred by
their own PSFs, ``f_i = k_i * s + n_i``, so the *cross residual*

.. math::

    r(q) = k_2(q) * f_1 - k_1(q) * f_2

is texture-free at the true inverse depth ``q`` wherever both linear convolutions are valid
(the image less a kernel's half-width on every side: no tile boundary, no assumption on the
texture outside the frame). Its noise is stationary with spectrum
``P(u; q) = nu_1 |K_2(u)|^2 + nu_2 |K_1(u)|^2`` (``nu_i`` the frames' noise variances), and
with ``s`` profiled out of the Gaussian likelihood of the two frames (their noise does not
depend on ``q``, so no log-determinant term is left),

.. math::

    \mathrm{NLL}(q) = \frac{1}{B} \sum_{u \in \mathrm{band}} \frac{|R(u; q)|^2}{\tilde P(u; q)}

over the band's ``B`` bins; its expectation is 1 at the truth and larger elsewhere. ``R`` is
the spectrum of the residual (the whole valid region, or one tile of it) times a Tukey taper,
and ``P~`` is the *tapered* residual's expected periodogram, ``P`` convolved with the taper's
spectrum (the product of the residual's autocovariance and the taper's autocorrelation in
the lag domain): without it the taper's leakage from low into high frequencies, where ``P``
is small, makes even pure noise prefer some depths.

Per tile (:func:`tile_cross_residual_nll`) the residual is computed once over the frame and
cut into tiles, so a tile's residual uses the pixels a kernel's half-width around it (as a
CNN's receptive field does), and each tile takes the noise variances of its own mean level.
"""

from __future__ import annotations

import math
from typing import Sequence

import torch

from ..errors import InputError, ShapeError

__all__ = ["TAPER_FRACTION", "tukey_window", "kernel_spectra", "taper_lag_weight", "tapered_power",
           "tapered_periodograms", "band_weight", "valid_residual", "cross_residual_nll", "tile_cross_residual_nll",
           "parabolic_minima", "argmin_parabolic", "independent_bins", "curvature_sigma"]

TAPER_FRACTION = 0.1


def tukey_window(height: int, width: int | None = None, fraction: float = TAPER_FRACTION,
                 dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """Separable Tukey taper ``(height, width)``: flat, with raised-cosine edges over
    ``fraction / 2`` of each side.

    Example:
        >>> w = tukey_window(40, 30, fraction=0.2)
        >>> tuple(w.shape), float(w[20, 15]), float(w[0, 15])
        ((40, 30), 1.0, 0.0)
    """
    if not 0.0 <= fraction <= 1.0:
        raise InputError(f"taper fraction must lie in [0, 1], got {fraction}")

    def one(size: int) -> torch.Tensor:
        w1 = torch.ones(size, dtype=dtype)
        edge = int(fraction * size / 2)
        if edge:
            n = torch.arange(edge, dtype=dtype)
            w1[:edge] = 0.5 * (1.0 - torch.cos(math.pi * n / edge))
            w1[size - edge:] = w1[:edge].flip(0)
        return w1

    return one(height)[:, None] * one(height if width is None else width)[None, :]


def _check(y1: torch.Tensor, y2: torch.Tensor, k1: torch.Tensor, k2: torch.Tensor, band: float) -> None:
    if y1.ndim != 2 or y1.shape != y2.shape:
        raise ShapeError(f"frames must be two (H, W) of one shape, got {tuple(y1.shape)} and {tuple(y2.shape)}")
    if k1.ndim != 3 or k1.shape != k2.shape or k1.shape[-1] != k1.shape[-2] or k1.shape[-1] % 2 == 0:
        raise ShapeError(f"kernels must be two (Q, n, n) stacks of odd n, got {tuple(k1.shape)} and {tuple(k2.shape)}")
    if not (0.0 < band <= 0.5):
        raise InputError(f"band must lie in (0, 0.5] cycles/px, got {band}")


def _check_noise(*nus: torch.Tensor | float) -> None:
    for nu in nus:
        t = torch.as_tensor(nu, dtype=torch.float64)
        if not bool(torch.isfinite(t).all()) or not bool((t > 0).all()):
            raise InputError(f"noise variances must be finite and > 0, got {nu}")


def kernel_spectra(k: torch.Tensor, shape: tuple[int, int]) -> torch.Tensor:
    """``rfft2`` of centred ``(Q, n, n)`` kernels on a ``shape`` grid."""
    n = k.shape[-1]
    pad = torch.zeros(k.shape[0], *shape, dtype=torch.float64)
    pad[:, :n, :n] = k
    return torch.fft.rfft2(torch.roll(pad, (-(n // 2), -(n // 2)), (1, 2)))


def valid_residual(y1: torch.Tensor, y2: torch.Tensor, k1: torch.Tensor, k2: torch.Tensor) -> torch.Tensor:
    """``k2 * y1 - k1 * y2`` for each hypothesis where both linear convolutions are valid:
    ``(Q, H - n + 1, W - n + 1)`` float64, pixel ``(i, j)`` centred on image pixel
    ``(i + n // 2, j + n // 2)``."""
    _check(y1, y2, k1, k2, 0.5)
    h, w = y1.shape
    n = k1.shape[-1]
    if min(h, w) < n:
        raise ShapeError(f"frames of {h}x{w} px are smaller than the {n}-px kernels")
    y1, y2, k1, k2 = (t.to(torch.float64) for t in (y1, y2, k1, k2))
    F1, F2 = torch.fft.rfft2(y1), torch.fft.rfft2(y2)
    K1, K2 = kernel_spectra(k1, (h, w)), kernel_spectra(k2, (h, w))
    r = torch.fft.irfft2(K2 * F1[None] - K1 * F2[None], s=(h, w))  # circular; the valid part is linear
    half = n // 2
    return r[:, half: h - half, half: w - half]


def taper_lag_weight(taper: torch.Tensor) -> torch.Tensor:
    """The taper's autocorrelation (1 at lag 0) on the ``(mh, mw)`` lags of a residual of the
    taper's shape: what a stationary residual's autocovariance is multiplied by through the taper."""
    mh, mw = taper.shape
    big = torch.fft.fft2(taper, s=(2 * mh, 2 * mw))
    acw = torch.fft.ifft2(big.abs() ** 2).real / (mh * mw)
    ly, lx = (torch.fft.fftfreq(m, 1.0 / m).long() % (2 * m) for m in (mh, mw))
    return acw[ly][:, lx]


def tapered_power(k: torch.Tensor, lag_weight: torch.Tensor) -> torch.Tensor:
    """``|K|^2`` of ``(Q, n, n)`` kernels through the taper whose :func:`taper_lag_weight` is
    ``lag_weight``: the expected periodogram of a unit white noise blurred by each kernel, tapered."""
    mh, mw = lag_weight.shape
    power = kernel_spectra(k.to(torch.float64), (mh, mw)).abs() ** 2
    cov = torch.fft.irfft2(power, s=(mh, mw))  # the residual's autocovariance: a kernel's support
    return torch.fft.rfft2(cov * lag_weight).real


def tapered_periodograms(k1: torch.Tensor, k2: torch.Tensor, taper: torch.Tensor, model_taper: bool
                          ) -> tuple[torch.Tensor, torch.Tensor]:
    """The expected periodograms of the tapered residual of unit noise in frame 1 (``|K2|^2``
    through the taper) and in frame 2 (``|K1|^2`` through it): ``P~ = nu1 * A + nu2 * B``."""
    if model_taper:
        lag_weight = taper_lag_weight(taper)
        return tapered_power(k2, lag_weight), tapered_power(k1, lag_weight)
    shape = tuple(taper.shape)
    return (kernel_spectra(k2.to(torch.float64), shape).abs() ** 2,
            kernel_spectra(k1.to(torch.float64), shape).abs() ** 2)


def band_weight(mh: int, mw: int, band: float) -> torch.Tensor:
    """Each half-spectrum bin's count in the band (2 for a bin standing for its mirror, 1 for
    the self-conjugate columns, 0 outside; the lowest bins, below 1.5 cycles per patch, out)."""
    fy = torch.fft.fftfreq(mh, dtype=torch.float64)[:, None]
    fx = torch.fft.rfftfreq(mw, dtype=torch.float64)[None, :]
    f = torch.sqrt(fy ** 2 + fx ** 2)
    weight = torch.full_like(f, 2.0)
    weight[:, 0] = 1.0
    if mw % 2 == 0:
        weight[:, -1] = 1.0
    return weight * ((f > 1.5 / min(mh, mw)) & (f <= band)).to(torch.float64)


def independent_bins(tile: int, band: float = 0.25) -> float:
    """The number of independent spectral bins behind one tile's mean NLL (half the band's
    half-plane count: a real residual's bin and its mirror are one): the NLL's sum is this
    times its mean, and ``1 / (bins * d2 NLL / dq2)`` the variance of ``q`` at its minimum.

    Example:
        >>> independent_bins(64)
        394.0
    """
    if tile < 16:
        raise ShapeError(f"tiles must be at least 16 px, got {tile}")
    if not (0.0 < band <= 0.5):
        raise InputError(f"band must lie in (0, 0.5] cycles/px, got {band}")
    return float(band_weight(tile, tile, band).sum()) / 2.0


def cross_residual_nll(y1: torch.Tensor, y2: torch.Tensor, k1: torch.Tensor, k2: torch.Tensor, nu1: float,
                       nu2: float, band: float = 0.25, model_taper: bool = True) -> torch.Tensor:
    """Mean per-bin negative log-likelihood of each hypothesis over the whole valid region.

    Args:
        y1, y2: ``(H, W)`` frames, linear in irradiance, black level removed (any gain).
        k1, k2: ``(Q, n, n)`` each hypothesis's PSFs of frame 1 and 2 (odd ``n``, unit sum).
        nu1, nu2: the frames' noise variances per pixel (units of ``y`` squared).
        band: upper edge of the band in cycles/px, in ``(0, 0.5]`` (the lowest bins, below
            1.5 cycles per residual, are left out).
        model_taper: divide by the tapered residual's expected periodogram (True) or by ``P``
            itself (a plain Whittle likelihood, biased by the taper's leakage).

    Returns:
        ``(Q,)`` float64; about 1 at the true hypothesis.
    """
    _check(y1, y2, k1, k2, band)
    _check_noise(nu1, nu2)
    h, w = y1.shape
    n = k1.shape[-1]
    if min(h, w) < 2 * n + 8:
        raise ShapeError(f"frames of {h}x{w} px are too small for {n}-px kernels")
    v = valid_residual(y1, y2, k1, k2)
    mh, mw = v.shape[-2:]
    taper = tukey_window(mh, mw)
    taper = taper / float((taper ** 2).mean().sqrt())
    R = torch.fft.rfft2(v * taper)
    a, b = tapered_periodograms(k1, k2, taper, model_taper)
    weight = band_weight(mh, mw, band)
    terms = R.abs() ** 2 / (mh * mw) / (nu1 * a + nu2 * b).clamp_min(1e-300)
    return (terms * weight).sum((-1, -2)) / weight.sum()


def tile_cross_residual_nll(y1: torch.Tensor, y2: torch.Tensor, k1: torch.Tensor, k2: torch.Tensor,
                            nu1: torch.Tensor, nu2: torch.Tensor, origins: Sequence[tuple[int, int]], tile: int,
                            band: float = 0.25, fraction: float = TAPER_FRACTION, chunk: int = 256,
                            mask: torch.Tensor | None = None, shift: torch.Tensor | None = None) -> torch.Tensor:
    """:func:`cross_residual_nll` of each tile of the frame's residual.

    Each tile's residual is the valid part of the circular convolutions of its own region, the
    tile and a kernel's half-width around it (the same values as cutting the whole frame's
    residual, :func:`valid_residual`, without computing it where no tile needs it).

    Args:
        y1, y2, k1, k2, band: as for :func:`cross_residual_nll`.
        nu1, nu2: ``(T,)`` each tile's noise variances in frame 1 and 2 (at its own level).
        origins: ``T`` image pixels ``(row, col)``, the tiles' top-left corners; every tile
            must lie a kernel's half-width inside the frame (where the residual is valid).
        tile: the tiles' side in px (at least 16).
        fraction: the tiles' Tukey taper (see :func:`tukey_window`).
        chunk: (hypothesis, tile) pairs per pass (memory).
        mask: ``(Q, T)`` bool, the pairs to evaluate (``None``: all); the others are ``inf``.
        shift: ``(T, 2)`` px (row, column), where each tile's content lies in frame 2 relative to
            frame 1 (focus breathing and misregistration, :func:`tdfd.warp.misregister`: a scene
            point at ``p`` in frame 1 lies at ``p + shift`` in frame 2); ``None``: registered.
            Frame 2's region is moved back by a phase ramp on its spectrum (exact for the
            band-limited frame, and the noise stays white: nothing is interpolated); at most
            a kernel's half-width (the region's margin).

    Returns:
        ``(Q, T)`` float64; about 1 at each tile's true hypothesis.

    Raises:
        ShapeError: bad frames, kernels, a tile under 16 px or one outside the valid region.
        InputError: a bad band, taper, chunk, mask, or noise variances not ``(T,)``, finite and > 0.
    """
    _check(y1, y2, k1, k2, band)
    nu1, nu2 = (torch.as_tensor(v, dtype=torch.float64) for v in (nu1, nu2))
    n_t = len(origins)
    if nu1.shape != (n_t,) or nu2.shape != (n_t,):
        raise InputError(f"need one noise variance per tile: {n_t} tiles, got {tuple(nu1.shape)} and "
                         f"{tuple(nu2.shape)}")
    _check_noise(nu1, nu2)
    if tile < 16:
        raise ShapeError(f"tiles must be at least 16 px, got {tile}")
    if chunk < 1:
        raise InputError(f"chunk must be >= 1, got {chunk}")
    if mask is not None and (mask.shape != (k1.shape[0], n_t) or mask.dtype != torch.bool):
        raise InputError(f"mask must be a ({k1.shape[0]}, {n_t}) bool tensor, got {tuple(mask.shape)} {mask.dtype}")
    h, w = y1.shape
    half = k1.shape[-1] // 2
    if shift is not None and (shift.shape != (n_t, 2) or not bool(torch.isfinite(shift).all())
                              or bool((shift.abs() > half).any())):
        raise InputError(f"shift must be ({n_t}, 2) finite px of at most a kernel's half-width ({half} px), got "
                         f"{tuple(shift.shape)}" + ("" if shift.shape != (n_t, 2) else
                                                    f" up to {float(shift.abs().max()):.3g} px"))
    for r, c in origins:
        if r < half or c < half or r + tile > h - half or c + tile > w - half:
            raise ShapeError(f"tile at ({r}, {c}) of {tile} px leaves the valid residual of a {h}x{w} frame and "
                             f"{2 * half + 1}-px kernels")
    out = torch.full((k1.shape[0], n_t), math.inf, dtype=torch.float64)
    pairs = (torch.ones_like(out, dtype=torch.bool) if mask is None else mask).nonzero()  # (P, 2): hypothesis, tile
    if not n_t or not len(pairs):
        return out
    taper = tukey_window(tile, tile, fraction)
    taper = taper / float((taper ** 2).mean().sqrt())
    weight = band_weight(tile, tile, band)
    m = tile + 2 * half  # each tile's region
    rows = torch.tensor([r - half for r, _ in origins])[:, None] + torch.arange(m)[None]  # (T, m)
    cols = torch.tensor([c - half for _, c in origins])[:, None] + torch.arange(m)[None]
    y1, y2, k1, k2 = (t.to(torch.float64) for t in (y1, y2, k1, k2))
    F1 = torch.fft.rfft2(y1[rows[:, :, None], cols[:, None, :]])  # (T, m, m // 2 + 1)
    F2 = torch.fft.rfft2(y2[rows[:, :, None], cols[:, None, :]])
    if shift is not None:  # g(x) = f2(x + shift): frame 2 registered onto frame 1
        fr, fc = torch.fft.fftfreq(m, dtype=torch.float64), torch.fft.rfftfreq(m, dtype=torch.float64)
        sh = shift.to(torch.float64)
        F2 = F2 * torch.exp(2j * math.pi * (fr[None, :, None] * sh[:, 0, None, None]
                                            + fc[None, None, :] * sh[:, 1, None, None]))
    used = pairs[:, 0].unique()
    slot = torch.full((k1.shape[0],), -1, dtype=torch.long)
    slot[used] = torch.arange(len(used))
    K1, K2 = kernel_spectra(k1[used], (m, m)), kernel_spectra(k2[used], (m, m))
    a, b = tapered_periodograms(k1[used], k2[used], taper, True)  # (Q', tile, tile // 2 + 1)
    for start in range(0, len(pairs), chunk):
        qi, ti = pairs[start: start + chunk, 0], pairs[start: start + chunk, 1]
        j = slot[qi]
        r = torch.fft.irfft2(K2[j] * F1[ti] - K1[j] * F2[ti], s=(m, m))[:, half: half + tile, half: half + tile]
        R = torch.fft.rfft2(r * taper)
        p = nu1[ti, None, None] * a[j] + nu2[ti, None, None] * b[j]
        terms = R.abs() ** 2 / (tile * tile) / p.clamp_min(1e-300)
        out[qi, ti] = (terms * weight).sum((-1, -2)) / weight.sum()
    return out


def parabolic_minima(nll: torch.Tensor, grid: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Each column's grid minimum of ``nll`` ``(Q, T)`` refined by the parabola through it and its
    two neighbours (moved by at most one step; the grid's ends, and values of ``inf`` that mask
    hypotheses out, are not extrapolated).

    Returns:
        ``(q, value, curvature)``, each ``(T,)``: the refined minimum, the NLL at the grid
        minimum, and the parabola's second derivative ``d2 NLL / dq2`` (``nan`` where it is not
        finite and positive: a minimum on the grid's or a mask's edge).
    """
    step = float(grid[1] - grid[0])
    k = nll.argmin(0).clamp(1, len(grid) - 2)
    t = torch.arange(nll.shape[1])
    a, b, c = nll[k - 1, t], nll[k, t], nll[k + 1, t]
    den = a - 2 * b + c
    ok = torch.isfinite(den) & (den > 0)
    safe = torch.where(ok, den, torch.ones_like(den))
    off = torch.where(ok, (0.5 * (a - c) / safe).clamp(-1.0, 1.0), torch.zeros_like(den))
    curvature = torch.where(ok, safe / step ** 2, torch.full_like(den, math.nan))
    return grid[k] + off * step, b, curvature


def curvature_sigma(curvature: torch.Tensor, bins: float, noise: torch.Tensor | float = 1.0) -> torch.Tensor:
    """The standard deviation of each minimum in ``q`` from its curvature (:func:`parabolic_minima`):
    ``sqrt(noise / (bins * d2 NLL / dq2))`` with ``bins`` the independent bins behind the mean NLL
    (:func:`independent_bins`) and ``noise`` the NLL's unit (1 for a fit told the noise; the
    minimum itself for a unit-noise fit); ``inf`` where the curvature is ``nan`` (no weight).

    Example:
        >>> curvature_sigma(torch.tensor([100.0, float("nan")]), 4.0).tolist()
        [0.05, inf]
    """
    ok = torch.isfinite(curvature)
    var = noise / (bins * torch.where(ok, curvature, torch.ones_like(curvature)))
    return torch.where(ok, torch.as_tensor(var).sqrt(), torch.full_like(curvature, math.inf))


def argmin_parabolic(nll: torch.Tensor, grid: torch.Tensor) -> tuple[float, float]:
    """:func:`parabolic_minima` of one ``(Q,)`` curve: ``(argmin, value at the grid minimum)``."""
    q, value, _ = parabolic_minima(nll[:, None], grid)
    return float(q[0]), float(value[0])
