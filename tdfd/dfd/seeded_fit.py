r"""Each tile's cross-residual fit of ``q = 1/d``, searched near a seed, with its uncertainty.

The per-tile likelihood of :func:`tdfd.dfd.cross_residual.tile_cross_residual_nll` is evaluated
on a uniform grid of inverse depth, only within ``window`` (relative) of each tile's seed (the
refinement CNN's estimate: its robustness against the gross minima of weak textures is kept),
for every PSF hypothesis (:mod:`tdfd.dfd.psf_hypotheses`); the parabola through the grid minimum
refines it (:func:`~tdfd.dfd.cross_residual.parabolic_minima`).

The noise is not told. Both frames are taken to have the same noise variance ``nu`` (equal mean
levels: the caller matches the frames' means), unknown per tile, and the NLL is computed with
``nu = 1``; its expectation at the true ``q`` is then ``nu`` itself, so the minimum estimates the
tile's noise (model mismatch included, which only lowers the fit's weight), and

.. math::

    \operatorname{var}(\hat q) = \frac{\mathrm{NLL}_{\min}}{B \; \partial^2 \mathrm{NLL} / \partial q^2}

with ``B`` the tile's independent bins (:func:`~tdfd.dfd.cross_residual.independent_bins`). The
image shares one PSF hypothesis: the one with the least ``sum_t log NLL_min,t`` (the likelihood
of tiles of unknown noise, each profiled out) over the :data:`PROFILE_TILES` tiles the caller
ranks first (the model's most confident); every tile is then fitted with it alone. Only the
(hypothesis, tile) pairs inside a tile's window are evaluated, each on the tile's own region.

A seed off by more than the window leaves the minimum on the window's edge, and the tile no
weight. With ``walk`` such a tile's window moves to that edge and is searched again, up to
``walk`` times, downhill; the walked minimum counts only when its log-likelihood beats the first
window's edge by :data:`WALK_GAIN` nats (a likelihood that merely drifts from a good seed gains
little).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import torch

from ..camera import Camera
from ..errors import InputError, ShapeError
from ..optics.thin_lens import camera_sigmas
from .cross_residual import curvature_sigma, independent_bins, parabolic_minima, tile_cross_residual_nll
from .psf_hypotheses import PsfHypothesis

__all__ = ["SEED_WINDOW", "Q_STEP", "PROFILE_TILES", "WALK_GAIN", "inverse_depth_grid", "seed_mask", "kernel_side",
           "kernel_pairs", "SeededFit", "seeded_tile_fit"]

#: The relative half-width of each tile's search around its seed.
SEED_WINDOW = 0.05
#: The grid step of inverse depth (1/m).
Q_STEP = 0.01
#: The tiles that choose the shared PSF hypothesis (the rest is fitted with it alone).
PROFILE_TILES = 32
#: The least log-likelihood gain (nats) of a walked minimum over its first window's edge for it to
#: count: a seed truly off finds a deep minimum (gains of 30-100 on the structure scenes), while a
#: likelihood that drifts from a good seed gains little (3-15); see ``docs/BENCHMARKS.md``,
#: section ``psf_structure``'s notes.
WALK_GAIN = 20.0


def inverse_depth_grid(camera: Camera, window: float = SEED_WINDOW, step: float = Q_STEP) -> torch.Tensor:
    """``(Q,)`` float64 uniform grid of ``q`` (1/m) over the camera's depth range widened so that
    a seed at either end keeps its whole window: ``(1 - 4 w) / d_far`` to ``(1 + 2 w) / d_near``.

    Example:
        >>> from tdfd import Camera
        >>> g = inverse_depth_grid(Camera.preset("reference"))
        >>> round(float(g[0]), 2), round(float(g[-1]), 2), len(g)
        (0.8, 3.66, 287)
    """
    if not 0 < window < 0.25:
        raise InputError(f"seed window must lie in (0, 0.25), got {window}")
    if not step > 0:
        raise InputError(f"q step must be > 0, got {step}")
    near, far = camera.depth_range_m
    lo, hi = (1.0 - 4.0 * window) / far, (1.0 + 2.0 * window) / near
    return lo + step * torch.arange(int(math.floor((hi - lo) / step + 1e-9)) + 1, dtype=torch.float64)


def seed_mask(grid: torch.Tensor, seed_q: torch.Tensor, window: float = SEED_WINDOW) -> torch.Tensor:
    """``(Q, T)``: the hypotheses within ``window`` (relative) of each tile's seed ``(T,)``, and
    for a seed off the grid at least its nearest grid point.

    Example:
        >>> m = seed_mask(torch.arange(1.0, 2.01, 0.1, dtype=torch.float64), torch.tensor([1.5, 9.0]), 0.07)
        >>> m[:, 0].nonzero().flatten().tolist(), m[:, 1].nonzero().flatten().tolist()
        ([4, 5, 6], [10])
    """
    if window <= 0:
        raise InputError(f"seed_window must be > 0, got {window}")
    if seed_q.ndim != 1:
        raise InputError(f"need one seed per tile, (T,), got {tuple(seed_q.shape)}")
    if not bool(torch.isfinite(seed_q).all()) or not bool((seed_q > 0).all()):
        raise InputError("seeds must be finite inverse depths > 0")
    dist = (grid[:, None] - seed_q[None, :].to(grid.dtype)).abs()
    near = dist <= window * seed_q[None, :]
    near[dist.argmin(0), torch.arange(seed_q.shape[0])] = True
    return near


def kernel_side(camera: Camera, hypotheses: Sequence[PsfHypothesis], grid: torch.Tensor, max_kernel: int,
                tile: int | None = None) -> int:
    """The odd kernel side the fit uses: what the largest blur on ``grid`` needs under any
    hypothesis, at most ``max_kernel`` and, given the ``tile``, smaller than it (a tile's residual
    spectrum holds no larger kernel; larger blurs, e.g. an aberrated PSF far from focus, are
    truncated and renormalised)."""
    if max_kernel < 3 or max_kernel % 2 == 0:
        raise InputError(f"max_kernel must be odd and >= 3, got {max_kernel}")
    if tile is not None:
        max_kernel = min(max_kernel, tile - 1 if tile % 2 == 0 else tile - 2)
    smax = max(float(s.abs().max()) for s in camera_sigmas(camera, 1.0 / grid))
    return min(max(h.kernel_size(smax) for h in hypotheses), max_kernel) | 1


def kernel_pairs(camera: Camera, hypothesis: PsfHypothesis, q: torch.Tensor, size: int) -> torch.Tensor:
    """``(Q, 2, size, size)`` float64: the two frames' kernels under ``hypothesis`` at each inverse
    depth of ``q`` ``(Q,)`` (1/m), the camera's blurs (paper eqs. 1-7)."""
    sig = torch.stack([s.reshape(-1) for s in camera_sigmas(camera, 1.0 / q)], 1).to(torch.float64)
    return hypothesis.kernels(sig.reshape(-1), size).reshape(len(q), 2, size, size)


@dataclass(frozen=True)
class SeededFit:
    """One image's seeded per-tile fit (:func:`seeded_tile_fit`).

    Attributes:
        q: ``(T,)`` each tile's inverse depth (1/m).
        sigma_q: ``(T,)`` its standard deviation (1/m); ``inf`` where the minimum lies on the
            search window's edge or the curvature is not positive (no weight).
        noise: ``(T,)`` the NLL at the minimum: the tile's noise variance relative to the fit's
            unit (about 1 for a well-modelled tile of unit noise).
        hypothesis: the PSF the image shares.
        walked: ``(T,)`` bool, the tiles whose walked minimum counts (all False without ``walk``;
            ``None`` on a fit built by hand).
        unwalked: the fit before any walk (``None`` without ``walk``), for a caller's check of the
            walked tiles against their neighbours (:mod:`tdfd.dfd.walk_gate`).
    """

    q: torch.Tensor
    sigma_q: torch.Tensor
    noise: torch.Tensor
    hypothesis: PsfHypothesis
    walked: torch.Tensor | None = None
    unwalked: "SeededFit | None" = None


def seeded_tile_fit(y1: torch.Tensor, y2: torch.Tensor, camera: Camera, origins: Sequence[tuple[int, int]], tile: int,
                    seed_q: torch.Tensor, hypotheses: Sequence[PsfHypothesis], *, window: float = SEED_WINDOW,
                    step: float = Q_STEP, band: float = 0.25, max_kernel: int = 65,
                    profile_tiles: int = PROFILE_TILES, profile_by: torch.Tensor | None = None,
                    walk: int = 0, walk_tiles: torch.Tensor | None = None, walk_gain: float = WALK_GAIN,
                    shift: torch.Tensor | None = None) -> SeededFit:
    """The seeded fit of every tile of one image.

    Args:
        y1, y2: ``(H, W)`` frames linear in irradiance, black level removed, means matched.
        camera: the thin-lens camera that maps ``q`` to each frame's blur (paper eqs. 1-7).
        origins: ``T`` tiles' top-left pixels; each a kernel's half-width inside the frame.
        tile: tile side in px.
        seed_q: ``(T,)`` the seeds (1/m).
        hypotheses: the PSFs profiled over (at least one).
        window, step: the search's relative half-width and grid step (:func:`inverse_depth_grid`).
        band: the likelihood's band, cycles/px.
        max_kernel: the largest kernel side (odd); larger blurs are truncated.
        profile_tiles: how many tiles choose the shared PSF (then every tile is fitted with it).
        profile_by: ``(T,)`` the tiles' priority for that choice (e.g. the model's confidence;
            ``None``: the first ``profile_tiles``).
        walk: how many times a tile whose minimum lies on its window's edge has its window
            moved there and is searched again (0: never). Each move follows the likelihood
            downhill by up to ``window``, so a seed off by more than the window can still reach
            an interior minimum; one still on an edge after ``walk`` moves keeps no weight.
        walk_tiles: ``(T,)`` bool, the tiles that may walk (``None``: all), e.g. those whose
            seed is uncertain enough to lie off by more than the window.
        walk_gain: the least gain of the walked minimum's log-likelihood, ``B log(NLL_edge /
            NLL_min)`` with ``B`` the tile's independent bins, over the first window's edge
            (:data:`WALK_GAIN`); a walked tile below it keeps its first fit (no weight).
        shift: ``(T, 2)`` px, where each tile's content lies in frame 2 relative to frame 1
            (:func:`~tdfd.dfd.cross_residual.tile_cross_residual_nll`; e.g. the pair's fitted
            registration, :mod:`tdfd.dfd.pair_registration`); ``None``: registered frames.

    Raises:
        InputError: no hypothesis, seeds not ``(T,)`` finite and > 0, bad options.
        ShapeError: bad frames or a tile outside the valid residual.
    """
    if not hypotheses:
        raise InputError("the fit needs at least one PSF hypothesis")
    if seed_q.shape != (len(origins),):
        raise InputError(f"need one seed per tile ({len(origins)}), got {tuple(seed_q.shape)}")
    if y1.ndim != 2 or y1.shape != y2.shape:
        raise ShapeError(f"frames must be two (H, W) of one shape, got {tuple(y1.shape)} and {tuple(y2.shape)}")
    if profile_tiles < 1:
        raise InputError(f"profile_tiles must be >= 1, got {profile_tiles}")
    if walk < 0:
        raise InputError(f"walk must be >= 0, got {walk}")
    if not walk_gain >= 0:
        raise InputError(f"walk_gain must be >= 0, got {walk_gain}")
    if walk_tiles is not None and (walk_tiles.shape != (len(origins),) or walk_tiles.dtype != torch.bool):
        raise InputError(f"walk_tiles must be a ({len(origins)},) bool tensor, got {tuple(walk_tiles.shape)} "
                         f"{walk_tiles.dtype}")
    grid = inverse_depth_grid(camera, window, step)
    mask = seed_mask(grid, seed_q.to(torch.float64), window)
    size = kernel_side(camera, hypotheses, grid, max_kernel, tile)
    unit = torch.ones(len(origins), dtype=torch.float64)

    def minima(hyp: PsfHypothesis, tiles: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        sub = torch.zeros_like(mask)  # the current windows (a walk moves some)
        sub[:, tiles] = mask[:, tiles]
        idx = sub.any(1).nonzero().flatten()
        ks = kernel_pairs(camera, hyp, grid[idx], size)
        nll = torch.full((len(grid), len(origins)), math.inf, dtype=torch.float64)
        nll[idx] = tile_cross_residual_nll(y1, y2, ks[:, 0], ks[:, 1], unit, unit, origins, tile, band,
                                           mask=sub[idx], shift=shift)
        q, value, curvature = parabolic_minima(nll[:, tiles], grid)
        return q, value, curvature

    every = torch.arange(len(origins))
    c = 0
    if len(hypotheses) > 1:  # the shared PSF, from the profile_tiles tiles the model is surest of
        order = every if profile_by is None else torch.argsort(-profile_by.to(torch.float64), stable=True)
        chosen = order[:profile_tiles].sort().values
        totals = [float(torch.log(minima(h, chosen)[1].clamp_min(1e-300)).sum()) for h in hypotheses]
        c = min(range(len(hypotheses)), key=totals.__getitem__)
    q, value, curvature = minima(hypotheses[c], every)
    first = (q.clone(), value.clone(), curvature.clone())
    walked = torch.zeros(len(origins), dtype=torch.bool)
    for _ in range(walk):
        k = torch.round((q - grid[0]) / step).long().clamp(0, len(grid) - 1)
        inside = mask[(k - 1).clamp_min(0), every] & mask[(k + 1).clamp_max(len(grid) - 1), every]
        edge = ~torch.isfinite(curvature) & ~inside & (k > 0) & (k < len(grid) - 1)
        if walk_tiles is not None:
            edge &= walk_tiles
        if not bool(edge.any()):
            break
        moved = edge.nonzero().flatten()
        walked[moved] = True
        mask[:, moved] = seed_mask(grid, grid[k[moved]], window)
        q[moved], value[moved], curvature[moved] = minima(hypotheses[c], moved)
    bins = independent_bins(tile, band)
    weak = walked & (bins * torch.log(first[1] / value.clamp_min(1e-300)) < walk_gain)
    q, value, curvature = (torch.where(weak, a, b) for a, b in zip(first, (q, value, curvature)))
    sigma = curvature_sigma(curvature, bins, value)
    unwalked = None
    if walk:
        unwalked = SeededFit(q=first[0], sigma_q=curvature_sigma(first[2], bins, first[1]), noise=first[1],
                             hypothesis=hypotheses[c], walked=torch.zeros_like(walked))
    return SeededFit(q=q, sigma_q=sigma, noise=value, hypothesis=hypotheses[c], walked=walked & ~weak,
                     unwalked=unwalked)
