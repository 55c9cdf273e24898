r"""The ECVFL power that focuses a depth (thin lens, CONTRACT.md section 1)."""

from __future__ import annotations

import math

from ..camera import Camera

__all__ = ["in_focus_power_dpt"]


def in_focus_power_dpt(camera: Camera, depth_m: float) -> float:
    """ECVFL power that focuses an object at ``depth_m`` metres: ``1/d_o + 1/d_s - 1/f0``.

    ``depth_m = inf`` gives the power that focuses at infinity.
    """
    if math.isinf(depth_m) and depth_m > 0:
        return 1.0 / camera.sensor_distance_m - camera.fixed_power_dpt
    return camera.in_focus_power_dpt(depth_m)
