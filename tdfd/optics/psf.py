r"""Point-spread functions and optical transfer functions of defocus.

Every PSF here is parameterised by the same size: ``sigma`` in pixels, the per-axis RMS
radius (square root of the second moment along x). For the Gaussian of paper eq. 7 that is
its ``sigma``; a uniform disk (pillbox) of radius ``R`` has ``sigma = R / 2``; the
power-exponential family ``h ∝ exp(-(r/alpha)^beta)`` between them (``beta = 2`` Gaussian,
``beta -> inf`` pillbox) has ``alpha`` chosen so its RMS radius is ``sigma`` too. Matching
second moments makes all shapes agree at low spatial frequency, so ``mu`` keeps one meaning.
Signs are ignored (``|sigma|`` is used): a PSF does not know on which side of focus it is.

Kernels are normalised to unit sum, collapse to a delta as ``sigma -> 0`` and are
differentiable in ``sigma``.

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
from typing import Union

import torch
import torch.nn.functional as F

from ..errors import InputError, ShapeError

__all__ = [
    "PSFShape",
    "gaussian_psf",
    "pillbox_psf",
    "power_exponential_psf",
    "psf_kernel",
    "kernel_size_for",
    "gaussian_otf",
    "pillbox_otf",
    "psf_second_moment",
]

#: A PSF shape: "gaussian", "pillbox", or a power-exponential exponent ``beta`` >= 1.
PSFShape = Union[str, float]

_SQRT2 = math.sqrt(2.0)


def _grid(size: int, like: torch.Tensor) -> torch.Tensor:
    if size < 1 or size % 2 == 0:
        raise ShapeError(f"PSF kernel size must be a positive odd integer, got {size}")
    return torch.arange(size, dtype=like.dtype, device=like.device) - (size // 2)


def gaussian_psf(sigma: torch.Tensor, size: int) -> torch.Tensor:
    """Pixel-integrated Gaussian PSF (paper eq. 7), exact delta at ``sigma = 0``.

    Each tap is the Gaussian's integral over the pixel (difference of ``erf``), separable.

    Args:
        sigma: RMS radius in pixels, shape ``(*)``; sign ignored.
        size: odd kernel side length.

    Returns:
        Kernels of shape ``(*, size, size)`` summing to one.
    """
    s = sigma.abs().clamp_min(1e-6)[..., None]
    x = _grid(size, sigma)
    cdf_hi = torch.erf((x + 0.5) / (_SQRT2 * s))
    cdf_lo = torch.erf((x - 0.5) / (_SQRT2 * s))
    k1 = 0.5 * (cdf_hi - cdf_lo)
    k1 = k1 / k1.sum(-1, keepdim=True)
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


def power_exponential_psf(sigma: torch.Tensor, beta: float, size: int, supersample: int = 4) -> torch.Tensor:
    """Power-exponential PSF ``h ∝ exp(-(r / alpha)^beta)`` with RMS radius ``|sigma|``.

    ``alpha = sigma * sqrt(2 Gamma(2/beta) / Gamma(4/beta))``; ``beta = 2`` is the Gaussian,
    large ``beta`` approaches the pillbox. Evaluated on a ``supersample``-times finer grid
    and box-integrated over each pixel; normalised with a softmax so it stays a delta as
    ``sigma -> 0``.
    """
    if not (beta >= 1.0 and math.isfinite(beta)):
        raise InputError(f"power-exponential beta must be finite and >= 1, got {beta}")
    ss = int(supersample)
    scale = math.sqrt(2.0 * math.exp(math.lgamma(2.0 / beta) - math.lgamma(4.0 / beta)))
    alpha = (sigma.abs() * scale).clamp_min(1e-4)[..., None, None]
    n = size * ss
    x = (torch.arange(n, dtype=sigma.dtype, device=sigma.device) + 0.5) / ss - size / 2.0
    r = torch.sqrt(x[:, None] ** 2 + x[None, :] ** 2)
    # float64 logits: (r / alpha)^beta overflows float32 for small sigma and large beta
    logits = -((r.double() / alpha.double()) ** beta)
    batch = logits.shape[:-2]
    w = torch.softmax(logits.reshape(*batch, -1), dim=-1).reshape(*batch, size, ss, size, ss)
    return w.sum((-1, -3)).to(sigma.dtype)


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
