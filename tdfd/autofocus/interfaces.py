r"""What the autofocus loop needs from the outside world: a depth estimator and a plant.

Structural protocols (:class:`typing.Protocol`): the estimators of
:mod:`tdfd.autofocus.estimators` and the plants of :mod:`tdfd.autofocus.sim` and
:mod:`tdfd.autofocus.hardware` satisfy them without inheriting from them.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np

from ..camera import Camera
from .messages import Capture, CaptureFault, Estimate, Estimation, EstimateFault, Frame, LensAck, LensFault, SetPower

__all__ = ["Estimator", "Plant", "run_estimator"]


@runtime_checkable
class Estimator(Protocol):
    """Two frames in, depth and confidence on the tile grid out.

    Attributes:
        camera: the camera the estimator was built for (its two ECVFL powers).
        tile: tile size (px).
        stride: tile stride (px).
    """

    camera: Camera
    tile: int
    stride: int

    def __call__(self, image_f1: np.ndarray, image_f2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(H, W)`` float32 linear intensity in [0, 1] each -> ``(depth_m, confidence)``, each ``(h, w)``.

        An estimator that registers focus breathing sets ``takes_optical_centre = True`` and
        accepts ``optical_centre=(row, col)``: where the optical centre lies in the images'
        pixels (:func:`run_estimator`).
        """
        ...


@runtime_checkable
class Plant(Protocol):
    """What executes commands: the simulated bench or the real camera + lens."""

    def set_power(self, cmd: SetPower) -> LensAck | LensFault: ...

    def capture(self, cmd: Capture) -> Frame | CaptureFault: ...

    def estimate(self, cmd: Estimate) -> Estimation | EstimateFault: ...

    def should_halt(self) -> bool: ...

    def now(self) -> float: ...


def run_estimator(estimator: Estimator, cmd: Estimate) -> tuple[np.ndarray, np.ndarray]:
    """Run ``estimator`` on an :class:`~tdfd.autofocus.messages.Estimate` command: its crop's
    ``optical_centre`` goes along to an estimator that takes it (``takes_optical_centre``:
    one that registers focus breathing, which must register about the optical centre, not
    the crop's); any other gets the two images only."""
    if cmd.optical_centre is not None and getattr(estimator, "takes_optical_centre", False):
        return estimator(cmd.image_f1, cmd.image_f2, optical_centre=cmd.optical_centre)  # type: ignore[call-arg]
    return estimator(cmd.image_f1, cmd.image_f2)
