r"""Calibration of the blur constant ``mu`` (paper sec. 3: "mu ... needs to be
experimentally calibrated"; sec. 4 calibrates it from a pair at 46 cm).

The estimator measures ``D = sigma1^2 - sigma2^2 = mu^2 (r_1^2 - r_2^2)`` with ``r_j`` the
geometric blur radii from the thin-lens model (eq. 3) at the known distance. Hence

* from one pair: ``mu = sqrt(D / (r_1^2 - r_2^2))``;
* from several known distances: least squares over ``D_i = mu^2 a_i``,
  ``mu^2 = sum(a_i D_i) / sum(a_i^2)`` (optionally weighted by confidence).

**Conditioning.** At the distance where the pair blurs both frames equally
(:func:`equal_blur_distance_m`: ``r_1^2 = r_2^2``, the midpoint of the two in-focus powers
for an ECVFL pair) ``D = 0`` whatever ``mu``: a pair there measures the distance, not
``mu``. Near it an error ``dq`` (dpt) of the pair's measured in-focus power moves ``mu`` by
``0.5 |a'/a| dq``, i.e. ``dq / (2 |q - q_eq|)`` for an ECVFL pair
(:func:`mu_relative_uncertainty`). The paper calibrates at 46 cm, 1.2 dpt from its pair's
midpoint (1.03 m); the reference camera's midpoint is 0.4545 m, so one pair at 46 cm fixes
its ``mu`` only to a few per cent (simulated paper pattern, 6 captures: -3.0 .. +2.2 %)
against -0.4 .. 0.0 % at 30 cm (docs/BENCHMARKS.md, ``paper``, *Calibration distance*). :func:`calibrate_mu` refuses such a fit.

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

import numpy as np

import torch

from ..camera import Camera
from ..errors import InputError
from ..optics.thin_lens import camera_sigmas
from .fourier_ratio import FourierRatioDFD

__all__ = ["radius_square_difference", "mu_from_square_difference", "calibrate_mu", "equal_blur_distance_m",
           "mu_relative_uncertainty", "ill_conditioned_range_m", "PAIR_POWER_SD_DPT", "MAX_MU_UNCERTAINTY"]

#: standard error (dpt) of one DFD pair's in-focus power assumed by the conditioning check:
#: the simulated paper pattern's one-region fit scatters by about 0.0025 dpt (its mu from one
#: pair at 46 cm spans -4.7 .. +4.3 % over 8 captures on the reference camera); doubled for
#: real optics.
PAIR_POWER_SD_DPT = 0.005
#: largest relative standard uncertainty of ``mu`` a calibration is allowed to leave.
MAX_MU_UNCERTAINTY = 0.05


def radius_square_difference(camera: Camera, depth_m: float) -> float:
    """``r_1^2 - r_2^2`` in m^2 for an object at ``depth_m`` (eq. 3 for both frames, each
    with its own power, sensor distance and aperture)."""
    r1, r2 = (float(s) for s in camera_sigmas(camera, float(depth_m), 1.0))
    return r1 * r1 - r2 * r2


def _square_difference_slope(camera: Camera, depth_m: float) -> tuple[float, float]:
    """``a = r_1^2 - r_2^2`` (m^2) at ``depth_m`` and its derivative ``da/dq`` in inverse depth
    ``q = 1/d`` (m^2 per dpt; central difference, ``a`` is a quadratic in ``q``)."""
    q, h = 1.0 / float(depth_m), 1e-3
    a = radius_square_difference(camera, depth_m)
    return a, (radius_square_difference(camera, 1.0 / (q + h)) - radius_square_difference(camera, 1.0 / (q - h))) / (2 * h)


def equal_blur_distance_m(camera: Camera) -> float | None:
    """The distance (m) at which the camera's pair blurs both frames equally (``r_1^2 = r_2^2``),
    between the two frames' focus distances (:attr:`tdfd.camera.Camera.equal_blur_inverse_depth`);
    ``None`` when there is none at a positive distance.

    Example:
        >>> from tdfd import Camera
        >>> round(equal_blur_distance_m(Camera.preset("reference")), 4)    # 1 / ((1.7 + 2.7) / 2)
        0.4545
    """
    q = camera.equal_blur_inverse_depth
    return None if q is None else 1.0 / q


def mu_relative_uncertainty(camera: Camera, depths_m: Sequence[float], weights: Sequence[float] | None = None,
                            power_sd_dpt: float = PAIR_POWER_SD_DPT) -> float:
    r"""Relative standard uncertainty of ``mu`` fitted from pairs at ``depths_m``.

    Each pair's ``D`` carries the error of an in-focus power error ``dq`` (standard deviation
    ``power_sd_dpt``, independent between pairs): ``dD_i = mu^2 a'_i dq_i``, so the weighted
    least squares ``mu^2 = sum(w a D) / sum(w a^2)`` has relative error
    ``power_sd sqrt(sum (w_i a_i a'_i)^2) / sum(w_i a_i^2)``, and ``mu`` half that.

    Returns:
        The relative uncertainty (``inf`` when no pair has a blur difference).

    Example:
        >>> from tdfd import Camera
        >>> cam = Camera.preset("reference")
        >>> round(mu_relative_uncertainty(cam, [0.46]), 3), round(mu_relative_uncertainty(cam, [0.30]), 4)
        (0.096, 0.0022)
    """
    if not depths_m:
        raise InputError("need at least one calibration distance")
    if not (math.isfinite(power_sd_dpt) and power_sd_dpt > 0):
        raise InputError(f"power_sd_dpt must be finite and > 0, got {power_sd_dpt}")
    w = np.ones(len(depths_m)) if weights is None else np.asarray(weights, dtype=np.float64)
    if w.shape != (len(depths_m),):
        raise InputError(f"need one weight per distance, got {w.shape[0] if w.ndim else 0} for {len(depths_m)}")
    a, da = (np.array(v) for v in zip(*(_square_difference_slope(camera, d) for d in depths_m)))
    den = float(np.sum(w * a * a))
    if not den > 0:
        return math.inf
    return 0.5 * power_sd_dpt * float(np.sqrt(np.sum((w * a * da) ** 2))) / den


def ill_conditioned_range_m(camera: Camera, max_relative: float = MAX_MU_UNCERTAINTY,
                            power_sd_dpt: float = PAIR_POWER_SD_DPT) -> tuple[float, float] | None:
    """``(near, far)``: the distances around :func:`equal_blur_distance_m` at which one pair
    leaves ``mu`` more uncertain than ``max_relative`` (``None``: no such distance).

    Example:
        >>> from tdfd import Camera
        >>> near, far = ill_conditioned_range_m(Camera.preset("reference"))
        >>> round(near, 3), round(far, 3)
        (0.444, 0.465)
    """
    d_eq = equal_blur_distance_m(camera)
    if d_eq is None:
        return None

    def bad(d: float) -> bool:
        return mu_relative_uncertainty(camera, [d], power_sd_dpt=power_sd_dpt) > max_relative

    q_eq, ends = 1.0 / d_eq, []
    for direction in (1.0, -1.0):  # nearer (larger q), then farther
        lo, hi = 0.0, 0.5 * q_eq  # offsets in dpt: bad at lo, good at hi (or the search's end)
        if bad(1.0 / (q_eq + direction * hi)):
            ends.append(1.0 / (q_eq + direction * hi))
            continue
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if bad(1.0 / (q_eq + direction * mid)) else (lo, mid)
        ends.append(1.0 / (q_eq + direction * hi))
    return ends[0], ends[1]


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
                 stride: int | None = None, max_relative_uncertainty: float | None = MAX_MU_UNCERTAINTY,
                 power_sd_dpt: float = PAIR_POWER_SD_DPT, **estimator_kwargs) -> float:
    """Calibrate ``mu`` from image pairs of a target at known distances.

    Args:
        camera: camera whose ``mu_px_per_m`` is to be found (its value is not used).
        pairs: ``(image_f1, image_f2, depth_m)`` with images ``(B, 1, H, W)`` in [0, 1].
        tile: tile size; ``stride`` defaults to ``tile``.
        max_relative_uncertainty: refuse distances that leave ``mu`` more uncertain than this
            (:func:`mu_relative_uncertainty` with ``power_sd_dpt``; module docstring,
            *Conditioning*); ``None`` accepts any.
        power_sd_dpt: assumed standard error of one pair's in-focus power (dpt).
        **estimator_kwargs: passed to :class:`~tdfd.dfd.FourierRatioDFD`.

    Returns:
        ``mu`` in px/m. The per-pair ``D`` is the confidence-weighted median over tiles.

    Raises:
        InputError: no pair, or distances too near the equal-blur distance (the message names
            the distances to avoid).
    """
    pairs = list(pairs)
    if not pairs:
        raise InputError("need at least one calibration pair")
    if max_relative_uncertainty is not None:
        depths_m = [float(p[2]) for p in pairs]
        u = mu_relative_uncertainty(camera, depths_m, power_sd_dpt=power_sd_dpt)
        if not u <= max_relative_uncertainty:
            d_eq = equal_blur_distance_m(camera)
            bad = ill_conditioned_range_m(camera, max_relative_uncertainty, power_sd_dpt)
            avoid = f"; one pair needs a distance outside {bad[0]:.3f}-{bad[1]:.3f} m" if bad else ""
            where = f" (the pair blurs both frames equally at {d_eq:.4f} m, where D does not depend on mu)" if d_eq else ""
            raise InputError(f"calibration distances {', '.join(f'{d:g}' for d in depths_m)} m leave mu uncertain by "
                             f"{u:.1%} for a {power_sd_dpt:g} dpt error of a pair's in-focus power, over the "
                             f"{max_relative_uncertainty:.1%} allowed{where}{avoid}")
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
