r"""Image measures on the ROI: sharpness (contrast-detect AF, verification) and texture over the noise floor.

Sharpness measures (on the ROI, normalised by the squared mean intensity so the
exposure does not matter): ``"laplacian"`` (variance of the 3x3 Laplacian of a lightly
smoothed image) and ``"tenengrad"`` (mean squared Sobel gradient). :func:`texture_snr`
and :func:`pair_texture_snr` tell a texture-less target (about 1) from a textured one.

Example:
    >>> import numpy as np
    >>> rng = np.random.default_rng(0)
    >>> sharp = rng.random((64, 64)).astype(np.float32)
    >>> import cv2
    >>> blurred = cv2.GaussianBlur(sharp, (0, 0), 2.0)
    >>> sharpness(sharp) > sharpness(blurred)
    True
"""

from __future__ import annotations

import math

import numpy as np

from ..errors import InputError
from .roi import Roi

__all__ = ["MEASURES", "sharpness", "noise_variance", "texture_snr", "pair_texture_snr"]

#: the sharpness measures :func:`sharpness` knows.
MEASURES = ("laplacian", "tenengrad")


def sharpness(image: np.ndarray, roi: Roi | None = None, measure: str = "laplacian") -> float:
    """Sharpness of the ROI of a frame (dimensionless, higher is sharper).

    Args:
        image: ``(H, W)`` linear intensity.
        roi: region (default: the whole frame).
        measure: ``"laplacian"`` or ``"tenengrad"``.

    Returns:
        The measure divided by the squared mean intensity of the ROI.
    """
    import cv2

    if measure not in MEASURES:
        raise InputError(f"sharpness measure must be one of {MEASURES}, got {measure!r}")
    img = np.asarray(image, dtype=np.float32)
    if img.ndim != 2:
        raise InputError(f"image must be (H, W), got {img.shape}")
    if roi is not None:
        img = roi.crop(img)
    mean = float(img.mean())
    norm = max(mean * mean, 1e-12)
    if measure == "laplacian":
        smooth = cv2.GaussianBlur(img, (5, 5), 0.8, borderType=cv2.BORDER_REFLECT)
        lap = cv2.Laplacian(smooth, cv2.CV_32F, ksize=3, borderType=cv2.BORDER_REFLECT)
        return float(lap[2:-2, 2:-2].var()) / norm
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3, borderType=cv2.BORDER_REFLECT)
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3, borderType=cv2.BORDER_REFLECT)
    return float((gx[1:-1, 1:-1] ** 2 + gy[1:-1, 1:-1] ** 2).mean()) / norm


def noise_variance(image: np.ndarray) -> float:
    """Robust white-noise variance of a frame (intensity units squared).

    From the median absolute deviation of the diagonal second difference
    ``x[i,j] - x[i+1,j] - x[i,j+1] + x[i+1,j+1]`` (variance ``4 s^2`` for white noise of
    variance ``s^2``), whose pass band holds little of a defocused image's signal.
    """
    x = np.asarray(image, dtype=np.float64)
    d = x[:-1, :-1] - x[1:, :-1] - x[:-1, 1:] + x[1:, 1:]
    mad = float(np.median(np.abs(d - np.median(d))))
    return (mad / 0.6745) ** 2 / 4.0


_DOG_CACHE: dict[tuple[float, float], tuple[np.ndarray, float]] = {}


def texture_snr(image: np.ndarray, roi: Roi | None = None, sigmas_px: tuple[float, float] = (1.0, 2.0),
                noise_var: float | None = None) -> float:
    """Band-pass contrast of the ROI relative to the noise floor (dimensionless; ~1 for a texture-less target).

    The variance of a difference-of-Gaussians (``sigmas_px``, periods of about 6-12 px)
    divided by what white noise of variance ``noise_var`` would give through the same
    filter. A texture-less or uniformly lit target reads about 1; usable texture reads
    several times more. ``noise_var`` defaults to :func:`noise_variance` of the ROI itself,
    which a sharp pixel-scale texture inflates: pass the estimate of a blurrier frame of
    the same scene when there is one (:func:`pair_texture_snr`).

    Args:
        image: ``(H, W)`` linear intensity.
        roi: region (default: the whole frame).
        sigmas_px: the two Gaussian widths (px).
        noise_var: the noise variance (intensity units squared).

    Example:
        >>> rng = np.random.default_rng(0)
        >>> flat = 0.5 + 0.01 * rng.standard_normal((96, 96))
        >>> import cv2
        >>> textured = flat + cv2.GaussianBlur(0.2 * rng.random((96, 96)), (0, 0), 2.0)
        >>> texture_snr(flat) < 1.5 < texture_snr(textured)
        True
    """
    import cv2

    img = np.asarray(image, dtype=np.float32)
    if roi is not None:
        img = roi.crop(img)
    key = (float(sigmas_px[0]), float(sigmas_px[1]))
    if key not in _DOG_CACHE:
        half = int(math.ceil(4 * max(key)))
        g1 = cv2.getGaussianKernel(2 * half + 1, key[0])
        g2 = cv2.getGaussianKernel(2 * half + 1, key[1])
        dog = (g1 @ g1.T - g2 @ g2.T).astype(np.float32)
        _DOG_CACHE[key] = (dog, float((dog.astype(np.float64) ** 2).sum()))
    dog, gain = _DOG_CACHE[key]
    half = dog.shape[0] // 2
    if min(img.shape) <= 2 * half + 2:
        raise InputError(f"ROI {img.shape} too small for the texture measure (needs > {2 * half + 2} px)")
    band = cv2.filter2D(img, cv2.CV_32F, dog, borderType=cv2.BORDER_REFLECT)[half:-half, half:-half]
    nv = noise_variance(img) if noise_var is None else float(noise_var)
    return float(band.astype(np.float64).var() / max(nv * gain, 1e-20))


def pair_texture_snr(image_f1: np.ndarray, image_f2: np.ndarray, roi: Roi | None = None) -> float:
    """:func:`texture_snr` of the more textured frame of a DFD pair, against the smaller
    noise estimate of the two (the blurrier frame's is the least inflated by texture).

    Example:
        >>> rng = np.random.default_rng(1)
        >>> a, b = (0.5 + 0.01 * rng.standard_normal((96, 96)) for _ in range(2))
        >>> pair_texture_snr(a, b) < 1.5
        True
    """
    x1, x2 = (np.asarray(im, dtype=np.float32) for im in (image_f1, image_f2))
    if roi is not None:
        x1, x2 = roi.crop(x1), roi.crop(x2)
    nv = min(noise_variance(x1), noise_variance(x2))
    return max(texture_snr(x1, noise_var=nv), texture_snr(x2, noise_var=nv))

