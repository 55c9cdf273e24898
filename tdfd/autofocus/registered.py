r"""An estimator behind focus-breathing registration (a calibrated camera's ``magnification_per_dpt``).

A camera whose ECVFL breathes images frame 2 of a pair at ``(1 + m P_2) / (1 + m P_1)``
times frame 1's scale (:mod:`tdfd.breathing`). :class:`BreathingRegistered` brings both
frames to their common scale with the model's own registration
(:func:`tdfd.registration.register_breathing`: whole pixels moved about the centre of the
frames it is given, which leaves the sensor noise white, unlike an interpolator) and passes
the pair on to the wrapped estimator. The autofocus controller sends the grid-aligned crop
around its ROI with the optical centre's position in it (``optical_centre``): each frame
is first moved by the breathing's translation at the crop's position
(:func:`tdfd.breathing.window_shifts`, whole pixels, the crop's border pixel repeated where
the move runs past it), so that registering the crop about its own centre equals
registering the whole frame about the optical centre (without it, a ROI 100 px off the
centre keeps a 0.4 px translation at 0.4 %/dpt over a 1 dpt pair).

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

from ..breathing import breathing_scales, breathing_window
from ..registration import register_breathing, registration_magnifications

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
        takes_optical_centre: ``True`` (:func:`~tdfd.autofocus.interfaces.run_estimator`).
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

    takes_optical_centre = True

    def __call__(self, image_f1: np.ndarray, image_f2: np.ndarray,
                 optical_centre: tuple[float, float] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Register, then estimate; ``optical_centre``: ``(row, col)`` of the optical centre in
        the frames' pixels when they are a crop (default: their centre).

        Raises:
            NonFiniteError: a non-finite ``optical_centre``.
        """
        im1, im2 = (np.asarray(x, dtype=np.float32) for x in (image_f1, image_f2))
        if optical_centre is not None:
            H, W = im1.shape[-2:]
            im1, im2 = breathing_window(im1, im2, (0, H, 0, W), registration_magnifications(self.scales), optical_centre)
        a, b = (torch.as_tensor(np.ascontiguousarray(x, dtype=np.float32))[None, None] for x in (im1, im2))
        a, b = register_breathing(a, b, self.scales)
        return self.estimator(a[0, 0].numpy(), b[0, 0].numpy())

    def __repr__(self) -> str:
        return f"BreathingRegistered({self.estimator!r}, magnification_per_dpt={self.magnification_per_dpt:g})"
