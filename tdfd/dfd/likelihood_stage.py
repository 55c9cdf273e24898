r"""A likelihood stage after the refinement CNN: each tile's cross-residual fit, seeded by the model's
map and fused with it by inverse variance.

The refinement CNN (:class:`tdfd.model.DFDModel`) is robust (a weak texture rarely gives it a
gross error) but its errors are correlated over a surface; the cross-residual likelihood
(:mod:`tdfd.dfd.cross_residual`: ``k2(q) * f1 - k1(q) * f2`` is texture-free at the true ``q``)
comes close to the information limit where the texture is informative. Per tile of the model's
grid the stage:

1. matches frame 2's mean to frame 1's (blur keeps the mean; a gain or exposure difference is
   what is left) after removing the black level;
2. fits ``q = 1/d`` within ``seed_window`` of the model's estimate, the PSF shared by the image
   and profiled over the hypotheses (:mod:`tdfd.dfd.psf_hypotheses`: the measured family's
   shape, or every shape, each without and with the diffraction of the working f-number), the
   noise not told (:func:`tdfd.dfd.seeded_fit.seeded_tile_fit`);
3. with ``scales.shared_bias``, divides the model's map by its bias, measured against the fit
   over the image or, with ``scales.bias_radius``, over the fitted tiles near each tile
   (:mod:`tdfd.dfd.shared_bias`: the CNN's error is mostly shared by neighbouring tiles, which a
   per-tile fusion cannot remove);
4. fuses the fit with the model by inverse variance, each sigma times its factor for the tile's
   slope in the model's map (the fit assumes a fronto-parallel tile), fitted on training scenes
   (:mod:`tdfd.dfd.inverse_variance`, ``training/fit_likelihood_stage.py``), and
   states the fused sigma as a confidence on the model's scale, through a map of the fused
   scale fitted on the same training scenes (``scales.fused_scale``: the two errors are
   correlated, and the fit's sigma is not proportional to its error); a tile the fit adds
   nothing to keeps the model's confidence;
5. with a ``pooling`` (opt-in), pools the fused map along the depth structure
   (:mod:`tdfd.dfd.stage_pooling`: the model's own structure pooling, each tile weighted by its
   fused confidence), into ``depth_pooled``; each tile's confidence stays its fused one;
6. with ``ambiguity`` (opt-in), checks each image's fit against the likelihood over the whole range
   (:mod:`tdfd.dfd.scene_ambiguity`): an image whose most informative tiles fit a depth at least
   10 % away better keeps its map, every confidence capped at the one that states a 10 % error
   (before the pooling, so ``depth_pooled`` weighs its tiles alike);
7. with ``register`` (opt-in), fits the pair's focus breathing and shift to its own likelihood
   (:mod:`tdfd.dfd.pair_registration`), alternating with the tiles' fits, and fits every tile
   again with frame 2 moved back by its tile's shift (steps 2-6 then use that fit).

Tiles closer to the frame's edge than a kernel's half-width (where the residual is not valid)
keep the model's estimate (without the image's bias, where it is removed) and confidence; so do
tiles whose fit has no minimum inside its window. Without ``register`` the stage models neither
breathing nor misregistration (register the frames first where they matter,
:mod:`tdfd.registration`, or fit them with ``register``); it never models vignetting. Its cost
grows with the hypotheses (12 without a measured family, 2 with one) and the spread of depths in
the frame: see ``docs/BENCHMARKS.md``, section ``likelihood_stage``.

Example:
    >>> import torch
    >>> from tdfd import Camera
    >>> stage = LikelihoodStage(Camera.preset("reference"), tile=64, stride=32, confidence_scale=0.01,
    ...                         family="gaussian")
    >>> g = torch.Generator().manual_seed(0)
    >>> i1, i2 = torch.rand(1, 1, 160, 160, generator=g), torch.rand(1, 1, 160, 160, generator=g)
    >>> depth, conf = torch.full((1, 1, 4, 4), 0.5), torch.full((1, 1, 4, 4), 0.5)
    >>> out = stage(i1, i2, depth, conf)
    >>> out.fitted[0, 0].int().tolist()
    [[0, 0, 0, 0], [0, 1, 1, 0], [0, 1, 1, 0], [0, 0, 0, 0]]
    >>> bool((out.depth[out.fitted == 0] == 0.5).all())
    True
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Callable, Sequence

import torch
from torch import nn

from ..camera import Camera
from ..errors import InputError, NonFiniteError, ShapeError
from ..grid import grid_shape
from .inverse_variance import LikelihoodScales, confidence_from_sigma, fuse, model_sigma, tile_slope
from .psf_hypotheses import WAVELENGTH_M, PsfHypothesis, psf_hypotheses
from .pair_registration import BREATHING_SCAN, SHIFT_SCAN_PX, centre_offsets, fit_pair_registration, tile_shifts
from .shared_bias import bias_map
from .scene_ambiguity import AMBIGUITY_MARGIN, ambiguity_cap, chosen_tiles, likelihood_margins
from .stage_pooling import pool_stage_map
from .seeded_fit import PROFILE_TILES, Q_STEP, SEED_WINDOW, inverse_depth_grid, kernel_side, seeded_tile_fit
from .walk_gate import neighbour_consensus, walk_rejected

#: with ``register``: fit, register, fit registered, register again (a fit off by the breathing's
#: bias profiles the registration's likelihood away from the tiles' depths), then the final fit
REGISTRATION_PASSES = 2

__all__ = ["REGISTRATION_PASSES", "LikelihoodStageResult", "valid_tiles", "fuse_with_fit", "likelihood_stage",
           "LikelihoodStage"]


@dataclass
class LikelihoodStageResult:
    """What :func:`likelihood_stage` returns, per tile ``(B, 1, h, w)``.

    Attributes:
        depth: the fused object distance in metres (the model's where not ``fitted``).
        confidence: the fused confidence, on the model's scale, in [0, 1].
        depth_fit: the likelihood fit's own distance (``nan`` where not fitted).
        sigma_fit: the fit's relative standard deviation after its factor (``inf`` where it has
            no weight).
        sigma_fit_raw: ``(B, 1, h, w)`` float64, the same before its factor (the curvature's), which
            another :class:`~tdfd.dfd.inverse_variance.LikelihoodScales` can fuse again
            (:func:`fuse_with_fit`).
        fitted: where the fit was made (bool).
        hypotheses: per image, the PSF it shares.
        slope: each fitted tile's slope in the model's map
            (:func:`~tdfd.dfd.inverse_variance.tile_slope`; 0 where not fitted), which picks its
            sigma factors.
        bias: ``(B, 1, h, w)`` float64, the model's bias in ``log q`` removed before the fusion
            (0 without ``scales.shared_bias``, or with too few fitted tiles).
        depth_pooled: with a ``pooling``, ``depth`` pooled along the depth structure
            (:func:`~tdfd.dfd.stage_pooling.pool_stage_map`; its confidence is ``confidence``);
            ``None`` without.
        scene_margin: with ``ambiguity``, ``(B,)`` float64 each image's median log-likelihood margin
            (nats) of its fitted depths over depths far from them
            (:mod:`tdfd.dfd.scene_ambiguity`; ``inf`` for an image without a fit to doubt); an
            image under :data:`~tdfd.dfd.scene_ambiguity.AMBIGUITY_MARGIN` is ambiguous and every
            confidence of it is capped (:attr:`ambiguous`); ``None`` without the check.
        registration: with ``register``, ``(B, 3)`` float64 each pair's fitted ``(beta, d_row,
            d_col)``: frame 2's breathing and shift (px) against frame 1
            (:mod:`tdfd.dfd.pair_registration`); ``None`` without.
    """

    depth: torch.Tensor
    confidence: torch.Tensor
    depth_fit: torch.Tensor
    sigma_fit: torch.Tensor
    fitted: torch.Tensor
    hypotheses: list[PsfHypothesis]
    slope: torch.Tensor
    bias: torch.Tensor
    sigma_fit_raw: torch.Tensor
    depth_pooled: torch.Tensor | None = None
    scene_margin: torch.Tensor | None = None
    registration: torch.Tensor | None = None

    @property
    def ambiguous(self) -> torch.Tensor | None:
        """``(B,)`` bool: the images whose likelihood did not tell their fitted depths from depths
        far from them (:attr:`scene_margin` under the threshold); ``None`` without the check."""
        return None if self.scene_margin is None else self.scene_margin < AMBIGUITY_MARGIN


def valid_tiles(height: int, width: int, tile: int, stride: int, half: int) -> torch.Tensor:
    """``(h, w)`` bool: the grid's tiles at least ``half`` px inside a ``height`` x ``width`` frame.

    Example:
        >>> valid_tiles(160, 192, 64, 32, 32).int().tolist()
        [[0, 0, 0, 0, 0], [0, 1, 1, 1, 0], [0, 1, 1, 1, 0], [0, 0, 0, 0, 0]]
    """
    h, w = grid_shape(height, width, tile, stride)
    rows = torch.arange(h) * stride
    cols = torch.arange(w) * stride
    ok_r = (rows >= half) & (rows + tile <= height - half)
    ok_c = (cols >= half) & (cols + tile <= width - half)
    return ok_r[:, None] & ok_c[None, :]


def _check(image_f1: torch.Tensor, image_f2: torch.Tensor, depth: torch.Tensor, confidence: torch.Tensor, tile: int,
           stride: int) -> None:
    if image_f1.ndim != 4 or image_f1.shape[1] != 1 or image_f1.shape != image_f2.shape:
        raise ShapeError(f"frames must be two (B, 1, H, W) of one shape, got {tuple(image_f1.shape)} and "
                         f"{tuple(image_f2.shape)}")
    b, _, height, width = image_f1.shape
    h, w = grid_shape(height, width, tile, stride)
    for name, t in (("depth", depth), ("confidence", confidence)):
        if t.shape != (b, 1, h, w):
            raise ShapeError(f"{name} must be the tile grid (B, 1, h, w) = {(b, 1, h, w)}, got {tuple(t.shape)}")
    for name, t in (("image_f1", image_f1), ("image_f2", image_f2), ("depth", depth), ("confidence", confidence)):
        if not bool(torch.isfinite(t).all()):
            raise NonFiniteError(f"{name} has non-finite values")
    if not bool((depth > 0).all()):
        raise InputError("depths must be > 0")


def fuse_with_fit(q_model: torch.Tensor, sigma_model: torch.Tensor, q_fit: torch.Tensor, sigma_fit: torch.Tensor,
                  slope: torch.Tensor, scales: LikelihoodScales, confidence_scale: float, rows: torch.Tensor,
                  cols: torch.Tensor, grid: tuple[int, int]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Steps 3-4 of the stage for one image's fitted tiles ``(T,)``: the model's bias removed (with
    ``scales.shared_bias``) and the inverse-variance fusion.

    Args:
        q_model: the model's inverse depths (1/m).
        sigma_model: the model's relative sigma from its confidence, before its factor
            (:func:`~tdfd.dfd.inverse_variance.model_sigma`).
        q_fit, sigma_fit: the fit's inverse depths and their sigma (1/m), before its factor.
        slope: the tiles' slopes in the model's map (which pick the factors).
        scales: the factors and whether the bias is removed.
        confidence_scale: the model's ``b0``.
        rows, cols, grid: the tiles' cells on the ``(h, w)`` tile grid.

    Returns:
        ``(q, confidence, bias, scale)``: the fused inverse depths; their confidence on the
        model's scale, from the fused Laplace scale through ``scales``' map (its slope part at ``slope``)
        (:meth:`~tdfd.dfd.inverse_variance.LikelihoodScales.fused_scale`) where the fit has a
        finite sigma (elsewhere the fusion is the model's own estimate, and so is the
        confidence); the ``(h, w)`` map of the bias removed from the model's ``log q`` (0 without
        ``shared_bias``); and the fused Laplace scale of the relative error before the map,
        ``sigma / (q f_model sqrt(2))`` (what the map is fitted on, ``training/fit_likelihood_stage.py``).
    """
    f_fit, f_model = scales.factors(slope)
    s_model = sigma_model.to(torch.float64) * f_model  # relative
    s_fit = sigma_fit.to(torch.float64) * f_fit  # 1/m
    q_model = q_model.to(torch.float64)
    if scales.shared_bias:
        bias = bias_map(q_model, s_model, q_fit, s_fit / q_fit, rows, cols, grid, scales.bias_radius)
    else:
        bias = torch.zeros(grid, dtype=torch.float64)
    q_model = q_model * torch.exp(-bias[rows, cols])
    q, s_q = fuse(q_fit, s_fit, q_model, s_model * q_model)
    scale = s_q / q / f_model / math.sqrt(2.0)  # Laplace: the standard deviation is sqrt(2) b
    stated = torch.where(torch.isfinite(s_fit), scales.fused_scale(scale, slope), scale)
    return q, confidence_from_sigma(math.sqrt(2.0) * stated, confidence_scale), bias, scale


def likelihood_stage(image_f1: torch.Tensor, image_f2: torch.Tensor, depth: torch.Tensor, confidence: torch.Tensor,
                     camera: Camera, *, tile: int, stride: int, confidence_scale: float,
                     scales: LikelihoodScales = LikelihoodScales(), hypotheses: tuple[PsfHypothesis, ...] | None = None,
                     black_level: float = 0.0, seed_window: float = SEED_WINDOW, q_step: float = Q_STEP,
                     band: float = 0.25, max_kernel: int = 65, profile_tiles: int = PROFILE_TILES, walk: int = 0,
                     pooling: Callable[[torch.Tensor, torch.Tensor], torch.Tensor] | None = None,
                     ambiguity: bool = False, register: bool = False) -> LikelihoodStageResult:
    """The model's depth map refined by each tile's likelihood fit (see the module documentation).

    Args:
        image_f1, image_f2: ``(B, 1, H, W)`` the DFD pair, linear in irradiance (any gain).
        depth, confidence: ``(B, 1, h, w)`` the model's map on its tile grid (metres, [0, 1]).
        camera: the camera the frames come from.
        tile, stride: the model's tile grid in px.
        confidence_scale: the model's ``b0`` (its confidence's Laplace scale).
        scales: the sigmas' factors (:class:`~tdfd.dfd.inverse_variance.LikelihoodScales`).
        hypotheses: the PSFs to profile over; ``None``: every shape
            (:func:`~tdfd.dfd.psf_hypotheses.psf_hypotheses` of an unknown family).
        black_level: the frames' black level, in their units.
        seed_window, q_step, band, max_kernel, profile_tiles, walk: see
            :func:`~tdfd.dfd.seeded_fit.seeded_tile_fit` (the model's most confident tiles choose the PSF;
            ``walk`` moves a window whose minimum lies on its edge, on the tiles whose model
            sigma reaches past the window at two sigmas: the model's confident tiles keep theirs;
            a walk that ends farther from the fitted neighbours than its seed is undone,
            :mod:`tdfd.dfd.walk_gate`).
        pooling: ``(inverse_depth, scale) -> inverse_depth`` (e.g. the model's
            :class:`~tdfd.model.structure_pooling.StructurePooling`): also pool the fused map along the
            depth structure (``depth_pooled``, :func:`~tdfd.dfd.stage_pooling.pool_stage_map`); ``None``: not.
        ambiguity: also check each image's fit against the whole range
            (:mod:`tdfd.dfd.scene_ambiguity`): an image whose likelihood prefers depths
            :data:`~tdfd.dfd.scene_ambiguity.AMBIGUITY_FAR` from its fits keeps its map,
            every confidence capped at the one that states that error
            (:func:`~tdfd.dfd.scene_ambiguity.ambiguity_cap`).
        register: fit each pair's focus breathing and shift to its own likelihood before the
            final fit (:mod:`tdfd.dfd.pair_registration`: :data:`REGISTRATION_PASSES` times a fit
            without a walk, registered as far as known, and the registration on its most
            informative tiles; then the fit with frame 2 moved back by each tile's shift); the
            breathing is searched only as far as the tiles' margins (a kernel's half-width) hold the
            shift of the tile farthest from the centre.

    Returns:
        :class:`LikelihoodStageResult`.

    Raises:
        ShapeError: frames, or a map not on their tile grid.
        NonFiniteError: non-finite inputs.
        InputError: depths not > 0, confidences outside [0, 1], a frame with no light above the
            black level, bad options.
    """
    _check(image_f1, image_f2, depth, confidence, tile, stride)
    hyps = psf_hypotheses(camera) if hypotheses is None else tuple(hypotheses)
    if not hyps:
        raise InputError("the stage needs at least one PSF hypothesis")
    b, _, height, width = image_f1.shape
    half = kernel_side(camera, hyps, inverse_depth_grid(camera, seed_window, q_step), max_kernel, tile) // 2
    valid = valid_tiles(height, width, tile, stride, half)
    ii, jj = valid.nonzero(as_tuple=True)
    origins = [(int(i) * stride, int(j) * stride) for i, j in zip(ii, jj)]
    sigma_m = model_sigma(confidence, confidence_scale)  # relative, (B, 1, h, w), before its factor
    out_d, out_c = depth.clone(), confidence.clone()
    fit_d = torch.full_like(depth, math.nan)
    fit_s = torch.full_like(depth, math.inf)
    fit_raw = torch.full(depth.shape, math.inf, dtype=torch.float64)
    slopes = torch.zeros_like(depth)
    chosen = []
    biases = torch.zeros(depth.shape, dtype=torch.float64)
    margins = torch.full((b,), math.inf, dtype=torch.float64) if ambiguity else None
    registrations = torch.zeros(b, 3, dtype=torch.float64) if register else None
    if register and origins:
        reach = float(centre_offsets(origins, tile, (height, width)).abs().max())
        breathing_scan = min(BREATHING_SCAN, (half - SHIFT_SCAN_PX) / max(reach, 1.0))
        if breathing_scan <= 0:
            raise InputError(f"register needs kernels wider than twice the shift scan ({SHIFT_SCAN_PX} px); their "
                             f"half-width is {half} px")
    for k in range(b):
        if not origins:
            chosen.append(hyps[0])
            continue
        y1, y2 = (im[k, 0].to(torch.float64) - black_level for im in (image_f1, image_f2))
        m1, m2 = float(y1.mean()), float(y2.mean())
        if not (m1 > 0 and m2 > 0):
            raise InputError(f"image {k}: a frame has no light above the black level (means {m1:.4g}, {m2:.4g})")
        y2 = y2 * (m1 / m2)
        seed = 1.0 / depth[k, 0, ii, jj].to(torch.float64)
        slope = tile_slope(1.0 / depth[k, 0].to(torch.float64))[ii, jj]
        shift = None
        for _ in range(REGISTRATION_PASSES if registrations is not None else 0):
            # a fit (registered as far as known), the pair's registration from its informative tiles
            first = seeded_tile_fit(y1, y2, camera, origins, tile, seed, hyps, window=seed_window, step=q_step,
                                    band=band, max_kernel=max_kernel, profile_tiles=profile_tiles,
                                    profile_by=confidence[k, 0, ii, jj], shift=shift)
            registrations[k] = fit_pair_registration(y1, y2, camera, first.hypothesis, origins, tile, first.q,
                                                     first.sigma_q, band=band, max_kernel=max_kernel,
                                                     breathing_scan=breathing_scan)
            shift = tile_shifts(registrations[k], origins, tile, (height, width))
        fit = seeded_tile_fit(y1, y2, camera, origins, tile, seed, hyps, window=seed_window, step=q_step, band=band,
                              max_kernel=max_kernel, profile_tiles=profile_tiles, profile_by=confidence[k, 0, ii, jj],
                              walk=walk, walk_tiles=2.0 * sigma_m[k, 0, ii, jj] > seed_window, shift=shift)
        if fit.unwalked is not None:  # a walk away from the fitted neighbours is a drift: back to the first fit
            first = fit.unwalked
            consensus = neighbour_consensus(first.q, torch.isfinite(first.sigma_q), ii, jj, tuple(depth.shape[-2:]))
            back = walk_rejected(fit.q, seed, consensus, fit.walked)
            fit = replace(fit, **{f: torch.where(back, getattr(first, f), getattr(fit, f))
                                  for f in ("q", "sigma_q", "noise")}, walked=fit.walked & ~back)
        f_fit, _ = scales.factors(slope)
        q, conf_q, biases[k, 0], _ = fuse_with_fit(seed, sigma_m[k, 0, ii, jj], fit.q, fit.sigma_q, slope, scales,
                                                   confidence_scale, ii, jj, tuple(depth.shape[-2:]))
        out_d[k] = (depth[k].to(torch.float64) * torch.exp(biases[k])).to(depth.dtype)  # the ring too
        out_d[k, 0, ii, jj] = (1.0 / q).to(depth.dtype)
        out_c[k, 0, ii, jj] = conf_q.to(confidence.dtype)
        fit_d[k, 0, ii, jj] = (1.0 / fit.q).to(depth.dtype)
        fit_raw[k, 0, ii, jj] = fit.sigma_q.to(torch.float64) / fit.q.to(torch.float64)
        fit_s[k, 0, ii, jj] = (fit_raw[k, 0, ii, jj] * f_fit).to(depth.dtype)
        slopes[k, 0, ii, jj] = slope.to(depth.dtype)
        chosen.append(fit.hypothesis)
        if margins is not None:
            pick = chosen_tiles(fit.sigma_q)
            if len(pick):
                margins[k] = float(likelihood_margins(y1, y2, camera, fit.hypothesis, [origins[int(t)] for t in pick],
                                                      tile, fit.q[pick], band=band, window=seed_window, step=q_step,
                                                      max_kernel=max_kernel,
                                                      shift=None if shift is None else shift[pick]).median())
            if margins[k] < AMBIGUITY_MARGIN:  # the whole image: its fits and the model's seeds alike
                out_c[k] = out_c[k].clamp_max(ambiguity_cap(confidence_scale))
    fitted = torch.zeros_like(depth, dtype=torch.bool)
    fitted[:, 0, ii, jj] = True
    pooled = None if pooling is None else pool_stage_map(out_d, out_c, confidence_scale, pooling)
    return LikelihoodStageResult(out_d, out_c, fit_d, fit_s, fitted, chosen, slopes, biases, fit_raw, pooled, margins,
                                 registrations)


class LikelihoodStage(nn.Module):
    """:func:`likelihood_stage` with its camera, grid, scales and PSF hypotheses bound.

    Args:
        camera: the camera the frames come from.
        tile, stride, confidence_scale: the model's grid and ``b0``.
        scales: the sigmas' factors (default: the raw sigmas).
        family: the measured PSF family (``"gaussian"``, ``"pillbox"``; ``None`` or
            ``"unknown"``: every shape).
        wavelength_m: the diffraction hypothesis's wavelength.
        hypotheses: the PSFs to profile over instead of the family's, e.g. the one a focus sweep
            measured (:func:`tdfd.calibration.psf_model.psf_model_from_frames`, a camera file's
            ``psf_model``: :meth:`~tdfd.dfd.psf_hypotheses.PsfHypothesis.from_dict`).
        black_level, seed_window, q_step, band, max_kernel, profile_tiles, walk, pooling, ambiguity, register:
            as for :func:`likelihood_stage`.
    """

    def __init__(self, camera: Camera, tile: int = 64, stride: int = 32, confidence_scale: float = 0.01, *,
                 scales: LikelihoodScales = LikelihoodScales(), family: str | None = None,
                 wavelength_m: float = WAVELENGTH_M, hypotheses: Sequence[PsfHypothesis] | None = None,
                 black_level: float = 0.0, seed_window: float = SEED_WINDOW, q_step: float = Q_STEP,
                 band: float = 0.25, max_kernel: int = 65, profile_tiles: int = PROFILE_TILES, walk: int = 0,
                 pooling: Callable[[torch.Tensor, torch.Tensor], torch.Tensor] | None = None,
                 ambiguity: bool = False, register: bool = False) -> None:
        super().__init__()
        if pooling is not None and not callable(pooling):
            raise InputError(f"pooling must be a callable (inverse_depth, scale) -> inverse_depth, got {pooling!r}")
        self.pooling = pooling
        self.camera, self.tile, self.stride = camera, int(tile), int(stride)
        self.confidence_scale, self.scales = float(confidence_scale), scales
        if hypotheses is not None:
            self.hypotheses = tuple(hypotheses)
            if not self.hypotheses or not all(isinstance(h, PsfHypothesis) for h in self.hypotheses):
                raise InputError(f"hypotheses must be one or more PsfHypothesis, got {hypotheses!r}")
        else:
            self.hypotheses = psf_hypotheses(camera, family, wavelength_m)
        self.options = dict(black_level=float(black_level), seed_window=float(seed_window), q_step=float(q_step),
                            band=float(band), max_kernel=int(max_kernel), profile_tiles=int(profile_tiles),
                            walk=int(walk), ambiguity=bool(ambiguity), register=bool(register))
        if walk < 0:
            raise InputError(f"walk must be >= 0, got {walk}")
        inverse_depth_grid(camera, seed_window, q_step)  # bad options fail here, not on the first pair
        if not 0.0 < band <= 0.5:
            raise InputError(f"band must lie in (0, 0.5] cycles/px, got {band}")

    @classmethod
    def for_model(cls, model: nn.Module, pool: bool = False, **kwargs) -> "LikelihoodStage":
        """The stage for a :class:`~tdfd.model.DFDModel`'s camera, grid and confidence scale; with
        ``pool`` its fused map is also pooled by the model's own structure pooling.

        Raises:
            InputError: ``pool`` for a model without a structure pooling.
        """
        if pool:
            if getattr(model, "structure_pooling", None) is None:
                raise InputError("pool asks for the model's structure pooling, and this model has none")
            kwargs["pooling"] = model.structure_pooling
        return cls(model.camera, model.tile, model.stride, model.confidence_scale, **kwargs)

    def forward(self, image_f1: torch.Tensor, image_f2: torch.Tensor, depth: torch.Tensor,
                confidence: torch.Tensor, black_level: float | None = None) -> LikelihoodStageResult:
        """:func:`likelihood_stage` of one batch; ``black_level`` replaces the bound one for this call."""
        options = self.options if black_level is None else {**self.options, "black_level": float(black_level)}
        with torch.no_grad():
            return likelihood_stage(image_f1, image_f2, depth, confidence, self.camera, tile=self.tile,
                                    stride=self.stride, confidence_scale=self.confidence_scale, scales=self.scales,
                                    hypotheses=self.hypotheses, pooling=self.pooling, **options)
