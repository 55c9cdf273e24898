r"""An estimator behind focus-breathing registration (a calibrated camera's ``magnification_per_dpt``).

A camera whose ECVFL breathes images frame 2 of a pair at ``(1 + m P_2) / (1 + m P_1)``
times frame 1's scale (:mod:`tdfd.breathing`). :class:`BreathingRegistered` brings both
frames to their common scale with the model's own registration
(:func:`tdfd.registration.register_breathing`: whole pixels moved about the centre of the
frames it is given, which leaves the sensor noise white, unlike an interpolator) and passes
the pair on to the wrapped estimator. The autofocus
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
    >>> [round(v, 6) for v in est.scales], est.tile, est.stride
    ([1.0068, 1.0108], 64, 32)
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from ..breathing import breathing_scales
from ..registration import register_breathing

__all__ = ["BreathingRegistered"]


class BreathingRegistered:
    """Registers frame 2 to frame 1's image scale, then runs ``estimator``.

    Args:
        estimator: an :class:`~tdfd.autofocus.interfaces.Estimator` (its ``camera``'s
            ``lens_powers_dpt`` are the pair's powers).
        magnification_per_dpt: the camera's breathing ``m`` (1/dpt), e.g. a calibrated
            camera file's.

    Attributes:
        scales: the two frames' image scales ``(1 + m P_1, 1 + m P_2)``.
        camera, tile, stride, min_confidence, confidence_scale: the wrapped estimator's.

    Raises:
        NonFiniteError, RangeError: a non-finite or implausible (``|m| >= 0.1``) magnification.
    """

    def __init__(self, estimator: Any, magnification_per_dpt: float) -> None:
        self.estimator = estimator
        self.camera = estimator.camera
        self.tile, self.stride = estimator.tile, estimator.stride
        self.scales = breathing_scales(magnification_per_dpt, self.camera.lens_powers_dpt)
        self.magnification_per_dpt = float(magnification_per_dpt)
        for key in ("min_confidence", "confidence_scale", "backend"):
            if hasattr(estimator, key):
                setattr(self, key, getattr(estimator, key))

    def __call__(self, image_f1: np.ndarray, image_f2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        a, b = (torch.as_tensor(np.asarray(x, dtype=np.float32))[None, None] for x in (image_f1, image_f2))
        a, b = register_breathing(a, b, self.scales)
        return self.estimator(a[0, 0].numpy(), b[0, 0].numpy())

    def __repr__(self) -> str:
        return f"BreathingRegistered({self.estimator!r}, magnification_per_dpt={self.magnification_per_dpt:g})"
