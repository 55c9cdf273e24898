r"""The controller's own evidence that a focus is right, before it declares it.

Two kinds, both in ECVFL dioptres of focus error and, through the thin lens, pixels of
residual blur (the success criterion is a geometric blur radius under 1 px):

* **The estimate's uncertainty** (no extra frame): the depth model's per-tile confidence
  is a monotone map of its predicted Laplace scale ``b`` of the relative inverse-depth
  error, ``conf = 1 / (1 + (b / b0)^2)`` (tdfd.model; the analytic estimator's ``b`` is its
  predicted relative error). :func:`estimate_uncertainty` inverts it, takes the median over
  the ROI's tiles (the tiles' errors are largely shared by the plane, so they are not
  averaged down) and combines it with the tiles' disagreement.
* **The DFD pair without the model** (:func:`pair_focus_interval`): the relative blur of
  the two frames bounds the in-focus power; the model's estimate must fall inside.
* **A verification frame** at the in-focus power (:func:`verify_focus`): the relative blur
  between it and each earlier frame of the run (the DFD pair, earlier verification frames)
  is measured directly on the ROI (:func:`relative_blur_px2`, no depth model involved).
  With Gaussian blur ``sigma = M |P - P*|`` (``M = mu (A/2) d_s`` px/dpt, paper eqs. 3 and
  7), a reference frame at ``P_k`` and the verification frame at ``P_v`` give
  ``sigma_k^2 - sigma_v^2 = M^2 (P_k - P_v)(P_k + P_v - 2 P*)``, which is linear in the
  in-focus power ``P*``: every reference frame is one more DFD measurement of the focus
  error ``e = P_v - P*``, taken with one frame near focus.

Sign convention: ``e > 0`` when the lens's power is above the power that focuses the ROI.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from ..camera import Camera, in_focus_power_dpt
from ..errors import InputError
from .aggregate import DepthAggregate
from .relative_blur import relative_blur, relative_blur_px2, relative_blur_search_px2
from .roi import Roi
from .sharpness import noise_variance, sharpness

__all__ = [
    "LAPLACE_STD_PER_SCALE",
    "blur_px_per_dpt",
    "sigma_px_per_dpt",
    "working_powers_dpt",
    "relative_error_scale",
    "FocusUncertainty",
    "estimate_uncertainty",
    "relative_blur_px2",
    "relative_blur_search_px2",
    "shared_noise_variance",
    "FocusCheck",
    "verify_focus",
    "pair_focus_interval",
    "FocusEstimate",
    "combine_focus_error",
]


def blur_px_per_dpt(camera: Camera) -> float:
    """Geometric blur radius (px) per dioptre of focus error: ``(A/2) d_s / pixel pitch`` (paper eq. 3)."""
    return camera.blur_scale_m_dpt / camera.pixel_pitch_m


def working_powers_dpt(camera: Camera, margin_dpt: float = 0.15) -> tuple[float, float]:
    """``(lo, hi)``: the ECVFL powers that focus the camera's depth range (far, near), each
    widened by ``margin_dpt``. A power outside focuses no target the camera is made for.

    Example:
        >>> from tdfd import Camera
        >>> lo, hi = working_powers_dpt(Camera.preset("reference"))
        >>> lo < hi
        True
    """
    near, far = camera.depth_range_m
    return in_focus_power_dpt(camera, far) - margin_dpt, in_focus_power_dpt(camera, near) + margin_dpt


#: standard deviation of a Laplace distribution per unit of its scale ``b``: ``sqrt(2)``
LAPLACE_STD_PER_SCALE = math.sqrt(2.0)


def sigma_px_per_dpt(camera: Camera) -> float:
    """Gaussian PSF standard deviation (px) per dioptre of focus error: ``M = mu (A/2) d_s`` (paper eq. 7)."""
    return camera.mu_px_per_m * camera.blur_scale_m_dpt


def relative_error_scale(confidence: np.ndarray, confidence_scale: float) -> np.ndarray:
    """The predicted relative inverse-depth error scale ``b = b0 sqrt(1/conf - 1)`` behind a confidence.

    Args:
        confidence: per-tile confidence in [0, 1].
        confidence_scale: ``b0``, the relative error at which the confidence is 0.5.

    Example:
        >>> float(relative_error_scale(np.array(0.5), 0.01))
        0.01
    """
    if not confidence_scale > 0:
        raise InputError(f"confidence_scale must be > 0, got {confidence_scale}")
    c = np.clip(np.asarray(confidence, dtype=np.float64), 1e-12, 1.0)
    return confidence_scale * np.sqrt(1.0 / c - 1.0)


@dataclass(frozen=True)
class FocusUncertainty:
    """How far off the in-focus power of an ROI estimate may be.

    Attributes:
        relative_error: median predicted relative error of ``1/d_o`` over the ROI's tiles.
        model_dpt: that error in dioptres (``relative_error / d_o``).
        spread_dpt: the inlier tiles' disagreement (weighted standard deviation, 1/m).
        sigma_dpt: ``sqrt(model_dpt^2 + spread_dpt^2)`` (dpt).
        blur_px: ``sigma_dpt`` as a geometric blur radius (px).

    ``model_dpt`` is a Laplace scale ``b``, not a standard deviation: :attr:`std_dpt` is the
    standard deviation a weighted mean with another estimate needs.
    """

    relative_error: float
    model_dpt: float
    spread_dpt: float
    sigma_dpt: float
    blur_px: float

    @property
    def std_dpt(self) -> float:
        """The estimate's standard deviation (dpt): ``sqrt(2 model_dpt^2 + spread_dpt^2)``.

        The model's scale is the Laplace ``b`` it was trained and calibrated as (median
        ``|e| = b ln 2``), whose standard deviation is ``sqrt(2) b``; the spread is already a
        standard deviation. What a fusion with another estimate (variances, a discrepancy in
        standard deviations: :func:`tdfd.autofocus.lit_tiles.fuse_with_region`) needs. For the
        analytic estimator alone, whose scale is its predicted error (a standard deviation),
        this is ``sqrt(2)`` wide: a fusion then leans towards the other estimate.

        Example:
            >>> round(FocusUncertainty(0.05, 0.05, 0.0, 0.05, 0.1).std_dpt, 4)
            0.0707
        """
        return math.hypot(LAPLACE_STD_PER_SCALE * self.model_dpt, self.spread_dpt)


def estimate_uncertainty(aggregate: DepthAggregate, confidence: np.ndarray, mask: np.ndarray, camera: Camera,
                         confidence_scale: float) -> FocusUncertainty:
    """The uncertainty of an ROI's in-focus power from the model's own confidence and the tiles' agreement.

    Args:
        aggregate: the ROI's :class:`~tdfd.autofocus.aggregate.DepthAggregate`.
        confidence: ``(h, w)`` per-tile confidence.
        mask: ``(h, w)`` the ROI's tiles.
        camera: thin-lens constants (blur per dioptre).
        confidence_scale: the estimator's ``b0`` (see :func:`relative_error_scale`).

    Returns:
        A :class:`FocusUncertainty`; infinite if the ROI has no finite confidence.
    """
    c = np.asarray(confidence, dtype=np.float64)[np.asarray(mask, bool)]
    c = c[np.isfinite(c)]
    q = aggregate.inverse_depth
    if c.size == 0 or not math.isfinite(q) or q <= 0:
        return FocusUncertainty(math.inf, math.inf, aggregate.spread_dpt, math.inf, math.inf)
    rel = float(np.median(relative_error_scale(c, confidence_scale)))
    model = rel * q
    sigma = math.hypot(model, aggregate.spread_dpt)
    return FocusUncertainty(rel, model, aggregate.spread_dpt, sigma, sigma * blur_px_per_dpt(camera))


# ------------------------------------------------------------------ verification
def shared_noise_variance(frames: Sequence[np.ndarray], roi: Roi | None = None) -> float:
    """The sensor noise variance the frames of one scene share: the smallest
    :func:`~tdfd.autofocus.sharpness.noise_variance` of their ROIs.

    The frames see one scene at one exposure, so their noise is the same; what differs is
    how much of a sharp frame's texture leaks into the estimator's pass band (a sharp
    checkerboard or stripe pattern can read 3-10x the true noise). The blurriest frame's
    estimate is the least inflated, and an inflated estimate would bias
    :func:`relative_blur_px2` towards zero (its noise correction would be too large).

    Raises:
        InputError: no frame.
    """
    if len(frames) == 0:
        raise InputError("shared_noise_variance needs at least one frame")
    crop = (lambda im: roi.crop(np.asarray(im, dtype=np.float32))) if roi is not None else np.asarray
    return min(noise_variance(crop(im)) for im in frames)


def _search_px2(camera: Camera, max_px2: float | None) -> float:
    """The relative-blur search range: ``max_px2`` if given, else the camera's
    (:func:`relative_blur_search_px2`)."""
    return relative_blur_search_px2(camera) if max_px2 is None else float(max_px2)


@dataclass(frozen=True)
class FocusCheck:
    """The verdict on a verification frame.

    Attributes:
        passed: the focus error is confirmed below ``tolerance_dpt``.
        error_dpt: combined estimate of the focus error ``e = P_v - P*`` (dpt).
        sigma_dpt: its standard uncertainty (dpt).
        consistent: the references agree with each other within their uncertainties.
        estimates: per reference ``(power_dpt, e_dpt, sigma_dpt)``.
        reason: why it did not pass (``None`` if it passed).
    """

    passed: bool
    error_dpt: float
    sigma_dpt: float
    consistent: bool
    estimates: tuple[tuple[float, float, float], ...]
    reason: str | None = None


def verify_focus(frame: np.ndarray, power_dpt: float, references: Sequence[tuple[np.ndarray, float]], camera: Camera,
                 roi: Roi | None = None, *, tolerance_dpt: float | None = None, z: float = 2.0,
                 noise_px2: float = 0.12, relative_noise: float = 0.06, shape_range: tuple[float, float] = (0.85, 1.5),
                 consistency_sigmas: float = 3.0, max_px2: float | None = None,
                 texture_factor: float = 2.0, min_sharpness_ratio: float = 0.9) -> FocusCheck:
    r"""Check a frame taken at ``power_dpt`` against frames of the same scene at other powers.

    Each reference frame ``(image, P_k)`` gives ``D_k`` (:func:`relative_blur_px2`), which
    the model ``D_k = alpha M^2 a_k (a_k + 2 e)``, ``a_k = P_k - P_v``, ties to the focus
    error ``e = P_v - P*``. ``alpha`` is the ratio of the fitted Gaussian's variance to the
    blur's: 1 for a Gaussian PSF, 1.1-2.0 for a uniform disk on the bench depending on the
    texture (the fit weighs the frequencies the texture has; median 1.35), unknown for a
    real lens, so it is fitted over ``shape_range`` together with ``e``: with two
    references at different powers both are determined (the ratio ``D_1 / D_2`` does not
    depend on ``alpha``); with one, the range of ``alpha`` widens the uncertainty. Each
    ``D_k`` has the standard uncertainty ``noise_px2 + relative_noise |D_k|`` (px², the
    bench's measured error model) combined with ``texture_factor`` times the measurement's
    own, from the frames' texture (:class:`~tdfd.autofocus.relative_blur.RelativeBlur`):
    a periodic or band-limited texture whose frequencies a frame's blur has wiped out
    pins ``D_k`` down far less than a broadband one. All frames share one noise estimate
    (:func:`shared_noise_variance`).

    A frame in focus is at least as sharp as any frame of the scene at another power,
    whatever the texture and the PSF (a defocus PSF's MTF is below 1 at every frequency),
    while the relative blur's Gaussian model can be misled (a periodic texture through a
    disk PSF past its first MTF zero reverses its contrast). So a frame whose sharpness
    (:func:`~tdfd.autofocus.sharpness.sharpness`, on the ROI) is below
    ``min_sharpness_ratio`` times its sharpest reference's fails, its references counted as
    not agreeing (its relative blurs mislead).

    The focus passes if ``|e| + z sigma_e <= tolerance_dpt`` and the references agree
    (their chi-square at the best ``alpha`` within ``consistency_sigmas`` per degree of
    freedom); ``sigma_e`` holds the measurement noise and the spread of ``e`` over the
    ``alpha`` values the data allow (chi-square within 1 of its minimum).

    Args:
        frame: ``(H, W)`` the verification frame.
        power_dpt: its ECVFL power ``P_v`` (dpt).
        references: ``(image, power_dpt)`` of earlier frames of the run.
        camera: thin-lens constants.
        roi: region (default: whole frame).
        tolerance_dpt: the largest focus error accepted (default: half a pixel of blur).
        z: coverage factor on the uncertainty.
        noise_px2, relative_noise, shape_range: the error model above, measured on the bench
            (docs/BENCHMARKS.md, ``reliability``).
        consistency_sigmas: see above.
        max_px2: the relative-blur search range (px²; default
            :func:`relative_blur_search_px2` of ``camera``).
        min_sharpness_ratio: see above (0 disables; 0.9 keeps every correct verification of
            the reliability benchmark's tuning seeds, whose lowest ratio was 0.93).
        texture_factor: the weight of the texture-dependent uncertainty (the local Cramér-Rao
            bound leaves out the fit's other errors; 2 covers 99 % of the bench's Gaussian-optics
            measurements within 2.5 standard uncertainties).

    Raises:
        InputError: no reference frame.
    """
    if not references:
        raise InputError("verify_focus needs at least one reference frame")
    m2 = sigma_px_per_dpt(camera) ** 2
    tol = 0.5 / blur_px_per_dpt(camera) if tolerance_dpt is None else float(tolerance_dpt)
    # pairs (i, j) of frames at offsets b = P - P_v: the verification frame against each reference,
    # and the first two references against each other (the DFD pair: a check on alpha and e)
    frames = [(np.asarray(frame), 0.0)] + [(np.asarray(im), float(p) - float(power_dpt)) for im, p in references]
    pairs = [(0, k) for k in range(1, len(frames)) if abs(frames[k][1]) >= 0.02]
    if len(frames) >= 3 and abs(frames[1][1] - frames[2][1]) >= 0.02:
        pairs.append((1, 2))
    if not pairs:
        return FocusCheck(False, math.nan, math.inf, False, (), "no reference frame at another power")
    search = _search_px2(camera, max_px2)
    nv = shared_noise_variance([im for im, _ in frames], roi)
    meas = [relative_blur(frames[i][0], frames[j][0], roi, max_px2=search, noise_var=nv) for i, j in pairs]
    informative = [k for k, m in enumerate(meas) if math.isfinite(m.sd_px2)]
    if not informative:
        return FocusCheck(False, math.nan, math.inf, False, (), "the texture does not measure the relative blur")
    pairs, meas = [pairs[k] for k in informative], [meas[k] for k in informative]
    bi = np.array([frames[i][1] for i, _ in pairs])
    bj = np.array([frames[j][1] for _, j in pairs])
    d = np.array([m.px2 for m in meas])  # sigma_j^2 - sigma_i^2
    sd = np.hypot(noise_px2 + relative_noise * np.abs(d), texture_factor * np.array([m.sd_px2 for m in meas]))
    a = bj - bi
    alphas = np.linspace(shape_range[0], shape_range[1], 66)
    e_k = (d[None, :] / (alphas[:, None] * m2 * a[None, :]) - (bi + bj)[None, :]) / 2.0  # (alpha, pair)
    s_k = sd[None, :] / (2.0 * alphas[:, None] * m2 * np.abs(a[None, :]))
    w = 1.0 / s_k**2
    e_hat = (w * e_k).sum(1) / w.sum(1)
    chi = (w * (e_k - e_hat[:, None]) ** 2).sum(1)
    best = int(np.argmin(chi))
    allowed = chi <= chi[best] + 1.0
    spread = 0.5 * float(e_hat[allowed].max() - e_hat[allowed].min())
    mean = float(e_hat[best])
    sigma = math.hypot(float(1.0 / math.sqrt(w[best].sum())), spread)
    dof = max(1, len(a) - 2)
    consistent = bool(chi[best] <= consistency_sigmas**2 * dof) if len(a) > 2 else True
    est = tuple((float(power_dpt) + float(bj_), float(ek), float(sk)) for bj_, ek, sk in zip(bj, e_k[best], s_k[best]))
    reason = None
    if not consistent:
        reason = f"the reference frames disagree (focus errors {', '.join(f'{x:+.3f}' for _, x, _ in est)} dpt)"
    elif abs(mean) + z * sigma > tol:
        reason = f"focus error {mean:+.3f} +- {sigma:.3f} dpt exceeds {tol:.3f} dpt"
    elif min_sharpness_ratio > 0:
        ratio = sharpness(frames[0][0], roi) / max(sharpness(im, roi) for im, _ in frames[1:])
        if ratio < min_sharpness_ratio:
            consistent = False
            reason = (f"the frame is less sharp than a reference frame ({ratio:.2f}x, below {min_sharpness_ratio:g}x): "
                      f"its relative blurs (focus error {mean:+.3f} dpt) mislead")
    return FocusCheck(reason is None, mean, sigma, consistent, est, reason)


def pair_focus_interval(image_f1: np.ndarray, power_f1_dpt: float, image_f2: np.ndarray, power_f2_dpt: float,
                        camera: Camera, roi: Roi | None = None, *, shape_range: tuple[float, float] = (1.0, 1.3),
                        noise_px2: float = 0.12, relative_noise: float = 0.06, z: float = 2.0,
                        max_px2: float | None = None, texture_factor: float = 2.0) -> tuple[float, float]:
    r"""The in-focus powers the DFD pair itself allows, measured without the depth model.

    ``D = sigma_2^2 - sigma_1^2`` (:func:`relative_blur_px2`) and
    ``D = alpha M^2 (P_2 - P_1)(P_1 + P_2 - 2 P*)`` give
    ``P* = (P_1 + P_2)/2 - D / (2 alpha M^2 (P_2 - P_1))``; the interval spans ``alpha`` over
    ``shape_range`` and ``D`` over ``z`` standard uncertainties. It is a second, independent
    opinion on the model's estimate: a model that is confidently wrong lands outside it.

    ``max_px2``: the relative-blur search range (px², default
    :func:`relative_blur_search_px2` of ``camera``). ``D``'s uncertainty is
    :func:`verify_focus`'s (``noise_px2``, ``relative_noise``, ``texture_factor``).

    Returns:
        ``(low, high)`` ECVFL powers (dpt).

    Raises:
        InputError: the two powers are equal.
    """
    dp = float(power_f2_dpt) - float(power_f1_dpt)
    if abs(dp) < 0.02:
        raise InputError("the DFD pair needs two different powers")
    m2 = sigma_px_per_dpt(camera) ** 2
    m = relative_blur(image_f1, image_f2, roi, max_px2=_search_px2(camera, max_px2),
                      noise_var=shared_noise_variance([image_f1, image_f2], roi))
    d = m.px2
    sd = math.hypot(noise_px2 + relative_noise * abs(d), texture_factor * m.sd_px2)
    if not math.isfinite(sd):
        return -math.inf, math.inf
    mid = 0.5 * (float(power_f1_dpt) + float(power_f2_dpt))
    cands = [mid - dd / (2.0 * a * m2 * dp) for a in shape_range for dd in (d - z * sd, d + z * sd)]
    return min(cands), max(cands)


@dataclass(frozen=True)
class FocusEstimate:
    """The focus error of the lens's present power from the model's estimate and a verification frame together.

    Attributes:
        error_dpt: ``e = P_v - P*`` (dpt): the lens moves by ``-error_dpt`` to focus.
        sigma_dpt: its standard uncertainty (dpt).
        discrepancy: the model's and the verification's errors apart, in their combined
            standard uncertainties.
    """

    error_dpt: float
    sigma_dpt: float
    discrepancy: float


def combine_focus_error(check: FocusCheck, model_sigma_dpt: float, *, model_error_dpt: float = 0.0,
                        gate: float = 2.0) -> FocusEstimate | None:
    r"""The three-frame focus estimate: the model's (from the DFD pair) and the verification frame's, weighted.

    The lens sits at the model's in-focus power, so the model says ``e = model_error_dpt``
    (0) with its uncertainty ``model_sigma_dpt`` (:func:`estimate_uncertainty`); the
    verification frame measures ``e`` without the model (:func:`verify_focus`). The two are
    independent opinions: when they agree within ``gate`` combined standard uncertainties
    and the verification's references agree among themselves, their inverse-variance
    weighted mean is the estimate, with ``sigma = (1/s_m^2 + 1/s_v^2)^{-1/2}``.

    Args:
        check: the verification's :class:`FocusCheck`.
        model_sigma_dpt: the model's standard uncertainty of the in-focus power (dpt).
        model_error_dpt: the model's focus error of the present power (dpt; 0 when the lens sits at its estimate).
        gate: the largest discrepancy (in combined standard uncertainties) still combined.

    Returns:
        A :class:`FocusEstimate`, or ``None`` when the two disagree, the verification's
        references disagree, or either uncertainty is not finite and positive.

    Example:
        >>> chk = FocusCheck(False, 0.1, 0.05, True, ())
        >>> est = combine_focus_error(chk, 0.05)
        >>> round(est.error_dpt, 3), round(est.sigma_dpt, 4), round(est.discrepancy, 2)
        (0.05, 0.0354, 1.41)
        >>> combine_focus_error(FocusCheck(False, 0.2, 0.05, True, ()), 0.01) is None  # 3.9 sigma apart
        True
    """
    sm, sv = float(model_sigma_dpt), float(check.sigma_dpt)
    if not (check.consistent and math.isfinite(check.error_dpt) and 0 < sm < math.inf and 0 < sv < math.inf):
        return None
    discrepancy = abs(check.error_dpt - model_error_dpt) / math.hypot(sm, sv)
    if discrepancy > gate:
        return None
    wm, wv = 1.0 / sm**2, 1.0 / sv**2
    return FocusEstimate((wm * model_error_dpt + wv * check.error_dpt) / (wm + wv), 1.0 / math.sqrt(wm + wv),
                         discrepancy)
