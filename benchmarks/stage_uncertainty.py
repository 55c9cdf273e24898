"""The likelihood stage's confidence as an uncertainty: section ``uncertainty``'s deciles on the stage's output.

The stage (:mod:`tdfd.dfd.likelihood_stage`) states each fused tile's standard deviation as a
confidence on the model's scale, ``conf = 1 / (1 + (b / b0)^2)``. Issue 19 asks of a confidence
that its predicted error match the observed one within 20 % in every confidence decile; this
scores the stage's confidence (and the model's, on the same tiles) by the same deciles and
scene bootstrap as ``benchmarks/bench_uncertainty.py``
(:func:`benchmarks.uncertainty.decile_table`, :func:`benchmarks.uncertainty.scene_bootstrap`).

Example:
    >>> import torch
    >>> g = torch.Generator().manual_seed(0)
    >>> b = 0.002 + 0.05 * torch.rand(4000, generator=g, dtype=torch.float64)  # Laplace scales
    >>> conf = 1 / (1 + (b / 0.01) ** 2)
    >>> u = torch.rand(4000, generator=g, dtype=torch.float64) - 0.5
    >>> e = -b * torch.sign(u) * torch.log1p(-2 * u.abs())  # Laplace errors of those scales
    >>> row = decile_summary(conf, e, torch.arange(4000) // 40, 0.01, reps=20)
    >>> row[0], row[1]
    ('10 of 10', 0)
"""

from __future__ import annotations

import torch

from benchmarks.depth_models import predicted_scale
from benchmarks.uncertainty import decile_table, outside_band, scene_bootstrap, worst_decile
from tdfd.errors import InputError

__all__ = ["decile_summary", "relative_inverse_depth_error"]


def relative_inverse_depth_error(depth: torch.Tensor, true_depth: torch.Tensor) -> torch.Tensor:
    """``e = (q - q_true) / q_true`` with ``q = 1 / d``: the error the confidence's scale is of.

    Raises:
        InputError: shapes that differ or depths not finite and > 0.
    """
    if depth.shape != true_depth.shape:
        raise InputError(f"depth and true depth must share one shape, got {tuple(depth.shape)} and "
                         f"{tuple(true_depth.shape)}")
    for name, d in (("depth", depth), ("true depth", true_depth)):
        if not bool(torch.isfinite(d).all()) or not bool((d > 0).all()):
            raise InputError(f"{name} must be finite and > 0")
    return true_depth.double() / depth.double() - 1.0


def decile_summary(confidence: torch.Tensor, error: torch.Tensor, scene: torch.Tensor, confidence_scale: float,
                   reps: int = 100) -> list[object]:
    """One row of the stage's calibration table: deciles within 20 %, those outside by more than
    two standard errors (over the scenes), the ratios' range and the worst ratio with its error.

    Args:
        confidence: ``(N,)`` the tiles' confidences in [0, 1].
        error: ``(N,)`` their signed relative inverse-depth errors
            (:func:`relative_inverse_depth_error`).
        scene: ``(N,)`` each tile's scene (the bootstrap draws whole scenes).
        confidence_scale: the model's ``b0``.
        reps: bootstrap resamples.

    Raises:
        InputError: as :func:`benchmarks.uncertainty.decile_table` and
            :func:`benchmarks.uncertainty.scene_bootstrap`.
    """
    scale = predicted_scale(confidence.double(), confidence_scale)
    table = decile_table(confidence, scale, error)
    for row, se in zip(table, scene_bootstrap(confidence, scale, error, scene, reps=reps)):
        row["ratio_se"] = float(se)
    ratios = [r["ratio"] for r in table]
    k = worst_decile(table)
    return [f"{sum(r['ok'] for r in table)} of {len(table)}", sum(outside_band(r) for r in table),
            f"{min(ratios):.2f}-{max(ratios):.2f}", f"{ratios[k]:.2f} +- {table[k]['ratio_se']:.2f} (decile {k + 1})"]
