r"""The in-focus powers that the sharpness order of a run's frames allows, with no blur model.

A defocus PSF's MTF falls as the defocus grows, so of two frames of one scene at powers
``P_a`` and ``P_b`` the one nearer the in-focus power ``P*`` is the sharper (within the
first MTF lobe; :func:`~tdfd.autofocus.sharpness.sharpness` sums over the ROI's
frequencies). A frame clearly sharper than another therefore puts ``P*`` on its side of
the two powers' midpoint. Each such comparison is a half-line; :func:`sharpness_bracket`
intersects them. No blur model is involved, so the bracket holds where the relative blur's
Gaussian model misleads: a periodic or band-limited texture through a disk PSF can make the
relative blur of the DFD pair and of a verification frame agree on a power a dioptre away
from focus, on the wrong side of a frame that is visibly sharper. Its one assumption, the
first MTF lobe, fails for a disk PSF on a periodic texture past the MTF's first zero, where a
blurrier frame can look sharper (contrast reversal): on the reliability benchmark a bracket
then excluded a true focus that the cross-blur focus, clearly a disk, had found
(:mod:`~tdfd.autofocus.declaration` lets such a fit stand outside the bracket).

Example:
    >>> import numpy as np
    >>> scene = np.random.default_rng(0).random((96, 96))
    >>> def box(x, k):  # a k x k box blur
    ...     return sum(np.roll(x, (i, j), (0, 1)) for i in range(k) for j in range(k)) / k**2
    >>> frames = [(box(scene, k), p) for k, p in ((1, 2.0), (3, 1.0), (5, 3.5))]
    >>> lo, hi = sharpness_bracket(frames)
    >>> bool(lo <= 2.0 <= hi), (lo, hi)
    (True, (1.5, 2.25))
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from ..errors import InputError
from .roi import Roi
from .sharpness import sharpness

__all__ = ["sharpness_bracket"]


def sharpness_bracket(frames: Sequence[tuple[np.ndarray, float]], roi: Roi | None = None, *, margin: float = 0.02,
                      min_separation_dpt: float = 0.02, measure: str = "laplacian") -> tuple[float, float]:
    """``(lo, hi)``: the in-focus powers (dpt) that the frames' sharpness order allows.

    For every two frames at least ``min_separation_dpt`` apart whose sharpness differs by
    more than the factor ``1 + margin`` (sensor noise), ``P*`` lies on the sharper frame's
    side of their midpoint (module docstring). ``lo > hi`` when the order contradicts itself
    (no power is allowed: the frames do not share one scene, or a PSF past its first MTF
    zero reverses a periodic texture's contrast); ``(-inf, inf)`` when no two frames
    compare.

    Args:
        frames: ``(image, power_dpt)`` of the run, ``(H, W)`` images of one scene.
        roi: region compared (default: the whole frame).
        margin: relative sharpness difference below which two frames do not compare.
        min_separation_dpt: frames closer in power than this do not compare.
        measure: the sharpness measure (:func:`~tdfd.autofocus.sharpness.sharpness`).

    Raises:
        InputError: a power is not finite, or ``margin`` or ``min_separation_dpt`` is negative.
    """
    if margin < 0 or min_separation_dpt < 0:
        raise InputError(f"need margin >= 0 and min_separation_dpt >= 0, got {margin}, {min_separation_dpt}")
    powers = [float(p) for _, p in frames]
    if not all(math.isfinite(p) for p in powers):
        raise InputError(f"frame powers must be finite, got {powers}")
    values = [sharpness(np.asarray(im), roi, measure) for im, _ in frames]
    lo, hi = -math.inf, math.inf
    for a in range(len(frames)):
        for b in range(len(frames)):
            if abs(powers[a] - powers[b]) < min_separation_dpt or not values[a] > (1.0 + margin) * values[b]:
                continue
            mid = 0.5 * (powers[a] + powers[b])
            if powers[a] > powers[b]:
                lo = max(lo, mid)
            else:
                hi = min(hi, mid)
    return lo, hi
