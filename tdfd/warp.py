r"""Focus breathing and misregistration between the two DFD frames (separable resampling).

An ECVFL changes the magnification slightly between the two powers (focus breathing) and
the two exposures may be sub-pixel apart (vibration, rolling readout):
:func:`misregister` magnifies frame 2 by ``1 + breathing`` about the image centre and
shifts it by ``(shift_y_px, shift_x_px)`` relative to frame 1, splitting the warp half and
half between the frames so that both are resampled alike (Keys cubic, ``a = -1/2``,
reflected borders) and the depth map stays aligned with their mean. This is the forward
model's geometry stage (:mod:`tdfd.forward`).

Example:
    >>> import torch
    >>> x = torch.rand(1, 2, 32, 32)
    >>> torch.equal(misregister(x, 0.0, 0.0, 0.0), x)
    True
    >>> misregister(x, 0.01, 0.3, -0.2).shape
    torch.Size([1, 2, 32, 32])
"""

from __future__ import annotations

import math

import torch
from torch import nn

from .errors import ShapeError

__all__ = ["misregister", "Misregistration"]


def _keys_weights(t: torch.Tensor) -> torch.Tensor:
    """Keys cubic-convolution weights (``a = -1/2``) of the taps at offsets -1, 0, 1, 2 for a
    fractional position ``t`` in [0, 1): ``(n, 4)``. This kernel reproduces polynomials up
    to degree 2, so a resampled image keeps its centroid exactly (PyTorch's bicubic uses
    ``a = -3/4``, which shifts centroids of fractionally moved content by up to ~30 %)."""
    t2, t3 = t * t, t * t * t
    return torch.stack([(-t3 + 2 * t2 - t) / 2, (3 * t3 - 5 * t2 + 2) / 2, (-3 * t3 + 4 * t2 + t) / 2,
                        (t3 - t2) / 2], dim=-1)


def _resample_axis(x: torch.Tensor, pos: torch.Tensor, dim: int) -> torch.Tensor:
    """Values of ``x`` at fractional source positions ``pos`` (px) along ``dim`` (Keys cubic,
    reflected borders)."""
    n = x.shape[dim]
    i0 = torch.floor(pos)
    w = _keys_weights((pos - i0).to(x.dtype))  # (m, 4)
    out = None
    for k in range(4):
        idx = (i0.long() + (k - 1)).abs()  # reflect at 0 ...
        idx = torch.where(idx > n - 1, 2 * (n - 1) - idx, idx).clamp(0, n - 1)  # ... and at n - 1
        shape = [1] * x.ndim
        shape[dim] = -1
        term = x.index_select(dim, idx) * w[:, k].reshape(shape)
        out = term if out is None else out + term
    return out


def _magnify_shift(img: torch.Tensor, scale: float, shift_y: float, shift_x: float) -> torch.Tensor:
    """Content of ``img`` ``(..., H, W)`` magnified by ``scale`` about the centre and moved by
    ``(shift_y, shift_x)`` px: output ``p`` samples the input at ``c + (p - c - shift) / scale``."""
    h, w = img.shape[-2:]
    cy, cx = (h - 1) / 2.0, (w - 1) / 2.0
    py = cy + (torch.arange(h, dtype=torch.float64) - cy - shift_y) / scale
    px = cx + (torch.arange(w, dtype=torch.float64) - cx - shift_x) / scale
    return _resample_axis(_resample_axis(img, py, img.ndim - 2), px, img.ndim - 1)


def misregister(frames: torch.Tensor, breathing: float, shift_y_px: float, shift_x_px: float) -> torch.Tensor:
    """Apply focus breathing and misregistration to a frame pair.

    Frame 2 ends magnified by ``1 + breathing`` about the image centre and shifted by
    ``(shift_y_px, shift_x_px)`` relative to frame 1; the warp is split half and half between
    the frames (separable Keys cubic resampling, reflected borders). Zero parameters return
    the input unchanged.

    Args:
        frames: ``(B, 2, H, W)`` (frame 1, frame 2 as channels).
        breathing: relative magnification of frame 2 minus 1 (e.g. ``0.01``).
        shift_y_px, shift_x_px: displacement of frame 2's content in pixels.

    Returns:
        ``(B, 2, H, W)``.

    Raises:
        ShapeError: ``frames`` is not ``(B, 2, H, W)``.
    """
    if frames.ndim != 4 or frames.shape[1] != 2:
        raise ShapeError(f"frames must be (B, 2, H, W), got {tuple(frames.shape)}")
    if breathing == 0 and shift_y_px == 0 and shift_x_px == 0:
        return frames
    half = math.sqrt(1.0 + breathing)
    m = 1.0 + breathing  # frame 2 = c + m (frame-1 position - c) + shift, exactly
    f1 = _magnify_shift(frames[:, 0], 1.0 / half, -0.5 * shift_y_px / m, -0.5 * shift_x_px / m)
    f2 = _magnify_shift(frames[:, 1], half, 0.5 * shift_y_px, 0.5 * shift_x_px)
    return torch.stack([f1, f2], dim=1)


class Misregistration(nn.Module):
    """:func:`misregister` as a module: ``forward(frames, breathing, shift_y_px, shift_x_px)``.

    Shape:
        - frames: ``(B, 2, H, W)``; output the same.
    """

    def forward(self, frames: torch.Tensor, breathing: float = 0.0, shift_y_px: float = 0.0,
                shift_x_px: float = 0.0) -> torch.Tensor:
        return misregister(frames, breathing, shift_y_px, shift_x_px)
