r"""A lens PSF: shape between Gaussian and pillbox, diffraction, mild aberration (:class:`PSFModel`).

The synthesiser draws one per sample (``data_synth.params.draw_psf``); the likelihood stage
takes one as its PSF hypothesis (:mod:`tdfd.dfd.psf_hypotheses`) and the calibration measures one
from a focus sweep (:mod:`tdfd.calibration.psf_model`).

Every PSF keeps the tdfd size convention: ``sigma`` is the per-axis RMS radius in pixels
(:mod:`tdfd.optics.psf`), so ``sigma = mu * r_b`` keeps one meaning for every shape.

* **Shape**: ``"gaussian"`` (paper eq. 7), ``"pillbox"`` (uniform disk of radius
  ``2 |sigma|``, the geometric blur circle when ``mu = 1 / (2 pitch)``), or a
  power-exponential ``exp(-(r / alpha)^beta)`` in between (``beta`` 2 to ~16).
* **Diffraction softening**: the Airy pattern of the aperture, approximated by a Gaussian of
  RMS ``0.42 lambda N`` (``N = F / A``, the working f-number) in pixels, convolved with the
  defocus PSF (the RMS radii add in quadrature).
* **Mild aberration**:

  - astigmatism: the PSF is stretched by ``1 + a`` along an axis at ``angle`` and squeezed
    by ``1 - a`` across it; the stretch swaps axes on the other side of focus (``a`` takes
    the sign of ``sigma``), as the sagittal and tangential foci straddle the best focus;
  - spherical aberration: a radial weight ``1 + s (r^2 / (2 sigma^2) - 1)`` with ``s`` of the
    sign of ``sigma``: a bright rim on one side of focus, a bright core on the other. The
    profile is rescaled so that its RMS radius stays ``sigma``.

Only the aberration model lives here: the profiles, their sampling and box integration,
the kernel-size rule and the Gaussian diffraction kernel are :mod:`tdfd.optics.psf`'s
(:func:`~tdfd.optics.psf.sampled_psf` takes the astigmatic metric and the spherical weight
defined here). Kernels sum to one and collapse to a delta as ``sigma -> 0``.

Example:
    >>> import torch
    >>> m = PSFModel(shape="pillbox", astigmatism=0.1, spherical=0.2, diffraction_sigma_px=0.5)
    >>> k = m.kernels(torch.tensor([0.0, 2.0]))
    >>> k.shape[0], [round(float(v), 5) for v in k.sum((-1, -2))]
    (2, [1.0, 1.0])
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from ..errors import InputError
from .psf import (convolve_gaussian, diffraction_pad, full_conv_1d, gaussian_psf_1d, kernel_size_for,
                  power_exponential_psf, psf_kernel, sampled_psf)

__all__ = ["PSFModel", "check_psf_parameters", "kurtosis"]


def kurtosis(beta: float) -> float:
    """``E[r^4] / E[r^2]^2`` of the 2-D profile ``exp(-(r/alpha)^beta)`` (2 Gaussian, 4/3 disk)."""
    if math.isinf(beta):
        return 4.0 / 3.0
    lg = math.lgamma
    return math.exp(lg(6.0 / beta) + lg(2.0 / beta) - 2.0 * lg(4.0 / beta))


def check_psf_parameters(shape: str | float, diffraction_px: float, astigmatism: float, astigmatism_angle: float,
                         spherical: float) -> None:
    """Raise :class:`~tdfd.errors.InputError` naming the first of a lens PSF's parameters out of range:
    ``shape`` ``"gaussian"``, ``"pillbox"`` or a finite ``beta >= 1``; a finite diffraction RMS radius
    ``>= 0`` (px); ``0 <= astigmatism < 0.5`` along a finite angle (rad); ``|spherical| < 0.5``.

    Example:
        >>> check_psf_parameters(5.0, 0.5, 0.1, 0.3, -0.2)
        >>> check_psf_parameters("gaussian", 0.0, 0.5, 0.0, 0.0)
        Traceback (most recent call last):
        ...
        tdfd.errors.InputError: need 0 <= astigmatism < 0.5, a finite angle and |spherical| < 0.5; got 0.5, 0.0, 0.0
    """
    if isinstance(shape, str):
        if shape not in ("gaussian", "pillbox"):
            raise InputError(f"unknown PSF shape {shape!r}; use 'gaussian', 'pillbox' or a beta >= 1")
    elif not (float(shape) >= 1.0 and math.isfinite(float(shape))):
        raise InputError(f"a power-exponential shape needs a finite beta >= 1, got {shape}")
    if not (0.0 <= diffraction_px < math.inf):
        raise InputError(f"the diffraction RMS radius must be finite and >= 0 px, got {diffraction_px}")
    if not (0.0 <= astigmatism < 0.5 and math.isfinite(astigmatism_angle) and abs(spherical) < 0.5):
        raise InputError(f"need 0 <= astigmatism < 0.5, a finite angle and |spherical| < 0.5; got "
                         f"{astigmatism}, {astigmatism_angle}, {spherical}")


@dataclass(frozen=True)
class PSFModel:
    """One sample's lens PSF family (see the module documentation).

    Args:
        shape: ``"gaussian"``, ``"pillbox"``, or a power-exponential exponent ``beta >= 1``.
        diffraction_sigma_px: RMS radius of the diffraction blur in px (0: none).
        astigmatism: relative stretch ``a`` in [0, 0.5).
        astigmatism_angle: axis of the stretch in radians.
        spherical: spherical-aberration weight ``s`` in (-0.5, 0.5).
    """

    shape: str | float = "gaussian"
    diffraction_sigma_px: float = 0.0
    astigmatism: float = 0.0
    astigmatism_angle: float = 0.0
    spherical: float = 0.0

    def __post_init__(self) -> None:
        check_psf_parameters(self.shape, self.diffraction_sigma_px, self.astigmatism, self.astigmatism_angle,
                             self.spherical)

    @property
    def plain(self) -> bool:
        """No aberration: the kernels are exactly :func:`tdfd.optics.psf.psf_kernel`'s."""
        return self.astigmatism == 0 and self.spherical == 0

    @property
    def beta(self) -> float:
        """The power-exponential exponent (2 Gaussian, ``inf`` pillbox)."""
        if self.shape == "gaussian":
            return 2.0
        if self.shape == "pillbox":
            return math.inf
        return float(self.shape)

    @property
    def diffraction_pad(self) -> int:
        """Half-size of the diffraction kernel (:func:`tdfd.optics.psf.diffraction_pad`)."""
        return diffraction_pad(self.diffraction_sigma_px)

    def kernel_size(self, sigma_max: float) -> int:
        """Odd kernel side that holds the PSF of RMS radius ``sigma_max``: the library's rule
        (:func:`tdfd.optics.psf.kernel_size_for`) for the blur grown by the aberration, plus
        the diffraction kernel."""
        grow = (1.0 + self.astigmatism) * (1.0 + 0.5 * abs(self.spherical))
        s = abs(float(sigma_max)) * grow
        return kernel_size_for(s, "pillbox" if self.shape == "pillbox" else "gaussian") + 2 * self.diffraction_pad

    def kernels(self, sigma: torch.Tensor, size: int | None = None, supersample: int | None = None) -> torch.Tensor:
        """PSFs ``(N, k, k)`` for signed blurs ``sigma`` ``(N,)`` in px, unit sum.

        ``supersample`` (odd): evaluate every shape on that many samples per pixel and side and
        box-integrate them, instead of the renderer's fast default (3 below 1.5 px of blur,
        pixel centres above). Finer sampling makes the kernels smooth functions of their
        parameters, as derivatives with respect to them need.
        """
        sigma = sigma.reshape(-1)
        smax = float(sigma.detach().abs().max()) if sigma.numel() else 0.0
        size = self.kernel_size(smax) if size is None else int(size)
        dpad = self.diffraction_pad
        core = size - 2 * dpad
        if supersample is not None:
            if supersample < 1 or supersample % 2 == 0:
                raise InputError(f"supersample must be a positive odd integer, got {supersample}")
            k = self._aberrated(sigma, core, int(supersample))
        elif self.plain:
            k = psf_kernel(sigma, self.shape, core) if isinstance(self.shape, str) else \
                power_exponential_psf(sigma, float(self.shape), core)
        else:  # aberrated: fine supersampling where the PSF is only a few pixels
            k = torch.empty(sigma.numel(), core, core, dtype=sigma.dtype)
            small = sigma.abs() < 1.5
            for mask, ss in ((small, 3), (~small, 1)):
                if bool(mask.any()):
                    k[mask] = self._aberrated(sigma[mask], core, ss)
        if dpad:
            k = convolve_gaussian(k, self.diffraction_sigma_px, dpad)
        return k

    def separable_gaussian(self, sigma: torch.Tensor, size: int) -> tuple[torch.Tensor, torch.Tensor]:
        """The plain Gaussian PSF (with its diffraction blur) as separable 1-D factors."""
        if self.shape != "gaussian" or not self.plain:
            raise InputError("separable kernels exist only for the plain Gaussian")
        dpad = self.diffraction_pad
        k1 = gaussian_psf_1d(sigma.reshape(-1), size - 2 * dpad)
        if dpad:
            g1 = gaussian_psf_1d(torch.tensor([self.diffraction_sigma_px], dtype=k1.dtype), 2 * dpad + 1)
            k1 = full_conv_1d(k1, g1[0], -1)
            k1 = k1 / k1.sum(-1, keepdim=True)
        return k1, k1

    def _aberrated(self, sigma: torch.Tensor, size: int, ss: int = 3) -> torch.Tensor:
        """Kernels of the (possibly aberrated) profile on an ``ss``-times supersampled grid
        (:func:`tdfd.optics.psf.sampled_psf`): the astigmatic stretch is a metric on the
        sample grid, the spherical aberration a radial weight, and the RMS radius is
        rescaled so that the weighted profile keeps ``sigma``."""
        sgn = torch.where(sigma < 0, -1.0, 1.0).to(sigma.dtype)
        s_sph = self.spherical * sgn  # (N,)
        s_ast = self.astigmatism * sgn
        scale = 1.0 / torch.sqrt(1.0 + s_sph * (kurtosis(self.beta) - 1.0))
        radius2 = weight = None
        if self.astigmatism:
            c, s = math.cos(self.astigmatism_angle), math.sin(self.astigmatism_angle)

            def radius2(yy: torch.Tensor, xx: torch.Tensor) -> torch.Tensor:
                u = (c * xx + s * yy)[None] / (1.0 + s_ast)[:, None, None]
                v = (c * yy - s * xx)[None] / (1.0 - s_ast)[:, None, None]
                return u * u + v * v
        if self.spherical:
            def weight(r2: torch.Tensor, sig: torch.Tensor) -> torch.Tensor:
                return (1.0 + s_sph[:, None, None] * (r2 / (2.0 * sig * sig) - 1.0)).clamp_min(0.0)
        return sampled_psf(sigma.abs() * scale, self.beta, size, ss, radius2, weight)
