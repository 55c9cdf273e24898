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

The OTFs depend on ``|f|`` only, so the residual is summed over rings of ``|f|`` a sixteenth
of the spectrum's resolution wide (:data:`RINGS_PER_BIN`): the spectra's powers and cross term
are summed per ring once, and each candidate costs a few thousand OTF values instead of the
whole grid's. On the paper's captures through a disk (512-px region, 10 distances, both
illuminators) the ring sums' minimum over a 0.005-dpt grid is the per-frequency cost's
(:func:`~tdfd.autofocus.cross_blur.profile_cost` on the whole grid) at every one, in 57 ms
against 1.1 s;
the fit searches 0.05-dpt steps over the working powers, then 0.005-dpt steps within two of
the best: 15 ms on a 512-px region, 5 ms on 128 px (2 cores).

Its statistical uncertainty: with white noise the per-frequency residual ``c(P)`` at the
minimum estimates the noise variance per frequency, so the negative log-likelihood is
``N c(P) / c_min`` over ``N`` frequencies and

.. math::

    \sigma_{curve}^2 = \kappa \, c_{min} / (N \, c''(P^*))

with ``c''`` from a parabola through the curve at ``P* +- h`` (which also refines ``P*``
below the search's step) and ``kappa = 2.25`` the Hann window's equivalent noise bandwidth
in two dimensions. On the paper's two bars through a disk this is far too small (1.1-34x
against the scatter of 10 captures at each of 6 distances from 30 to 100 cm, both
illuminators, ``benchmarks/paper_experiment.py``'s captures): the pattern fills few
frequencies, the noise is signal-dependent, and at large blur the curve has several shallow
minima (the projector's blurred bars at 90 cm: two within 0.03 % of each other, 0.08 dpt
apart). The scatter there (0.002-0.044 dpt RMS about the truth) follows the search's contrast
(the median cost over the coarse search over the least, minus one, as
:attr:`~tdfd.autofocus.cross_blur.CrossBlurFocus.contrast`: about 12 for the coherent bars, 1
for the projector's at 1 m), so the fit states

.. math::

    \sigma_{P^*}^2 = \sigma_{curve}^2 + (a + b / contrast)^2 + s_{window}^2

with ``a`` = :data:`FLOOR_DPT` and ``b`` = :data:`CONTRAST_DPT`: there it states 0.013-0.046 dpt,
the RMS error over the stated 0.15-1.31 (2026-11-26, ad hoc). ``s_window``: a small region adds a bias: the Hann
window does not commute with the blur (``w (I * h) != (w I) * h``), and the bars' edges sit on
the window's slope. Noise-free, the paper's bars through a disk at 0.35-1 m were off by up to
0.08 / 0.027 / 0.014 / 0.006 dpt in regions of 128 / 192 / 256 / 384 px (0.0013 at 512 px), so
``s_window`` = :data:`WINDOW_BIAS_DPT` ``x (256 / size)^2.5`` (0.085 dpt at 128 px, 0.0027
at 512): on a small ROI the lit tiles keep their weight. ``q = 1/F(P*) - 1/d_s``, so
``sigma_q = sigma_P``.

Example:
    >>> import numpy as np
    >>> from tdfd import Camera
    >>> from tdfd.autofocus.cross_blur import disk_otf
    >>> from tdfd.autofocus.evidence import sigma_px_per_dpt
    >>> cam = Camera.preset("reference")
    >>> spec = np.fft.rfft2(np.random.default_rng(0).random((256, 256)))
    >>> f = np.sqrt(np.fft.fftfreq(256)[:, None] ** 2 + np.fft.rfftfreq(256)[None, :] ** 2)
    >>> def frame(p, focus=1.5):  # a disk lens's blur, by its OTF
    ...     return np.fft.irfft2(spec * disk_otf(2 * sigma_px_per_dpt(cam) * abs(p - focus), f), s=(256, 256))
    >>> fit = fit_region_cross_blur(frame(1.7), frame(2.7), (1.7, 2.7), cam, psf_family="pillbox")
    >>> q_true = cam.total_power_dpt(1.5) - 1 / cam.sensor_distance_m   # 1.5 1/m: 0.67 m
    >>> round(q_true, 2), round(fit.inverse_depth, 2), round(fit.rel_error * fit.inverse_depth, 3)
    (1.5, 1.5, 0.018)
"""

from __future__ import annotations

import math

import numpy as np

from ..camera import Camera
from ..errors import InputError, RangeError, ShapeError
from ..region_fusion import DEFAULT_MU_UNCERTAINTY, RegionFit, region_sigma_dpt
from .cross_blur import PSF_FAMILIES, profile_cost, windowed_spectra
from .evidence import sigma_px_per_dpt, working_powers_dpt

__all__ = ["fit_region_cross_blur", "ring_costs", "WINDOW_KAPPA", "FLOOR_DPT", "CONTRAST_DPT", "WINDOW_BIAS_DPT", "MIN_REGION_PX", "RINGS_PER_BIN"]

#: the Hann window's equivalent noise bandwidth in two dimensions (module docs).
WINDOW_KAPPA = 2.25
#: the scatter floor of the fit (dpt) and its part inversely proportional to the search's
#: contrast (dpt), measured on the paper's pattern through a disk (module docs).
FLOOR_DPT, CONTRAST_DPT = 0.01, 0.03
#: the window's bias in a 256-px region (dpt), scaled by ``(256 / size)^2.5`` (module docs; measured).
WINDOW_BIAS_DPT = 0.015
#: the smallest region fitted (px), as :data:`tdfd.dfd.region_fit.MIN_REGION_PX`.
MIN_REGION_PX = 64
#: rings of ``|f|`` per frequency bin of the region's spectrum (module docs).
RINGS_PER_BIN = 16
#: the search's coarse step over the working powers, and its fine step (and the parabola's)
#: within two coarse steps of the coarse minimum (dpt).
_COARSE_DPT, _STEP_DPT = 0.05, 0.005


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
        :class:`~tdfd.region_fusion.RegionFit`: ``confidence`` is ``contrast / (1 + contrast)``,
        ``contrast`` the median cost over the searched powers over the least, minus one (as
        :attr:`~tdfd.autofocus.cross_blur.CrossBlurFocus.contrast`).

    Raises:
        ShapeError: frames of different shapes, not 2-D, or smaller than :data:`MIN_REGION_PX`.
        InputError: an unknown family, not two finite powers or less than 0.02 dpt apart,
            non-finite images, a non-positive ``sigma_scale``.
        RangeError: the minimum lies at the edge of the working powers, or the cost curve
            has no curvature there (no estimate to fuse).
    """
    if psf_family not in PSF_FAMILIES:
        raise InputError(f"psf_family must be one of {PSF_FAMILIES}, got {psf_family!r}")
    if len(powers_dpt) != 2 or not all(math.isfinite(float(p)) for p in powers_dpt):
        raise InputError(f"powers_dpt must be the pair's two finite powers (dpt), got {tuple(powers_dpt)}")
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
    if not sigma_scale > 0:
        raise InputError(f"sigma_scale must be > 0, got {sigma_scale}")
    lo, hi = working_powers_dpt(camera)
    coarse = np.arange(lo, hi + 1e-9, _COARSE_DPT)
    rings = _Rings(frames, camera, psf_family, sigma_scale)
    coarse_costs = rings.costs(coarse)
    k = int(np.argmin(coarse_costs))
    if k in (0, len(coarse) - 1):
        raise RangeError(f"the {psf_family} cross-blur minimum lies at the edge of the working powers "
                         f"({coarse[k]:.2f} dpt): the region's depth is outside the camera's range")
    grid = np.arange(coarse[k] - 2 * _COARSE_DPT, coarse[k] + 2 * _COARSE_DPT + 1e-9, _STEP_DPT)
    costs, n_freq = rings.costs(grid), rings.n_freq
    k = int(np.clip(np.argmin(costs), 1, len(grid) - 2))
    c_lo, c_0, c_hi = costs[k - 1:k + 2]
    curvature = (c_lo + c_hi - 2.0 * c_0) / _STEP_DPT**2
    if not (curvature > 0 and math.isfinite(curvature)):
        raise RangeError(f"the {psf_family} cross-blur cost has no curvature at its minimum: no region estimate")
    shift = float(np.clip(0.5 * _STEP_DPT * (c_lo - c_hi) / (c_lo + c_hi - 2.0 * c_0), -_STEP_DPT, _STEP_DPT))
    p_star = float(grid[k]) + shift
    c_min = max(c_0 - 0.5 * curvature * shift**2, 0.0)
    contrast = float(np.median(coarse_costs)) / max(c_min, 1e-300) - 1.0
    floor = FLOOR_DPT + CONTRAST_DPT / max(contrast, 1e-3)
    window = WINDOW_BIAS_DPT * (256.0 / size) ** 2.5
    sigma_p = math.sqrt(WINDOW_KAPPA * c_min / (n_freq * curvature) + floor**2 + window**2)
    q = camera.total_power_dpt(p_star) - 1.0 / camera.sensor_distance_m
    if not q > 0:
        raise RangeError(f"the cross-blur focus {p_star:.3f} dpt lies beyond infinity for this camera")
    rel = sigma_p / q
    return RegionFit(inverse_depth=q, sigma_dpt=region_sigma_dpt(q, rel, camera, psf_family, mu_uncertainty,
                                                                 fit_family=psf_family),
                     rel_error=rel, confidence=float(contrast / (1.0 + contrast)) if contrast > 0 else 0.0,
                     size_px=size, fit_family=psf_family)


class _Rings:
    """The pair's spectra summed over rings of ``|f|`` (module docs), for costs at any candidate."""

    def __init__(self, frames: list[tuple[np.ndarray, float]], camera: Camera, psf_family: str,
                 sigma_scale: float) -> None:
        power, cross, f2, f, self.powers = windowed_spectra(frames, None, (psf_family,))
        if len(power) != 2:
            raise InputError(f"a region fit takes one pair of frames, got {len(power)}")
        rings = np.floor(f * f.shape[0] * RINGS_PER_BIN).astype(np.intp).ravel()
        count = np.bincount(rings)
        used = count > 0
        self.f = np.bincount(rings, f.ravel())[used] / count[used]
        self.p1, self.p2, self.c12 = (np.bincount(rings, x.ravel())[used] for x in (power[0], power[1], cross[(0, 1)]))
        self.m, self.family, self.n_freq = sigma_px_per_dpt(camera) * float(sigma_scale), psf_family, int(f2.size)

    def costs(self, candidates_dpt: np.ndarray) -> np.ndarray:
        """The cost per frequency at each candidate in-focus power (dpt)."""
        power, cross, f2 = [self.p1, self.p2], {(0, 1): self.c12}, self.f**2
        return np.array([profile_cost(power, cross, self.powers - float(c), self.m, self.family, f2, self.f)
                         for c in np.asarray(candidates_dpt, dtype=np.float64)]) / self.n_freq


def ring_costs(frames: list[tuple[np.ndarray, float]], camera: Camera, candidates_dpt: np.ndarray, psf_family: str, *,
               sigma_scale: float = 1.0) -> tuple[np.ndarray, int]:
    """The pair's cross-blur cost per frequency at each candidate in-focus power, summed over
    rings of ``|f|`` (module docs), and the number of frequencies it averages.

    Example:
        >>> rng = np.random.default_rng(0)
        >>> from tdfd import Camera
        >>> a = rng.random((64, 64))                       # equal frames: equal blur, focus midway
        >>> c, n = ring_costs([(a, 1.7), (a, 2.7)], Camera.preset("reference"), np.array([1.9, 2.2, 2.5]), "pillbox")
        >>> int(np.argmin(c)), n
        (1, 2112)
    """
    rings = _Rings(frames, camera, psf_family, sigma_scale)
    return rings.costs(candidates_dpt), rings.n_freq
