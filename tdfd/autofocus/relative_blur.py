r"""The relative blur of two frames of one scene, measured without a depth model.

:func:`relative_blur_px2` blurs the sharper frame by a Gaussian until it matches the other
(least squares, the blurred noise's share of the residual subtracted): the difference of
the two frames' Gaussian blur variances, ``sigma_b^2 - sigma_a^2`` (px²). The scene's
texture cancels, so it is the controller's model-free evidence
(:mod:`tdfd.autofocus.evidence`: the DFD pair's own in-focus interval, verification frames).
:func:`relative_blur_search_px2` scales its search range to a camera's largest blur.
"""

from __future__ import annotations

import math

import numpy as np

from ..camera import Camera
from ..errors import InputError
from .roi import Roi
from .sharpness import noise_variance

__all__ = ["MIN_SEARCH_PX2", "relative_blur_px2", "relative_blur_search_px2", "search_margin_px"]


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


def relative_blur_px2(image_a: np.ndarray, image_b: np.ndarray, roi: Roi | None = None, *,
                      max_px2: float = MIN_SEARCH_PX2, margin_px: int | None = None) -> float:
    r"""Difference of Gaussian blur variances ``sigma_b^2 - sigma_a^2`` (px²) of two frames of one scene.

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

    Example:
        >>> import cv2
        >>> rng = np.random.default_rng(0)
        >>> scene = cv2.GaussianBlur(rng.random((96, 96)).astype(np.float32), (0, 0), 0.7)
        >>> blurred = cv2.GaussianBlur(scene, (0, 0), 2.0)
        >>> round(relative_blur_px2(scene, blurred))
        4
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
    na, nb = noise_variance(a), noise_variance(b)
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
    return 0.5 * (lo + hi)
