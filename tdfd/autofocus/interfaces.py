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

__all__ = ["Estimator", "Plant"]


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
        """``(H, W)`` float32 linear intensity in [0, 1] each -> ``(depth_m, confidence)``, each ``(h, w)``."""
        ...


@runtime_checkable
class Plant(Protocol):
    """What executes commands: the simulated bench or the real camera + lens."""

    def set_power(self, cmd: SetPower) -> LensAck | LensFault: ...

    def capture(self, cmd: Capture) -> Frame | CaptureFault: ...

    def estimate(self, cmd: Estimate) -> Estimation | EstimateFault: ...

    def should_halt(self) -> bool: ...

    def now(self) -> float: ...
