r"""Point-spread functions and optical transfer functions of defocus.

Every PSF here is parameterised by the same size: ``sigma`` in pixels, the per-axis RMS
radius (square root of the second moment along x). For the Gaussian of paper eq. 7 that is
its ``sigma``; a uniform disk (pillbox) of radius ``R`` has ``sigma = R / 2``; the
power-exponential family ``h ∝ exp(-(r/alpha)^beta)`` between them (``beta = 2`` Gaussian,
``beta -> inf`` pillbox) has ``alpha`` chosen so its RMS radius is ``sigma`` too. Matching
second moments makes all shapes agree at low spatial frequency, so ``mu`` keeps one meaning.
Signs are ignored (``|sigma|`` is used): a PSF does not know on which side of focus it is.

Kernels are normalised to unit sum, collapse to a delta as ``sigma -> 0`` and are
differentiable in ``sigma``. This module is the one implementation of every PSF shape and of
the kernel-size rule (:func:`kernel_size_for`); the renderer, the synthesiser's aberrated
lens PSFs (``data_synth.psf``, which adds its coordinate stretch and radial weight through
:func:`sampled_psf`), the benchmarks and the simulated bench all take their kernels here.

Frequencies: OTFs take the angular frequency ``omega`` in rad/pixel (``2 pi f`` with ``f``
in cycles/pixel); the Gaussian OTF is ``exp(-sigma^2 omega^2 / 2)`` (paper eq. 11 without
its constant factor).

Example:
    >>> import torch
    >>> k = gaussian_psf(torch.tensor([0.0, 1.5]), 9)
    >>> k.shape, [round(float(s), 6) for s in k.sum((-1, -2))]
    (torch.Size([2, 9, 9]), [1.0, 1.0])
    >>> float(k[0, 4, 4])
    1.0
"""

from __future__ import annotations

import math
from typing import Callable, Union

import torch
import torch.nn.functional as F

from ..errors import InputError, ShapeError

__all__ = [
    "PSFShape",
    "gaussian_psf",
    "gaussian_psf_1d",
    "pillbox_psf",
    "power_exponential_psf",
    "sampled_psf",
    "profile",
    "psf_kernel",
    "kernel_size_for",
    "gaussian_otf",
    "pillbox_otf",
    "psf_second_moment",
    "full_conv_1d",
    "convolve_gaussian",
    "diffraction_sigma_px",
    "diffraction_pad",
]

#: A PSF shape: "gaussian", "pillbox", or a power-exponential exponent ``beta`` >= 1.
PSFShape = Union[str, float]

_SQRT2 = math.sqrt(2.0)


def _grid(size: int, like: torch.Tensor) -> torch.Tensor:
    if size < 1 or size % 2 == 0:
        raise ShapeError(f"PSF kernel size must be a positive odd integer, got {size}")
    return torch.arange(size, dtype=like.dtype, device=like.device) - (size // 2)


def gaussian_psf_1d(sigma: torch.Tensor, size: int) -> torch.Tensor:
    """One separable factor of :func:`gaussian_psf`: ``(*, size)``, unit sum.

    ``gaussian_psf(sigma, size)`` is the outer product of this factor with itself; the
    renderer uses the factor directly (cheaper OTFs, same kernel).
    """
    s = sigma.abs().clamp_min(1e-6)[..., None]
    x = _grid(size, sigma)
    cdf_hi = torch.erf((x + 0.5) / (_SQRT2 * s))
    cdf_lo = torch.erf((x - 0.5) / (_SQRT2 * s))
    k1 = 0.5 * (cdf_hi - cdf_lo)
    return k1 / k1.sum(-1, keepdim=True)


def gaussian_psf(sigma: torch.Tensor, size: int) -> torch.Tensor:
    """Pixel-integrated Gaussian PSF (paper eq. 7), exact delta at ``sigma = 0``.

    Each tap is the Gaussian's integral over the pixel (difference of ``erf``), separable
    (:func:`gaussian_psf_1d`).

    Args:
        sigma: RMS radius in pixels, shape ``(*)``; sign ignored.
        size: odd kernel side length.

    Returns:
        Kernels of shape ``(*, size, size)`` summing to one.
    """
    k1 = gaussian_psf_1d(sigma, size)
    return k1[..., :, None] * k1[..., None, :]


def pillbox_psf(sigma: torch.Tensor, size: int) -> torch.Tensor:
    """Antialiased uniform-disk PSF of radius ``R = 2 |sigma|``.

    Pixel coverage is approximated by a one-pixel linear ramp across the disk edge,
    ``clamp(R - r + 1/2, 0, 1)`` with ``r`` the pixel-centre distance, which makes the
    kernel differentiable in ``R`` and a delta at ``R = 0``.
    """
    radius = 2.0 * sigma.abs()[..., None, None]
    x = _grid(size, sigma)
    r = torch.sqrt(x[:, None] ** 2 + x[None, :] ** 2)
    k = (radius - r + 0.5).clamp(0.0, 1.0)
    return k / k.sum((-1, -2), keepdim=True)


def _alpha_scale(beta: float) -> float:
    """``alpha / sigma`` of the power-exponential profile: ``sqrt(2 Gamma(2/beta) / Gamma(4/beta))``."""
    return math.sqrt(2.0 * math.exp(math.lgamma(2.0 / beta) - math.lgamma(4.0 / beta)))


def _check_beta(beta: float) -> float:
    b = float(beta)
    if not (b >= 1.0 and (math.isfinite(b) or b == math.inf)):
        raise InputError(f"power-exponential beta must be >= 1 (inf: pillbox), got {beta}")
    return b


def profile(r2: torch.Tensor, sigma: torch.Tensor, beta: float, supersample: int = 1) -> torch.Tensor:
    """Unnormalised radial profile of RMS radius ``sigma`` at squared radii ``r2`` (px^2).

    ``beta = 2``: ``exp(-r^2 / (2 sigma^2))``; ``beta = inf``: the disk of radius ``2 sigma``
    with a linear edge ramp one sample (``1 / supersample`` px) wide; otherwise
    ``exp(-(r / alpha)^beta)`` (computed in logs, so it cannot overflow in float32).
    ``sigma`` broadcasts against ``r2`` (e.g. ``(N, 1, 1)`` against ``(N, m, m)``).
    """
    if beta == math.inf:
        return ((2.0 * sigma - torch.sqrt(r2)) * supersample + 0.5).clamp(0.0, 1.0)
    if beta == 2.0:
        return torch.exp(-0.5 * r2 / (sigma * sigma))
    alpha = sigma * _alpha_scale(beta)
    expo = (0.5 * beta) * (torch.log(r2.clamp_min(1e-30)) - 2.0 * torch.log(alpha))
    return torch.exp(-torch.exp(expo.clamp(max=80.0)))


#: ``radius2(yy, xx) -> (N, m, m)``: squared radius of every sample point of every kernel
#: (``yy`` ``(m, 1)``, ``xx`` ``(1, m)`` in px from the kernel centre), e.g. a stretched metric.
Radius2Fn = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
#: ``weight(r2, sigma) -> (N, m, m)``: a radial weight multiplying the profile.
WeightFn = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


def sampled_psf(sigma: torch.Tensor, beta: float, size: int, supersample: int = 1,
                radius2: Radius2Fn | None = None, weight: WeightFn | None = None) -> torch.Tensor:
    """Kernels ``(N, size, size)`` of :func:`profile` sampled on a ``supersample``-times finer
    grid and box-integrated over each pixel, unit sum (a delta where the sum vanishes).

    With ``supersample = 1`` the samples are the pixel centres; a smooth profile then gets the
    pixel's ``1/12`` px^2 of variance added to its own (what box integration adds), the
    pillbox its one-pixel edge ramp. An odd ``supersample`` keeps a sample on every pixel
    centre. ``radius2`` and ``weight`` let a caller deform the profile (the synthesiser's
    astigmatism and spherical aberration, ``data_synth.psf``); by default it is isotropic.

    Args:
        sigma: RMS radius in px ``(N,)`` (sign ignored; clamped to >= 1e-4).
        beta: shape exponent (2 Gaussian, ``inf`` pillbox, >= 1).
        size: odd kernel side.
        supersample: samples per pixel and side (>= 1).
        radius2, weight: see :data:`Radius2Fn`, :data:`WeightFn`.
    """
    beta = _check_beta(beta)
    ss = int(supersample)
    if ss < 1:
        raise InputError(f"supersample must be >= 1, got {supersample}")
    _grid(size, sigma)  # validates the size
    n = sigma.numel()
    sig = sigma.reshape(-1).abs().clamp_min(1e-4)[:, None, None]
    if ss == 1 and beta != math.inf:
        sig = torch.sqrt(sig * sig + 1.0 / 12.0)
    m = size * ss
    t = (torch.arange(m, dtype=sigma.dtype, device=sigma.device) - (m - 1) / 2.0) / ss
    yy, xx = t[:, None], t[None, :]
    r2 = (xx * xx + yy * yy)[None].expand(n, m, m) if radius2 is None else radius2(yy, xx)
    prof = profile(r2, sig, beta, ss)
    if weight is not None:
        prof = prof * weight(r2, sig)
    k = prof.reshape(n, size, ss, size, ss).sum((-1, -3)) if ss > 1 else prof
    total = k.sum((-1, -2), keepdim=True)
    delta = torch.zeros_like(k)
    delta[:, size // 2, size // 2] = 1.0
    return torch.where(total > 1e-12, k / total.clamp_min(1e-30), delta)


def power_exponential_psf(sigma: torch.Tensor, beta: float, size: int, supersample: int | None = None) -> torch.Tensor:
    """Power-exponential PSF ``h ∝ exp(-(r / alpha)^beta)`` with RMS radius ``|sigma|``.

    ``alpha = sigma * sqrt(2 Gamma(2/beta) / Gamma(4/beta))``; ``beta = 2`` is the Gaussian,
    large ``beta`` approaches the pillbox. Evaluated by :func:`sampled_psf`: by default 3x
    supersampled where ``|sigma| < 1.5`` px (the PSF is only a few pixels wide) and at pixel
    centres above (with the pixel's 1/12 px^2 of variance added), or at ``supersample``
    samples per pixel everywhere.

    Args:
        sigma: RMS radius in px, shape ``(*)``.
        beta: exponent, finite and >= 1.
        size: odd kernel side.
        supersample: fixed supersampling, or ``None`` for the adaptive default.

    Returns:
        ``(*, size, size)`` kernels summing to one.
    """
    if not (float(beta) >= 1.0 and math.isfinite(float(beta))):
        raise InputError(f"power-exponential beta must be finite and >= 1, got {beta}")
    flat = sigma.reshape(-1)
    if supersample is not None:
        k = sampled_psf(flat, beta, size, supersample)
    else:
        _grid(size, sigma)
        k = flat.new_empty(flat.numel(), size, size)
        small = flat.detach().abs() < 1.5
        for mask, ss in ((small, 3), (~small, 1)):
            if bool(mask.any()):
                k = k.index_put((mask,), sampled_psf(flat[mask], beta, size, ss))
    return k.reshape(*sigma.shape, size, size)


def psf_kernel(sigma: torch.Tensor, shape: PSFShape, size: int) -> torch.Tensor:
    """Kernel of any supported shape: ``"gaussian"``, ``"pillbox"`` or a beta (float)."""
    if isinstance(shape, str):
        if shape == "gaussian":
            return gaussian_psf(sigma, size)
        if shape == "pillbox":
            return pillbox_psf(sigma, size)
        raise InputError(f"unknown PSF shape {shape!r}; use 'gaussian', 'pillbox' or a beta >= 1")
    if float(shape) == 2.0:
        return gaussian_psf(sigma, size)
    return power_exponential_psf(sigma, float(shape), size)


def kernel_size_for(sigma_max: float, shape: PSFShape = "gaussian") -> int:
    """Odd kernel size that holds a PSF of RMS radius ``sigma_max`` (> 99.9 % of its energy)."""
    s = abs(float(sigma_max))
    extent = 2.0 * s + 1.5 if shape == "pillbox" else 3.5 * s + 1.0
    return 2 * int(math.ceil(extent)) + 1


def gaussian_otf(sigma: torch.Tensor, omega: torch.Tensor) -> torch.Tensor:
    """Gaussian OTF ``exp(-sigma^2 omega^2 / 2)``; ``omega`` in rad/pixel (paper eq. 11)."""
    return torch.exp(-0.5 * sigma**2 * omega**2)


def pillbox_otf(sigma: torch.Tensor, omega: torch.Tensor) -> torch.Tensor:
    """OTF of a continuous uniform disk of radius ``R = 2|sigma|``: ``2 J1(R w) / (R w)``."""
    x = 2.0 * sigma.abs() * omega
    safe = torch.where(x.abs() < 1e-4, torch.ones_like(x), x)
    return torch.where(x.abs() < 1e-4, 1.0 - x**2 / 8.0, 2.0 * torch.special.bessel_j1(safe) / safe)


def psf_second_moment(kernel: torch.Tensor) -> torch.Tensor:
    """Per-axis variance (pixels^2) of kernels ``(*, k, k)`` about their centre tap."""
    size = kernel.shape[-1]
    x = _grid(size, kernel)
    return (kernel * (x[None, :] ** 2)).sum((-1, -2)) / kernel.sum((-1, -2))


def full_conv_1d(x: torch.Tensor, taps: torch.Tensor, dim: int) -> torch.Tensor:
    """Full 1-D convolution of ``x`` along ``dim`` with a short symmetric kernel ``taps``
    (a few shifted copies: no convolution primitive to build for every new shape)."""
    n = taps.numel()
    shape = list(x.shape)
    shape[dim] += n - 1
    out = x.new_zeros(shape)
    for j, w in enumerate(taps.tolist()):
        out.narrow(dim, j, x.shape[dim]).add_(x, alpha=w)
    return out


def convolve_gaussian(k: torch.Tensor, sigma_px: float, pad: int) -> torch.Tensor:
    """Full convolution of kernels ``(N, k, k)`` with a pixel-integrated Gaussian of RMS radius
    ``sigma_px`` (e.g. the diffraction blur), renormalised to unit sum; the kernels grow by ``2 pad``.

    Example:
        >>> k = convolve_gaussian(torch.ones(1, 3, 3) / 9, 0.5, 2)
        >>> tuple(k.shape), round(float(k.sum()), 6)
        ((1, 7, 7), 1.0)
    """
    g1 = gaussian_psf_1d(torch.tensor([sigma_px], dtype=k.dtype), 2 * pad + 1)
    x = full_conv_1d(full_conv_1d(k, g1[0], -1), g1[0], -2)
    return x / x.sum((-1, -2), keepdim=True)


def diffraction_sigma_px(f_number: float, wavelength_m: float, pixel_pitch_m: float) -> float:
    """RMS radius (px) of the Gaussian approximation of the Airy pattern: ``0.42 lambda N / pitch``."""
    return 0.42 * wavelength_m * f_number / pixel_pitch_m


def diffraction_pad(sigma_px: float) -> int:
    """Half-size of the kernel of a Gaussian diffraction blur of RMS radius ``sigma_px``
    (:func:`kernel_size_for` of it; 0 without one): what :func:`convolve_gaussian` grows a PSF by."""
    return kernel_size_for(sigma_px) // 2 if sigma_px > 0 else 0
