r"""Thin-lens defocus geometry (paper sec. 3, eqs. 1-6).

Sign convention (stated once, used everywhere in tdfd): the blur-circle radius ``r_b`` is
**signed**,

.. math:: r_b = \frac{A}{2} d_s \left(\frac{1}{F} - \frac{1}{d_o} - \frac{1}{d_s}\right)
   \quad\text{(eq. 3)},

positive when the object lies *beyond* the plane in focus (the image forms in front of the
sensor) and negative when it is nearer. The blur parameter is ``sigma = mu * r_b``
(eq. 4), signed too; a Gaussian PSF depends only on ``sigma**2``. Distances are metres,
powers dioptres, ``sigma`` pixels when ``mu`` is in px/m.

Any varying parameter (paper, remark after eq. 13): frame ``i`` of a camera blurs by eq. 4
with the subscript where the parameter varies,
``sigma_i = mu (A_i/2) d_s,i (1/F_i - 1/d_o - 1/d_s,i)``, a line in inverse depth
``q = 1/d_o``: ``sigma_i = alpha_i - a_i q`` (:meth:`tdfd.camera.Camera.sigma_lines_px`).
Then ``D = sigma1^2 - sigma2^2 = (a1^2 - a2^2) q^2 - 2 (alpha1 a1 - alpha2 a2) q +
alpha1^2 - alpha2^2``: linear in ``q`` for the ECVFL pair (``a1 = a2``, eq. 6), a quadratic
for two sensor distances or two apertures, solved on the working range's side of its
turning point (:func:`depth_from_square_difference`).

All functions take Python floats or tensors (broadcast together) and are differentiable.

Example:
    >>> from tdfd import Camera
    >>> cam = Camera.preset("reference")
    >>> s1, s2 = camera_sigmas(cam, 0.5)
    >>> abs(float(s1 - s2) - cam.sigma_difference_px) < 1e-5
    True
    >>> round(float(depth_from_sigma(s1, cam.focal_lengths_m[0], cam.sensor_distance_m,
    ...                              cam.aperture_m, cam.mu_px_per_m)), 6)
    0.5
"""

from __future__ import annotations

import math
from typing import Union

import torch

from ..camera import Camera
from ..errors import InputError

__all__ = [
    "blur_radius",
    "blur_radius_from_power",
    "sigma_from_depth",
    "depth_from_sigma",
    "sigma_difference",
    "sigmas_from_square_difference",
    "camera_sigmas",
    "camera_blur_radii_px",
    "depth_from_square_difference",
    "square_difference_slope",
    "sensor_varying_sigmas",
    "depth_from_square_difference_sensor_varying",
]

Number = Union[float, torch.Tensor]


def _t(x: Number, like: torch.Tensor | None = None) -> torch.Tensor:
    if isinstance(x, torch.Tensor):
        return x
    dtype = like.dtype if like is not None else torch.float64  # Python floats keep double precision
    device = like.device if like is not None else None
    return torch.as_tensor(x, dtype=dtype, device=device)


def blur_radius(depth_m: Number, focal_length_m: Number, sensor_distance_m: Number, aperture_m: Number) -> torch.Tensor:
    """Signed blur-circle radius ``r_b`` on the sensor in metres (paper eq. 3).

    Args:
        depth_m: object distance ``d_o`` (m), any shape.
        focal_length_m: focal length ``F`` (m).
        sensor_distance_m: lens-to-sensor distance ``d_s`` (m).
        aperture_m: aperture diameter ``A`` (m).

    Returns:
        ``(A/2) d_s (1/F - 1/d_o - 1/d_s)`` broadcast over the inputs.
    """
    d = _t(depth_m)
    return 0.5 * aperture_m * sensor_distance_m * (1.0 / _t(focal_length_m, d) - 1.0 / d - 1.0 / _t(sensor_distance_m, d))


def blur_radius_from_power(camera: Camera, depth_m: Number, ecvfl_power_dpt: Number) -> torch.Tensor:
    """Signed blur radius in metres for ``camera`` at ECVFL power ``P_e`` (eq. 3 with
    ``1/F = 1/f0 + P_e``)."""
    d = _t(depth_m)
    inv_f = camera.fixed_power_dpt + _t(ecvfl_power_dpt, d)
    return camera.blur_scale_m_dpt * (inv_f - 1.0 / d - 1.0 / camera.sensor_distance_m)


def sigma_from_depth(depth_m: Number, focal_length_m: Number, sensor_distance_m: Number, aperture_m: Number,
                     mu: Number) -> torch.Tensor:
    """Signed blur parameter ``sigma = mu r_b`` (paper eq. 4)."""
    return mu * blur_radius(depth_m, focal_length_m, sensor_distance_m, aperture_m)


def depth_from_sigma(sigma: Number, focal_length_m: Number, sensor_distance_m: Number, aperture_m: Number,
                     mu: Number) -> torch.Tensor:
    """Object distance from a signed blur parameter (paper eq. 5).

    ``d_o = 1 / (1/F - 1/d_s - 2 sigma / (mu A d_s))``. The result is non-positive or
    infinite when ``sigma`` implies an object at or beyond infinity; callers that need a
    finite depth work in inverse depth (see :func:`depth_from_square_difference`).
    """
    s = _t(sigma)
    return 1.0 / (1.0 / _t(focal_length_m, s) - 1.0 / _t(sensor_distance_m, s) - 2.0 * s / (mu * aperture_m * sensor_distance_m))


def sigma_difference(focal_length_1_m: Number, focal_length_2_m: Number, sensor_distance_m: Number,
                     aperture_m: Number, mu: Number) -> torch.Tensor:
    """``sigma1 - sigma2 = mu A d_s / 2 (1/F1 - 1/F2)`` (paper eq. 6), independent of depth."""
    f1 = _t(focal_length_1_m)
    return 0.5 * mu * aperture_m * sensor_distance_m * (1.0 / f1 - 1.0 / _t(focal_length_2_m, f1))


def sigmas_from_square_difference(square_difference: Number, difference: Number) -> tuple[torch.Tensor, torch.Tensor]:
    """Solve ``sigma1, sigma2`` from ``D = sigma1^2 - sigma2^2`` and ``c = sigma1 - sigma2``.

    With ``c != 0``: ``sigma1 + sigma2 = D / c``, so ``sigma1 = (D/c + c)/2`` and
    ``sigma2 = (D/c - c)/2`` (paper eqs. 6 and 13 combined). The sign of each sigma comes
    out of the solve: no ambiguity remains.

    Raises:
        InputError: if ``difference`` is zero (two equal focal settings).
    """
    c = _t(difference)
    if bool(torch.any(c == 0)):
        raise InputError("sigma1 - sigma2 is zero: the two focal settings must differ")
    d = _t(square_difference, c)
    s = d / c
    return 0.5 * (s + c), 0.5 * (s - c)


def camera_sigmas(camera: Camera, depth_m: Number, mu: Number | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Signed ``(sigma1, sigma2)`` in pixels for an object at ``depth_m`` (eq. 4, both frames,
    each with its own ``F_i``, ``d_s,i`` and ``A_i``).

    ``mu`` defaults to ``camera.mu_px_per_m``.
    """
    mu = camera.mu_px_per_m if mu is None else mu
    if camera.sensor_distances_m is None and camera.apertures_m is None:
        p1, p2 = camera.lens_powers_dpt
        return mu * blur_radius_from_power(camera, depth_m, p1), mu * blur_radius_from_power(camera, depth_m, p2)
    frames = zip(camera.focal_lengths_m, camera.frame_sensor_distances_m, camera.frame_apertures_m)
    return tuple(sigma_from_depth(depth_m, f, ds, a, mu) for f, ds, a in frames)  # type: ignore[return-value]


def camera_blur_radii_px(camera: Camera, depth_m: Number, ecvfl_power_dpt: Number) -> torch.Tensor:
    """Signed geometric blur radius in **pixels** at ECVFL power ``P_e``."""
    return blur_radius_from_power(camera, depth_m, ecvfl_power_dpt) / camera.pixel_pitch_m


def depth_from_square_difference(camera: Camera, square_difference: Number, mu: Number | None = None
                                 ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Inverse depth, ``sigma1`` and ``sigma2`` from a measured ``sigma1^2 - sigma2^2``.

    ECVFL pair (one sensor distance, one aperture): eqs. 6 + 13 for the sigmas and eq. 5 for
    the depth, written in inverse depth ``1/d_o = 1/F1 - 1/d_s - 2 sigma1 / (mu A d_s)`` so
    that it is finite for every input.

    Two sensor distances or apertures: with ``sigma_i = alpha_i - a_i q`` (module
    docstring), ``D`` is a quadratic ``Qa q^2 + Qb q + Qc`` in ``q = 1/d_o`` whose roots
    are symmetric about its turning point; the camera guarantees its working range lies on
    one side of it (:attr:`tdfd.camera.Camera.turning_inverse_depth`) and the root on that
    side is taken, in the cancellation-free form of the two. A ``D`` beyond the quadratic's
    extremum (no real root) gives the turning point itself, outside the working range
    (the estimator's confidence is then ~0).

    Returns:
        ``(inverse_depth [1/m], sigma1 [px], sigma2 [px])``; inverse depth may be <= 0 for
        inputs that imply an object beyond infinity.
    """
    mu = camera.mu_px_per_m if mu is None else mu
    if camera.sensor_distances_m is not None or camera.apertures_m is not None:
        return _depth_from_square_difference_general(camera, square_difference, mu)
    p1, p2 = camera.lens_powers_dpt
    c = mu * camera.blur_scale_m_dpt * (p1 - p2)
    s1, s2 = sigmas_from_square_difference(square_difference, c)
    inv_depth = (camera.total_power_dpt(p1) - 1.0 / camera.sensor_distance_m) - s1 / (mu * camera.blur_scale_m_dpt)
    return inv_depth, s1, s2


def _quadratic(camera: Camera, mu: float) -> tuple[float, float, float, tuple[tuple[float, float], tuple[float, float]]]:
    (al1, a1), (al2, a2) = lines = camera.sigma_lines_px(float(mu))
    return a1 * a1 - a2 * a2, -2.0 * (al1 * a1 - al2 * a2), al1 * al1 - al2 * al2, lines


def _depth_from_square_difference_general(camera: Camera, square_difference: Number, mu: float
                                          ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    qa, qb, qc0, ((al1, a1), (al2, a2)) = _quadratic(camera, mu)
    d = _t(square_difference)
    near, far = camera.depth_range_m
    q_mid = 0.5 * (1.0 / near + 1.0 / far)
    if qa == 0.0:  # equal blur slopes (A1 d_s1 = A2 d_s2): linear after all
        q = (d - qc0) / qb
    else:
        turn = -qb / (2.0 * qa)
        s = math.copysign(1.0, qa) * math.copysign(1.0, q_mid - turn)  # root on the range's side
        disc = (qb * qb - 4.0 * qa * (qc0 - d)).clamp_min(0.0)
        root = torch.sqrt(disc + 1e-30) if disc.dtype == torch.float64 else torch.sqrt(disc + 1e-12)
        if qb != 0.0 and s == math.copysign(1.0, qb):  # -qb + s*root would cancel: use 2 Qc / (-qb - s root)
            q = 2.0 * (qc0 - d) / (-qb - s * root)
        else:
            q = (-qb + s * root) / (2.0 * qa)
    return q, al1 - a1 * q, al2 - a2 * q


def square_difference_slope(camera: Camera, inverse_depth: Number, mu: Number | None = None) -> torch.Tensor:
    """``|dD/dq|``, the sensitivity of ``D = sigma1^2 - sigma2^2`` (px^2) to inverse depth
    (1/m), for error propagation: ``|2 Qa q + Qb|`` (constant ``2 a |sigma1 - sigma2|`` for
    the ECVFL pair)."""
    mu = camera.mu_px_per_m if mu is None else mu
    qa, qb, _, _ = _quadratic(camera, float(mu))
    q = _t(inverse_depth)
    return (2.0 * qa * q + qb).abs()


# --------------------------------------------------------------------------------------
# Variant noted in the paper: the sensor distance d_s (not F) varies between the captures.
# --------------------------------------------------------------------------------------
def sensor_varying_sigmas(depth_m: Number, focal_length_m: Number, sensor_distances_m: tuple[Number, Number],
                          aperture_m: Number, mu: Number) -> tuple[torch.Tensor, torch.Tensor]:
    """``(sigma1, sigma2)`` when the two captures differ in ``d_s`` at a fixed ``F`` (eq. 4).

    Here ``sigma_j = mu A/2 (d_sj K - 1)`` with ``K = 1/F - 1/d_o``, so ``sigma1 - sigma2``
    depends on depth (unlike eq. 6).
    """
    return tuple(sigma_from_depth(depth_m, focal_length_m, ds, aperture_m, mu) for ds in sensor_distances_m)  # type: ignore[return-value]


def depth_from_square_difference_sensor_varying(square_difference: Number, focal_length_m: float,
                                                sensor_distances_m: tuple[float, float], aperture_m: float,
                                                mu: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Both depth solutions for the sensor-varying variant from ``D = sigma1^2 - sigma2^2``.

    With ``a = mu A / 2`` and ``K = 1/F - 1/d_o``: ``D/a^2 = (d1^2 - d2^2) K^2 - 2 (d1 - d2) K``,
    a quadratic in ``K``. Its two roots give two candidate depths; the caller picks the one
    inside its working range (a Gaussian PSF cannot tell them apart from one pair).

    Returns:
        ``(depth_a, depth_b)`` in metres (NaN where the discriminant is negative).

    Raises:
        InputError: if the two sensor distances are equal.
    """
    d1, d2 = (float(x) for x in sensor_distances_m)
    if d1 == d2:
        raise InputError("the two sensor distances must differ")
    a = 0.5 * mu * aperture_m
    dsq = _t(square_difference)
    qa, qb, qc = d1 * d1 - d2 * d2, -2.0 * (d1 - d2), -dsq / (a * a)
    disc = torch.sqrt(qb * qb - 4.0 * qa * qc)
    k_roots = ((-qb + disc) / (2 * qa), (-qb - disc) / (2 * qa))
    return tuple(1.0 / (1.0 / focal_length_m - k) for k in k_roots)  # type: ignore[return-value]
