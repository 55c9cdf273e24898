"""Registration of a sensor-distance pair before the estimator.

A camera whose sensor moves between the two frames (``sensor_distances_m``, paper remark
after eq. 13) images the scene at two scales: chief rays pass the lens centre undeviated,
so frame 2 is frame 1 magnified by ``d_s2 / d_s1`` about the optical centre (taken as the
image centre), whatever the depth. The Fourier-ratio estimator compares the two frames'
spectra tile by tile, so frame 2 is resampled to frame 1's scale first (separable Lanczos,
:func:`tdfd.breathing.magnify`, which adds no interpolation blur to speak of). Pixels within
about ``|1 - d_s1/d_s2| * max(H, W) / 2`` of the border have no counterpart in frame 2 and
hold extrapolated values.

ECVFL and aperture pairs share one sensor distance: their frames come back unchanged.
The renderer (:func:`tdfd.optics.render_pair`) renders on frame 1's grid, already registered.

Example:
    >>> import torch
    >>> from tdfd import Camera
    >>> cam = Camera.preset("reference")
    >>> x = torch.rand(1, 1, 32, 32, generator=torch.Generator().manual_seed(0))
    >>> register_sensor_pair(x, cam) is x
    True
"""

from __future__ import annotations

import torch

from ..breathing import magnify
from ..camera import Camera
from ..errors import ShapeError

__all__ = ["register_sensor_pair"]


def register_sensor_pair(image_f2: torch.Tensor, camera: Camera) -> torch.Tensor:
    """Resample ``image_f2`` ``(B, 1, H, W)`` to frame 1's image scale (``d_s1/d_s2``).

    Args:
        image_f2: the second frame, linear intensity, ``(B, 1, H, W)``.
        camera: the camera (its ``frame_sensor_distances_m``).

    Returns:
        ``image_f2`` itself when the sensor distance does not vary, else the registered
        frame, same shape and dtype.

    Raises:
        ShapeError: ``image_f2`` is not ``(B, 1, H, W)``.
    """
    if not isinstance(image_f2, torch.Tensor) or image_f2.ndim != 4 or image_f2.shape[1] != 1:
        raise ShapeError(f"image_f2 must be a (B, 1, H, W) tensor, got {getattr(image_f2, 'shape', type(image_f2).__name__)}")
    scale = camera.image_scale_ratio
    if scale == 1.0:
        return image_f2
    out = magnify(image_f2.detach().cpu().double().numpy(), 1.0 / scale)
    return torch.from_numpy(out).to(dtype=image_f2.dtype, device=image_f2.device)
