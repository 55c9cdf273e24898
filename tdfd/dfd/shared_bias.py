r"""The model's bias, measured against the likelihood fit, removed before the two are fused per tile.

The refinement CNN's error is mostly shared by the tiles of one image: on the refinement
benchmark's planes its per-tile median error (1.55 %) is nearly all the planes' shared error
(1.31 %; ``models/README.md``, "Where the planes' error sits"), a regression to its prior's
centre that depends on the texture. The likelihood fit's errors are nearly independent from
tile to tile. A per-tile inverse-variance fusion treats the model's error as independent too,
so the shared part survives it in proportion to the model's weight. This module removes it
first: with ``d_t = log(q_model,t / q_fit,t)`` on every fitted tile,

.. math::

    d_t = b + u_t - e_t, \qquad \operatorname{var}(u_t - e_t) = s_{m,t}^2 + s_{f,t}^2

(``s`` the two relative standard deviations after their factors), so the bias ``b`` is the
weighted median of ``d_t`` with weights ``1 / (s_m^2 + s_f^2)`` (a median: a tile whose fit found
another surface, or whose model erred grossly, does not pull it), and the model's map divided by
``exp(b)`` in inverse depth is what the stage fuses. :func:`shared_bias` measures one bias over
the tiles it is given; :func:`bias_map` one per cell of the grid, over the fitted tiles within a
radius (a scene whose surfaces differ in texture and depth does not share one bias). Measured
(``docs/BENCHMARKS.md``, section ``likelihood_stage``): per plane it helps, on the structure
benchmark's scenes it does not, so the stage removes it only when its scales file asks
(``LikelihoodScales.shared_bias``).

Example:
    >>> import math
    >>> import torch
    >>> q_fit = torch.linspace(1.0, 3.0, 8, dtype=torch.float64)
    >>> s = torch.full((8,), 0.01, dtype=torch.float64)
    >>> q_model = q_fit * 1.02
    >>> q_model[0] = 9.0  # a gross error does not pull the median
    >>> round(shared_bias(q_model, s, q_fit, s), 5), round(math.log(1.02), 5)
    (0.0198, 0.0198)
    >>> shared_bias(q_model[:4], s[:4], q_fit[:4], s[:4])  # too few tiles: nothing removed
    0.0
"""

from __future__ import annotations

import math

import torch

from ..errors import InputError

__all__ = ["MIN_BIAS_TILES", "weighted_median", "shared_bias", "bias_map"]

#: The fewest tiles with a finite weight that measure an image's bias (fewer: no bias removed).
MIN_BIAS_TILES = 8


def weighted_median(x: torch.Tensor, w: torch.Tensor) -> float:
    """The smallest ``x_i`` at which the weights of the values ``<= x_i`` reach half the total.

    Args:
        x: ``(N,)`` values.
        w: ``(N,)`` weights, finite and >= 0, with a positive sum.

    Raises:
        InputError: shapes that differ, an empty input, weights negative, non-finite or all 0.

    Example:
        >>> weighted_median(torch.tensor([1.0, 2.0, 3.0]), torch.tensor([1.0, 1.0, 5.0]))
        3.0
    """
    if x.ndim != 1 or x.shape != w.shape or x.numel() == 0:
        raise InputError(f"need two non-empty (N,) tensors, got {tuple(x.shape)} and {tuple(w.shape)}")
    if not bool(torch.isfinite(w).all()) or bool((w < 0).any()) or not float(w.sum()) > 0:
        raise InputError("weights must be finite, >= 0 and not all 0")
    order = torch.argsort(x)
    cum = torch.cumsum(w[order].to(torch.float64), 0)
    k = int(torch.searchsorted(cum, cum[-1] * 0.5))
    return float(x[order][min(k, x.numel() - 1)])


def shared_bias(q_model: torch.Tensor, sigma_model: torch.Tensor, q_fit: torch.Tensor, sigma_fit: torch.Tensor,
                min_tiles: int = MIN_BIAS_TILES) -> float:
    """The model's bias in ``log q`` over one image's tiles, measured against the fit (module docstring).

    Args:
        q_model, q_fit: ``(T,)`` inverse depths (1/m), finite and > 0.
        sigma_model, sigma_fit: ``(T,)`` their relative standard deviations after their factors
            (``inf``: no weight; a tile needs both finite).
        min_tiles: the fewest weighted tiles that measure a bias.

    Returns:
        ``b`` with ``q_model / exp(b)`` the model's map without it; 0 when fewer than
        ``min_tiles`` tiles carry weight.

    Raises:
        InputError: shapes that differ, inverse depths not finite and > 0, sigmas negative or
            nan, ``min_tiles < 1``.
    """
    _check(q_model, sigma_model, q_fit, sigma_fit, min_tiles)
    return _bias(*_log_ratio_and_variance(q_model, sigma_model, q_fit, sigma_fit), min_tiles)


def _check(q_model: torch.Tensor, sigma_model: torch.Tensor, q_fit: torch.Tensor, sigma_fit: torch.Tensor,
           min_tiles: int) -> None:
    if min_tiles < 1:
        raise InputError(f"min_tiles must be >= 1, got {min_tiles}")
    shapes = {tuple(t.shape) for t in (q_model, sigma_model, q_fit, sigma_fit)}
    if len(shapes) != 1 or q_model.ndim != 1:
        raise InputError(f"need four (T,) tensors of one shape, got {sorted(shapes)}")
    for name, q in (("q_model", q_model), ("q_fit", q_fit)):
        if not bool(torch.isfinite(q).all()) or not bool((q > 0).all()):
            raise InputError(f"{name} must be finite and > 0")
    for name, s in (("sigma_model", sigma_model), ("sigma_fit", sigma_fit)):
        if bool(torch.isnan(s).any()) or bool((s < 0).any()):
            raise InputError(f"{name} must be >= 0 (inf: no weight), got nan or negative values")


def _log_ratio_and_variance(q_model: torch.Tensor, sigma_model: torch.Tensor, q_fit: torch.Tensor,
                            sigma_fit: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``d_t = log(q_model / q_fit)`` and its variance ``s_m^2 + s_f^2`` (float64)."""
    d = torch.log(q_model.to(torch.float64) / q_fit.to(torch.float64))
    return d, sigma_model.to(torch.float64) ** 2 + sigma_fit.to(torch.float64) ** 2


def _bias(d: torch.Tensor, var: torch.Tensor, min_tiles: int) -> float:
    """The weighted median of ``d`` over the tiles of finite ``var`` (0 with fewer than ``min_tiles``)."""
    ok = torch.isfinite(var)
    if int(ok.sum()) < min_tiles:
        return 0.0
    zero = var[ok] == 0
    # a zero variance: those tiles alone decide
    w = zero.to(torch.float64) if bool(zero.any()) else 1.0 / var[ok].clamp_min(1e-200)
    b = weighted_median(d[ok], w)
    return b if math.isfinite(b) else 0.0


def bias_map(q_model: torch.Tensor, sigma_model: torch.Tensor, q_fit: torch.Tensor, sigma_fit: torch.Tensor,
             rows: torch.Tensor, cols: torch.Tensor, grid: tuple[int, int], radius: int | None = None,
             min_tiles: int = MIN_BIAS_TILES) -> torch.Tensor:
    """The model's bias for every cell of an ``(h, w)`` tile grid, from the fitted tiles ``(T,)`` at
    ``(rows, cols)``: with ``radius`` the :func:`shared_bias` of the fitted tiles within ``radius``
    cells (Chebyshev) of the cell, where at least ``min_tiles`` of them carry weight, else the
    image's; without it (``None``) the image's everywhere.

    A scene whose bias varies over the frame (several surfaces, textures and depths) keeps each
    region's own; a plane gets nearly the image's.

    Raises:
        InputError: as :func:`shared_bias`; positions off the grid or not ``(T,)``; ``radius < 1``.

    Example:
        >>> import torch
        >>> q_fit = torch.ones(16, dtype=torch.float64)
        >>> q_model = torch.where(torch.arange(16) % 4 < 2, 1.02, 0.98).to(torch.float64)  # left / right
        >>> s = torch.full((16,), 0.01, dtype=torch.float64)
        >>> r, c = torch.arange(16) // 4, torch.arange(16) % 4
        >>> b = bias_map(q_model, s, q_fit, s, r, c, (4, 4), radius=1, min_tiles=4)
        >>> [round(100 * float(x), 2) for x in b[0]]
        [1.98, 1.98, -2.02, -2.02]
    """
    h, w = int(grid[0]), int(grid[1])
    _check(q_model, sigma_model, q_fit, sigma_fit, min_tiles)
    if radius is not None and radius < 1:
        raise InputError(f"the bias radius must be >= 1 tile (None: the whole image), got {radius}")
    if rows.shape != q_model.shape or cols.shape != q_model.shape:
        raise InputError(f"need one grid position per tile, got {tuple(rows.shape)} and {tuple(cols.shape)}")
    if q_model.numel() and (int(rows.min()) < 0 or int(rows.max()) >= h or int(cols.min()) < 0
                            or int(cols.max()) >= w):
        raise InputError(f"tile positions must lie on the {h}x{w} grid")
    d, var = _log_ratio_and_variance(q_model, sigma_model, q_fit, sigma_fit)
    out = torch.full((h, w), _bias(d, var, min_tiles), dtype=torch.float64)
    if radius is None:
        return out
    weighted = torch.isfinite(var)
    for i in range(h):
        for j in range(w):
            near = ((rows - i).abs() <= radius) & ((cols - j).abs() <= radius)
            if int((near & weighted).sum()) >= min_tiles:
                out[i, j] = _bias(d[near], var[near], min_tiles)
    return out
