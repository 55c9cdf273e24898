r"""Pooling the tile depths along the scene's depth structure: a robust local surface fit.

Each tile's refined inverse depth ``q`` (1/m) carries its own error, with the Laplace scale
``b`` of its relative error that the model predicts (:mod:`tdfd.model.combined`, calibrated by
:mod:`tdfd.model.scale_calibration`). Real surfaces are smooth between occlusion edges, so a
tile's neighbours that lie on the same surface measure nearly the same depth and can lower
its error; neighbours across an edge measure another surface and must not. This stage fits,
around every tile, a low-order polynomial surface ``q(y, x)`` to the tiles of a
``(2r + 1) x (2r + 1)`` window by iteratively reweighted least squares (a local polynomial
regression with a robust kernel: Cleveland & Devlin, JASA 1988; the edge-preserving weights
of a bilateral filter, Tomasi & Manduchi, ICCV 1998), with weights

``w_j = 1 / (b_j^2 + f^2) * (exp(-z_j^2 / 2) + 1e-6)``,  ``z_j = (q_j - p_j) / (k q_i sqrt(b_i^2 + b_j^2 + f^2))``

(``p_j`` the current fit at tile ``j``, the centre's own ``q_i`` at the first pass; ``f`` a
floor of the scale; ``k`` the kernel's width in combined standard errors), and returns the
fit's value at the centre. A tile on the same surface as its confident neighbours inherits
their information; a neighbour across an occlusion edge, many combined scales away, gets a
negligible weight; tiles outside the grid get none (a tile at the grid's edge fits a one-sided
window). Degree 2 (the default) follows slanted and curved surfaces without the bias a
constant fit has on them; a small ridge on the non-constant terms keeps the fit defined where
the window holds too few tiles (a grid under 3 tiles a side: there the result tends to the
weighted mean).

A quadratic's three curvature terms also fit part of the noise, which costs a planar surface
(a fronto-parallel or slanted face) accuracy that a plane would keep. With ``curvature_test``
``tau > 0`` each tile chooses, after the last pass: the plane through the same weights unless
the curvature terms lower the fit's robust chi-square,

``chi^2 = sum_j w'_j ((q_j - p_j) / q_i)^2 / 2``,  ``w'_j = exp(-z_j^2 / 2) / (b_j^2 + f^2)``

(the squared residuals in units of the tiles' Laplace variance ``2 b^2``, ``z_j`` against the
quadratic), by more than ``tau``: a local model selection, the F-test's criterion (Cleveland &
Devlin 1988 choose the local degree the same way). A curved surface keeps its quadratic.

Everything is convolutions with fixed kernels (gathering the window, forming the normal
equations) and an unrolled Gauss-Jordan solve of the small normal equations, element-wise per
tile, and the curvature test a ``where``: no data-dependent control flow, so it exports to ONNX
as plain operators.

Example:
    >>> import torch
    >>> yy, xx = torch.meshgrid(torch.arange(6.0).double(), torch.arange(7.0).double(), indexing="ij")
    >>> q = (2.0 + 0.05 * yy - 0.03 * xx + 0.004 * xx * yy).reshape(1, 1, 6, 7)
    >>> out = pool_inverse_depth(q, torch.full_like(q, 0.01), ridge=0.0)
    >>> bool(torch.allclose(out, q, rtol=1e-9))  # a quadratic surface is kept
    True
    >>> noisy = q * (1 + 0.01 * torch.randn(q.shape, generator=torch.Generator().manual_seed(0), dtype=q.dtype))
    >>> bool(((pool_inverse_depth(noisy, torch.full_like(q, 0.01)) - q).abs().mean() < (noisy - q).abs().mean()))
    True
"""

from __future__ import annotations

import math
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from .._tracing import is_exporting
from ..errors import InputError, NonFiniteError, RangeError, ShapeError

__all__ = ["pool_inverse_depth", "StructurePooling", "POOLING_KEYS"]

#: keys of the stage's JSON description (:meth:`StructurePooling.to_config`)
POOLING_KEYS = ("radius", "degree", "kernel_width", "iterations", "scale_floor", "ridge", "curvature_test")

_PIVOT_FLOOR = 1e-9


def _design(radius: int, degree: int, dtype: torch.dtype) -> torch.Tensor:
    """The window's regressors ``(S, P)``: 1, y, x (degree >= 1), y^2, x^2, xy (degree 2), in
    tiles scaled by ``radius`` so that every column is of order one; the squares less their
    window mean, so that no column is near another (float32 solves stay accurate)."""
    r = torch.arange(-radius, radius + 1, dtype=torch.float64) / max(radius, 1)
    yy, xx = torch.meshgrid(r, r, indexing="ij")
    y, x = yy.flatten(), xx.flatten()
    cols = [torch.ones_like(y)]
    if degree >= 1:
        cols += [y, x]
    if degree >= 2:
        cols += [y * y - (y * y).mean(), x * x - (x * x).mean(), y * x]
    return torch.stack(cols, 1).to(dtype)


def _gather(x: torch.Tensor, side: int, pad_mode: str) -> torch.Tensor:
    """``(N, 1, h, w)`` to ``(N, S, h, w)``: channel ``s`` is the window's ``s``-th tile
    (row-major), by a convolution with one-hot kernels."""
    r = side // 2
    eye = torch.eye(side * side, dtype=x.dtype, device=x.device).reshape(side * side, 1, side, side)
    return F.conv2d(F.pad(x, (r, r, r, r), mode=pad_mode), eye)


def _solve_spd(system: torch.Tensor) -> torch.Tensor:
    """Gauss-Jordan elimination of the augmented systems ``(B, P, P + 1, h, w)`` ``[A | r]``, one
    per tile, ``A`` symmetric positive definite (no pivoting needed): ``(B, P, h, w)`` solutions.

    Each step works on whole tensors (about eight operators per unknown), so the ONNX graph stays
    small: operator count, not arithmetic, sets the cost of these tiny systems in ONNX Runtime.
    """
    p = system.shape[1]
    for j in range(p):
        unit = torch.zeros(1, p, 1, 1, 1, dtype=system.dtype, device=system.device)
        unit[:, j] = 1.0
        row = system[:, j:j + 1]
        row = row / row[:, :, j:j + 1].clamp_min(_PIVOT_FLOOR)
        # row j becomes the scaled pivot row, every other row loses its multiple of it
        system = system - (system[:, :, j:j + 1] - unit) * row
    return system[:, :, p]


def pool_inverse_depth(inverse_depth: torch.Tensor, scale: torch.Tensor, radius: int = 2, degree: int = 2,
                       kernel_width: float = 2.5, iterations: int = 2, scale_floor: float = 0.005,
                       ridge: float = 1e-3, curvature_test: float = 0.0) -> torch.Tensor:
    """Robust, precision-weighted local polynomial fit of the tile inverse depths (module docstring).

    Args:
        inverse_depth: ``(B, 1, h, w)`` refined inverse depth ``q`` in 1/m, > 0.
        scale: ``(B, 1, h, w)`` predicted Laplace scale ``b`` of each tile's relative error, >= 0.
        radius: the window's half side in tiles (>= 1).
        degree: of the local surface: 0 (constant), 1 (plane) or 2 (quadratic).
        kernel_width: ``k``, the robust kernel's width in combined scales (> 0).
        iterations: reweighting passes (>= 1).
        scale_floor: ``f`` (> 0), added in quadrature to every scale.
        ridge: penalty on the non-constant terms, relative to the window's total weight (>= 0).
        curvature_test: ``tau`` (>= 0; degree 2 only): the plane through the last pass's weights
            wherever the curvature terms lower the robust chi-square by ``tau`` or less (module
            docstring); 0: the quadratic everywhere.

    Returns:
        ``(B, 1, h, w)``: the fitted inverse depth at each tile, 1/m.

    Raises:
        ShapeError: the two inputs are not equal ``(B, 1, h, w)`` tensors.
        NonFiniteError: a NaN or infinite value in either input.
        RangeError: an inverse depth <= 0 or a negative scale.
        InputError: an option out of its range.
    """
    if inverse_depth.dim() != 4 or inverse_depth.shape[1] != 1 or scale.shape != inverse_depth.shape:
        raise ShapeError(f"inverse_depth and scale must be equal (B, 1, h, w) tensors, got "
                         f"{tuple(inverse_depth.shape)} and {tuple(scale.shape)}")
    _check_options(radius, degree, kernel_width, iterations, scale_floor, ridge, curvature_test)
    if not is_exporting():
        if not bool(torch.isfinite(inverse_depth).all() and torch.isfinite(scale).all()):
            raise NonFiniteError("inverse_depth and scale must be finite (NaN or inf found)")
        if not bool((inverse_depth > 0).all() and (scale >= 0).all()):
            raise RangeError("inverse_depth must be > 0 (1/m) and scale >= 0")
    q, b = inverse_depth, scale
    side = 2 * radius + 1
    design = _design(radius, degree, q.dtype).to(q.device)  # (S, P)
    n_par = design.shape[1]
    q_win = _gather(q, side, "replicate")
    b_win = _gather(b, side, "replicate")
    inside = _gather(torch.ones_like(q), side, "constant")  # 0 outside the grid
    precision = inside / (b_win * b_win + scale_floor * scale_floor)
    width = kernel_width * q * torch.sqrt(b * b + b_win * b_win + scale_floor * scale_floor)
    # 1x1 kernels: the normal matrix's entries sum_s w_s X_si X_sj (row-major), the right side
    # sum_s w_s (q_s - q) X_si, and the fit's value at every window tile sum_i beta_i X_si
    matrix_k = (design.t()[:, None, :] * design.t()[None, :, :]).reshape(n_par * n_par, -1, 1, 1)
    rhs_k = design.t().reshape(n_par, -1, 1, 1)
    predict_k = design.reshape(side * side, n_par, 1, 1)
    ridge_m = torch.diag(torch.tensor([0.0] + [ridge] * (n_par - 1), dtype=q.dtype, device=q.device))
    ridge_m = ridge_m.reshape(1, n_par, n_par, 1, 1)
    centre_index = (side * side) // 2
    fit = q.expand(-1, side * side, -1, -1)
    for _ in range(iterations):
        z = (q_win - fit) / width
        weight = precision * (torch.exp(-0.5 * z * z) + 1e-6)
        weight = weight / weight.sum(1, keepdim=True)  # the window's total weight is one
        matrix = F.conv2d(weight, matrix_k).unflatten(1, (n_par, n_par)) + ridge_m
        right = F.conv2d(weight * (q_win - q), rhs_k).unsqueeze(2)  # relative to the centre: small numbers
        coeffs = _solve_spd(torch.cat([matrix, right], 2))
        fit = q + F.conv2d(coeffs, predict_k)
    centre = fit[:, centre_index:centre_index + 1]
    if curvature_test <= 0 or degree < 2:
        return centre
    # the plane through the same weights: the normal equations' leading 3x3 block
    plane_coeffs = _solve_spd(torch.cat([matrix[:, :3, :3], right[:, :3]], 2))
    plane = q + F.conv2d(plane_coeffs, predict_k[:, :3])
    kept = precision * torch.exp(-0.5 * ((q_win - fit) / width) ** 2)  # the last fit's robust weights, unnormalised
    chi_quadratic = (kept * ((q_win - fit) / q) ** 2).sum(1, keepdim=True)
    chi_plane = (kept * ((q_win - plane) / q) ** 2).sum(1, keepdim=True)
    curved = 0.5 * (chi_plane - chi_quadratic) > curvature_test  # Laplace: the variance is 2 b^2
    return torch.where(curved, centre, plane[:, centre_index:centre_index + 1])


def _check_options(radius: int, degree: int, kernel_width: float, iterations: int, scale_floor: float,
                   ridge: float, curvature_test: float = 0.0) -> None:
    if not isinstance(radius, int) or radius < 1:
        raise InputError(f"pooling radius must be an integer >= 1 (tiles), got {radius!r}")
    if degree not in (0, 1, 2):
        raise InputError(f"pooling degree must be 0, 1 or 2, got {degree!r}")
    if not isinstance(iterations, int) or iterations < 1:
        raise InputError(f"pooling iterations must be an integer >= 1, got {iterations!r}")
    if not kernel_width > 0 or not scale_floor > 0 or not ridge >= 0:
        raise InputError(f"pooling needs kernel_width > 0, scale_floor > 0 and ridge >= 0, got {kernel_width!r}, "
                         f"{scale_floor!r}, {ridge!r}")
    if not curvature_test >= 0:
        raise InputError(f"pooling curvature_test must be >= 0 (0: off), got {curvature_test!r}")
    if not all(math.isfinite(float(v)) for v in (kernel_width, scale_floor, ridge, curvature_test)):
        raise InputError("pooling options must be finite")


class StructurePooling(nn.Module):
    """:func:`pool_inverse_depth` as a module with its options fixed (no parameters).

    Args:
        radius, degree, kernel_width, iterations, scale_floor, ridge, curvature_test: as in
            :func:`pool_inverse_depth`.

    Shape:
        - ``inverse_depth``, ``scale``: ``(B, 1, h, w)``.
        - Output: ``(B, 1, h, w)``, 1/m.

    Example:
        >>> pool = StructurePooling(radius=1, degree=1)
        >>> q = torch.full((1, 1, 4, 5), 2.0)
        >>> bool(torch.allclose(pool(q, torch.full_like(q, 0.02)), q))
        True
        >>> StructurePooling.from_config(pool.to_config()).to_config() == pool.to_config()
        True
    """

    def __init__(self, radius: int = 2, degree: int = 2, kernel_width: float = 2.5, iterations: int = 2,
                 scale_floor: float = 0.005, ridge: float = 1e-3, curvature_test: float = 0.0) -> None:
        super().__init__()
        _check_options(radius, degree, kernel_width, iterations, scale_floor, ridge, curvature_test)
        self.radius, self.degree, self.iterations = radius, degree, iterations
        self.kernel_width, self.scale_floor, self.ridge = float(kernel_width), float(scale_floor), float(ridge)
        self.curvature_test = float(curvature_test)

    def to_config(self) -> dict[str, Any]:
        """The options as a JSON-serialisable dict (keys :data:`POOLING_KEYS`)."""
        return {"radius": self.radius, "degree": self.degree, "kernel_width": self.kernel_width,
                "iterations": self.iterations, "scale_floor": self.scale_floor, "ridge": self.ridge,
                "curvature_test": self.curvature_test}

    @classmethod
    def from_config(cls, cfg: dict[str, Any]) -> "StructurePooling":
        """Build from :meth:`to_config` output.

        Raises:
            InputError: unknown keys or options out of range.
        """
        unknown = set(cfg) - set(POOLING_KEYS)
        if unknown:
            raise InputError(f"unknown structure pooling option(s) {sorted(unknown)}; known: {list(POOLING_KEYS)}")
        return cls(**cfg)

    def forward(self, inverse_depth: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
        return pool_inverse_depth(inverse_depth, scale, self.radius, self.degree, self.kernel_width,
                                  self.iterations, self.scale_floor, self.ridge, self.curvature_test)
