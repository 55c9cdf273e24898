r"""An estimator behind focus-breathing registration (a calibrated camera's ``magnification_per_dpt``).

A camera whose ECVFL breathes images frame 2 of a pair at ``(1 + m P_2) / (1 + m P_1)``
times frame 1's scale (:mod:`tdfd.breathing`). :class:`BreathingRegistered` resamples frame
2 to frame 1's scale (:func:`tdfd.breathing.register_to_power`, about the centre of the
frames it is given) and passes the pair on to the wrapped estimator. The autofocus
controller sends the grid-aligned crop around its ROI; with a ROI about the optical centre
(the default) the crop's centre is the optical centre to within a tile, and the residual
is a translation of ``(rho - 1)`` times that offset (well under 0.1 px), which the
Fourier-ratio estimator does not see.

This is the loop's own registration for an estimator without it (the analytic estimator);
an estimator that registers the pair itself must not be wrapped.

Example:
    >>> import numpy as np
    >>> from tdfd import Camera
    >>> from tdfd.autofocus.estimators import AnalyticEstimator
    >>> est = BreathingRegistered(AnalyticEstimator(Camera.preset("reference")), 0.004)
    >>> round(est.scale, 6), est.tile, est.stride
    (0.996043, 64, 32)
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from ..breathing import magnify
from ..errors import InputError

__all__ = ["BreathingRegistered"]


class BreathingRegistered:
    """Registers frame 2 to frame 1's image scale, then runs ``estimator``.

    Args:
        estimator: an :class:`~tdfd.autofocus.interfaces.Estimator` (its ``camera``'s
            ``lens_powers_dpt`` are the pair's powers).
        magnification_per_dpt: the camera's breathing ``m`` (1/dpt), e.g. a calibrated
            camera file's.

    Attributes:
        scale: the magnification applied to frame 2, ``(1 + m P_1) / (1 + m P_2)``.
        camera, tile, stride, min_confidence, confidence_scale: the wrapped estimator's.

    Raises:
        InputError: a non-finite or implausible (``|m| >= 0.1``) magnification.
    """

    def __init__(self, estimator: Any, magnification_per_dpt: float) -> None:
        m = float(magnification_per_dpt)
        if not math.isfinite(m) or abs(m) >= 0.1:
            raise InputError(f"magnification_per_dpt must be finite with |m| < 0.1, got {magnification_per_dpt!r}")
        self.estimator, self.magnification_per_dpt = estimator, m
        self.camera = estimator.camera
        self.tile, self.stride = estimator.tile, estimator.stride
        p1, p2 = self.camera.lens_powers_dpt
        self.scale = (1.0 + m * p1) / (1.0 + m * p2)
        for key in ("min_confidence", "confidence_scale", "backend"):
            if hasattr(estimator, key):
                setattr(self, key, getattr(estimator, key))

    def __call__(self, image_f1: np.ndarray, image_f2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        b = np.asarray(image_f2)
        if self.scale != 1.0:
            b = magnify(b, self.scale).astype(np.float32)
        return self.estimator(image_f1, b)

    def __repr__(self) -> str:
        return f"BreathingRegistered({self.estimator!r}, magnification_per_dpt={self.magnification_per_dpt:g})"
