r"""Whether a pair's likelihood tells the depth it was fitted at from depths far from it.

The likelihood stage (:mod:`tdfd.dfd.likelihood_stage`) searches each tile's likelihood only
within a window around the model's estimate (:mod:`tdfd.dfd.seeded_fit`). On narrow-band or
periodic textures (stripes, band-limited noise, dots through a disk PSF) the cross-residual
likelihood has several minima over the working range, and a whole scene can be fitted, with
small curvature sigmas, at a depth 10-25 % from the truth: the model's seed is off by as much and
the window holds a local minimum (``docs/BENCHMARKS.md``, section ``psf_structure``'s notes of
the sixteenth session).

This check evaluates the same likelihood (:func:`~tdfd.dfd.cross_residual.tile_cross_residual_nll`,
the image's PSF hypothesis, every second hypothesis of the stage's grid) over the *whole* range on
the scene's :data:`AMBIGUITY_TILES` most informative fitted tiles, and takes each tile's
log-likelihood margin of its fitted depth over every depth more than :data:`AMBIGUITY_FAR` away,

.. math::

    m = B \log \frac{\min_{|q - \hat q| > f \hat q} \mathrm{NLL}(q)}{\min_{|q - \hat q| \le n \hat q} \mathrm{NLL}(q)}

(``B`` the tile's independent bins, the NLL's unit noise profiled out as in the fit; ``n`` =
:data:`AMBIGUITY_NEAR`, ``f`` = :data:`AMBIGUITY_FAR`). A scene whose median margin is under
:data:`AMBIGUITY_MARGIN` (0: its likelihood prefers depths at least ``f`` from its fits on most
of its informative tiles) is *ambiguous*, so none of its tiles can state a relative error under
``f`` (:func:`ambiguity_cap`).

Example:
    >>> import torch
    >>> chosen_tiles(torch.tensor([0.02, math.inf, 0.01, 0.5]), tiles=2).tolist()
    [2, 0]
"""

from __future__ import annotations

import math
from typing import Sequence

import torch

from ..camera import Camera
from ..errors import InputError, ShapeError
from .cross_residual import independent_bins, tile_cross_residual_nll
from .inverse_variance import confidence_from_sigma
from .psf_hypotheses import PsfHypothesis
from .seeded_fit import Q_STEP, SEED_WINDOW, inverse_depth_grid, kernel_pairs, kernel_side, seed_mask

__all__ = ["AMBIGUITY_TILES", "AMBIGUITY_NEAR", "AMBIGUITY_FAR", "AMBIGUITY_MARGIN", "likelihood_margins",
           "chosen_tiles", "ambiguity_cap"]

#: the most informative fitted tiles (least fit sigma) whose margins decide a scene
AMBIGUITY_TILES = 12
#: the relative distance from the fitted depth within which the fit's own minimum is taken
AMBIGUITY_NEAR = 0.03
#: the relative distance beyond which another depth counts as a different answer
AMBIGUITY_FAR = 0.10
#: the least median margin (nats) of a scene that is not ambiguous: 0, a scene whose likelihood
#: prefers depths far from its fits. Chosen on the calibration seeds: of 0, 2, 5, 10, 15 and 20
#: nats the one that keeps the decile calibration best while it removes a third of the confident
#: tiles off by more than 5 % (``docs/BENCHMARKS.md``, section ``psf_structure``'s notes of the
#: sixteenth session)
AMBIGUITY_MARGIN = 0.0


def likelihood_margins(y1: torch.Tensor, y2: torch.Tensor, camera: Camera, hypothesis: PsfHypothesis,
                       origins: Sequence[tuple[int, int]], tile: int, q_fit: torch.Tensor, *, band: float = 0.25,
                       window: float = SEED_WINDOW, step: float = Q_STEP, max_kernel: int = 65,
                       near: float = AMBIGUITY_NEAR, far: float = AMBIGUITY_FAR,
                       shift: torch.Tensor | None = None) -> torch.Tensor:
    """Each tile's log-likelihood margin (nats) of its fitted inverse depth over every one more than
    ``far`` (relative) from it (module documentation).

    Args:
        y1, y2: ``(H, W)`` the frames as the fit saw them (black level removed, means matched).
        camera, hypothesis: the camera and the PSF the image's fit shares.
        origins: ``T`` tiles' top-left pixels (each a kernel's half-width inside the frame).
        tile: tile side in px.
        q_fit: ``(T,)`` the fitted inverse depths (1/m), finite and > 0.
        band, window, step, max_kernel: the fit's (:func:`~tdfd.dfd.seeded_fit.seeded_tile_fit`); the
            margins use every second hypothesis of its grid.
        near, far: the relative distances of :data:`AMBIGUITY_NEAR` and :data:`AMBIGUITY_FAR`.
        shift: ``(T, 2)`` px, each tile's content in frame 2 against frame 1, as the fit used it
            (:mod:`tdfd.dfd.pair_registration`); ``None``: registered frames.

    Returns:
        ``(T,)`` float64 margins: negative where a depth ``far`` away fits better; ``inf`` where the
        grid holds no depth that far.

    Raises:
        InputError: ``q_fit`` not ``(T,)``, finite and > 0, or ``near``, ``far`` not ``0 < near < far``.
        ShapeError: bad frames or a tile outside the valid residual.
    """
    if q_fit.shape != (len(origins),) or not bool(torch.isfinite(q_fit).all()) or not bool((q_fit > 0).all()):
        raise InputError(f"need one finite inverse depth > 0 per tile ({len(origins)}), got {tuple(q_fit.shape)}")
    if not 0 < near < far:
        raise InputError(f"need 0 < near < far, got {near}, {far}")
    if not origins:
        return torch.zeros(0, dtype=torch.float64)
    grid = inverse_depth_grid(camera, window, step)[::2]
    size = kernel_side(camera, (hypothesis,), grid, max_kernel, tile)
    if shift is not None and len(shift):  # the kernels' margin holds the shift (tile_cross_residual_nll)
        size = max(size, 2 * math.ceil(float(shift.abs().max())) + 1)
    ks = kernel_pairs(camera, hypothesis, grid, size)
    unit = torch.ones(len(origins), dtype=torch.float64)
    nll = tile_cross_residual_nll(y1, y2, ks[:, 0], ks[:, 1], unit, unit, origins, tile, band,
                                  shift=shift)  # (Q, T)
    q = q_fit.to(torch.float64)
    close = seed_mask(grid, q, near)  # within near of the fit, at least the nearest hypothesis
    far_away = (grid[:, None] - q[None, :]).abs() > far * q[None, :]
    at_fit = torch.where(close, nll, torch.full_like(nll, math.inf)).min(0).values
    elsewhere = torch.where(far_away, nll, torch.full_like(nll, math.inf)).min(0).values
    margin = independent_bins(tile, band) * torch.log(elsewhere / at_fit.clamp_min(1e-300))
    return torch.where(torch.isfinite(elsewhere), margin, torch.full_like(margin, math.inf))


def chosen_tiles(sigma: torch.Tensor, tiles: int = AMBIGUITY_TILES) -> torch.Tensor:
    """The indices of the ``tiles`` tiles of least finite fit ``sigma`` ``(T,)``, in increasing sigma
    (empty where none is finite): the tiles whose median margin decides the scene.

    Raises:
        ShapeError: ``sigma`` not ``(T,)``.
        InputError: ``tiles`` < 1.
    """
    if sigma.ndim != 1:
        raise ShapeError(f"sigma must be (T,), got {tuple(sigma.shape)}")
    if tiles < 1:
        raise InputError(f"tiles must be >= 1, got {tiles}")
    finite = torch.isfinite(sigma).nonzero().flatten()
    return finite[torch.argsort(sigma[finite], stable=True)[:tiles]]


def ambiguity_cap(confidence_scale: float, far: float = AMBIGUITY_FAR) -> float:
    """The highest confidence an ambiguous scene's tile keeps: the one that states a relative
    standard deviation of ``far`` on the model's scale ``b0``.

    Example:
        >>> round(ambiguity_cap(0.01), 4)
        0.0196
    """
    return float(confidence_from_sigma(torch.tensor([far], dtype=torch.float64), confidence_scale)[0])
