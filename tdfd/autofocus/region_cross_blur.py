r"""One region's depth from the pair's cross-blur, for a lens told its PSF family (numpy).

The one-region Fourier ratio (:func:`tdfd.dfd.region_fit.fit_region`, paper eqs. 8-13) is
exact for the paper's Gaussian PSF (eq. 7); through a disk (pillbox) lens it is biased by
about half the target's distance in dioptres from the distance the pair blurs equally
(:mod:`tdfd.region_fusion`). A lens calibrated as a disk (``tdfd calibrate``: its
``psf_family`` and ``psf_sigma_scale``) has its own exact model: blurring each frame by the
other's PSF gives the same image whatever the texture, ``I_1 * h_2 = I_2 * h_1``
(:mod:`tdfd.autofocus.cross_blur`), so the in-focus power ``P*`` that minimises the pair's
cross-blur residual over the region, with the disk's OTF ``2 J1(2 pi f R) / (2 pi f R)``, is
the region's depth, ``q = 1/F(P*) - 1/d_s`` (thin lens, paper eq. 1).

Its statistical uncertainty: with white noise the per-frequency residual ``c(P)`` at the
minimum estimates the noise variance per frequency, so the negative log-likelihood is
``N c(P) / c_min`` over ``N`` frequencies and

.. math::

    \sigma_{curve}^2 = \kappa \, c_{min} / (N \, c''(P^*))

with ``c''`` from a parabola through the curve at ``P* +- h`` (which also refines ``P*``
below the search's step) and ``kappa = 2.25`` the Hann window's equivalent noise bandwidth
in two dimensions. On the paper's two bars through a disk this is 1.1-34x too small (10
captures at each of 30-100 cm, both illuminators, ``benchmarks/paper_experiment.py``'s
captures): the pattern fills few frequencies, the noise is signal-dependent, and at large
blur the curve has several shallow minima (the projector's blurred bars at 90 cm: two
within 0.03 % of each other, 0.08 dpt apart). The scatter measured there, 0.002-0.040 dpt,
follows the search's contrast (:attr:`~tdfd.autofocus.cross_blur.CrossBlurFocus.contrast`:
about 12 for the coherent bars, 1 for the projector's at 1 m), so the fit states

.. math::

    \sigma_{P^*}^2 = \sigma_{curve}^2 + (a + b / contrast)^2

with ``a`` = :data:`FLOOR_DPT` and ``b`` = :data:`CONTRAST_DPT`, which covers every scatter
measured there within a factor 1.4 (0.0125-0.046 dpt). ``q = 1/F(P*) - 1/d_s``, so ``sigma_q = sigma_P``.

Example:
    >>> import numpy as np
    >>> from tdfd import Camera
    >>> from tdfd.autofocus.cross_blur import disk_otf
    >>> from tdfd.autofocus.evidence import sigma_px_per_dpt
    >>> cam = Camera.preset("reference")
    >>> spec = np.fft.rfft2(np.random.default_rng(0).random((128, 128)))
    >>> f = np.sqrt(np.fft.fftfreq(128)[:, None] ** 2 + np.fft.rfftfreq(128)[None, :] ** 2)
    >>> def frame(p, focus=1.5):  # a disk lens's blur, by its OTF
    ...     return np.fft.irfft2(spec * disk_otf(2 * sigma_px_per_dpt(cam) * abs(p - focus), f), s=(128, 128))
    >>> fit = fit_region_cross_blur(frame(1.7), frame(2.7), (1.7, 2.7), cam, psf_family="pillbox")
    >>> q_true = cam.total_power_dpt(1.5) - 1 / cam.sensor_distance_m   # 1.5 1/m: 0.67 m
    >>> round(q_true, 2), round(fit.inverse_depth, 2), fit.rel_error * fit.inverse_depth < 0.02
    (1.5, 1.5, True)
"""

from __future__ import annotations

import math

import numpy as np

from ..camera import Camera
from ..errors import InputError, RangeError, ShapeError
from ..region_fusion import DEFAULT_MU_UNCERTAINTY, RegionFit, region_sigma_dpt
from .cross_blur import PSF_FAMILIES, cross_blur_costs, cross_blur_focus

__all__ = ["fit_region_cross_blur", "WINDOW_KAPPA", "FLOOR_DPT", "CONTRAST_DPT", "MIN_REGION_PX"]

#: the Hann window's equivalent noise bandwidth in two dimensions (module docs).
WINDOW_KAPPA = 2.25
#: the scatter floor of the fit (dpt) and its part inversely proportional to the search's
#: contrast (dpt), measured on the paper's pattern through a disk (module docs).
FLOOR_DPT, CONTRAST_DPT = 0.01, 0.03
#: the smallest region fitted (px), as :data:`tdfd.dfd.region_fit.MIN_REGION_PX`.
MIN_REGION_PX = 64
#: the step of the search and of the parabola around its minimum (dpt).
_FINE_DPT = 0.01


def fit_region_cross_blur(image_f1: np.ndarray, image_f2: np.ndarray, powers_dpt: tuple[float, float],
                          camera: Camera, *, psf_family: str, sigma_scale: float = 1.0,
                          mu_uncertainty: float = DEFAULT_MU_UNCERTAINTY) -> RegionFit:
    """The depth of the central square of a pair by its cross-blur with a told PSF family.

    Args:
        image_f1, image_f2: ``(H, W)`` linear intensity (any array-like, e.g. a ``(1, 1, H, W)``
            tensor's numpy view squeezed).
        powers_dpt: the ECVFL powers the two frames were taken at (dpt).
        camera: thin lens and ``mu`` (px of Gaussian sigma per dioptre of defocus, eq. 7).
        psf_family: ``"pillbox"`` (a disk lens) or ``"gaussian"``.
        sigma_scale: the family's RMS blur per dioptre over the camera's (a camera file's
            ``psf_sigma_scale``).
        mu_uncertainty: relative uncertainty of ``mu`` (times ``sigma_scale``), for the
            fit's uncertainty (:func:`tdfd.region_fusion.region_sigma_dpt`).

    Returns:
        :class:`~tdfd.region_fusion.RegionFit`: ``confidence`` is ``contrast / (1 + contrast)`` of
        the search (:attr:`~tdfd.autofocus.cross_blur.CrossBlurFocus.contrast`).

    Raises:
        ShapeError: frames of different shapes, not 2-D, or smaller than :data:`MIN_REGION_PX`.
        InputError: an unknown family, powers less than 0.02 dpt apart, non-finite images.
        RangeError: the minimum lies at the edge of the working powers, or the cost curve
            has no curvature there (no estimate to fuse).
    """
    if psf_family not in PSF_FAMILIES:
        raise InputError(f"psf_family must be one of {PSF_FAMILIES}, got {psf_family!r}")
    a, b = (np.asarray(im, dtype=np.float64) for im in (image_f1, image_f2))
    a, b = (x.reshape(x.shape[-2:]) if x.ndim == 4 and x.shape[:2] == (1, 1) else x for x in (a, b))
    if a.shape != b.shape or a.ndim != 2:
        raise ShapeError(f"frames must be (H, W) of one shape, got {a.shape} and {b.shape}")
    if not (np.isfinite(a).all() and np.isfinite(b).all()):
        raise InputError("frames hold NaN or inf")
    h, w = a.shape
    size = min(h, w) - min(h, w) % 2
    if size < MIN_REGION_PX:
        raise ShapeError(f"a region of {h}x{w} px is smaller than the {MIN_REGION_PX} px a region fit needs")
    top, left = (h - size) // 2, (w - size) // 2
    frames = [(a[top:top + size, left:left + size], float(powers_dpt[0])),
              (b[top:top + size, left:left + size], float(powers_dpt[1]))]
    best = cross_blur_focus(frames, camera, shapes=(psf_family,), sigma_scale=sigma_scale, fine_dpt=_FINE_DPT)
    if best.at_edge:
        raise RangeError(f"the {psf_family} cross-blur minimum lies at the edge of the working powers "
                         f"({best.power_dpt:.2f} dpt): the region's depth is outside the camera's range")
    p0 = best.power_dpt
    c_lo, c_0, c_hi = cross_blur_costs(frames, camera, [p0 - _FINE_DPT, p0, p0 + _FINE_DPT], psf_family,
                                       sigma_scale=sigma_scale)
    curvature = (c_lo + c_hi - 2.0 * c_0) / _FINE_DPT**2
    if not (curvature > 0 and math.isfinite(curvature)):
        raise RangeError(f"the {psf_family} cross-blur cost has no curvature at its minimum: no region estimate")
    shift = float(np.clip(_FINE_DPT * (c_lo - c_hi) / (2.0 * (c_lo + c_hi - 2.0 * c_0)), -_FINE_DPT, _FINE_DPT))
    p_star = p0 + shift
    c_min = max(c_0 - 0.5 * curvature * shift**2, 0.0)
    n_freq = size * (size // 2 + 1)
    floor = FLOOR_DPT + CONTRAST_DPT / max(best.contrast, 1e-3)
    sigma_p = math.sqrt(WINDOW_KAPPA * c_min / (n_freq * curvature) + floor**2)
    q = camera.total_power_dpt(p_star) - 1.0 / camera.sensor_distance_m
    if not q > 0:
        raise RangeError(f"the cross-blur focus {p_star:.3f} dpt lies beyond infinity for this camera")
    rel = sigma_p / q
    return RegionFit(inverse_depth=q, sigma_dpt=region_sigma_dpt(q, rel, camera, psf_family, mu_uncertainty,
                                                                 fit_family=psf_family),
                     rel_error=rel, confidence=float(best.contrast / (1.0 + best.contrast)) if best.contrast > 0 else 0.0,
                     size_px=size)
