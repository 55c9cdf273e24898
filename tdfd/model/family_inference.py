r"""The lens's PSF family inferred from the whole image, for a CNN that was not told it.

A tile whose texture sits in one or two spatial frequencies (a sine grating, a narrow-band
texture) fixes the ratio of the two frames' transfer functions at those frequencies only,
and that ratio maps to a depth only through the PSF's shape: a Gaussian and a pillbox blur
put the same ratio at different depths. With the family unknown, such a tile is ambiguous
however much signal it has. The other tiles of the same image, with broader spectra, show
the shape (the frames share one lens), which is why the Cramér-Rao bound with the PSF
learnt from the whole image is lower than with the PSF learnt from each tile alone
(``benchmarks/bench_bound.py``). The CNN's neighbourhood is a few tiles; this layer gives
it the image's verdict.

:class:`FamilyInference` reads the standardised per-tile features, gives every tile class
logits over ``(gaussian, pillbox, other)`` and a weight in (0, 1), averages the logits over
each image's tiles with those weights (a mean, so the verdict does not sharpen with the
frame size), and returns the softmax's first two probabilities as a soft family code, the
code of :mod:`tdfd.model.psf_family_code` (``(1, 0)`` Gaussian, ``(0, 1)`` pillbox,
``(0, 0)`` unknown, which is also what "other" maps to). :func:`complete_family_code`
puts it in place of an unknown code and leaves a told one alone. Training supervises the
image logits with each sample's true family (a cross-entropy, :mod:`training.losses`).

Example:
    >>> import torch
    >>> layer = FamilyInference(in_channels=6, hidden=8)
    >>> code, logits = layer(torch.randn(2, 6, 3, 4))
    >>> code.shape, logits.shape, bool((code >= 0).all() and (code.sum(1) <= 1).all())
    (torch.Size([2, 2, 1, 1]), torch.Size([2, 3]), True)
"""

from __future__ import annotations

import torch
from torch import nn

from ..errors import InputError, ShapeError

__all__ = ["FAMILY_CLASSES", "FamilyInference", "complete_family_code", "family_classes"]

#: The classes of the image logits: the two families of the code, then every other shape.
FAMILY_CLASSES = ("gaussian", "pillbox", "other")
#: Floor of the summed tile weights of an image (an image whose tiles all weigh ~0 gets
#: logits ~0, the uniform verdict); >= 1e-6 so that ONNX export keeps it.
_WEIGHT_FLOOR = 1e-3


class FamilyInference(nn.Module):
    """Image-wide PSF family verdict from per-tile features.

    Args:
        in_channels: standardised feature channels per tile (the CNN's input without the code).
        hidden: width of the per-tile 1x1 layer.

    Shape:
        - Input: ``(B, C, h, w)``, any ``h, w >= 1``.
        - Output: ``(code, logits)``: the soft code ``(B, 2, 1, 1)`` (probabilities of
          Gaussian and pillbox, summing to at most 1) and the image logits ``(B, 3)`` over
          :data:`FAMILY_CLASSES`.
    """

    def __init__(self, in_channels: int, hidden: int = 32) -> None:
        super().__init__()
        if in_channels < 1 or hidden < 1:
            raise InputError(f"FamilyInference needs in_channels >= 1 and hidden >= 1, got {in_channels}, {hidden}")
        self.in_channels, self.hidden = int(in_channels), int(hidden)
        self.net = nn.Sequential(nn.Conv2d(in_channels, hidden, 1), nn.SiLU(),
                                 nn.Conv2d(hidden, len(FAMILY_CLASSES) + 1, 1))

    def forward(self, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        if features.dim() != 4 or features.shape[1] != self.in_channels:
            raise ShapeError(f"expected (B, {self.in_channels}, h, w) features, got {tuple(features.shape)}")
        out = self.net(features)
        k = len(FAMILY_CLASSES)
        weight = torch.sigmoid(out[:, k:])  # (B, 1, h, w)
        logits = (weight * out[:, :k]).sum((2, 3)) / weight.sum((2, 3)).clamp_min(_WEIGHT_FLOOR)
        prob = torch.softmax(logits, 1)
        return prob[:, :2].reshape(-1, 2, 1, 1), logits


def complete_family_code(given: torch.Tensor, inferred: torch.Tensor) -> torch.Tensor:
    """The code maps the CNN sees: ``given`` where a family was told, ``inferred`` where not.

    Args:
        given: the told code maps ``(B, 2, h, w)`` (one-hot, or all zeros for unknown).
        inferred: :class:`FamilyInference`'s code ``(B, 2, 1, 1)``.

    Returns:
        ``(B, 2, h, w)``.

    Example:
        >>> import torch
        >>> told = torch.tensor([[1.0, 0.0], [0.0, 0.0]]).reshape(2, 2, 1, 1)
        >>> guess = torch.tensor([[0.2, 0.7], [0.2, 0.7]]).reshape(2, 2, 1, 1)
        >>> complete_family_code(told, guess).flatten(1).tolist()
        [[1.0, 0.0], [0.20000000298023224, 0.699999988079071]]
    """
    if given.dim() != 4 or given.shape[1] != 2 or inferred.shape != (given.shape[0], 2, 1, 1):
        raise ShapeError(f"need given (B, 2, h, w) and inferred (B, 2, 1, 1), got {tuple(given.shape)}, "
                         f"{tuple(inferred.shape)}")
    told = given.sum(1, keepdim=True).clamp(0.0, 1.0)
    return given + (1.0 - told) * inferred


def family_classes(params: list, ignore_index: int = -1) -> torch.Tensor:
    """Each sample's true class index in :data:`FAMILY_CLASSES` ``(B,)`` (int64), from the
    ``data_synth`` parameters' ``psf_shape``; ``ignore_index`` where no shape is recorded.

    Example:
        >>> family_classes([{"psf_shape": "pillbox"}, {"psf_shape": "beta"}, None]).tolist()
        [1, 2, -1]
    """
    out = []
    for p in params:
        shape = p.get("psf_shape") if isinstance(p, dict) else None
        if shape is None:
            out.append(ignore_index)
        else:
            out.append(FAMILY_CLASSES.index(shape) if shape in FAMILY_CLASSES[:2] else 2)
    return torch.tensor(out, dtype=torch.int64)
