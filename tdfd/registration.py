r"""Focus-breathing registration of a DFD pair in torch, before the estimator (exportable to ONNX).

An ECVFL magnifies the image a little with its power (:mod:`tdfd.breathing`): the frame at
power ``P`` is the ideal frame scaled by ``s(P) = 1 + m P`` about the optical centre (``m``
the camera file's ``magnification_per_dpt``). Frames at ``P1`` and ``P2`` then differ by
``s2 / s1``; a tile far from the centre sees its content shifted between the frames by
``(s2/s1 - 1)`` times its distance from the centre, which decorrelates the tile's two
windows and biases the Fourier ratio.

:func:`register_breathing` brings both frames to the common scale ``sqrt(s1 s2)`` about the
centre of the frames it is given: frame 1 is magnified by ``k1 = sqrt(s2/s1)``, frame 2 by
``k2 = sqrt(s1/s2)`` (half the correction each, so the two frames are resampled alike and
the depth grid stays aligned with their mean, as :func:`tdfd.warp.misregister` splits the
forward model's breathing). Output pixel ``p`` of a frame magnified by ``k`` samples the
input at ``c + (p - c) / k`` with ``c = (n - 1) / 2``.

Resampling moves whole pixels (nearest source pixel, separable: one gather per axis),
never interpolates: any interpolator, Lanczos included, lowers the sensor noise near the
Nyquist frequency by an amount that changes with each pixel's fractional position, while
the estimator's noise model assumes white noise; on the breathing benchmark Lanczos
registration of noisy frames cost more than the breathing itself (see :func:`_resample_rows`).
What remains is at most half a pixel of misalignment per frame. The gather's indices are
computed from the axis length, so the graph stays valid for any input height and width
(dynamic shapes in ONNX). A magnification of exactly 1 is the identity (nothing resampled),
and :class:`BreathingRegistration` with ``m = 0`` (or equal powers) returns its inputs.

Frames that are a crop of a larger frame (a region of interest) whose centre is not the
optical centre also need a translation ``(c_opt - c_crop)(1 - 1/k)`` per frame, which the
caller applies when it cuts the crop (:meth:`tdfd.runtime.DepthRuntime.__call__` with
``window=``; :func:`window_shifts`).

Example:
    >>> import torch
    >>> reg = BreathingRegistration(0.005, (1.7, 2.7))
    >>> x = torch.rand(1, 1, 64, 64, generator=torch.Generator().manual_seed(0))
    >>> a, b = reg(x, x)
    >>> a.shape, reg.enabled
    (torch.Size([1, 1, 64, 64]), True)
    >>> BreathingRegistration(0.0, (1.7, 2.7))(x, x)[0] is x
    True
"""

from __future__ import annotations

import math
from typing import Sequence

import torch
from torch import nn

from .breathing import (MAX_MAGNIFICATION_PER_DPT, breathing_scales, check_magnification_per_dpt,
                        registration_magnifications, window_shifts)
from .errors import NonFiniteError, RangeError, ShapeError

__all__ = ["magnify_about_centre", "register_breathing", "breathing_scales", "registration_magnifications",
           "window_shifts", "check_magnification_per_dpt", "BreathingRegistration", "MAX_MAGNIFICATION_PER_DPT"]



def _resample_rows(x: torch.Tensor, scale: float) -> torch.Tensor:
    """``x`` ``(..., n, W)`` magnified by ``scale`` about its centre along ``n``: output row
    ``p`` is input row ``round(c + (p - c) / scale)`` (nearest, clamped to the frame).

    Whole rows are moved, never interpolated: any interpolator (Lanczos included) lowers
    the sensor noise near the Nyquist frequency by an amount that changes with each row's
    fractional position, and the estimator's noise model assumes white noise; measured on
    the breathing benchmark (``docs/BENCHMARKS.md``), Lanczos registration of noisy frames
    raised the refined error 1.45x where whole-pixel registration gave 1.02x. The cost is
    a residual misalignment of at most half a pixel per frame, and a repeated (or skipped)
    row every ``1 / |1 - 1/scale|`` rows.
    """
    n = x.shape[-2]
    dt = torch.float64 if x.dtype == torch.float64 else torch.float32
    pos = torch.arange(n, device=x.device).to(dt)
    last = pos[-1:]
    centre = last * 0.5
    idx = torch.round(centre + (pos - centre) * (1.0 / scale))
    idx = torch.minimum(torch.clamp(idx, min=0.0), last).to(torch.int64)
    return x.index_select(x.ndim - 2, idx)


def magnify_about_centre(image: torch.Tensor, scale: float) -> torch.Tensor:
    """Magnify ``image`` ``(..., H, W)`` by ``scale`` about its centre, whole pixels moved.

    Output pixel ``p`` is the input pixel nearest ``c + (p - c) / scale``, ``c = (n - 1)/2``
    per axis (clamped to the frame).

    Args:
        image: ``(..., H, W)`` tensor.
        scale: magnification (1: the input itself is returned).

    Returns:
        ``(..., H, W)``, same dtype.

    Raises:
        ShapeError: fewer than 2 dimensions.
        NonFiniteError, RangeError: a non-finite or non-positive scale, or one outside (0.5, 2).
    """
    if not isinstance(image, torch.Tensor) or image.ndim < 2:
        raise ShapeError(f"image must be a tensor (..., H, W), got {getattr(image, 'shape', type(image).__name__)}")
    s = float(scale)
    if not math.isfinite(s):
        raise NonFiniteError(f"scale must be finite, got {scale!r}")
    if not 0.5 < s < 2.0:
        raise RangeError(f"scale {s} is implausible for focus breathing (expected within (0.5, 2))")
    if s == 1.0:
        return image
    y = _resample_rows(image, s)
    return _resample_rows(y.transpose(-1, -2), s).transpose(-1, -2)


def register_breathing(image_f1: torch.Tensor, image_f2: torch.Tensor,
                       scales: Sequence[float]) -> tuple[torch.Tensor, torch.Tensor]:
    """Bring a pair whose frames have image scales ``(s1, s2)`` to the common scale ``sqrt(s1 s2)``.

    Args:
        image_f1, image_f2: ``(B, 1, H, W)`` frames (about the optical centre, i.e. full
            frames or centred crops).
        scales: ``(s1, s2)``, e.g. :func:`breathing_scales`.

    Returns:
        The registered ``(image_f1, image_f2)``; the inputs themselves when ``s1 == s2``.
    """
    if image_f1.ndim != 4 or image_f2.ndim != 4 or image_f1.shape[1] != 1 or image_f2.shape[1] != 1:
        raise ShapeError(f"frames must be (B, 1, H, W), got {tuple(image_f1.shape)} and {tuple(image_f2.shape)}")
    k1, k2 = registration_magnifications(scales)
    if k1 == 1.0 and k2 == 1.0:
        return image_f1, image_f2
    return magnify_about_centre(image_f1, k1), magnify_about_centre(image_f2, k2)


class BreathingRegistration(nn.Module):
    """:func:`register_breathing` for a camera: ``forward(image_f1, image_f2)``.

    Args:
        magnification_per_dpt: the camera's focus breathing ``m`` (1/dpt).
        lens_powers_dpt: the ECVFL powers ``(P1, P2)`` of the two frames (dpt).

    Attributes:
        scales: ``(s1, s2)``.
        enabled: whether the frames are resampled at all (``m != 0`` and ``s1 != s2``); when
            not, :meth:`forward` returns its inputs and the exported graph has no such node.

    Shape:
        - image_f1, image_f2: ``(B, 1, H, W)``; outputs the same.

    Raises:
        NonFiniteError, RangeError: bad ``m`` or powers (:func:`breathing_scales`).
    """

    def __init__(self, magnification_per_dpt: float = 0.0, lens_powers_dpt: Sequence[float] = (0.0, 0.0)) -> None:
        super().__init__()
        self.magnification_per_dpt = check_magnification_per_dpt(magnification_per_dpt)
        self.lens_powers_dpt = tuple(float(p) for p in lens_powers_dpt)
        self.scales = breathing_scales(self.magnification_per_dpt, self.lens_powers_dpt)
        self.magnifications = registration_magnifications(self.scales)

    @property
    def enabled(self) -> bool:
        return self.magnification_per_dpt != 0.0 and self.scales[0] != self.scales[1]

    def extra_repr(self) -> str:
        return f"magnification_per_dpt={self.magnification_per_dpt}, lens_powers_dpt={self.lens_powers_dpt}"

    def forward(self, image_f1: torch.Tensor, image_f2: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        if not self.enabled:
            return image_f1, image_f2
        return register_breathing(image_f1, image_f2, self.scales)
