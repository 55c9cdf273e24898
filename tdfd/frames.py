"""Raw frames to linear intensity, written once (torch-free, numpy only).

The model's input convention (``CONTRACT.md`` section 2) is linear sensor intensity in
``[0, 1]``: raw value / white level, no gamma. :func:`raw_to_linear` is the one conversion
the device runtime (:mod:`tdfd.runtime`), the hardware capture path and the simulated
bench's scene loader use. Its policy, the same everywhere:

* ``uint8`` / ``uint16`` frames are divided by ``white_level`` (default: the dtype's maximum,
  255 / 65535; pass e.g. 4095 for 12-bit data in 16-bit words). A value **above** the white
  level raises :class:`~tdfd.errors.RangeError` naming the frame: it means the white level
  is wrong, and clipping would silently flatten the highlights the DFD ratio needs.
* float frames (``float16/32/64``) are taken as already scaled (or divided by
  ``white_level`` when given); values outside ``[0, 1]`` by more than rounding
  (``1e-6``) raise :class:`~tdfd.errors.RangeError`, NaN or inf
  :class:`~tdfd.errors.NonFiniteError`; the rounding excess is clipped.
* anything else raises :class:`~tdfd.errors.DTypeError`.

The result is float32 of the input's shape.

Example:
    >>> import numpy as np
    >>> raw_to_linear(np.array([[0, 4095]], np.uint16), white_level=4095).tolist()
    [[0.0, 1.0]]
    >>> raw_to_linear(np.array([[300]], np.uint16), white_level=255)
    Traceback (most recent call last):
    ...
    tdfd.errors.RangeError: frame has values up to 300, above the white level 255
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from .errors import DTypeError, NonFiniteError, RangeError

__all__ = ["raw_to_linear", "srgb_to_linear", "FLOAT_TOLERANCE"]

#: Float frames may exceed [0, 1] by this much (rounding) and are clipped; more raises.
FLOAT_TOLERANCE = 1e-6


def _level(white_level: float) -> np.float32:
    level = float(white_level)
    if not math.isfinite(level) or level <= 0:
        raise RangeError(f"white_level must be finite and > 0, got {white_level!r}")
    return np.float32(level)


def raw_to_linear(frame: Any, white_level: float | None = None, name: str = "frame") -> np.ndarray:
    """A raw frame as float32 linear intensity in ``[0, 1]`` (see the module's policy).

    Args:
        frame: numpy array of any shape, ``uint8``/``uint16`` or float.
        white_level: raw value of full scale (default: the integer dtype's maximum; 1 for floats).
        name: the frame's name in error messages (e.g. ``"image_f1"``).

    Raises:
        DTypeError: not a numpy array, or an unsupported dtype.
        RangeError: integer values above the white level, float values outside [0, 1], or a
            non-positive white level.
        NonFiniteError: NaN or inf in a float frame.
    """
    if not isinstance(frame, np.ndarray):
        raise DTypeError(f"{name} must be a numpy array, got {type(frame).__name__}")
    dt = frame.dtype
    if dt in (np.uint8, np.uint16):
        level = _level(np.iinfo(dt).max if white_level is None else white_level)
        hi = int(frame.max()) if frame.size else 0
        if hi > level:
            raise RangeError(f"{name} has values up to {hi}, above the white level {float(level):g}")
        return frame.astype(np.float32) / level
    if dt in (np.float16, np.float32, np.float64):
        out = frame.astype(np.float32, copy=False)
        if white_level is not None:
            out = out / _level(white_level)
        if not np.isfinite(out).all():
            raise NonFiniteError(f"{name} contains NaN or inf")
        if out.size:
            lo, hi = float(out.min()), float(out.max())
            if lo < -FLOAT_TOLERANCE or hi > 1.0 + FLOAT_TOLERANCE:
                raise RangeError(f"{name} has values in [{lo:.4g}, {hi:.4g}]; float images must be linear intensity "
                                 f"in [0, 1] (divide raw values by the white level)")
        return np.clip(out, 0.0, 1.0)
    raise DTypeError(f"{name} has dtype {dt}; expected uint8, uint16 (scaled by the white level) or float in [0, 1]")


def srgb_to_linear(x: np.ndarray) -> np.ndarray:
    """Undo the sRGB transfer curve of intensities in [0, 1] (for cameras that cannot
    deliver linear data; DFD needs linear intensity)."""
    x = np.asarray(x)
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)
