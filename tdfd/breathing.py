r"""Focus breathing: magnification that changes with the ECVFL power, and its undoing.

An electrically tunable lens changes the image scale a little with its power. tdfd models
it as a pure magnification about the optical centre (taken as the image centre): a frame at
ECVFL power ``P`` is the ideal frame scaled by ``s(P) = 1 + m P`` (``m`` in 1/dpt, the camera
file's ``magnification_per_dpt``). Scaled content at pixel ``x`` comes from ``c + (x - c)/s``.

Resampling is separable windowed-sinc (Lanczos) interpolation, written as two small
matrices, ``out = R_y x R_x^T``: no interpolation blur to speak of, unlike bilinear
resampling whose position-dependent low-pass would bias defocus measurements.

Registering a DFD pair (the model does it before its estimator, :mod:`tdfd.registration`,
in torch and in the ONNX graph): frames at powers ``P1``, ``P2`` have scales ``(s1, s2)``
(:func:`breathing_scales`) and are brought to ``sqrt(s1 s2)`` by magnifying them by
``(k1, k2) = (sqrt(s2/s1), sqrt(s1/s2))`` (:func:`registration_magnifications`) about the
centre of the frames given. A crop whose centre is not the optical centre needs a
translation per frame on top (:func:`window_shifts`), applied when the crop is cut
(rounded to whole pixels, :func:`crop_offset`; :class:`tdfd.runtime.DepthRuntime` does it for
``window=``). This
module needs numpy only (the device runtime imports it).

Example:
    >>> import numpy as np
    >>> x = np.random.default_rng(0).random((32, 32))
    >>> bool(np.allclose(magnify(x, 1.0), x))
    True
    >>> y = magnify(magnify(x, 1.01), 1 / 1.01)
    >>> float(np.abs(y - x)[8:-8, 8:-8].mean()) < 0.02
    True
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from .errors import InputError, NonFiniteError, RangeError, ShapeError

__all__ = ["lanczos_matrix", "magnify", "register_to_power", "crop_offset", "breathing_window", "check_magnification_per_dpt",
           "breathing_scales", "registration_magnifications", "window_shifts", "LANCZOS_A",
           "MAX_MAGNIFICATION_PER_DPT"]

#: Lanczos window half-width (taps each side).
LANCZOS_A = 6


def lanczos_matrix(n_out: int, n_in: int, scale: float, offset: float = 0.0, a: int = LANCZOS_A) -> np.ndarray:
    """``(n_out, n_in)`` matrix sampling a 1-D signal at ``c_in + (i - c_out)/scale``.

    ``c_out = (n_out - 1)/2 + offset`` … with ``c_in = (n_in - 1)/2`` (both centres), so the
    output is the input magnified by ``scale`` about the centre. Rows are normalised to
    unit sum (flat fields stay flat).
    """
    if not np.isfinite(scale) or scale <= 0:
        raise InputError(f"scale must be finite and > 0, got {scale}")
    c_out, c_in = (n_out - 1) / 2.0, (n_in - 1) / 2.0
    src = c_in + (np.arange(n_out) - c_out) / scale + offset
    t = src[:, None] - np.arange(n_in)[None, :]
    w = np.sinc(t) * np.sinc(t / a) * (np.abs(t) < a)
    s = w.sum(1, keepdims=True)
    if np.any(np.abs(s) < 1e-6):
        raise ShapeError(f"magnification {scale} samples outside the {n_in}-px input; give a larger margin")
    return w / s


def magnify(image: np.ndarray, scale: float, out_shape: tuple[int, int] | None = None) -> np.ndarray:
    """Magnify ``image`` ``(..., H, W)`` by ``scale`` about its centre.

    Args:
        image: array ``(..., H, W)``.
        scale: relative magnification (1 leaves the image unchanged).
        out_shape: output ``(h, w)`` (centred crop of the magnified input); default ``(H, W)``.

    Returns:
        ``(..., h, w)`` float64.
    """
    x = np.asarray(image, dtype=np.float64)
    if x.ndim < 2:
        raise ShapeError(f"image must be at least 2-D, got {x.shape}")
    h_in, w_in = x.shape[-2:]
    h, w = out_shape if out_shape is not None else (h_in, w_in)
    ry = lanczos_matrix(h, h_in, scale)
    rx = lanczos_matrix(w, w_in, scale)
    return ry @ x @ rx.T


def register_to_power(image: np.ndarray, power_dpt: float, reference_power_dpt: float,
                      magnification_per_dpt: float) -> np.ndarray:
    """Undo breathing: resample a frame taken at ``power_dpt`` to the scale at ``reference_power_dpt``."""
    s = (1.0 + magnification_per_dpt * reference_power_dpt) / (1.0 + magnification_per_dpt * power_dpt)
    return magnify(image, s)


#: Largest plausible ``|magnification_per_dpt|`` (1/dpt); the camera file's limit as well.
MAX_MAGNIFICATION_PER_DPT = 0.1


def check_magnification_per_dpt(m: float, name: str = "magnification_per_dpt") -> float:
    """``m`` as a float after checking it is finite and plausible (``|m| < 0.1`` per dioptre).

    Raises:
        NonFiniteError: ``m`` is NaN or infinite (or not a number).
        RangeError: ``|m| >= 0.1``.
    """
    try:
        v = float(m)
    except (TypeError, ValueError):
        raise NonFiniteError(f"{name} must be a finite number, got {m!r}") from None
    if isinstance(m, bool) or not math.isfinite(v):
        raise NonFiniteError(f"{name} must be a finite number, got {m!r}")
    if abs(v) >= MAX_MAGNIFICATION_PER_DPT:
        raise RangeError(f"{name} {v} is implausible (|m| < {MAX_MAGNIFICATION_PER_DPT} per dioptre expected)")
    return v


def breathing_scales(magnification_per_dpt: float, lens_powers_dpt: Sequence[float]) -> tuple[float, float]:
    """Image scales ``(s1, s2) = (1 + m P1, 1 + m P2)`` of the two frames.

    Raises:
        NonFiniteError, RangeError: a bad ``m`` or power, or a scale outside (0.5, 2).
    """
    m = check_magnification_per_dpt(magnification_per_dpt)
    try:
        p1, p2 = (float(p) for p in lens_powers_dpt)
    except (TypeError, ValueError):
        raise NonFiniteError(f"lens_powers_dpt must be two numbers, got {lens_powers_dpt!r}") from None
    if not (math.isfinite(p1) and math.isfinite(p2)):
        raise NonFiniteError(f"lens_powers_dpt must be finite, got {lens_powers_dpt!r}")
    s = (1.0 + m * p1, 1.0 + m * p2)
    if not all(0.5 < v < 2.0 for v in s):
        raise RangeError(f"breathing scales {s} (m {m} at powers {p1}, {p2} dpt) are implausible")
    return s


def registration_magnifications(scales: Sequence[float]) -> tuple[float, float]:
    """Magnifications ``(k1, k2) = (sqrt(s2/s1), sqrt(s1/s2))`` that bring frames at scales
    ``(s1, s2)`` to their common scale ``sqrt(s1 s2)``."""
    s1, s2 = (float(v) for v in scales)
    return math.sqrt(s2 / s1), math.sqrt(s1 / s2)


def window_shifts(centre_offset_px: float, magnifications: Sequence[float]) -> tuple[float, float]:
    """Per-frame translation (px) of a crop whose centre lies ``centre_offset_px`` from the
    optical centre (``c_crop - c_opt`` along one axis), so that registering the crop about its
    own centre equals registering the whole frame about the optical centre and cropping.

    The crop of frame ``i`` is cut at its nominal origin plus ``-centre_offset_px (1 - 1/k_i)``.

    Example:
        >>> [round(v, 6) for v in window_shifts(100.0, (1.01, 1 / 1.01))]
        [-0.990099, 1.0]
    """
    d = float(centre_offset_px)
    return tuple(-d * (1.0 - 1.0 / float(k)) for k in magnifications)  # type: ignore[return-value]


def breathing_window(image_f1: np.ndarray, image_f2: np.ndarray, window: tuple[int, int, int, int],
                     magnifications: Sequence[float], optical_centre: tuple[float, float] | None = None
                     ) -> tuple[np.ndarray, np.ndarray]:
    """The crops ``window = (y0, y1, x0, x1)`` of a pair, each frame moved by whole pixels by
    its breathing translation at the window's position (:func:`window_shifts`, rounded;
    :func:`crop_offset`), so that registering the crops about their own centre with the
    per-frame ``magnifications`` equals registering the whole frames about
    ``optical_centre`` (``(row, col)`` in the frames' pixels; default: their centre).

    Raises:
        NonFiniteError: a non-finite ``optical_centre``.
        ShapeError: the window is empty or not inside the frames.
    """
    H, W = np.shape(image_f1)[-2:]
    cy, cx = ((H - 1) / 2.0, (W - 1) / 2.0) if optical_centre is None else (float(v) for v in optical_centre)
    if not (math.isfinite(cy) and math.isfinite(cx)):
        raise NonFiniteError(f"optical_centre must be finite, got {optical_centre!r}")
    y0, y1, x0, x1 = (int(v) for v in window)
    sy = window_shifts((y0 + (y1 - y0 - 1) / 2.0) - cy, magnifications)
    sx = window_shifts((x0 + (x1 - x0 - 1) / 2.0) - cx, magnifications)
    return tuple(crop_offset(im, (y0, y1, x0, x1), (round(dy), round(dx)))  # type: ignore[return-value]
                 for im, dy, dx in zip((image_f1, image_f2), sy, sx))


def crop_offset(image: np.ndarray, window: tuple[int, int, int, int], shift: tuple[int, int] = (0, 0)) -> np.ndarray:
    """The crop ``window = (y0, y1, x0, x1)`` of ``image`` ``(..., H, W)`` moved by whole pixels
    ``shift = (dy, dx)``: output pixel ``(u, v)`` is image pixel ``(y0 + u + dy, x0 + v + dx)``,
    the nearest border pixel where that lies outside the image (no interpolation, so the
    sensor noise stays white).

    Raises:
        ShapeError: the window is empty or not inside the image.
        InputError: a shift that is not a whole number of pixels.
    """
    x = np.asarray(image)
    if x.ndim < 2:
        raise ShapeError(f"image must be at least 2-D, got {x.shape}")
    n_y, n_x = x.shape[-2:]
    y0, y1, x0, x1 = (int(v) for v in window)
    if not (0 <= y0 < y1 <= n_y and 0 <= x0 < x1 <= n_x):
        raise ShapeError(f"window {tuple(window)} is empty or not inside the {n_y}x{n_x} image")
    if any(isinstance(v, bool) or not float(v).is_integer() for v in shift):
        raise InputError(f"shift must be whole pixels, got {shift}")
    dy, dx = (int(v) for v in shift)
    if dy == 0 and dx == 0:
        return x[..., y0:y1, x0:x1]
    rows = np.clip(np.arange(y0, y1) + dy, 0, n_y - 1)
    cols = np.clip(np.arange(x0, x1) + dx, 0, n_x - 1)
    return x[..., rows[:, None], cols[None, :]]
