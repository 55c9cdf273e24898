"""Piecewise-linear maps through knots, and the monotone map of a log error scale they make.

A map of a predicted error scale must keep the order of what it calibrates (a more confident
tile stays more confident), be exportable to ONNX as element-wise operators, and hold
constant beyond its end knots. :func:`calibrate_log_scale` is that map,
``log b' = log b + s(log b)`` with ``s`` linear between knots ``(x_k, y_k - x_k)``;
:func:`validate_knots` checks its knots. Both the CNN's post-hoc calibration
(:mod:`tdfd.model.scale_calibration`) and the likelihood stage's fused scale
(:mod:`tdfd.dfd.inverse_variance`) use them.

Example:
    >>> import torch
    >>> calibrate_log_scale(torch.tensor([-4.0]), torch.tensor([-5.0, -3.0]), torch.tensor([-4.0, -3.0]))
    tensor([-3.5000])
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch

from .errors import InputError

__all__ = ["finite_floats", "knot_pairs", "validate_knots", "piecewise_linear", "calibrate_log_scale"]


def finite_floats(values: Sequence[float], what: str) -> list[float]:
    """``values`` as floats, each finite.

    Raises:
        InputError: a value that is not a number, or not finite (``what`` names them).
    """
    try:
        out = [float(v) for v in values]
    except (TypeError, ValueError) as exc:
        raise InputError(f"scale calibration {what} must be numbers: {exc}") from exc
    if not all(math.isfinite(v) for v in out):
        raise InputError(f"scale calibration {what} must be finite")
    return out


def knot_pairs(xs: Sequence[float], ys: Sequence[float], x_name: str, y_name: str) -> tuple[list[float], list[float]]:
    """Finite numbers, as many ``xs`` as ``ys`` (at least 2), ``xs`` strictly increasing."""
    x, y = finite_floats(xs, x_name), finite_floats(ys, y_name)
    if len(x) != len(y) or len(x) < 2:
        raise InputError(f"scale calibration needs as many {x_name} as {y_name} knots, at least 2; "
                         f"got {len(x)} and {len(y)}")
    if any(b <= a for a, b in zip(x, x[1:])):
        raise InputError(f"scale calibration knots {x_name} must be strictly increasing")
    return x, y


def validate_knots(log_b: Sequence[float], log_b_calibrated: Sequence[float]) -> tuple[list[float], list[float]]:
    """Check the scale part's knots: as many of each (at least 2), finite, ``log_b`` strictly
    increasing and ``log_b_calibrated`` non-decreasing (the map must keep the confidence's order).

    Returns:
        The knots as two lists of floats.

    Raises:
        InputError: naming what is wrong.
    """
    x, y = knot_pairs(log_b, log_b_calibrated, "log_b", "log_b_calibrated")
    if any(b < a for a, b in zip(y, y[1:])):
        raise InputError("scale calibration knots log_b_calibrated must be non-decreasing (the map keeps the "
                         "confidence's order)")
    return x, y


def piecewise_linear(x: torch.Tensor, knots_x: torch.Tensor, knots_y: torch.Tensor) -> torch.Tensor:
    """The function through ``(knots_x[k], knots_y[k])``, linear between knots and constant beyond the ends.

    Args:
        x: any shape.
        knots_x: ``(K,)`` strictly increasing, ``K >= 2``.
        knots_y: ``(K,)`` values at the knots.

    Returns:
        The shape of ``x``; a sum of clamped hinges, so it exports to ONNX as element-wise operators.

    Example:
        >>> piecewise_linear(torch.tensor([-1.0, 0.5, 3.0]), torch.tensor([0.0, 1.0, 2.0]), torch.tensor([1.0, 3.0, 0.0]))
        tensor([1., 2., 0.])
    """
    kx = knots_x.to(x.dtype)
    ky = knots_y.to(x.dtype)
    lo, hi = kx[:-1], kx[1:]
    slope = (ky[1:] - ky[:-1]) / (hi - lo)
    inside = torch.minimum(torch.maximum(x.unsqueeze(-1), lo), hi) - lo  # (..., K - 1) against the segments
    return ky[0] + (inside * slope).sum(-1)


def calibrate_log_scale(log_scale: torch.Tensor, knots_log_b: torch.Tensor, knots_log_b_calibrated: torch.Tensor
                        ) -> torch.Tensor:
    """Map predicted log scales through the scale part's knots: ``log b + s(log b)``.

    Args:
        log_scale: ``log b``, any shape (e.g. ``(B, 1, h, w)``), natural log of the relative error scale.
        knots_log_b: ``(K,)`` strictly increasing knot positions ``x_k`` (:func:`validate_knots`).
        knots_log_b_calibrated: ``(K,)`` non-decreasing calibrated values ``y_k``.

    Returns:
        ``log b'``, the shape of ``log_scale``: ``log b + s(log b)``, ``s`` linear between the
        knots' shifts ``y_k - x_k`` and equal to the end shifts beyond them.

    Example:
        >>> x = torch.tensor([-5.0, -3.0]); y = torch.tensor([-4.0, -3.0])
        >>> calibrate_log_scale(torch.tensor([-6.0, -4.0, -2.0]), x, y)
        tensor([-5.0000, -3.5000, -2.0000])
    """
    return log_scale + piecewise_linear(log_scale, knots_log_b, knots_log_b_calibrated.to(knots_log_b.dtype) - knots_log_b)
