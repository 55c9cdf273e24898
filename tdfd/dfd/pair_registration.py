r"""The pair's focus breathing and misregistration, fitted from its own likelihood.

An ECVFL magnifies frame 2 against frame 1 a little (focus breathing, :mod:`tdfd.breathing`),
and a pair may be shifted by a fraction of a pixel (vibration between the exposures). A scene
point at ``p`` in frame 1 then lies at

.. math::

    p + \delta(p), \qquad \delta(p) = \beta\,(p - c) + d

in frame 2 (:func:`tdfd.warp.misregister`: ``beta`` the relative magnification minus 1, ``c`` the
frame's centre, ``d`` the shift), and a tile ``t`` sees its content moved by ``delta`` at its
centre. The cross residual (:mod:`tdfd.dfd.cross_residual`) is texture-free only for
registered frames: on the structure benchmark's slanted planes, the fit told the true PSF
within 10 % of the truth reads 0.99 % per tile with the world's breathing (up to 1 %) and
0.76 % told each tile's ``delta`` (``docs/BENCHMARKS.md``, section ``psf_structure``'s notes of
the seventeenth session).

:func:`fit_pair_registration` fits ``(beta, d_row, d_col)`` to the pair itself: the sum over
the image's :data:`REGISTRATION_TILES` most informative fitted tiles (a quarter from each quadrant
about the centre, :func:`spread_tiles`) of ``B log NLL``, each tile's
inverse depth profiled within :data:`REGISTRATION_NEAR` of its fit, minimised by a coordinate
search (a scan of ``beta``, then rounds of finer steps). A calibrated breathing
(:class:`tdfd.registration.BreathingRegistration`) resamples whole pixels; this fit moves frame
2's spectrum by a phase ramp, so nothing is interpolated and the noise stays white.

Example:
    >>> import torch
    >>> tile_shifts(torch.tensor([0.01, 0.5, -0.25], dtype=torch.float64), [(0, 0), (100, 200)], 64,
    ...             (164, 264)).tolist()
    [[0.0, -1.25], [1.0, 0.75]]
"""

from __future__ import annotations

import math
from typing import Sequence

import torch

from ..camera import Camera
from ..errors import InputError, ShapeError
from .cross_residual import independent_bins, tile_cross_residual_nll
from .psf_hypotheses import PsfHypothesis
from .scene_ambiguity import chosen_tiles
from .seeded_fit import kernel_pairs, kernel_side

__all__ = ["REGISTRATION_TILES", "REGISTRATION_NEAR", "BREATHING_SCAN", "SHIFT_SCAN_PX", "centre_offsets",
           "tile_shifts", "spread_tiles", "registration_objective", "fit_pair_registration"]

#: the most informative fitted tiles (least fit sigma, a quarter per quadrant) whose likelihood fits the
#: registration
REGISTRATION_TILES = 12
#: each tile's inverse depth is profiled within this relative distance of its fit (5 hypotheses)
REGISTRATION_NEAR = 0.02
#: the breathing scanned first: ``beta`` in ``[-BREATHING_SCAN, BREATHING_SCAN]`` (twice the
#: synthesis's largest, ``data_synth``'s ``breathing_max``)
BREATHING_SCAN = 0.02
#: the largest shift (px) per axis the fit may reach
SHIFT_SCAN_PX = 1.0
#: hypotheses per tile in its profiled window
HYPOTHESES = 5


def centre_offsets(origins: Sequence[tuple[int, int]], tile: int, frame_shape: tuple[int, int]) -> torch.Tensor:
    """``(T, 2)`` float64 px: each tile's centre less the frame's centre ``c`` (row, column), the
    lever arm of the breathing.

    Example:
        >>> centre_offsets([(0, 0)], 64, (164, 264)).tolist()
        [[-50.0, -100.0]]
    """
    centre = torch.tensor([(frame_shape[0] - 1) / 2, (frame_shape[1] - 1) / 2], dtype=torch.float64)
    at = torch.tensor([[r + (tile - 1) / 2, c + (tile - 1) / 2] for r, c in origins],
                      dtype=torch.float64).reshape(-1, 2)
    return at - centre


def tile_shifts(registration: torch.Tensor, origins: Sequence[tuple[int, int]], tile: int,
                frame_shape: tuple[int, int]) -> torch.Tensor:
    """Each tile's ``delta`` at its centre (module documentation).

    Args:
        registration: ``(3,)`` ``(beta, d_row, d_col)``.
        origins: ``T`` tiles' top-left pixels.
        tile: tile side in px.
        frame_shape: ``(H, W)`` of the frames.

    Returns:
        ``(T, 2)`` float64 px (row, column).

    Raises:
        ShapeError: ``registration`` not ``(3,)``.
    """
    if registration.shape != (3,):
        raise ShapeError(f"registration must be (3,) (beta, d_row, d_col), got {tuple(registration.shape)}")
    reg = registration.to(torch.float64)
    return reg[0] * centre_offsets(origins, tile, frame_shape) + reg[1:]


def spread_tiles(sigma: torch.Tensor, origins: Sequence[tuple[int, int]], tile: int, frame_shape: tuple[int, int],
                 tiles: int = REGISTRATION_TILES) -> torch.Tensor:
    """The indices of up to ``tiles`` tiles of least finite ``sigma`` ``(T,)``, a quarter from each
    quadrant about the frame's centre (fewer where a quadrant has fewer fits; the rest from the
    others): tiles on both sides of the centre in both axes tell the breathing from the shift."""
    if sigma.shape != (len(origins),):
        raise ShapeError(f"sigma must be ({len(origins)},), got {tuple(sigma.shape)}")
    offsets = centre_offsets(origins, tile, frame_shape)
    quadrant = 2 * (offsets[:, 0] > 0).long() + (offsets[:, 1] > 0).long()
    picked = []
    for k in range(4):
        inside = (quadrant == k).nonzero().flatten()
        picked.append(inside[chosen_tiles(sigma[inside], max(tiles // 4, 1))] if len(inside) else inside)
    pick = torch.cat(picked)
    if len(pick) < tiles:  # a quadrant short of fits: the best of the rest
        rest = torch.ones(len(origins), dtype=torch.bool)
        rest[pick] = False
        others = rest.nonzero().flatten()
        pick = torch.cat([pick, others[chosen_tiles(sigma[others], tiles - len(pick))]]) if len(others) else pick
    return pick


def registration_objective(y1: torch.Tensor, y2: torch.Tensor, kernels: torch.Tensor, mask: torch.Tensor,
                           origins: Sequence[tuple[int, int]], tile: int, band: float,
                           registration: torch.Tensor) -> float:
    """``sum_t B log min_q NLL_t(q)`` under ``registration`` (nats, up to a constant), each tile's
    minimum over its hypotheses (``mask``'s column) refined by a parabola where it lies inside them
    (a minimum on a window's end keeps its grid value)."""
    shift = tile_shifts(registration, origins, tile, tuple(y1.shape))
    unit = torch.ones(len(origins), dtype=torch.float64)
    nll = tile_cross_residual_nll(y1, y2, kernels[:, 0], kernels[:, 1], unit, unit, origins, tile, band, mask=mask,
                                  shift=shift)
    k = nll.argmin(0)
    t = torch.arange(nll.shape[1])
    a, b, c = (nll[(k + d).clamp(0, nll.shape[0] - 1), t] for d in (-1, 0, 1))
    den = a - 2 * b + c
    inside = (k > 0) & (k < nll.shape[0] - 1)  # the stack's two ends have no neighbour on one side
    ok = inside & torch.isfinite(a) & torch.isfinite(c) & (den > 0)
    low = torch.where(ok, b - 0.125 * (a - c) ** 2 / torch.where(ok, den, torch.ones_like(den)), b)
    return float(independent_bins(tile, band) * torch.log(low.clamp_min(1e-300)).sum())


def fit_pair_registration(y1: torch.Tensor, y2: torch.Tensor, camera: Camera, hypothesis: PsfHypothesis,
                          origins: Sequence[tuple[int, int]], tile: int, q_fit: torch.Tensor, sigma_q: torch.Tensor,
                          *, band: float = 0.25, max_kernel: int = 65, tiles: int = REGISTRATION_TILES,
                          near: float = REGISTRATION_NEAR, breathing_scan: float = BREATHING_SCAN,
                          shift_scan_px: float = SHIFT_SCAN_PX, rounds: int = 2) -> torch.Tensor:
    """The pair's ``(beta, d_row, d_col)`` that minimise :func:`registration_objective` over its
    most informative fitted tiles (module documentation).

    Args:
        y1, y2: ``(H, W)`` the frames as the fit saw them (black level removed, means matched).
        camera, hypothesis: the camera and the PSF the image's fit shares.
        origins: ``T`` tiles' top-left pixels (each a kernel's half-width inside the frame).
        tile: tile side in px.
        q_fit, sigma_q: ``(T,)`` the first fit's inverse depths (1/m) and their standard deviations
            (``inf`` where the fit has no weight).
        band, max_kernel: the fit's.
        tiles: how many of the least-sigma tiles take part (:data:`REGISTRATION_TILES`).
        near: each tile's profiled relative window (:data:`REGISTRATION_NEAR`).
        breathing_scan, shift_scan_px: the search's bounds.
        rounds: refinement rounds after the scans (each a quarter of the last step: with the
            default 2 the breathing is resolved to 0.00025 and the shift to 0.03 px).

    Returns:
        ``(3,)`` float64 ``(beta, d_row, d_col)``; zeros where fewer than 3 tiles have a finite fit.

    Raises:
        InputError: ``q_fit``, ``sigma_q`` not ``(T,)``, bad bounds.
        ShapeError: a chosen tile closer to the frame's edge than the kernels' half-width, which
            is at least the largest shift the bounds allow.
    """
    if q_fit.shape != (len(origins),) or sigma_q.shape != (len(origins),):
        raise InputError(f"need one fit and sigma per tile ({len(origins)}), got {tuple(q_fit.shape)} and "
                         f"{tuple(sigma_q.shape)}")
    if not (0 < near < 0.5 and 0 < breathing_scan < 0.1 and 0 < shift_scan_px and rounds >= 0):
        raise InputError(f"need 0 < near < 0.5, 0 < breathing_scan < 0.1, shift_scan_px > 0, rounds >= 0; got "
                         f"{near}, {breathing_scan}, {shift_scan_px}, {rounds}")
    good = torch.isfinite(sigma_q) & torch.isfinite(q_fit) & (q_fit > 0)
    pick = spread_tiles(torch.where(good, sigma_q.to(torch.float64), torch.full_like(sigma_q, math.inf,
                                                                                      dtype=torch.float64)),
                        origins, tile, tuple(y1.shape), tiles)
    reg = torch.zeros(3, dtype=torch.float64)
    if len(pick) < 3:
        return reg
    sub = [origins[int(t)] for t in pick]
    offsets = torch.linspace(-near, near, HYPOTHESES, dtype=torch.float64)
    qs = (q_fit[pick].to(torch.float64)[None, :] * (1 + offsets[:, None])).T.reshape(-1)  # tile-major
    reach = centre_offsets(sub, tile, tuple(y1.shape)).abs().max()
    largest = math.ceil(float(breathing_scan * reach) + shift_scan_px)  # the largest shift the search can try
    size = max(kernel_side(camera, (hypothesis,), qs, max_kernel, tile), 2 * largest + 1)  # its margin holds it
    kernels = kernel_pairs(camera, hypothesis, qs, size)
    mask = torch.zeros(len(qs), len(sub), dtype=torch.bool)
    for t in range(len(sub)):
        mask[HYPOTHESES * t: HYPOTHESES * (t + 1), t] = True
    limit = torch.tensor([breathing_scan, shift_scan_px, shift_scan_px], dtype=torch.float64)
    cost = {}

    def f(r: torch.Tensor) -> float:
        key = tuple(round(float(x), 9) for x in r)
        if key not in cost:
            cost[key] = registration_objective(y1, y2, kernels, mask, sub, tile, band, r)
        return cost[key]

    def line(r: torch.Tensor, axis: int, values: torch.Tensor) -> torch.Tensor:
        best = r
        for v in values:
            trial = r.clone()
            trial[axis] = v.clamp(-limit[axis], limit[axis])
            if f(trial) < f(best):
                best = trial
        return best

    reg = line(reg, 0, torch.linspace(-breathing_scan, breathing_scan, 11, dtype=torch.float64))
    steps = torch.tensor([breathing_scan / 5, shift_scan_px / 2, shift_scan_px / 2], dtype=torch.float64)
    for axis in (1, 2):
        reg = line(reg, axis, reg[axis] + steps[axis] * torch.arange(-2, 3, dtype=torch.float64))
    for _ in range(rounds):
        steps = steps / 4
        for axis in range(3):
            reg = line(reg, axis, reg[axis] + steps[axis] * torch.arange(-2, 3, dtype=torch.float64))
    return reg
