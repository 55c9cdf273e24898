r"""One region's analytic fit: its full uncertainty, and its fusion with a tile estimate (torch-free).

A sparse pattern (the assist light's two bars on a dark, texture-less target) gives a cue
only along its edges: a handful of 64-px tiles each see a piece of it, while one Fourier
ratio over a region holding the whole pattern (paper sec. 4: "one region covering the
pattern") pools every edge into one fit. Where the lens's blur is Gaussian (the paper's
eq. 7) that fit is the better estimate; through a disk (pillbox) lens it is biased by its
model, by about half the target's distance in dioptres from the distance the pair blurs
equally (measured: 0.52-0.57 x ``|q - q_eq|`` at 35-70 cm on the paper's pattern,
``benchmarks.paper_experiment --optics pillbox``), where the refinement CNN, told the family,
is not. Neither is always better, so the two are weighed by their uncertainties:

.. math::

    \sigma_R^2 = (e_{rel} q)^2 + (2 u_\mu (q - q_{eq}))^2 + (s_{shape} (q - q_{eq}))^2

with ``e_rel`` the fit's own predicted relative error (:class:`~tdfd.dfd.FourierRatioDFD`),
``u_mu`` the relative uncertainty of ``mu`` (a pair's estimate moves by ``2 u_mu (q - q_eq)``
dpt when ``mu`` is off by ``u_mu``: :mod:`tdfd.dfd.calibrate`, *Conditioning*), and
``s_shape`` the PSF family's model term (:data:`SHAPE_SIGMA`: 0 for a Gaussian lens). A lens
told it is a disk has its own exact region fit, the pair's disk cross-blur
(:mod:`tdfd.autofocus.region_cross_blur`), whose shape term is 0 for it
(:func:`region_sigma_dpt`'s ``fit_family``).

The two estimates are not independent: the tiles see a subset of the region's pixels, so
their noise is part of the region's. For an efficient estimator ``R`` and any unbiased ``T``
of the same quantity ``cov(R, T) = var(R)`` (Rao, *Linear Statistical Inference*, 5a.2), so
the region's statistical term ``(e_rel q)^2`` is the covariance of the two (capped at the
tiles' own variance), while its ``mu`` and shape terms, and the model's own error, are
independent. The fused inverse depth is the best linear unbiased combination of two
correlated estimates (:func:`fuse_inverse_depths` with ``covariance``): a tile estimate
noisier than the region's statistics adds information only where the region has a
systematic term, and none on a Gaussian lens with ``mu`` known. All in inverse depth
``q = 1/d`` (dpt), where blur is linear (paper eq. 4). The fit itself (torch) is
:func:`tdfd.dfd.region_fit.fit_region`; this module needs numpy only (the autofocus loop and
the device runtime import it without torch).

Example:
    >>> q, s, chi = fuse_inverse_depths(2.0, 0.01, 2.1, 0.03)
    >>> round(q, 3), round(s, 4), round(chi, 2)
    (2.01, 0.0095, 3.16)
    >>> fuse_inverse_depths(2.0, 0.01, 2.1, 0.03, covariance=0.01**2)[:2]   # b's noise holds all of a's
    (2.0, 0.01)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from .camera import Camera
from .errors import InputError

__all__ = ["SHAPE_SIGMA", "DEFAULT_MU_UNCERTAINTY", "RegionFit", "region_sigma_dpt", "fusion_weight", "fuse_inverse_depths"]

#: PSF-family model term ``s_shape`` of a Gaussian region fit (module docs): none for a
#: Gaussian lens; for a disk (pillbox) lens or an unmeasured one (``None``) the measured bias
#: of the Gaussian fit through a disk, 0.52-0.57 x ``|q - q_eq|``, rounded up.
SHAPE_SIGMA = {"gaussian": 0.0, "pillbox": 0.6, None: 0.6}
#: relative uncertainty of ``mu`` assumed when nothing better is known (a datasheet ``mu``).
DEFAULT_MU_UNCERTAINTY = 0.02


def region_sigma_dpt(inverse_depth: float, rel_error: float, camera: Camera, psf_family: str | None = None,
                     mu_uncertainty: float = DEFAULT_MU_UNCERTAINTY, fit_family: str = "gaussian") -> float:
    """Standard uncertainty (dpt) of a region fit's inverse depth (module docs).

    Args:
        inverse_depth: the fit's ``q`` (1/m).
        rel_error: its predicted relative error (statistical).
        camera: the camera (its equal-blur inverse depth, :attr:`~tdfd.camera.Camera.equal_blur_inverse_depth`).
        psf_family: the lens's family as told, ``"gaussian"``, ``"pillbox"`` or ``None`` (unknown).
        mu_uncertainty: relative uncertainty of the ``mu`` the fit used.
        fit_family: the PSF model of the fit itself: ``"gaussian"`` (the Fourier ratio,
            :data:`SHAPE_SIGMA`'s shape term where the lens is not known to be Gaussian) or
            ``"pillbox"`` (a disk cross-blur fit, :mod:`tdfd.autofocus.region_cross_blur`:
            no shape term for a lens told pillbox, the same 0.6 otherwise).

    Example:
        >>> from tdfd import Camera
        >>> cam = Camera.preset("reference")                   # equal blur at 1/2.2 m
        >>> round(region_sigma_dpt(2.2, 0.001, cam, "pillbox"), 4)   # at q_eq only the statistics count
        0.0022
        >>> round(region_sigma_dpt(1.2, 0.0, cam, "pillbox", mu_uncertainty=0.0), 2)
        0.6
    """
    if psf_family not in SHAPE_SIGMA:
        raise InputError(f"psf_family must be one of {list(SHAPE_SIGMA)}, got {psf_family!r}")
    if fit_family not in ("gaussian", "pillbox"):
        raise InputError(f"fit_family must be 'gaussian' or 'pillbox', got {fit_family!r}")
    for name, v in (("inverse_depth", inverse_depth), ("rel_error", rel_error), ("mu_uncertainty", mu_uncertainty)):
        if not (math.isfinite(v) and v >= 0):
            raise InputError(f"{name} must be finite and >= 0, got {v}")
    q_eq = camera.equal_blur_inverse_depth
    off = abs(inverse_depth - q_eq) if q_eq is not None else inverse_depth
    shape = 0.0 if psf_family == fit_family else SHAPE_SIGMA["pillbox"]  # the model's bias through the other family
    return math.sqrt((rel_error * inverse_depth) ** 2 + (2.0 * mu_uncertainty * off) ** 2 + (shape * off) ** 2)


def fusion_weight(sigma_a: float, sigma_b: float, covariance: float = 0.0) -> float:
    """Weight of estimate ``a`` in the best linear unbiased mean of two (:func:`fuse_inverse_depths`):
    ``(sigma_b^2 - c) / (sigma_a^2 + sigma_b^2 - 2c)``; 0 for an infinite ``sigma_a``, 1 for an
    infinite ``sigma_b``, 1/2 for two fully correlated estimates of equal uncertainty.

    Example:
        >>> round(fusion_weight(0.03, 0.01), 2), fusion_weight(0.03, 0.01, covariance=0.01**2)
        (0.1, 0.0)
    """
    if math.isinf(sigma_a) or math.isinf(sigma_b):
        return 0.0 if math.isinf(sigma_a) else 1.0
    va, vb = sigma_a**2, sigma_b**2
    v_diff = va + vb - 2.0 * covariance
    if v_diff <= 1e-12 * (va + vb):
        return 0.5
    return (vb - covariance) / v_diff


def fuse_inverse_depths(q_a: float, sigma_a: float, q_b: float, sigma_b: float,
                        covariance: float = 0.0) -> tuple[float, float, float]:
    """Best linear unbiased mean of two inverse-depth estimates, independent or correlated.

    With ``c`` the covariance of their errors, the weight of ``a`` is
    ``w = (sigma_b^2 - c) / (sigma_a^2 + sigma_b^2 - 2c)``, the fused variance
    ``(sigma_a^2 sigma_b^2 - c^2) / (sigma_a^2 + sigma_b^2 - 2c)`` and the two estimates differ
    by ``sqrt(sigma_a^2 + sigma_b^2 - 2c)`` in standard deviation (Aitken's generalised least
    squares for two measurements). ``c = 0``: the inverse-variance mean; ``c = sigma_a^2``
    (``a``'s error a part of ``b``'s, as a subset's noise is of the whole set's): ``a`` alone.
    An estimate with an infinite uncertainty carries no weight (both infinite: an error).

    Args:
        q_a, sigma_a, q_b, sigma_b: the estimates (1/m) and their standard uncertainties (dpt).
        covariance: of their errors (dpt^2), ``|c| <= sigma_a sigma_b`` (Cauchy-Schwarz);
            ignored where an uncertainty is infinite.

    Returns:
        ``(q, sigma, discrepancy)``: the fused inverse depth and its standard uncertainty
        (dpt), and the two estimates apart in standard deviations of their difference
        (``inf`` when that is 0 and they differ).

    Raises:
        InputError: a NaN, a non-positive or NaN uncertainty, two infinite ones, or a
            covariance that is NaN or beyond ``sigma_a sigma_b``.
    """
    for name, v in (("q_a", q_a), ("q_b", q_b), ("sigma_a", sigma_a), ("sigma_b", sigma_b), ("covariance", covariance)):
        if math.isnan(v):
            raise InputError(f"{name} is NaN")
    if not (sigma_a > 0 and sigma_b > 0):
        raise InputError(f"uncertainties must be > 0, got {sigma_a} and {sigma_b}")
    if math.isinf(sigma_a) and math.isinf(sigma_b):
        raise InputError("both estimates have an infinite uncertainty: nothing to fuse")
    if math.isinf(sigma_a):
        return q_b, sigma_b, 0.0
    if math.isinf(sigma_b):
        return q_a, sigma_a, 0.0
    if not (math.isfinite(q_a) and math.isfinite(q_b)):
        raise InputError(f"estimates with finite uncertainties must be finite, got {q_a} and {q_b}")
    va, vb = sigma_a**2, sigma_b**2
    if not abs(covariance) <= sigma_a * sigma_b * (1 + 1e-12):
        raise InputError(f"covariance {covariance} exceeds sigma_a * sigma_b = {sigma_a * sigma_b} (Cauchy-Schwarz)")
    c = max(-sigma_a * sigma_b, min(covariance, sigma_a * sigma_b))
    v_diff = va + vb - 2.0 * c
    if v_diff <= 1e-12 * (va + vb):  # fully correlated with equal uncertainties: the same estimate twice
        chi = 0.0 if q_a == q_b else math.inf
        return 0.5 * (q_a + q_b), math.sqrt(max(c, 0.0)), chi
    w_a = fusion_weight(sigma_a, sigma_b, c)
    q = w_a * q_a + (1.0 - w_a) * q_b
    var = max((va * vb - c * c) / v_diff, 0.0)
    return q, math.sqrt(var), abs(q_a - q_b) / math.sqrt(v_diff)


@dataclass(frozen=True)
class RegionFit:
    """One fit over a region: the Gaussian Fourier ratio (:func:`tdfd.dfd.region_fit.fit_region`)
    or a disk lens's cross-blur (:func:`tdfd.autofocus.region_cross_blur.fit_region_cross_blur`).

    Attributes:
        inverse_depth: ``q`` (1/m), clamped to the estimator's extended range.
        sigma_dpt: its standard uncertainty (:func:`region_sigma_dpt`).
        rel_error: the fit's own predicted relative error (statistical: :attr:`noise_sigma_dpt`).
        confidence: the estimator's confidence in [0, 1].
        size_px: the side of the square region fitted.
        fit_family: the PSF model of the fit, ``"gaussian"`` or ``"pillbox"``.
    """

    inverse_depth: float
    sigma_dpt: float
    rel_error: float
    confidence: float
    size_px: int
    fit_family: str = "gaussian"

    @property
    def noise_sigma_dpt(self) -> float:
        """The statistical part of :attr:`sigma_dpt` (dpt), ``rel_error * inverse_depth``: the
        noise of the region's pixels, which a subset of them (the lit tiles) shares."""
        return self.rel_error * self.inverse_depth
