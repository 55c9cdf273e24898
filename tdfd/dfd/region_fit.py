"""One Fourier-ratio fit over a region: the paper's "one region covering the pattern" (sec. 4).

Its uncertainty and its fusion with the lit tiles are :mod:`tdfd.region_fusion` (torch-free).

Example:
    >>> import numpy as np
    >>> from tdfd import Camera
    >>> flat = np.full((96, 96), 0.3, np.float32)
    >>> fit = fit_region(flat, flat, Camera.preset("reference"))
    >>> fit.size_px, fit.confidence < 0.01                # no texture: no confidence
    (96, True)
"""

from __future__ import annotations

import functools

import torch

from ..camera import Camera
from ..errors import ShapeError
from ..region_fusion import DEFAULT_MU_UNCERTAINTY, RegionFit, region_sigma_dpt
from .fourier_ratio import FourierRatioDFD

__all__ = ["MIN_REGION_PX", "fit_region"]

#: the smallest region fitted (px).
MIN_REGION_PX = 64


@functools.lru_cache(maxsize=8)
def _region_estimator(camera: Camera, size: int) -> FourierRatioDFD:
    """The region estimator for a camera and region side, built once (its ring tables take
    25 ms at 160 px, 0.9 s at 512 px; a fit then takes 1.5-10 ms on 2 cores)."""
    return FourierRatioDFD(camera, tile=size, stride=size, max_bin=max(4, size // 8), gate_sharpness=8.0).double()


def fit_region(image_f1: torch.Tensor, image_f2: torch.Tensor, camera: Camera, *, psf_family: str | None = None,
               mu_uncertainty: float = DEFAULT_MU_UNCERTAINTY) -> RegionFit:
    """One Fourier-ratio fit over the central square of a pair (the paper's one region).

    The estimator is :class:`~tdfd.dfd.FourierRatioDFD` with the region as its tile,
    ``max_bin`` an eighth of it and the sharp band gate regions of hundreds of pixels want
    (``gate_sharpness=8``), as ``benchmarks/paper_experiment.py`` fits its region.

    Args:
        image_f1, image_f2: ``(H, W)`` or ``(1, 1, H, W)`` linear intensity in [0, 1].
        camera: the camera (its ``mu``).
        psf_family, mu_uncertainty: as :func:`tdfd.region_fusion.region_sigma_dpt`.

    Raises:
        ShapeError: frames of different shapes, or smaller than :data:`MIN_REGION_PX`.
    """
    a, b = (torch.as_tensor(im) for im in (image_f1, image_f2))
    a, b = (x if x.ndim == 4 else x.reshape(1, 1, *x.shape[-2:]) for x in (a, b))
    if a.shape != b.shape or a.ndim != 4 or a.shape[:2] != (1, 1):
        raise ShapeError(f"frames must be (H, W) or (1, 1, H, W) of one shape, got {tuple(a.shape)} and {tuple(b.shape)}")
    h, w = a.shape[-2:]
    size = min(h, w) - min(h, w) % 2
    if size < MIN_REGION_PX:
        raise ShapeError(f"a region of {h}x{w} px is smaller than the {MIN_REGION_PX} px a region fit needs")
    top, left = (h - size) // 2, (w - size) // 2
    crop = lambda x: x[..., top:top + size, left:left + size].double()  # noqa: E731
    r = _region_estimator(camera, size).analyse(crop(a), crop(b))
    q = float(1.0 / r.depth.flatten()[0])
    rel = float(r.rel_error.flatten()[0])
    return RegionFit(inverse_depth=q, sigma_dpt=region_sigma_dpt(q, rel, camera, psf_family, mu_uncertainty),
                     rel_error=rel, confidence=float(r.confidence.flatten()[0]), size_px=size)
