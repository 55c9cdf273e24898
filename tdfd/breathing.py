r"""Focus breathing: magnification that changes with the ECVFL power, and its undoing.

An electrically tunable lens changes the image scale a little with its power. tdfd models
it as a pure magnification about the optical centre (taken as the image centre): a frame at
ECVFL power ``P`` is the ideal frame scaled by ``s(P) = 1 + m P`` (``m`` in 1/dpt, the camera
file's ``magnification_per_dpt``). Scaled content at pixel ``x`` comes from ``c + (x - c)/s``.

Resampling is separable windowed-sinc (Lanczos) interpolation, written as two small
matrices, ``out = R_y x R_x^T``: no interpolation blur to speak of, unlike bilinear
resampling whose position-dependent low-pass would bias defocus measurements.

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

import numpy as np

from .errors import InputError, ShapeError

__all__ = ["lanczos_matrix", "magnify", "register_to_power", "LANCZOS_A"]

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
