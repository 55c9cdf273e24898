"""The refinement CNN: a small fully convolutional network on the tile grid.

:class:`RefineNet` maps per-tile features ``(B, C, h, w)`` (built by
:func:`tdfd.model.combined.tile_features` from the analytic estimator) to two maps: a
correction of the analytic inverse depth in dioptres and a log-scale correction of the
predicted relative error. It is a pointwise (1x1) stem, a few residual blocks of 3x3
convolutions over neighbouring tiles (replicate padding, so any ``h, w >= 1`` works and
border tiles see the same statistics as interior ones), and a 1x1 head initialised to
zero, so an untrained network leaves the analytic estimate unchanged.

Inputs are standardised with fixed per-channel buffers (``feature_mean``,
``feature_std``) that training fits once on synthetic data and that are saved with the
weights. No data-dependent control flow: it exports to ONNX as plain convolutions.

Example:
    >>> import torch
    >>> net = RefineNet(in_channels=8, hidden=16, blocks=1)
    >>> out = net(torch.randn(2, 8, 3, 5))
    >>> out.shape, float(out.detach().abs().max())
    (torch.Size([2, 2, 3, 5]), 0.0)
    >>> net(torch.randn(1, 8, 1, 1)).shape
    torch.Size([1, 2, 1, 1])
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from ..errors import InputError, ShapeError
from .family_inference import FamilyInference, complete_family_code

__all__ = ["RefineNet", "ResidualBlock"]


class ResidualBlock(nn.Module):
    """``x + conv1x1(act(conv_kxk(act(x))))`` with replicate padding.

    Args:
        channels: feature channels.
        kernel_size: odd spatial kernel size of the first convolution (1 = pointwise).
        dilation: spacing of its taps in tiles.
    """

    def __init__(self, channels: int, kernel_size: int = 3, dilation: int = 1) -> None:
        super().__init__()
        if kernel_size < 1 or kernel_size % 2 == 0:
            raise InputError(f"kernel_size must be a positive odd integer, got {kernel_size}")
        if dilation < 1:
            raise InputError(f"dilation must be >= 1, got {dilation}")
        self.pad = (kernel_size // 2) * dilation
        self.conv1 = nn.Conv2d(channels, channels, kernel_size, dilation=dilation)
        self.conv2 = nn.Conv2d(channels, channels, 1)
        self.act = nn.SiLU()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.act(x)
        if self.pad:
            y = F.pad(y, (self.pad,) * 4, mode="replicate")
        return x + self.conv2(self.act(self.conv1(y)))


class RefineNet(nn.Module):
    """Small fully convolutional refinement network on the tile grid.

    Args:
        in_channels: number of per-tile feature channels ``C``.
        hidden: width of the hidden layers.
        blocks: number of residual blocks.
        kernel_size: spatial kernel of the blocks (3 = each block sees its 8 neighbours).
        dilation_base: block ``i`` has dilation ``dilation_base ** i`` (1: none; 2: 1, 2, 4, ...),
            which widens the receptive field at no extra cost.
        out_channels: output maps (2: inverse-depth correction, log-scale correction).
        family_inference: the input's last two channels are the PSF family code
            (:mod:`tdfd.model.psf_family_code`); where it is all zeros (unknown), the code
            inferred from the whole image (:class:`~tdfd.model.family_inference.FamilyInference`
            on the other channels) takes its place.
        family_hidden: width of that inference's per-tile layer.

    Shape:
        - Input: ``(B, C, h, w)`` per-tile features, any ``h, w >= 1``.
        - Output: ``(B, out_channels, h, w)``; channel 0 in dioptres, channel 1 a log-scale.
    """

    def __init__(self, in_channels: int, hidden: int = 32, blocks: int = 2, kernel_size: int = 3,
                 dilation_base: int = 1, out_channels: int = 2, family_inference: bool = False,
                 family_hidden: int = 32) -> None:
        super().__init__()
        if in_channels < 1 or hidden < 1 or blocks < 0 or out_channels < 1:
            raise InputError(f"invalid RefineNet sizes: in={in_channels}, hidden={hidden}, blocks={blocks}, out={out_channels}")
        self.in_channels, self.hidden, self.blocks_n = int(in_channels), int(hidden), int(blocks)
        self.kernel_size, self.out_channels = int(kernel_size), int(out_channels)
        if dilation_base < 1:
            raise InputError(f"dilation_base must be >= 1, got {dilation_base}")
        self.dilation_base = int(dilation_base)
        self.register_buffer("feature_mean", torch.zeros(1, in_channels, 1, 1))
        self.register_buffer("feature_std", torch.ones(1, in_channels, 1, 1))
        self.stem = nn.Conv2d(in_channels, hidden, 1)
        self.blocks = nn.Sequential(*[ResidualBlock(hidden, kernel_size, self.dilation_base**i) for i in range(blocks)])
        self.act = nn.SiLU()
        self.head = nn.Conv2d(hidden, out_channels, 1)
        nn.init.zeros_(self.head.weight)
        nn.init.zeros_(self.head.bias)
        if family_inference and in_channels < 3:
            raise InputError(f"family_inference needs the two code channels and at least one feature, got {in_channels}")
        #: the image-wide PSF family inference (``None``: off)
        self.family = FamilyInference(in_channels - 2, family_hidden) if family_inference else None

    def config(self) -> dict:
        """Constructor arguments (JSON-serialisable)."""
        cfg = {"in_channels": self.in_channels, "hidden": self.hidden, "blocks": self.blocks_n,
               "kernel_size": self.kernel_size, "dilation_base": self.dilation_base, "out_channels": self.out_channels}
        if self.family is not None:
            cfg.update(family_inference=True, family_hidden=self.family.hidden)
        return cfg

    @torch.no_grad()
    def set_normaliser(self, mean: torch.Tensor, std: torch.Tensor) -> None:
        """Set the per-channel input standardisation (``(C,)`` tensors; std floored at 1e-3)."""
        if mean.numel() != self.in_channels or std.numel() != self.in_channels:
            raise ShapeError(f"normaliser needs {self.in_channels} channels, got {mean.numel()} and {std.numel()}")
        self.feature_mean.copy_(mean.reshape(1, -1, 1, 1))
        self.feature_std.copy_(std.reshape(1, -1, 1, 1).clamp_min(1e-3))

    def standardised(self, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """The blocks' input: standardised features with an unknown family code replaced by
        the inferred one, and the image family logits ``(B, 3)`` (``None`` without
        ``family_inference``)."""
        x = (features - self.feature_mean) / self.feature_std
        if self.family is None:
            return x, None
        code, logits = self.family(x[:, :-2])
        maps = complete_family_code(features[:, -2:], code)
        # standardised whole again rather than the code's channels alone: a (1, 2, 1, 1) slice of the
        # normaliser is a constant the ONNX exporter may merge with the equal-valued code initializer
        return (torch.cat([features[:, :-2], maps], 1) - self.feature_mean) / self.feature_std, logits

    def forward_with_family(self, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """:meth:`forward`'s output and, from the same pass, the image family logits ``(B, 3)``
        (``None`` without ``family_inference``): what training supervises."""
        x, logits = self.standardised(features)
        return self.head(self.act(self.blocks(self.stem(x)))), logits

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        return self.forward_with_family(features)[0]
