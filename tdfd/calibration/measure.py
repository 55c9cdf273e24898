"""Measurements for calibration: per-region blur differences of DFD pairs.

A pair's frames are first registered for focus breathing (the second frame resampled to
the first's scale, :func:`tdfd.breathing.register_to_power`), then the analytic
Fourier-ratio estimator (:class:`tdfd.dfd.FourierRatioDFD`, paper eq. 13 in its weighted
form) measures ``D = sigma1^2 - sigma2^2`` in px^2 on a grid of square regions (tile =
stride = region). ``D`` does not depend on ``mu`` or on the camera's geometry, only on the
images, so the nominal camera serves for the measurement.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ..breathing import register_to_power
from ..camera import Camera
from ..dfd import FourierRatioDFD

__all__ = ["PairMeasurement", "measure_pair", "in_focus_power_from_pair", "PREDICTION_REGION_PX"]

#: region side (px) of :func:`in_focus_power_from_pair` and of the known-distance route's
#: pair measurements: large blur needs large windows (the Hann window's leakage fills the
#: high frequencies a blurred frame lacks), and a planar target's larger regions average
#: more texture (192 px against 128: worst single-pair error 0.021 against 0.041 dpt over
#: 42 pairs, docs/CALIBRATION.md).
PREDICTION_REGION_PX = 192


@dataclass(frozen=True)
class PairMeasurement:
    """Per-region ``D`` of one pair.

    Attributes:
        power_a, power_b: lens powers of the two frames (read back), dioptres.
        square_difference: ``(rows, cols)`` ``sigma_a^2 - sigma_b^2`` in px^2.
        confidence: ``(rows, cols)`` estimator confidence in [0, 1].
        names: the two frames' names.
    """

    power_a: float
    power_b: float
    square_difference: np.ndarray
    confidence: np.ndarray
    names: tuple[str, str]


def _estimator(camera: Camera, p_a: float, p_b: float, region: int, mu: float | None = None) -> FourierRatioDFD:
    cam = camera.replace(lens_powers_dpt=(float(p_a), float(p_b)), depth_range_m=(0.05, 1e4))
    return FourierRatioDFD(cam, tile=region, stride=region, mu=mu)


def measure_pair(camera: Camera, image_a: np.ndarray, image_b: np.ndarray, power_a: float, power_b: float,
                 region: int = 64, magnification_per_dpt: float = 0.0, names: tuple[str, str] = ("a", "b")
                 ) -> PairMeasurement:
    """``D`` per region for frames ``image_a`` at ``power_a`` and ``image_b`` at ``power_b``."""
    b = register_to_power(image_b, power_b, power_a, magnification_per_dpt) if magnification_per_dpt else image_b
    est = _estimator(camera, power_a, power_b, region)
    t = lambda x: torch.from_numpy(np.ascontiguousarray(x, dtype=np.float64))[None, None]  # noqa: E731
    with torch.no_grad():
        r = est.analyse(t(image_a), t(b))
    return PairMeasurement(float(power_a), float(power_b), r.square_difference[0, 0].numpy(),
                           r.confidence[0, 0].numpy(), names)


def in_focus_power_from_pair(camera: Camera, image_1: np.ndarray, image_2: np.ndarray, power_1: float,
                             power_2: float, region: int = PREDICTION_REGION_PX, magnification_per_dpt: float = 0.0,
                             min_confidence: float = 0.5) -> float:
    """The ECVFL power that focuses a (planar) scene, from one pair, with a calibrated camera.

    Breathing is undone first; the analytic estimator's inverse depth per region (paper
    eqs. 5, 6, 13) becomes an in-focus power ``1/d_o + 1/d_s - 1/f0``; the median over
    regions whose confidence is at least ``min_confidence`` times the best region's is
    returned, dioptres.

    Regions are :data:`PREDICTION_REGION_PX` (192 px) by default: with 64-px regions the
    estimator's error grows with the larger blur of the pair, to 0.03-0.13 dpt when it
    reaches 3.3-3.8 px (the range ends of docs/BENCHMARKS.md's calibration camera); 128-px
    regions bring it under 0.02 dpt there, and 192-px regions halve the worst scatter of a
    single pair over a planar target (measured, docs/CALIBRATION.md). Frames smaller than
    a region need ``region`` given.
    """
    b = register_to_power(image_2, power_2, power_1, magnification_per_dpt) if magnification_per_dpt else image_2
    est = _estimator(camera, power_1, power_2, region)
    t = lambda x: torch.from_numpy(np.ascontiguousarray(x, dtype=np.float64))[None, None]  # noqa: E731
    with torch.no_grad():
        r = est.analyse(t(image_1), t(b))
    q = r.inverse_depth[0, 0].numpy()
    c = r.confidence[0, 0].numpy()
    sel = c >= min_confidence * c.max()
    return float(np.median(q[sel]) + 1.0 / camera.sensor_distance_m - camera.fixed_power_dpt)
