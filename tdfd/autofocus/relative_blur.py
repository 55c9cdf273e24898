r"""The relative blur of two frames of one scene, measured without a depth model.

:func:`relative_blur_px2` blurs the sharper frame by a Gaussian until it matches the other
(least squares, the blurred noise's share of the residual subtracted): the difference of
the two frames' Gaussian blur variances, ``sigma_b^2 - sigma_a^2`` (px²). The scene's
texture cancels, so it is the controller's model-free evidence
(:mod:`tdfd.autofocus.evidence`: the DFD pair's own in-focus interval, verification frames).
:func:`relative_blur_search_px2` scales its search range to a camera's largest blur.
:func:`relative_blur` also returns the measurement's standard uncertainty from the frames'
own texture (the Fisher information of the fit): a texture whose frequencies the blur has
wiped out (a periodic pattern past its first MTF zero, a band-limited one) pins the blur
difference down far less than a broadband one, and says so.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..camera import Camera
from ..errors import InputError
from .roi import Roi
from .sharpness import noise_variance

__all__ = ["MIN_SEARCH_PX2", "RelativeBlur", "relative_blur", "relative_blur_px2", "relative_blur_search_px2",
           "search_margin_px"]


def _gauss(image: np.ndarray, s: float) -> np.ndarray:
    import cv2

    return image if s <= 1e-3 else cv2.GaussianBlur(image, (0, 0), s, borderType=cv2.BORDER_REFLECT)


def _kernel_energy(s: float) -> float:
    """Sum of the squared taps of the 2-D Gaussian OpenCV applies for ``s`` (white-noise gain)."""
    import cv2

    if s <= 1e-3:
        return 1.0
    n = int(round(s * 4 * 2 + 1)) | 1  # OpenCV's kernel size for float images
    g = cv2.getGaussianKernel(n, s).ravel()
    return float((g * g).sum()) ** 2


def _laplacian_energy(s: float) -> float:
    """Sum of the squared taps of the 4-neighbour Laplacian of the Gaussian OpenCV applies
    for ``s``: the variance of white noise of unit variance through both."""
    import cv2

    if s <= 1e-3:
        return 20.0  # the 3x3 kernel [0 1 0; 1 -4 1; 0 1 0]
    n = int(round(s * 4 * 2 + 1)) | 1
    g = cv2.getGaussianKernel(n, s)
    lap = cv2.Laplacian(np.pad((g @ g.T).astype(np.float64), 1), cv2.CV_64F, ksize=1, borderType=cv2.BORDER_CONSTANT)
    return float((lap * lap).sum())


#: The relative-blur search range never goes below this (px²): the reference camera's frames
#: blur by at most 4 px (sigma), and the thresholds of docs/BENCHMARKS.md were tuned with it.
MIN_SEARCH_PX2 = 64.0


def relative_blur_search_px2(camera: Camera) -> float:
    """The :func:`relative_blur_px2` search range for ``camera``: ``(1.5 sigma_max)^2`` (px²),
    with ``sigma_max`` the larger frame blur of the DFD pair over the working range, and at
    least :data:`MIN_SEARCH_PX2` (so the reference camera keeps 64 px²; the paper camera, 4x
    binned, blurs by up to 32 px and needs about 2 300 px²).

    Example:
        >>> from tdfd import Camera
        >>> relative_blur_search_px2(Camera.preset("reference"))
        64.0
    """
    near, far = camera.depth_range_m
    sigma = max(abs(alpha - a * q) for alpha, a in camera.sigma_lines_px() for q in (1.0 / near, 1.0 / far))
    return max(MIN_SEARCH_PX2, (1.5 * sigma) ** 2)


def search_margin_px(max_px2: float) -> int:
    """Border (px) :func:`relative_blur_px2` leaves out of its residual for a search range
    ``max_px2``: 1.5 times the largest Gaussian sigma it applies (12 px for 64 px²)."""
    return max(12, int(math.ceil(1.5 * math.sqrt(max_px2))))


@dataclass(frozen=True)
class RelativeBlur:
    """A relative blur measurement (:func:`relative_blur`).

    Attributes:
        px2: ``sigma_b^2 - sigma_a^2`` (px²).
        sd_px2: its standard uncertainty from the sensor noise and the frames' texture (px²):
            ``sqrt(noise / sum J^2)`` with ``J = d(blurred frame)/dD = Laplacian / 2`` (the
            heat equation) over the residual's pixels, the Cramér-Rao bound of the fit. It
            leaves out a mismatch of the PSF's shape (a pillbox fitted by a Gaussian), which
            :func:`~tdfd.autofocus.evidence.verify_focus` models with its shape factor.
    """

    px2: float
    sd_px2: float


def relative_blur_px2(image_a: np.ndarray, image_b: np.ndarray, roi: Roi | None = None, *,
                      max_px2: float = MIN_SEARCH_PX2, margin_px: int | None = None,
                      noise_var: float | None = None) -> float:
    r"""Difference of Gaussian blur variances ``sigma_b^2 - sigma_a^2`` (px²) of two frames of one scene.

    :func:`relative_blur`'s value alone; the arguments are its.

    Example:
        >>> import cv2
        >>> rng = np.random.default_rng(0)
        >>> scene = cv2.GaussianBlur(rng.random((96, 96)).astype(np.float32), (0, 0), 0.7)
        >>> blurred = cv2.GaussianBlur(scene, (0, 0), 2.0)
        >>> round(relative_blur_px2(scene, blurred))
        4
    """
    return relative_blur(image_a, image_b, roi, max_px2=max_px2, margin_px=margin_px, noise_var=noise_var).px2


def relative_blur(image_a: np.ndarray, image_b: np.ndarray, roi: Roi | None = None, *,
                  max_px2: float = MIN_SEARCH_PX2, margin_px: int | None = None,
                  noise_var: float | None = None) -> RelativeBlur:
    r"""Difference of Gaussian blur variances ``sigma_b^2 - sigma_a^2`` (px²) of two frames of one scene, with its uncertainty.

    The sharper frame is blurred by a Gaussian of variance ``|D|`` until it matches the
    other in the least-squares sense, with the blurred noise's share of the residual
    subtracted (it would bias ``|D|`` upwards). No depth model is involved: the scene's
    texture cancels. Blur of another shape (a pillbox) is matched by the Gaussian of about
    the same second moment at small blur; at large blur the match is biased (measured in
    docs/BENCHMARKS.md, ``reliability``), which is why :func:`~tdfd.autofocus.evidence.verify_focus` weighs near
    references more.

    Args:
        image_a, image_b: ``(H, W)`` linear intensity, same scene and exposure.
        roi: region (default: the whole frame).
        max_px2: the search range ``|D| <= max_px2``.
        margin_px: border excluded from the residual (px; default :func:`search_margin_px` of
            ``max_px2``, 12 px for 64 px²).
        noise_var: the sensor noise variance both frames share (intensity units squared;
            default: :func:`~tdfd.autofocus.sharpness.noise_variance` of each frame's ROI,
            which a sharp periodic texture inflates; pass the smallest estimate of the
            frames of one scene, :func:`~tdfd.autofocus.evidence.shared_noise_variance`).

    Returns:
        A :class:`RelativeBlur`.

    Example:
        >>> import cv2
        >>> rng = np.random.default_rng(0)
        >>> scene = cv2.GaussianBlur(rng.random((96, 96)).astype(np.float32), (0, 0), 0.7)
        >>> noisy = lambda im: im + 0.01 * rng.standard_normal(im.shape).astype(np.float32)
        >>> m = relative_blur(noisy(scene), noisy(cv2.GaussianBlur(scene, (0, 0), 2.0)))
        >>> round(m.px2), m.sd_px2 < 0.1
        (4, True)
    """
    a = np.asarray(image_a, dtype=np.float32)
    b = np.asarray(image_b, dtype=np.float32)
    if a.shape != b.shape or a.ndim != 2:
        raise InputError(f"frames must be (H, W) of one shape, got {a.shape} and {b.shape}")
    if roi is not None:
        a, b = roi.crop(a), roi.crop(b)
    if margin_px is None:
        margin_px = search_margin_px(max_px2)
    if min(a.shape) <= 2 * margin_px + 8:
        raise InputError(f"ROI {a.shape} too small for the relative-blur measure (needs > {2 * margin_px + 8} px)")
    if noise_var is None:
        na, nb = noise_variance(a), noise_variance(b)
    elif not (math.isfinite(noise_var) and noise_var >= 0):
        raise InputError(f"noise_var must be finite and >= 0, got {noise_var}")
    else:
        na = nb = float(noise_var)
    inner = (slice(margin_px, -margin_px), slice(margin_px, -margin_px))

    def cost(d: float) -> float:
        if d >= 0:
            s = math.sqrt(d)
            r = _gauss(a, s) - b
            noise = na * _kernel_energy(s) + nb
        else:
            s = math.sqrt(-d)
            r = _gauss(b, s) - a
            noise = nb * _kernel_energy(s) + na
        return float(np.mean(r[inner].astype(np.float64) ** 2)) - noise

    grid = np.geomspace(0.05, max_px2, 12)
    grid = np.concatenate([-grid[::-1], [0.0], grid])
    values = [cost(float(d)) for d in grid]
    i = int(np.argmin(values))
    lo, hi = float(grid[max(i - 1, 0)]), float(grid[min(i + 1, len(grid) - 1)])
    g = (math.sqrt(5.0) - 1.0) / 2.0  # golden-section refinement inside the bracket
    c, d = hi - g * (hi - lo), lo + g * (hi - lo)
    fc, fd = cost(c), cost(d)
    for _ in range(18):
        if fc < fd:
            hi, d, fd = d, c, fc
            c = hi - g * (hi - lo)
            fc = cost(c)
        else:
            lo, c, fc = c, d, fd
            d = lo + g * (hi - lo)
            fd = cost(d)
    est = 0.5 * (lo + hi)
    # the fit's Fisher information: the blurred frame's change per px² of D is half its Laplacian
    import cv2

    s = math.sqrt(abs(est))
    src, n_src, n_other = (a, na, nb) if est >= 0 else (b, nb, na)
    lap = cv2.Laplacian(_gauss(src, s), cv2.CV_32F, ksize=1, borderType=cv2.BORDER_REFLECT)[inner]
    j2 = 0.25 * (float(np.mean(lap.astype(np.float64) ** 2)) - n_src * _laplacian_energy(s))
    noise = n_src * _kernel_energy(s) + n_other
    sd = math.sqrt(noise / (lap.size * j2)) if j2 > 0 else math.inf
    return RelativeBlur(est, sd)
