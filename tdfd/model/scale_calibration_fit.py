"""Fitting the post-hoc scale calibration (:mod:`tdfd.model.scale_calibration`) to observed errors.

A model's predicted Laplace scales ``b`` and the signed relative errors ``e`` it made on
held-out tiles give, in any group of tiles, a factor ``f`` such that Laplace errors of
scales ``f b`` would have the observed median ``|e|`` (:func:`laplace_mixture_median`).
:func:`fit_scale_calibration` turns those factors over equal-count bands of ``b`` into the
knots of ``s``; :func:`fit_tile_calibration` adds the depth part ``g`` (bands of the refined
inverse depth ``q``) and the edge part ``h`` (each distance to the grid's edge) by
backfitting: each part is refitted to the errors with the other two applied, a few rounds.
:func:`fit_covariate_calibration` backfits ``s`` with one part ``g(x)`` in any covariate the
predictor knows (the likelihood stage's fused scale and its tile's slope).
"""

from __future__ import annotations

import math

import torch

from ..errors import InputError
from .scale_calibration import calibrate_log_scale, piecewise_linear

__all__ = ["laplace_mixture_median", "fit_scale_calibration", "fit_tile_calibration", "fit_covariate_calibration"]


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


def _log_factor(error: torch.Tensor, scale: torch.Tensor) -> float:
    """``log f`` with the Laplace mixture median of ``f * scale`` equal to the median ``|error|``."""
    return math.log(max(float(error.abs().median()), 1e-300) / laplace_mixture_median(scale))


def _band_factors(key: torch.Tensor, scale: torch.Tensor, error: torch.Tensor, bins: int, tied: str
                  ) -> tuple[list[float], list[float]]:
    """Split the tiles into ``bins`` equal-count bands by ``key``: per band the median ``key`` and
    :func:`_log_factor`; ``tied`` is the error raised when two bands share a median."""
    medians, log_f = [], []
    for part in torch.tensor_split(torch.argsort(key, stable=True), bins):
        medians.append(float(key[part].median()))
        log_f.append(_log_factor(error[part], scale[part]))
    if any(b <= a for a, b in zip(medians, medians[1:])):
        raise InputError(tied)
    return medians, log_f


def _moving_average(v: torch.Tensor, width: int) -> torch.Tensor:
    if width <= 1:
        return v
    pad = width // 2
    padded = torch.cat([v[:1].expand(pad), v, v[-1:].expand(pad)])
    return padded.unfold(0, width, 1).mean(-1)


def _check(b: torch.Tensor, e: torch.Tensor, bins: int, smooth: int) -> None:
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


def fit_scale_calibration(scale: torch.Tensor, error: torch.Tensor, bins: int = 40, smooth: int = 3,
                          min_factor: float | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Fit the scale part's knots: the predicted scale made to match the observed errors band by band.

    The tiles are split into ``bins`` equal-count bins by ``b``; in each, the factor ``f``
    that makes the Laplace mixture median of ``f b`` equal the observed median ``|e|``
    moves the bin's median ``b`` to a knot. The log factors are averaged over ``smooth``
    neighbouring bins (a moving average, ends held), held at ``min_factor`` or more, then the
    knots are made non-decreasing.

    ``min_factor`` bounds the factor from below (``1``: only ever widen the CNN's scale, for a
    user who would rather keep it where its errors are smaller than it predicts).

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
    _check(b, e, bins, smooth)
    if min_factor is not None and not (math.isfinite(min_factor) and min_factor > 0):
        raise InputError(f"min_factor must be positive and finite or None, got {min_factor}")
    medians, log_f = _band_factors(b, b, e, bins, "bins with equal median scale: fewer bins, or scales that vary")
    kb = torch.tensor([math.log(v) for v in medians], dtype=torch.float64)
    f = _moving_average(torch.tensor(log_f, dtype=torch.float64), smooth)
    if min_factor is not None:
        f = f.clamp_min(math.log(min_factor))
    return kb, torch.cummax(kb + f, 0).values


def _fit_depth(q: torch.Tensor, log_b: torch.Tensor, e: torch.Tensor, bins: int, smooth: int,
               tied: str = "depth bins with equal median inverse depth: fewer depth bins, or depths that vary"
               ) -> tuple[torch.Tensor, torch.Tensor]:
    """A covariate part's knots (the depth's, or any covariate ``q``'s): the bands' median ``q`` and
    their log factors with ``log_b`` applied, smoothed over ``smooth`` bands; ``tied`` the error for
    bands with equal medians."""
    medians, log_f = _band_factors(q, log_b.exp(), e, bins, tied)
    return torch.tensor(medians, dtype=torch.float64), _moving_average(torch.tensor(log_f, dtype=torch.float64), smooth)


def _fit_border(n: torch.Tensor, log_b: torch.Tensor, e: torch.Tensor, levels: int) -> torch.Tensor:
    shifts = []
    for k in range(levels):
        part = n == k
        if int(part.sum()) < 2:
            raise InputError(f"fewer than 2 tiles {k} tiles from the edge: fewer border levels, or larger frames")
        shifts.append(_log_factor(e[part], log_b[part].exp()))
    return torch.tensor(shifts, dtype=torch.float64)


def fit_tile_calibration(scale: torch.Tensor, error: torch.Tensor, inverse_depth: torch.Tensor | None = None,
                         border: torch.Tensor | None = None, bins: int = 40, smooth: int = 3, depth_bins: int = 20,
                         border_levels: int = 5, rounds: int = 5, min_factor: float | None = None
                         ) -> dict[str, list[float]]:
    """Fit the whole calibration ``s(log b) + g(q) + h(n)`` by backfitting.

    Each round refits ``s`` (:func:`fit_scale_calibration` on the errors divided by the
    other parts' factors), then ``g`` on ``depth_bins`` equal-count bands of ``q`` (knots at
    the bands' median ``q``, log factors smoothed over ``smooth`` bands; not constrained to
    a shape), then ``h`` per distance ``0 .. border_levels - 1`` (the last level holds every
    tile that far or farther), each against the observed median ``|e|`` with the other
    parts applied. The parts can trade a constant; it is moved into ``s``, so that ``g`` is 0
    at the tiles' median depth factor and ``h`` is 0 for the innermost level.

    Args:
        scale: ``(N,)`` the CNN's own scale ``b`` (positive, finite).
        error: ``(N,)`` signed relative inverse-depth error (finite).
        inverse_depth: ``(N,)`` refined inverse depth ``q`` in 1/m (positive); ``None``: no depth part.
        border: ``(N,)`` distance in tiles to the grid's edge (integers >= 0); ``None``: no edge part.
        bins: bands of ``b`` (knots of ``s``).
        smooth: odd moving-average width over the bands of ``s`` and ``g``.
        depth_bins: bands of ``q`` (knots of ``g``), at least 2.
        border_levels: distances with their own factor, at least 2.
        rounds: backfitting rounds (1 with neither ``q`` nor ``border``).
        min_factor: as in :func:`fit_scale_calibration`, for ``s`` alone.

    Returns:
        The :class:`~tdfd.model.scale_calibration.ScaleCalibration` config: ``log_b``,
        ``log_b_calibrated`` and, with their inputs, ``inverse_depth_per_m``,
        ``depth_log_shift``, ``border_log_shift``.

    Raises:
        InputError: mismatched lengths, bad values, or too few tiles for the bins or levels.
    """
    b = torch.as_tensor(scale, dtype=torch.float64).flatten()
    e = torch.as_tensor(error, dtype=torch.float64).flatten()
    _check(b, e.abs(), bins, smooth)
    if rounds < 1:
        raise InputError(f"rounds must be >= 1, got {rounds}")
    q = n = None
    if inverse_depth is not None:
        q = torch.as_tensor(inverse_depth, dtype=torch.float64).flatten()
        if q.numel() != b.numel() or not bool(((q > 0) & torch.isfinite(q)).all()):
            raise InputError(f"inverse_depth must be {b.numel()} positive finite values (1/m)")
        if depth_bins < 2 or q.numel() < 2 * depth_bins:
            raise InputError(f"need at least 2 depth bins and 2 tiles per bin, got {depth_bins} for {q.numel()} tiles")
    if border is not None:
        n = torch.as_tensor(border, dtype=torch.float64).flatten()
        if n.numel() != b.numel() or not bool(((n >= 0) & (n == n.round())).all()):
            raise InputError(f"border must be {b.numel()} whole numbers of tiles >= 0")
        if border_levels < 2:
            raise InputError(f"border_levels must be >= 2, got {border_levels}")
        n = n.clamp(max=border_levels - 1)
    log_b = b.log()
    g_depth = torch.zeros_like(log_b)
    g_border = torch.zeros_like(log_b)
    cfg: dict[str, list[float]] = {}
    for _ in range(rounds if (q is not None or n is not None) else 1):
        kb, kc = fit_scale_calibration(b, e / (g_depth + g_border).exp(), bins=bins, smooth=smooth,
                                       min_factor=min_factor)
        cfg["log_b"], cfg["log_b_calibrated"] = kb.tolist(), kc.tolist()
        s = calibrate_log_scale(log_b, kb, kc)
        if q is not None:
            kx, ky = _fit_depth(q, s + g_border, e, depth_bins, smooth)
            g_depth = piecewise_linear(q, kx, ky)
            cfg["inverse_depth_per_m"], cfg["depth_log_shift"] = kx.tolist(), ky.tolist()
        if n is not None:
            hy = _fit_border(n, s + g_depth, e, border_levels)
            g_border = hy[n.long()]
            cfg["border_log_shift"] = hy.tolist()
    # the parts can trade a constant: move it into s, so that g is 0 at the tiles' median and
    # h is 0 for the innermost level (the same map; the parts then read as relative factors)
    shift = 0.0
    if "depth_log_shift" in cfg:
        c = float(g_depth.median())
        cfg["depth_log_shift"] = [v - c for v in cfg["depth_log_shift"]]
        shift += c
    if "border_log_shift" in cfg:
        c = cfg["border_log_shift"][-1]
        cfg["border_log_shift"] = [v - c for v in cfg["border_log_shift"]]
        shift += c
    cfg["log_b_calibrated"] = [v + shift for v in cfg["log_b_calibrated"]]
    return cfg


def fit_covariate_calibration(scale: torch.Tensor, error: torch.Tensor, covariate: torch.Tensor, bins: int = 40,
                              smooth: int = 3, covariate_bins: int = 10, rounds: int = 5
                              ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Fit ``log b' = log b + s(log b) + g(x)`` by backfitting: ``s`` as
    :func:`fit_scale_calibration` on the errors divided by ``exp(g)``, ``g`` piecewise linear in
    a covariate ``x`` the predictor knows (knots at the medians of ``covariate_bins`` equal-count
    bands of ``x``, log factors smoothed over ``smooth`` bands) with ``s`` applied, ``rounds``
    times; ``g`` is then shifted to 0 at the tiles' median ``g`` (the constant goes into ``s``).

    Args:
        scale: ``(N,)`` predicted Laplace scale ``b`` (positive, finite).
        error: ``(N,)`` observed signed relative error (finite).
        covariate: ``(N,)`` finite values of ``x`` (e.g. a log slope).
        bins, smooth: as in :func:`fit_scale_calibration`.
        covariate_bins: bands of ``x`` (knots of ``g``), at least 2.
        rounds: backfitting rounds, at least 1.

    Returns:
        ``(log_b, log_b_calibrated, x_knots, log_shift)``, float64: the knots of ``s``
        (:func:`~tdfd.knot_map.calibrate_log_scale`) and of ``g``
        (:func:`~tdfd.knot_map.piecewise_linear`).

    Raises:
        InputError: as :func:`fit_scale_calibration`; a covariate of another length or not
            finite, too few tiles per band, or bands with equal medians.

    Example:
        >>> g = torch.Generator().manual_seed(0)
        >>> b = torch.rand(20000, generator=g, dtype=torch.float64) * 0.05 + 0.01
        >>> x = torch.rand(20000, generator=g, dtype=torch.float64)
        >>> u = torch.rand(20000, generator=g, dtype=torch.float64) - 0.5
        >>> e = b * (1 + x) * -u.sign() * torch.log1p(-2 * u.abs())  # errors grow with x
        >>> kb, kr, kx, ky = fit_covariate_calibration(b, e, x, bins=10, covariate_bins=5)
        >>> bool(abs(float(ky[-1] - ky[0]) - math.log(1.8 / 1.2)) < 0.1)  # the bands' medians 0.1 .. 0.9
        True
    """
    b = torch.as_tensor(scale, dtype=torch.float64).flatten()
    e = torch.as_tensor(error, dtype=torch.float64).flatten()
    x = torch.as_tensor(covariate, dtype=torch.float64).flatten()
    _check(b, e, bins, smooth)
    if x.numel() != b.numel() or not bool(torch.isfinite(x).all()):
        raise InputError(f"covariate must be {b.numel()} finite values, got {x.numel()}")
    if covariate_bins < 2 or x.numel() < 2 * covariate_bins:
        raise InputError(f"need at least 2 covariate bins and 2 tiles per bin, got {covariate_bins} for "
                         f"{x.numel()} tiles")
    if rounds < 1:
        raise InputError(f"rounds must be >= 1, got {rounds}")
    log_b, g = b.log(), torch.zeros_like(b)
    for _ in range(rounds):
        kb, kc = fit_scale_calibration(b, e / g.exp(), bins=bins, smooth=smooth)
        kx, ky = _fit_depth(x, calibrate_log_scale(log_b, kb, kc), e, covariate_bins, smooth,
                            "covariate bands with equal medians: fewer bands, or a covariate that varies")
        g = piecewise_linear(x, kx, ky)
    c = float(g.median())
    return kb, kc + c, kx, ky - c
