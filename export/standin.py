"""The analytic layer alone, shaped like the combined model (for development and tests).

:class:`AnalyticModel` wraps :class:`tdfd.dfd.FourierRatioDFD` so that it returns
``(depth, confidence, depth)`` and carries ``camera``/``tile``/``stride`` like
:class:`tdfd.model.DFDModel`, so everything in :mod:`export` works on it.
"""

from __future__ import annotations

import torch
from torch import nn

from tdfd.camera import Camera
from tdfd.dfd import FourierRatioDFD

__all__ = ["AnalyticModel", "analytic_model"]


class AnalyticModel(nn.Module):
    """``forward(image_f1, image_f2) -> (depth, confidence, depth_analytic)`` from the
    analytic estimator only (``depth_analytic`` equals ``depth``).

    Args:
        camera: the camera description.
        tile, stride: the tile grid in pixels.
        **kwargs: further :class:`~tdfd.dfd.FourierRatioDFD` options.
    """

    def __init__(self, camera: Camera, tile: int = 64, stride: int = 32, **kwargs) -> None:
        super().__init__()
        self.camera, self.tile, self.stride = camera, int(tile), int(stride)
        self.analytic = FourierRatioDFD(camera, tile=tile, stride=stride, **kwargs)

    def forward(self, image_f1: torch.Tensor, image_f2: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        depth, conf = self.analytic(image_f1, image_f2)
        return depth, conf, depth


def analytic_model(camera: Camera | None = None, tile: int = 64, stride: int = 32) -> AnalyticModel:
    """:class:`AnalyticModel` for ``camera`` (default: the ``reference`` preset)."""
    return AnalyticModel(camera or Camera.preset("reference"), tile=tile, stride=stride)
