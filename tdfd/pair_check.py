r"""Is this a DFD pair at all? Capture faults that no depth estimator should vouch for.

Depth from defocus compares the blur of two frames of one scene taken at two ECVFL powers
(``CONTRACT.md`` section 1). Some pairs carry no such information, yet a model fed with
them answers confidently (an identical pair reads as an object at the distance where both
blurs are equal; a black frame as a strongly blurred one). They are capture faults, found
here with a few cheap whole-frame statistics (numpy only, no torch; 7-9 ms for a
1200 x 1600 pair and 0.5 ms for a 256 x 320 window on the 2-core development machine):

* **identical frames** — fewer than :data:`IDENTICAL_FRACTION` of the pixels differ: the
  lens did not move (or the camera returned the same buffer twice). Two real exposures
  never agree pixel for pixel: sensor noise alone changes most codes.
* **black frame** — a frame whose brightest pixel is at most :data:`BLACK_LEVEL` of full
  scale (no signal), or whose mean is below :data:`DARK_RATIO` times the other frame's
  (exposure, gain or the light changed between the frames: defocus blur preserves the
  mean intensity, so the two means of a real pair agree to a few per cent).
* **saturated frame** — at least :data:`SATURATED_FRACTION` of the pixels at the white
  level: the blur is clipped away.

:class:`tdfd.runtime.DepthRuntime` sets the confidence of such pairs to 0 and reports the
reason in :attr:`tdfd.runtime.DepthResult.problems`; the autofocus loop reports it as a
capture fault.

Example:
    >>> import numpy as np
    >>> f = np.random.default_rng(0).random((64, 64), dtype=np.float32)
    >>> pair_problem(f, f)
    'frames are identical: the lens did not move'
    >>> pair_problem(f, np.zeros_like(f))
    'second frame is black (brightest pixel 0% of full scale)'
    >>> pair_problem(f, np.clip(f + 0.01, 0, 1)) is None
    True
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from .errors import DTypeError, RangeError, ShapeError

__all__ = ["pair_problem", "IDENTICAL_FRACTION", "BLACK_LEVEL", "DARK_RATIO", "SATURATED_FRACTION",
           "SATURATION_LEVEL"]

#: A pair whose frames differ in fewer than this fraction of pixels counts as identical.
IDENTICAL_FRACTION = 0.005
#: A frame whose brightest pixel is at most this fraction of full scale is black.
BLACK_LEVEL = 0.02
#: A frame whose mean is below this fraction of the other frame's mean is (too) dark.
DARK_RATIO = 0.5
#: Pixel values at or above this fraction of full scale count as saturated.
SATURATION_LEVEL = 0.998
#: A frame with at least this fraction of saturated pixels is saturated.
SATURATED_FRACTION = 0.5

_NAMES = ("first", "second")


def _normalised(image: Any, white_level: float | None) -> np.ndarray:
    if not isinstance(image, np.ndarray):
        raise DTypeError(f"frames must be numpy arrays, got {type(image).__name__}")
    if image.dtype.kind in "ui":
        level = float(np.iinfo(image.dtype).max) if white_level is None else float(white_level)
    elif image.dtype.kind == "f":
        level = 1.0 if white_level is None else float(white_level)
    else:
        raise DTypeError(f"frames must hold integers or floats, got {image.dtype}")
    if not math.isfinite(level) or level <= 0:
        raise RangeError(f"white_level must be finite and > 0, got {white_level!r}")
    return image.astype(np.float32, copy=False) / np.float32(level)


def pair_problem(image_f1: np.ndarray, image_f2: np.ndarray, white_level: float | None = None) -> str | None:
    """Why the two frames cannot form a DFD pair, or ``None`` if they can.

    Args:
        image_f1: frame at the first ECVFL power, any shape (all pixels form one frame);
            float in [0, 1] or integer codes.
        image_f2: frame at the second power, same shape.
        white_level: raw value of full scale (default: the integer dtype's maximum, 1 for
            floats).

    Returns:
        A one-line reason a person can act on (``"frames are identical: the lens did not
        move"``, ``"second frame is black (...)"``, ``"first frame is saturated (...)"``,
        ...), or ``None``.

    Raises:
        ShapeError: empty frames or frames of different shapes.
        DTypeError: not numpy arrays of numbers.
        RangeError: a non-positive white level.
    """
    if getattr(image_f1, "shape", None) != getattr(image_f2, "shape", None):
        raise ShapeError(f"frames differ in shape: {getattr(image_f1, 'shape', None)} and "
                         f"{getattr(image_f2, 'shape', None)}")
    frames = [_normalised(image_f1, white_level), _normalised(image_f2, white_level)]
    if frames[0].size == 0:
        raise ShapeError(f"frames are empty (shape {frames[0].shape})")
    peaks = [float(f.max()) for f in frames]
    black = [p <= BLACK_LEVEL for p in peaks]
    if all(black):
        return f"both frames are black (brightest pixels {peaks[0]:.0%} and {peaks[1]:.0%} of full scale)"
    for k in (0, 1):
        if black[k]:
            return f"{_NAMES[k]} frame is black (brightest pixel {peaks[k]:.0%} of full scale)"
    means = [float(f.mean(dtype=np.float64)) for f in frames]
    for k in (0, 1):
        if means[k] < DARK_RATIO * means[1 - k]:
            return (f"{_NAMES[k]} frame is much darker than the {_NAMES[1 - k]} (mean {means[k]:.3g} against "
                    f"{means[1 - k]:.3g} of full scale): exposure, gain or light changed between the frames")
    for k in (0, 1):
        sat = np.count_nonzero(frames[k] >= SATURATION_LEVEL) / frames[k].size
        if sat >= SATURATED_FRACTION:
            return f"{_NAMES[k]} frame is saturated ({sat:.0%} of pixels at the white level)"
    differ = np.count_nonzero(frames[0] != frames[1]) / frames[0].size
    if differ < IDENTICAL_FRACTION:
        return "frames are identical: the lens did not move"
    return None
