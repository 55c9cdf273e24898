"""Post-hoc calibration of the predicted error scale: a map of ``log b``, the tile's depth and its place in the frame.

The refinement CNN predicts, per tile, a Laplace scale ``b`` of the relative inverse-depth
error ``e = (q - q_true) / q_true`` (:mod:`tdfd.model.combined`), trained by the Laplace
negative log-likelihood. On held-out scenes that scale is off by up to half at the
extremes (issue 19: the most confident tenth of the textured planes erred 1.56 times the
predicted median), and by up to 1.4x depending on where the tile is:

* its **depth**: at the same ``b``, tiles near the far end of the working range err more
  than predicted and tiles in the middle less (the defocus difference's sensitivity to
  depth, eqs. 4-6 of the paper, varies across the range in a way the CNN's scale follows
  only in part);
* its **distance to the frame's edge**: the CNN's convolutions over the tile grid pad by
  replicating the edge (:mod:`tdfd.model.refine`), so a tile at the edge sees its own
  measurement repeated as context and is more confident than its error warrants.

The calibration is

``log b' = log b + s(log b) + g(q) + h(n)``

with ``q`` the refined inverse depth (1/m), ``n`` the tile's distance in tiles to the
nearest edge of the grid it was computed on (a crop's own edge for a window), and ``s``,
``g``, ``h`` piecewise linear between knots and held constant beyond the end knots: ``s``
through knots ``(x_k, y_k - x_k)`` of ``log b``, ``g`` through knots of ``q``, ``h``
through the integers ``0, 1, .., K - 1``. ``s`` is non-decreasing in the sense that
``x + s(x)`` is, so at a given depth and place the map keeps the order of the tiles'
confidences. Each part is optional; without any the map is the identity. It is fitted
after training on scenes no training run or benchmark uses
(:mod:`tdfd.model.scale_calibration_fit`, :mod:`training.calibrate_scale`) so that the
median ``|e|`` is the Laplace median ``b' ln 2`` along each of the three.

In the graph every part is a sum of clamped hinges (no index lookup) and the distance to
the edge comes from cumulative sums of ones, so the ONNX export carries it as a few
element-wise operators on any frame size.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

from ..errors import InputError
from ..knot_map import calibrate_log_scale, finite_floats, knot_pairs, piecewise_linear, validate_knots

__all__ = ["piecewise_linear", "calibrate_log_scale", "tile_border_distance", "validate_knots",
           "validate_depth_knots", "validate_border_shifts", "ScaleCalibration"]

#: keys of a calibration's JSON description; the first two go together, and so do the next two
CONFIG_KEYS = ("log_b", "log_b_calibrated", "inverse_depth_per_m", "depth_log_shift", "border_log_shift")


def validate_depth_knots(inverse_depth: Sequence[float], log_shift: Sequence[float]) -> tuple[list[float], list[float]]:
    """Check the depth part's knots: as many of each (at least 2), finite, the inverse depths
    (1/m) positive and strictly increasing.

    Raises:
        InputError: naming what is wrong.
    """
    x, y = knot_pairs(inverse_depth, log_shift, "inverse_depth_per_m", "depth_log_shift")
    if x[0] <= 0:
        raise InputError("scale calibration knots inverse_depth_per_m must be positive")
    return x, y


def validate_border_shifts(log_shift: Sequence[float]) -> list[float]:
    """Check the edge part: at least 2 finite log shifts, for 0, 1, .. tiles from the edge.

    Raises:
        InputError: naming what is wrong.
    """
    y = finite_floats(log_shift, "border_log_shift")
    if len(y) < 2:
        raise InputError(f"scale calibration border_log_shift needs at least 2 values (0, 1, .. tiles from the edge), "
                         f"got {len(y)}")
    return y


def tile_border_distance(grid: torch.Tensor) -> torch.Tensor:
    """Each cell's distance, in cells, to the nearest edge of a ``(B, C, h, w)`` grid.

    Built from cumulative sums of ones (no shape arithmetic), so an ONNX graph computes it
    for any ``h, w``.

    Args:
        grid: ``(B, C, h, w)``; only its shape, dtype and device are used.

    Returns:
        ``(1, 1, h, w)`` of ``grid``'s dtype: ``min(i, h - 1 - i, j, w - 1 - j)``.

    Example:
        >>> tile_border_distance(torch.zeros(1, 1, 3, 4))[0, 0]
        tensor([[0., 0., 0., 0.],
                [0., 1., 1., 0.],
                [0., 0., 0., 0.]])
    """
    if grid.dim() != 4:
        raise InputError(f"grid must be (B, C, h, w), got shape {tuple(grid.shape)}")
    ones = torch.ones_like(grid[:1, :1])
    row = ones.cumsum(2)  # 1 .. h down the rows
    col = ones.cumsum(3)
    from_top, from_bottom = row - 1, ones.sum(2, keepdim=True) - row
    from_left, from_right = col - 1, ones.sum(3, keepdim=True) - col
    return torch.minimum(torch.minimum(from_top, from_bottom), torch.minimum(from_left, from_right))


class ScaleCalibration(nn.Module):
    """``log b' = log b + s(log b) + g(q) + h(n)`` with its knots as (non-persistent) buffers.

    The knots live in the model's JSON description (:meth:`to_config`), not its weights, so a
    calibration never changes the safetensors file and an uncalibrated model loads as before.
    Each part is optional; with none the module is the identity.

    Args:
        log_b: knot positions of ``s``, natural log of the predicted scale; ``None``: no ``s``.
        log_b_calibrated: calibrated values at those knots.
        inverse_depth_per_m: knot positions of ``g``, refined inverse depth (1/m); ``None``: no ``g``.
        depth_log_shift: ``g`` at those knots (natural log of a factor on ``b``).
        border_log_shift: ``h(0), h(1), ..``: the log factor on ``b`` of a tile 0, 1, .. tiles
            from the grid's edge, the last one held beyond; ``None``: no ``h``.
    """

    def __init__(self, log_b: Sequence[float] | None = None, log_b_calibrated: Sequence[float] | None = None,
                 inverse_depth_per_m: Sequence[float] | None = None, depth_log_shift: Sequence[float] | None = None,
                 border_log_shift: Sequence[float] | None = None) -> None:
        super().__init__()
        if (log_b is None) != (log_b_calibrated is None):
            raise InputError("scale calibration needs both log_b and log_b_calibrated, or neither")
        if (inverse_depth_per_m is None) != (depth_log_shift is None):
            raise InputError("scale calibration needs both inverse_depth_per_m and depth_log_shift, or neither")
        self.has_scale, self.has_depth = log_b is not None, inverse_depth_per_m is not None
        self.has_border = border_log_shift is not None
        self.identity = not (self.has_scale or self.has_depth or self.has_border)
        x, y = validate_knots(log_b, log_b_calibrated) if self.has_scale else ([0.0, 1.0], [0.0, 1.0])  # type: ignore[arg-type]
        dx, dy = (validate_depth_knots(inverse_depth_per_m, depth_log_shift) if self.has_depth  # type: ignore[arg-type]
                  else ([1.0, 2.0], [0.0, 0.0]))
        hy = validate_border_shifts(border_log_shift) if self.has_border else [0.0, 0.0]  # type: ignore[arg-type]
        for name, values in (("knots_log_b", x), ("knots_log_b_calibrated", y), ("knots_inverse_depth", dx),
                             ("knots_depth_log_shift", dy), ("knots_border", [float(k) for k in range(len(hy))]),
                             ("knots_border_log_shift", hy)):
            self.register_buffer(name, torch.tensor(values, dtype=torch.float32), persistent=False)

    def forward(self, log_scale: torch.Tensor, inverse_depth: torch.Tensor | None = None) -> torch.Tensor:
        """Calibrate ``log b``.

        Args:
            log_scale: ``(B, 1, h, w)`` predicted ``log b`` on the tile grid.
            inverse_depth: ``(B, 1, h, w)`` refined inverse depth (1/m); needed when the map has a depth part.

        Returns:
            ``(B, 1, h, w)`` calibrated ``log b'``.

        Raises:
            InputError: a depth part and no (or a differently shaped) ``inverse_depth``.
        """
        if self.identity:
            return log_scale
        out = calibrate_log_scale(log_scale, self.knots_log_b, self.knots_log_b_calibrated) if self.has_scale \
            else log_scale
        if self.has_depth:
            if inverse_depth is None or inverse_depth.shape != log_scale.shape:
                raise InputError("this scale calibration has a depth part: pass the inverse depth, shaped as log_scale "
                                 f"{tuple(log_scale.shape)}")
            out = out + piecewise_linear(inverse_depth.to(out.dtype), self.knots_inverse_depth,
                                         self.knots_depth_log_shift)
        if self.has_border:
            out = out + piecewise_linear(tile_border_distance(log_scale), self.knots_border, self.knots_border_log_shift)
        return out

    def to_config(self) -> dict[str, list[float]] | None:
        """The parts present as ``{"log_b", "log_b_calibrated", "inverse_depth_per_m",
        "depth_log_shift", "border_log_shift"}`` lists; ``None`` for the identity."""
        if self.identity:
            return None
        cfg: dict[str, list[float]] = {}
        for present, keys, buffers in ((self.has_scale, CONFIG_KEYS[0:2], ("knots_log_b", "knots_log_b_calibrated")),
                                       (self.has_depth, CONFIG_KEYS[2:4], ("knots_inverse_depth", "knots_depth_log_shift")),
                                       (self.has_border, CONFIG_KEYS[4:5], ("knots_border_log_shift",))):
            if present:
                for key, buf in zip(keys, buffers):
                    cfg[key] = [float(v) for v in getattr(self, buf)]
        return cfg

    @classmethod
    def from_config(cls, cfg: dict | None) -> "ScaleCalibration":
        """Inverse of :meth:`to_config` (a description written before the depth and edge parts,
        with only ``log_b`` and ``log_b_calibrated``, loads as the scale part alone)."""
        if cfg is None:
            return cls()
        if not isinstance(cfg, dict) or not cfg or not set(cfg) <= set(CONFIG_KEYS):
            raise InputError(f"scale calibration must be a non-empty dict with keys among {list(CONFIG_KEYS)}, "
                             f"got {cfg!r}")
        return cls(**cfg)
