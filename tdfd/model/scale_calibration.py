"""Post-hoc calibration of the predicted error scale: a monotone map of ``log b``.

The refinement CNN predicts, per tile, a Laplace scale ``b`` of the relative inverse-depth
error ``e = (q - q_true) / q_true`` (:mod:`tdfd.model.combined`), trained by the Laplace
negative log-likelihood. On held-out scenes that scale is off by up to half at the
extremes (issue 19: the most confident tenth of the textured planes errs 1.56 times the
predicted median). A calibration moves ``log b`` by a piecewise-linear, non-decreasing
function of itself, fitted after training on scenes no training run or benchmark uses
(:mod:`training.calibrate_scale`) so that in every band of ``b`` the median ``|e|`` is
the Laplace median ``b' ln 2``. The map keeps the order of the tiles' confidences; a model
without one (``knots None``) is the identity.

The map is ``log b' = log b + s(log b)`` with ``s`` linear between knots ``(x_k, y_k - x_k)``
and held constant beyond the end knots. In the graph it is a sum of clamped hinges (no
index lookup), so the ONNX export carries it as a few element-wise operators.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import nn

from ..errors import InputError

__all__ = ["calibrate_log_scale", "ScaleCalibration", "laplace_mixture_median", "fit_scale_calibration",
           "validate_knots"]


def validate_knots(log_b: Sequence[float], log_b_calibrated: Sequence[float]) -> tuple[list[float], list[float]]:
    """Check calibration knots: as many of each (at least 2), finite, ``log_b`` strictly
    increasing and ``log_b_calibrated`` non-decreasing (the map must keep the confidence's order).

    Returns:
        The knots as two lists of floats.

    Raises:
        InputError: naming what is wrong.
    """
    try:
        x = [float(v) for v in log_b]
        y = [float(v) for v in log_b_calibrated]
    except (TypeError, ValueError) as exc:
        raise InputError(f"scale calibration knots must be numbers: {exc}") from exc
    if len(x) != len(y) or len(x) < 2:
        raise InputError(f"scale calibration needs as many log_b as log_b_calibrated knots, at least 2; "
                         f"got {len(x)} and {len(y)}")
    if not all(math.isfinite(v) for v in x + y):
        raise InputError("scale calibration knots must be finite")
    if any(b <= a for a, b in zip(x, x[1:])):
        raise InputError("scale calibration knots log_b must be strictly increasing")
    if any(b < a for a, b in zip(y, y[1:])):
        raise InputError("scale calibration knots log_b_calibrated must be non-decreasing (the map keeps the "
                         "confidence's order)")
    return x, y


def calibrate_log_scale(log_scale: torch.Tensor, knots_log_b: torch.Tensor, knots_log_b_calibrated: torch.Tensor
                        ) -> torch.Tensor:
    """Map predicted log scales through the calibration's knots.

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
    x = knots_log_b.to(log_scale.dtype)
    shift = knots_log_b_calibrated.to(log_scale.dtype) - x
    lo, hi = x[:-1], x[1:]
    slope = (shift[1:] - shift[:-1]) / (hi - lo)
    flat = log_scale.unsqueeze(-1)  # (..., 1) against the K - 1 segments
    inside = torch.minimum(torch.maximum(flat, lo), hi) - lo
    return log_scale + shift[0] + (inside * slope).sum(-1)


class ScaleCalibration(nn.Module):
    """:func:`calibrate_log_scale` with its knots as (non-persistent) buffers; identity without knots.

    The knots live in the model's JSON description (:meth:`to_config`), not its weights, so a
    calibration never changes the safetensors file and an uncalibrated model loads as before.

    Args:
        log_b: knot positions, natural log of the predicted scale; ``None`` for the identity.
        log_b_calibrated: calibrated values at the knots.
    """

    def __init__(self, log_b: Sequence[float] | None = None, log_b_calibrated: Sequence[float] | None = None) -> None:
        super().__init__()
        if (log_b is None) != (log_b_calibrated is None):
            raise InputError("scale calibration needs both log_b and log_b_calibrated, or neither")
        self.identity = log_b is None
        x, y = ([0.0, 1.0], [0.0, 1.0]) if log_b is None else validate_knots(log_b, log_b_calibrated)  # type: ignore[arg-type]
        self.register_buffer("knots_log_b", torch.tensor(x, dtype=torch.float32), persistent=False)
        self.register_buffer("knots_log_b_calibrated", torch.tensor(y, dtype=torch.float32), persistent=False)

    def forward(self, log_scale: torch.Tensor) -> torch.Tensor:
        if self.identity:
            return log_scale
        return calibrate_log_scale(log_scale, self.knots_log_b, self.knots_log_b_calibrated)

    def to_config(self) -> dict[str, list[float]] | None:
        """``{"log_b": [...], "log_b_calibrated": [...]}``, or ``None`` for the identity."""
        if self.identity:
            return None
        return {"log_b": [float(v) for v in self.knots_log_b], "log_b_calibrated":
                [float(v) for v in self.knots_log_b_calibrated]}

    @classmethod
    def from_config(cls, cfg: dict | None) -> "ScaleCalibration":
        """Inverse of :meth:`to_config`."""
        if cfg is None:
            return cls()
        if not isinstance(cfg, dict) or set(cfg) != {"log_b", "log_b_calibrated"}:
            raise InputError(f"scale calibration must be {{'log_b': [...], 'log_b_calibrated': [...]}}, got {cfg!r}")
        return cls(cfg["log_b"], cfg["log_b_calibrated"])


def laplace_mixture_median(scales: torch.Tensor) -> float:
    """Median of ``|e|`` over tiles whose errors ``e`` are Laplace with scales ``scales``.

    The ``m`` at which the tiles' mean ``P(|e| <= m) = 1 - exp(-m / b)`` is one half.

    Example:
        >>> round(laplace_mixture_median(torch.tensor([0.01, 0.01])), 6)  # one Laplace: b ln 2
        0.006931
    """
    b = torch.as_tensor(scales, dtype=torch.float64).flatten()
    if b.numel() == 0 or not bool((b >= 0).all()) or bool(torch.isnan(b).any()):
        raise InputError("scales must be a non-empty set of values >= 0")
    finite = b[torch.isfinite(b)]
    if finite.numel() * 2 <= b.numel():  # half the tiles or more with no prediction: no finite median
        return math.inf
    lo, hi = 0.0, max(float(finite.max()), 1e-300) * 50.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        # b = 0 counts as P = 1 (exact), b = inf as P = 0
        p = torch.where(b > 0, 1.0 - torch.exp(-mid / b.clamp_min(1e-300)), torch.ones_like(b)).mean()
        if float(p) < 0.5:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def fit_scale_calibration(scale: torch.Tensor, error: torch.Tensor, bins: int = 40, smooth: int = 3,
                          min_factor: float | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Fit calibration knots that make the predicted scale match observed errors.

    The tiles are split into ``bins`` equal-count bins by ``b``; in each, the factor ``f``
    that makes the Laplace mixture median of ``f b`` equal the observed median ``|e|``
    moves the bin's median ``b`` to a knot. The log factors are averaged over ``smooth``
    neighbouring bins (a moving average, ends held), held at ``min_factor`` or more, then the
    knots are made non-decreasing.

    ``min_factor`` bounds the factor from below (``1``: only ever widen the CNN's scale, for a
    user who would rather keep it where its errors are smaller than it predicts). The shipped
    model's fit has no bound: on the autofocus reliability benchmark (6000 targets, the lens's
    family unknown and calibrated) the full map, the widening-only one and the CNN's own scale
    declared 7, 6 and 7 targets out of focus, the same within chance, and only the full map
    brings every confidence decile of the structure scenes within 20 % (``models/README.md``).

    Args:
        scale: ``(N,)`` predicted Laplace scale ``b`` (positive, finite).
        error: ``(N,)`` observed signed relative error (finite).
        bins: number of equal-count bins (knots), at least 2.
        smooth: odd moving-average width over the bins' log factors (1: none).
        min_factor: the smallest factor ``b' / b`` at a knot (> 0); ``None``: no bound.

    Returns:
        ``(log_b, log_b_calibrated)`` knots, ``(bins,)`` float64 each (:func:`calibrate_log_scale`).

    Raises:
        InputError: shapes differ, fewer than two tiles per bin, equal bin medians, or a
            scale that is not positive and finite.

    Example:
        >>> g = torch.Generator().manual_seed(0)
        >>> b = torch.rand(20000, generator=g, dtype=torch.float64) * 0.05 + 0.01
        >>> u = torch.rand(20000, generator=g, dtype=torch.float64) - 0.5
        >>> e = 2 * b * -u.sign() * torch.log1p(-2 * u.abs())  # Laplace errors of scale 2 b
        >>> kb, kr = fit_scale_calibration(b, e, bins=10)
        >>> bool(((kr - kb).exp() - 2).abs().max() < 0.15)  # errors twice the predicted: factor 2
        True
    """
    b = torch.as_tensor(scale, dtype=torch.float64).flatten()
    e = torch.as_tensor(error, dtype=torch.float64).flatten().abs()
    if b.numel() != e.numel():
        raise InputError(f"scale and error must have as many values, got {b.numel()} and {e.numel()}")
    if bins < 2 or b.numel() < 2 * bins:
        raise InputError(f"need at least 2 bins and 2 tiles per bin, got {bins} bins for {b.numel()} tiles")
    if smooth < 1 or smooth % 2 == 0:
        raise InputError(f"smooth must be an odd width >= 1, got {smooth}")
    if not bool(((b > 0) & torch.isfinite(b)).all()):
        raise InputError("scale must be positive and finite")
    if not bool(torch.isfinite(e).all()):
        raise InputError("error must be finite")
    if min_factor is not None and not (math.isfinite(min_factor) and min_factor > 0):
        raise InputError(f"min_factor must be positive and finite or None, got {min_factor}")
    order = torch.argsort(b, stable=True)
    log_b, log_f = [], []
    for part in torch.tensor_split(order, bins):
        log_b.append(math.log(float(b[part].median())))
        log_f.append(math.log(max(float(e[part].median()), 1e-300) / laplace_mixture_median(b[part])))
    kb = torch.tensor(log_b, dtype=torch.float64)
    if bool((kb[1:] <= kb[:-1]).any()):
        raise InputError("bins with equal median scale: fewer bins, or scales that vary")
    f = torch.tensor(log_f, dtype=torch.float64)
    if smooth > 1:
        pad = smooth // 2
        padded = torch.cat([f[:1].expand(pad), f, f[-1:].expand(pad)])
        f = padded.unfold(0, smooth, 1).mean(-1)
    if min_factor is not None:
        f = f.clamp_min(math.log(min_factor))
    return kb, torch.cummax(kb + f, 0).values
