"""Losses and metrics on the tile grid.

The refinement predicts inverse depth ``q`` and a Laplace scale ``b = exp(log_b)`` of the
relative error ``e = (q - q_true) / q_true`` (for small errors the relative depth error,
with opposite sign). The Laplace negative log-likelihood ``|e| / b + log b`` is minimised
by the median (matching the median error we report) and by ``b = E|e|``, which makes the
confidence ``1 / (1 + (b / b0)^2)`` a calibrated, monotone function of the expected error.

Example:
    >>> import torch
    >>> q = torch.tensor([2.0, 2.0]); qt = torch.tensor([2.0, 2.2])
    >>> round(float(laplace_nll(q, torch.zeros(2), qt)), 4)
    0.0455
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

__all__ = ["relative_error", "laplace_nll", "refinement_loss", "pooled_loss", "family_loss", "depth_relative_error"]


def relative_error(q: torch.Tensor, q_true: torch.Tensor) -> torch.Tensor:
    """``(q - q_true) / q_true``, the relative inverse-depth error."""
    return (q - q_true) / q_true


def laplace_nll(q: torch.Tensor, log_b: torch.Tensor, q_true: torch.Tensor) -> torch.Tensor:
    """Mean Laplace NLL of the relative inverse-depth error (constant ``log 2`` dropped)."""
    e = relative_error(q, q_true).abs()
    return (e * torch.exp(-log_b) + log_b).mean()


def refinement_loss(q: torch.Tensor, log_b: torch.Tensor, tile_depth: torch.Tensor, l1_weight: float = 0.0
                    ) -> tuple[torch.Tensor, dict[str, float]]:
    """Training loss: Laplace NLL plus ``l1_weight`` times the mean absolute relative error.

    Args:
        q: predicted inverse depth ``(B, 1, h, w)`` in 1/m.
        log_b: predicted log Laplace scale ``(B, 1, h, w)``.
        tile_depth: true per-tile depth ``(B, 1, h, w)`` in metres.
        l1_weight: weight of the plain L1 term.

    Returns:
        ``(loss, parts)`` with ``parts`` the detached ``nll`` and ``l1`` values.
    """
    q_true = 1.0 / tile_depth
    nll = laplace_nll(q, log_b, q_true)
    l1 = relative_error(q, q_true).abs().mean()
    loss = nll + l1_weight * l1 if l1_weight > 0 else nll
    return loss, {"nll": float(nll.detach()), "l1": float(l1.detach())}


def pooled_loss(q_pooled: torch.Tensor, log_b: torch.Tensor, tile_depth: torch.Tensor) -> torch.Tensor:
    """The structure-pooled map's loss: its absolute relative inverse-depth error in units of each
    tile's own predicted scale, ``mean(|e_pooled| / b)`` with ``b`` held fixed.

    The units make the term comparable with :func:`laplace_nll`'s (whose gradient in ``q`` is
    ``sign(e) / b`` per tile); holding ``b`` fixed leaves the scale to the NLL, so the scale stays
    the tile's own calibrated error, while the term still reaches the scales through the pooling's
    weights (:mod:`tdfd.model.structure_pooling`): the CNN learns tiles and scales that pool well.

    Args:
        q_pooled: the pooled inverse depth ``(B, 1, h, w)`` in 1/m (:meth:`tdfd.model.DFDModel.pooled_inverse_depth`).
        log_b: the tiles' log Laplace scale ``(B, 1, h, w)`` (not differentiated here).
        tile_depth: true per-tile depth ``(B, 1, h, w)`` in metres.

    Example:
        >>> import torch
        >>> qp = torch.tensor([2.02, 1.98]); lb = torch.log(torch.tensor([0.01, 0.02]))
        >>> round(float(pooled_loss(qp, lb, torch.tensor([0.5, 0.5]))), 4)  # (1 + 0.5) / 2
        0.75
    """
    e = relative_error(q_pooled, 1.0 / tile_depth).abs()
    return (e * torch.exp(-log_b.detach())).mean()


def family_loss(logits: torch.Tensor, family_class: torch.Tensor, ignore_index: int = -1) -> torch.Tensor:
    """Cross-entropy of the image-wide PSF family logits ``(B, 3)`` against the true classes
    ``(B,)`` (:func:`tdfd.model.family_inference.family_classes`; ``ignore_index``: no label);
    0 when no sample of the batch has a label.

    Example:
        >>> import torch
        >>> round(float(family_loss(torch.zeros(2, 3), torch.tensor([0, -1]))), 4)  # log 3
        1.0986
    """
    labelled = family_class != ignore_index
    if not bool(labelled.any()):
        return logits.sum() * 0.0
    return F.cross_entropy(logits[labelled], family_class[labelled])


def depth_relative_error(depth: torch.Tensor, true_depth: torch.Tensor) -> torch.Tensor:
    """Absolute relative depth error ``|d - d_true| / d_true`` (the reported metric)."""
    return (depth - true_depth).abs() / true_depth
