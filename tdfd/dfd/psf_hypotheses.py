r"""The lens PSFs a likelihood fit tries: the defocus profile's shape, with or without diffraction,
or the one PSF a calibration measured.

A real lens's defocus PSF lies between a Gaussian (aberrations and diffraction smooth the
blur circle; paper eq. 7) and a uniform disk (the geometric blur circle); tdfd writes every
shape as the power-exponential profile ``exp(-(r / alpha)^beta)`` of RMS radius ``sigma``
(:mod:`tdfd.optics.psf`: ``beta = 2`` Gaussian, ``beta -> inf`` pillbox), so one blur
``sigma = M |P - P*|`` (paper eq. 7) means the same for every shape. Diffraction softens it:
the Airy pattern of the working f-number ``N``, approximated by a Gaussian of RMS radius
``0.42 lambda N`` (metres; divided by the pixel pitch for pixels) convolved with the defocus
profile. A :class:`PsfHypothesis` is one such PSF, with the mild astigmatism and spherical
aberration of :class:`tdfd.optics.aberrated_psf.PSFModel` when a calibration measured them
(:mod:`tdfd.calibration.psf_model`, the camera file's ``psf_model``); :func:`psf_hypotheses` the
set a fit profiles over when the camera's family is measured (the camera file's ``psf_family``)
or not.

Example:
    >>> import torch
    >>> from tdfd import Camera
    >>> hyps = psf_hypotheses(Camera.preset("reference"), "pillbox")
    >>> [(h.shape, round(h.diffraction_px, 2)) for h in hyps]
    [('pillbox', 0.0), ('pillbox', 0.62)]
    >>> k = hyps[1].kernels(torch.tensor([2.0, -3.0], dtype=torch.float64), 21)
    >>> tuple(k.shape), [round(float(v), 6) for v in k.sum((-1, -2))]
    ((2, 21, 21), [1.0, 1.0])
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch

from ..camera import Camera
from ..camera_file import check_psf_model
from ..errors import InputError, ShapeError
from ..optics.aberrated_psf import PSFModel, check_psf_parameters
from ..optics.psf import (PSFShape, convolve_gaussian, diffraction_pad, diffraction_sigma_px, kernel_size_for,
                          psf_kernel)

__all__ = ["SHAPES", "WAVELENGTH_M", "PsfHypothesis", "diffraction_px", "psf_hypotheses"]

#: The profile shapes tried when the family is not measured: pillbox, power-exponential ``beta`` of
#: kurtosis steps between, Gaussian.
SHAPES: tuple[PSFShape, ...] = ("pillbox", 10.0, 5.0, 1 / 0.3, 2.5, "gaussian")
#: The wavelength of the diffraction hypothesis (m): a red laser pattern, the paper's assist light.
WAVELENGTH_M = 650e-9


def diffraction_px(camera: Camera, wavelength_m: float = WAVELENGTH_M) -> float:
    """RMS radius in px of the Gaussian approximation of the Airy pattern at frame 1's working
    f-number ``N = F1 / A`` (:func:`tdfd.optics.psf.diffraction_sigma_px`).

    Raises:
        InputError: a wavelength that is not finite and > 0.
    """
    if not (wavelength_m > 0 and wavelength_m < 1e-3):
        raise InputError(f"wavelength must be in (0, 1 mm), got {wavelength_m} m")
    return diffraction_sigma_px(camera.focal_lengths_m[0] / camera.aperture_m, wavelength_m, camera.pixel_pitch_m)


@dataclass(frozen=True)
class PsfHypothesis:
    """One lens PSF: a defocus profile's shape, a diffraction blur and mild aberrations.

    Args:
        shape: ``"gaussian"``, ``"pillbox"`` or a power-exponential exponent ``beta >= 1``.
        diffraction_px: RMS radius of the Gaussian diffraction blur in px (0: none).
        astigmatism: relative stretch in [0, 0.5) along ``astigmatism_angle`` (radians), which
            swaps axes across focus (:class:`~tdfd.optics.aberrated_psf.PSFModel`).
        spherical: spherical-aberration weight in (-0.5, 0.5), of the blur's sign.
        sigma_scale: the PSF's RMS blur over the camera's ``sigma = M (P - P*)`` (1: the camera's
            ``mu`` is the lens's; a disk lens calibrated by the Gaussian relative blur has about
            1.25), in [0.2, 5].
    """

    shape: PSFShape = "gaussian"
    diffraction_px: float = 0.0
    astigmatism: float = 0.0
    astigmatism_angle: float = 0.0
    spherical: float = 0.0
    sigma_scale: float = 1.0

    def __post_init__(self) -> None:
        check_psf_parameters(self.shape, self.diffraction_px, self.astigmatism, self.astigmatism_angle, self.spherical)
        if not 0.2 <= self.sigma_scale <= 5.0:
            raise InputError(f"sigma_scale must lie in [0.2, 5], got {self.sigma_scale}")

    @property
    def aberrated(self) -> bool:
        """Whether the PSF has astigmatism or spherical aberration."""
        return self.astigmatism != 0.0 or self.spherical != 0.0

    @classmethod
    def from_dict(cls, data: Any) -> "PsfHypothesis":
        """The PSF of a camera file's measured ``psf_model`` (:func:`tdfd.camera_file.check_psf_model`).

        Raises:
            CameraError: a mapping that is not a valid ``psf_model``.
        """
        d = check_psf_model(data)
        return cls(d["shape"], d["diffraction_px"], d["astigmatism"], d["astigmatism_angle_rad"], d["spherical"],
                   d["sigma_scale"])

    def to_dict(self) -> dict[str, Any]:
        """The PSF as a camera file's ``psf_model`` holds it (angles in radians)."""
        return {"shape": self.shape if isinstance(self.shape, str) else float(self.shape),
                "diffraction_px": float(self.diffraction_px), "astigmatism": float(self.astigmatism),
                "astigmatism_angle_rad": float(self.astigmatism_angle), "spherical": float(self.spherical),
                "sigma_scale": float(self.sigma_scale)}

    def model(self) -> PSFModel:
        """The same PSF as a :class:`~tdfd.optics.aberrated_psf.PSFModel` (the renderer's; its blur is
        the camera's times :attr:`sigma_scale`)."""
        return PSFModel(self.shape, self.diffraction_px, self.astigmatism, self.astigmatism_angle, self.spherical)

    @property
    def diffraction_pad(self) -> int:
        """Half-size of the diffraction kernel (:func:`tdfd.optics.psf.diffraction_pad`)."""
        return diffraction_pad(self.diffraction_px)

    def kernel_size(self, sigma_max: float) -> int:
        """Odd side that holds the PSF of the camera's RMS blur ``sigma_max`` px (times
        :attr:`sigma_scale`), its aberrations and its diffraction."""
        sigma_max = abs(float(sigma_max)) * self.sigma_scale
        if self.aberrated:
            return self.model().kernel_size(sigma_max)
        return kernel_size_for(sigma_max, "pillbox" if self.shape == "pillbox" else "gaussian") \
            + 2 * self.diffraction_pad

    def kernels(self, sigma: torch.Tensor, size: int) -> torch.Tensor:
        """PSFs ``(N, size, size)`` of unit sum for the camera's signed blurs ``sigma`` ``(N,)`` px
        (times :attr:`sigma_scale`; a ``size`` below :meth:`kernel_size` truncates them, each
        renormalised).

        Raises:
            ShapeError: an even ``size`` or one that leaves no room inside the diffraction pad.
        """
        pad = self.diffraction_pad
        if size % 2 == 0 or size - 2 * pad < 1:
            raise ShapeError(f"kernel size must be odd and above {2 * pad}, got {size}")
        sigma = sigma.reshape(-1) * self.sigma_scale
        if self.aberrated:
            return self.model().kernels(sigma, size)
        k = psf_kernel(sigma, self.shape, size - 2 * pad)
        return convolve_gaussian(k, self.diffraction_px, pad) if pad else k


def psf_hypotheses(camera: Camera, family: str | None = None, wavelength_m: float = WAVELENGTH_M
                   ) -> tuple[PsfHypothesis, ...]:
    """The PSFs a fit profiles over: the measured family's shape (``"gaussian"`` or
    ``"pillbox"``; ``None`` or ``"unknown"``: every shape of :data:`SHAPES`), each without and
    with the diffraction of :func:`diffraction_px`.

    Raises:
        InputError: an unknown family or a bad wavelength.
    """
    if family in (None, "unknown"):
        shapes: tuple[PSFShape, ...] = SHAPES
    elif family in ("gaussian", "pillbox"):
        shapes = (family,)
    else:
        raise InputError(f"psf family must be 'gaussian', 'pillbox', 'unknown' or None, got {family!r}")
    d = diffraction_px(camera, wavelength_m)
    return tuple(PsfHypothesis(sh, dd) for dd in (0.0, d) for sh in shapes)
