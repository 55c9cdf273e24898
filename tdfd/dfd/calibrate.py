r"""Calibration of the blur constant ``mu`` (paper sec. 3: "mu ... needs to be
experimentally calibrated"; sec. 4 calibrates it from a pair at 46 cm).

The estimator measures ``D = sigma1^2 - sigma2^2 = mu^2 (r_1^2 - r_2^2)`` with ``r_j`` the
geometric blur radii from the thin-lens model (eq. 3) at the known distance. Hence

* from one pair: ``mu = sqrt(D / (r_1^2 - r_2^2))``;
* from several known distances: least squares over ``D_i = mu^2 a_i``,
  ``mu^2 = sum(a_i D_i) / sum(a_i^2)`` (optionally weighted by confidence).

Example:
    >>> import torch
    >>> from tdfd import Camera
    >>> from tdfd.optics import render_pair
    >>> cam = Camera.preset("reference")
    >>> x = torch.rand(1, 1, 128, 128, generator=torch.Generator().manual_seed(1))
    >>> i1, i2 = render_pair(cam, x, torch.full_like(x, 0.36))
    >>> mu = calibrate_mu(cam, [(i1, i2, 0.36)], tile=128)
    >>> abs(mu / cam.mu_px_per_m - 1) < 0.01
    True
"""

from __future__ import annotations

import math
from typing import Iterable, Sequence

import torch

from ..camera import Camera
from ..errors import InputError
from ..optics.thin_lens import camera_sigmas
from .fourier_ratio import FourierRatioDFD

__all__ = ["radius_square_difference", "mu_from_square_difference", "calibrate_mu"]


def radius_square_difference(camera: Camera, depth_m: float) -> float:
    """``r_1^2 - r_2^2`` in m^2 for an object at ``depth_m`` (eq. 3 for both frames, each
    with its own power, sensor distance and aperture)."""
    r1, r2 = (float(s) for s in camera_sigmas(camera, float(depth_m), 1.0))
    return r1 * r1 - r2 * r2


def mu_from_square_difference(camera: Camera, depths_m: Sequence[float], square_differences: Sequence[float],
                              weights: Sequence[float] | None = None) -> float:
    """Least-squares ``mu`` (px/m) from measured ``sigma1^2 - sigma2^2`` at known distances.

    Raises:
        InputError: on mismatched lengths, no usable distance (all at ``r_1^2 = r_2^2``),
            or a fit giving ``mu^2 <= 0`` (measurements inconsistent with the geometry).
    """
    if len(depths_m) != len(square_differences) or not depths_m:
        raise InputError("need as many measurements as distances, at least one")
    w = [1.0] * len(depths_m) if weights is None else [float(v) for v in weights]
    a = [radius_square_difference(camera, d) for d in depths_m]
    num = sum(wi * ai * di for wi, ai, di in zip(w, a, square_differences))
    den = sum(wi * ai * ai for wi, ai in zip(w, a))
    if den <= 0:
        raise InputError("the calibration distances give no blur difference (r1^2 = r2^2); use other distances")
    mu2 = num / den
    if not math.isfinite(mu2) or mu2 <= 0:
        raise InputError(f"calibration gives mu^2 = {mu2:.4g}: measurements disagree with the thin-lens geometry")
    return math.sqrt(mu2)


def calibrate_mu(camera: Camera, pairs: Iterable[tuple[torch.Tensor, torch.Tensor, float]], tile: int = 64,
                 stride: int | None = None, **estimator_kwargs) -> float:
    """Calibrate ``mu`` from image pairs of a target at known distances.

    Args:
        camera: camera whose ``mu_px_per_m`` is to be found (its value is not used).
        pairs: ``(image_f1, image_f2, depth_m)`` with images ``(B, 1, H, W)`` in [0, 1].
        tile: tile size; ``stride`` defaults to ``tile``.
        **estimator_kwargs: passed to :class:`~tdfd.dfd.FourierRatioDFD`.

    Returns:
        ``mu`` in px/m. The per-pair ``D`` is the confidence-weighted median over tiles.
    """
    dfd = FourierRatioDFD(camera, tile=tile, stride=stride or tile, **estimator_kwargs)
    depths, dsq, weights = [], [], []
    for image_f1, image_f2, depth in pairs:
        r = dfd.analyse(image_f1, image_f2)
        d = r.square_difference.flatten()
        c = r.confidence.flatten()
        depths.append(float(depth))
        dsq.append(float(d.median()))
        weights.append(float(c.mean()) + 1e-6)
    return mu_from_square_difference(camera, depths, dsq, weights)
