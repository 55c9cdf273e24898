r"""The likelihood stage's fused map pooled along the scene's depth structure.

The stage (:mod:`tdfd.dfd.likelihood_stage`) refines each tile on its own: its fused estimate
and confidence depend on that tile's fit and the model's value there. Real surfaces are smooth
between occlusion edges, so the tiles on one surface can share what each measured. This step
runs a structure pooling (the model's own: :class:`tdfd.model.structure_pooling.StructurePooling`,
a robust, precision-weighted local surface fit whose weights come from each tile's Laplace
scale, with the model's options) on the stage's fused inverse depths, each tile weighted by the
scale its fused confidence states (``b = b0 sqrt(1 / c - 1)``,
:func:`~tdfd.dfd.inverse_variance.model_sigma` over ``sqrt(2)``). A tile at confidence 0 (no
information) brings the scale :data:`POOL_SCALE_CAP` to the fit, which gives it a weight of
about ``1e-6`` of a confident tile's.

The pooled map keeps each tile's fused confidence: pooling lowers the error a tile's confidence
states, so it stays a conservative statement (measured per confidence decile in
``docs/BENCHMARKS.md``, section ``psf_structure``). The step is opt-in
(``LikelihoodStage(pooling=...)``, ``tdfd depth --likelihood-pool``).

Example:
    >>> import torch
    >>> from tdfd.model.structure_pooling import StructurePooling
    >>> yy, xx = torch.meshgrid(torch.arange(5.0), torch.arange(6.0), indexing="ij")
    >>> truth = (1.0 / (2.0 + 0.05 * yy + 0.02 * xx)).reshape(1, 1, 5, 6).double()
    >>> noise = 0.02 * torch.randn(truth.shape, generator=torch.Generator().manual_seed(1), dtype=truth.dtype)
    >>> depth, conf = truth * (1 + noise), torch.full_like(truth, 0.2)
    >>> pooled = pool_stage_map(depth, conf, 0.01, StructurePooling(radius=2, degree=1))
    >>> bool((pooled / truth - 1).abs().mean() < (depth / truth - 1).abs().mean())
    True
"""

from __future__ import annotations

import math
from typing import Callable

import torch

from ..errors import InputError, ShapeError
from .inverse_variance import model_sigma

__all__ = ["POOL_SCALE_CAP", "pool_stage_map"]

#: the largest Laplace scale of the relative error a tile brings to the pooling's weights (a
#: tile at confidence 0 states an infinite one, which the pooling's weights cannot take)
POOL_SCALE_CAP = 10.0


def pool_stage_map(depth: torch.Tensor, confidence: torch.Tensor, confidence_scale: float,
                   pooling: Callable[[torch.Tensor, torch.Tensor], torch.Tensor]) -> torch.Tensor:
    """The stage's fused depth map pooled along the depth structure (module documentation).

    Args:
        depth: ``(B, 1, h, w)`` the fused object distances, metres (> 0).
        confidence: ``(B, 1, h, w)`` their confidences in [0, 1], on the model's scale ``b0``.
        confidence_scale: the model's ``b0`` (> 0).
        pooling: ``(inverse_depth, scale) -> inverse_depth`` on ``(B, 1, h, w)`` float64 tensors,
            e.g. :class:`~tdfd.model.structure_pooling.StructurePooling`.

    Returns:
        ``(B, 1, h, w)`` the pooled distances, metres, in ``depth``'s dtype.

    Raises:
        ShapeError: maps that are not one ``(B, 1, h, w)`` shape.
        InputError: depths not > 0 (and, from :func:`~tdfd.dfd.inverse_variance.model_sigma`,
            confidences outside [0, 1] or a scale not > 0).
    """
    if depth.ndim != 4 or depth.shape[1] != 1 or confidence.shape != depth.shape:
        raise ShapeError(f"depth and confidence must be one (B, 1, h, w) shape, got {tuple(depth.shape)} and "
                         f"{tuple(confidence.shape)}")
    if not bool((depth > 0).all()):
        raise InputError("depths must be > 0 to pool them")
    scale = (model_sigma(confidence, confidence_scale) / math.sqrt(2.0)).clamp_max(POOL_SCALE_CAP)
    return (1.0 / pooling(1.0 / depth.to(torch.float64), scale)).to(depth.dtype)
