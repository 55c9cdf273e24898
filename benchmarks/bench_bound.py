"""How accurate can any DFD estimator be on the refinement benchmark's planes? A Cramér-Rao bound.

Run from the repository root::

    .venv/bin/python -m benchmarks.bench_bound [--samples 256] [--model models/reference]

For every held-out plane of the ``refinement`` benchmark (same seed, same options, same
64/32 tile grid) it computes the Fisher information that the two noisy frames carry about
the plane's inverse depth ``q = 1/d``, and from it the Cramér-Rao lower bound on the depth
error of an unbiased estimator. The observation model, per 64x64 tile and spatial
frequency ``u`` (rectangular tile, circular blur, so that white noise is independent
across bins):

    G_i(u) = H_i(u; q) S(u) + N_i(u),   E|N_i(u)|^2 = nu_i = 64^2 var_i,   i = 1, 2,

with ``S`` the tile of the sharp scene as the sensor sees it (exposure and gain applied),
``H_i`` the optical transfer function of the sample's **own** PSF (shape, diffraction and
aberration as drawn, at the blur ``sigma_i(q)`` of paper eq. 4), and ``var_i`` the sensor's
variance (shot, read and quantisation noise, :meth:`tdfd.sensor.SensorModel.expected_variance`)
at the tile's mean level. The texture ``S(u)`` is unknown (a nuisance amplitude per bin, as
for any estimator that assumes nothing about the scene). Projecting it out gives, per bin,

    J(u) = 2 |S(u)|^2 (H1' H2 - H2' H1)^2 / (nu_2 H1^2 + nu_1 H2^2),   H' = dH/dq,

summed over the independent half of the spectrum. The bound on the relative depth error of
a tile is ``sqrt(1 / J) / q`` (a standard deviation); for a normal error its median
absolute value is 0.674 times that.

The lens PSF is itself unknown: ``data_synth`` draws its shape, diffraction and aberration
afresh for every sample (:data:`PSF_NUISANCES`). With those parameters ``eta`` added to
``theta = (q, eta)``, the per-bin information becomes the matrix

    J_jk(u) = 2 |S(u)|^2 Re(c_j conj(c_k)) / (nu_2 |H1|^2 + nu_1 |H2|^2),   c_j = dH1/dtheta_j H2 - dH2/dtheta_j H1,

and the bound on ``q`` is the ``qq`` entry of its inverse, with ``data_synth``'s spread of each
``eta`` added as prior information. Five versions:

* **per tile, PSF known**: one 64x64 tile's information, the PSF given;
* **per tile, PSF shared by the image**: a depth per tile, the PSF common to the image and
  learnt from all of its tiles: the best that a scene-agnostic estimator, such as the
  refinement CNN that sees the whole tile grid, can do;
* **per tile, PSF from the tile alone**: what a tile-local estimator can do;
* **per plane**, PSF known or unknown: the whole 256x256 plane's information (16 disjoint
  tiles summed), which bounds even an estimator that assumes the view is one
  fronto-parallel plane and pools every tile.

The benchmark scores a median over tiles, so for the per-tile bounds it also reports the
median that an unbiased estimator reaching the bound on every tile would score
(:func:`median_at_bound`). The bounds are optimistic for every real estimator: they know the
frames' noise levels, ignore clipping of over-exposed highlights, vignetting, breathing,
misregistration and frame gain jitter, and use no tile-boundary effects. Writes the ``bound``
section of ``docs/BENCHMARKS.md`` next to the refined model's measured errors on the same
planes.

Scenes with depth structure: :func:`tile_fisher` gives each tile the information of a
fronto-parallel plane at its own true depth (interpolated between depth nodes), which
:mod:`benchmarks.bench_structure` uses as a per-tile reference on slanted planes, smooth
surfaces and the faces of occlusion layouts away from their edges (its ``structure`` section).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import replace
from pathlib import Path

import torch
from tqdm import tqdm

from benchmarks.bench_refinement import BENCH_SEED, bench_tiles  # the refinement benchmark's planes
from benchmarks.report import ROOT, markdown_table, update_section
from data_synth import DefocusPairDataset
from data_synth.params import SynthConfig
from data_synth.psf import PSFModel, diffraction_sigma_px
from data_synth.psf import sample_psf_model as psf_model  # re-exported: the benchmarks' name
from tdfd import Camera
from tdfd.dfd import FourierRatioDFD
from tdfd.dfd.inverse_variance import MEDIAN_ABS_NORMAL
from tdfd.errors import InputError
from tdfd.model import DFDModel
from tdfd.optics.thin_lens import camera_sigmas
from tdfd.sensor import SensorModel
from training.config import EvalConfig
from training.losses import depth_relative_error

__all__ = ["plane_information", "plane_fisher", "tile_fisher", "otf_jacobian", "psf_prior_variance", "depth_variances", "median_at_bound", "otf", "ring_band", "sample_sensor", "main"]

TILE, STRIDE = 64, 32
MEDIAN_ABS = MEDIAN_ABS_NORMAL  # median |x| of a standard normal x
#: The lens PSF's parameters that ``data_synth`` draws afresh for every sample
#: (:func:`data_synth.params.draw_psf`) and that no estimator is told: the shape
#: ``kappa = 1 / beta`` (0 pillbox, 0.5 Gaussian), the diffraction variance ``sigma_d^2``
#: (px^2), the astigmatism ``a (cos 2 theta, sin 2 theta)`` and the spherical weight ``s``.
PSF_NUISANCES = ("shape", "diffraction", "astig_c", "astig_s", "spherical")
#: Samples per pixel and side of the bound's PSFs: fine enough that the kernels, hence the
#: OTFs' finite differences, vary smoothly with the shape (a hard-edged profile sampled at
#: pixel centres jumps as pixels cross its edge).
SUPERSAMPLE = 9
NUISANCE_STEPS = {"shape": 0.01, "astig_c": 0.01, "astig_s": 0.01, "spherical": 0.02}
#: The bounds that the benchmark reports, in table order, with their labels: :func:`depth_variances`'
#: five, and ``tile_band``, the PSF-shared bound of the bins in the analytic estimator's rings
#: (:func:`ring_band`), what a refinement of its ring features can at best reach.
VARIANTS = {"tile_known": "per tile, PSF known", "tile_shared": "per tile, PSF shared by the image",
            "tile_unknown": "per tile, PSF from the tile alone",
            "tile_band": "per tile, PSF shared, the estimator's rings only", "plane_known": "per plane, PSF known",
            "plane_unknown": "per plane, PSF unknown"}
BINS = ((0.30, 0.40), (0.40, 0.50), (0.50, 0.60), (0.60, 0.70), (0.70, 0.80), (0.80, 0.90), (0.90, 1.00))


def otf(model: PSFModel, sigma: float, size: int = TILE, supersample: int | None = None) -> torch.Tensor:
    """Optical transfer function ``(size, size)`` (complex; real for symmetric PSFs) of the
    PSF of signed blur ``sigma`` px, centred so that a delta PSF gives 1 everywhere
    (``supersample``: see :meth:`data_synth.psf.PSFModel.kernels`)."""
    k = model.kernels(torch.tensor([sigma], dtype=torch.float64), supersample=supersample)[0]
    n = k.shape[-1]
    if n > size:
        raise InputError(f"PSF of {n} px does not fit a {size} px tile")
    pad = torch.zeros(size, size, dtype=torch.float64)
    pad[:n, :n] = k
    pad = torch.roll(pad, (-(n // 2), -(n // 2)), (0, 1))  # kernel centre at pixel (0, 0)
    return torch.fft.fft2(pad)


def plane_information(camera: Camera, sharp: torch.Tensor, depth_m: float, params: dict,
                      dq: float = 1e-3) -> torch.Tensor:
    """Fisher information about ``q = 1/d`` (1/m^-2) of each tile of a fronto-parallel plane.

    Args:
        camera: the camera (blur per depth, eq. 4).
        sharp: the sharp radiance ``(H, W)`` of the plane (before the sensor).
        depth_m: the plane's distance.
        params: the sample's ``data_synth`` parameters (PSF, sensor, exposure).
        dq: finite-difference step of ``q`` in 1/m.

    Returns:
        ``(h, w)`` information of the 64/32 grid's tiles (``J`` in the module docs), with the
        PSF known.
    """
    return plane_fisher(camera, sharp, depth_m, params, nuisances=False, dq=dq)[..., 0, 0]


def _coords(model: PSFModel) -> list[float]:
    """The sample PSF's :data:`PSF_NUISANCES` coordinates."""
    kappa = 1.0 / model.beta if math.isfinite(model.beta) else 0.0
    two = 2.0 * model.astigmatism_angle
    return [kappa, model.diffraction_sigma_px**2, model.astigmatism * math.cos(two),
            model.astigmatism * math.sin(two), model.spherical]


def _with(model: PSFModel, name: str, value: float, coords: list[float]) -> PSFModel:
    """``model`` with one nuisance coordinate (shape or aberration) set to ``value``."""
    if name == "shape":
        return replace(model, shape=1.0 / value if value > 0 else "pillbox")
    c, s = coords[2], coords[3]
    if name == "astig_c":
        c = value
    elif name == "astig_s":
        s = value
    elif name == "spherical":
        return replace(model, spherical=value)
    return replace(model, astigmatism=math.hypot(c, s), astigmatism_angle=0.5 * math.atan2(s, c) % math.pi)


def otf_jacobian(camera: Camera, model: PSFModel, q: float, nuisances: bool = True, dq: float = 1e-3
                 ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Both frames' OTFs at inverse depth ``q`` and their derivatives.

    Returns:
        ``(H1, H2, dH1, dH2)``: ``(T, T)`` OTFs and ``(P, T, T)`` derivatives with respect to
        ``q`` (1/m) and, if ``nuisances``, the :data:`PSF_NUISANCES` coordinates (``P = 6``).
        The PSFs are supersampled :data:`SUPERSAMPLE` times. Shape and aberration by central
        differences (the shape one-sided next to the pillbox, where ``kappa`` cannot go below
        0); diffraction analytically, as the Gaussian factor ``exp(-2 pi^2 sigma_d^2 |f|^2)``
        it puts on the OTF.
    """
    def pair(m: PSFModel, qq: float) -> tuple[torch.Tensor, torch.Tensor]:
        s1, s2 = camera_sigmas(camera, 1.0 / qq)
        return otf(m, float(s1), supersample=SUPERSAMPLE), otf(m, float(s2), supersample=SUPERSAMPLE)

    h1, h2 = pair(model, q)
    (p1, p2), (m1, m2) = pair(model, q + dq), pair(model, q - dq)
    d1, d2 = [(p1 - m1) / (2 * dq)], [(p2 - m2) / (2 * dq)]
    if nuisances:
        coords = _coords(model)
        f = torch.fft.fftfreq(TILE, dtype=torch.float64)
        f2 = f[:, None] ** 2 + f[None, :] ** 2  # cycles^2 / px^2
        for i, name in enumerate(PSF_NUISANCES):
            if name == "diffraction":
                d1.append(-2.0 * math.pi**2 * f2 * h1)
                d2.append(-2.0 * math.pi**2 * f2 * h2)
                continue
            step = NUISANCE_STEPS[name]
            lo, hi = coords[i] - step, coords[i] + step
            if name == "shape" and lo < 0.5 * step:  # next to the pillbox: kappa >= 0
                lo, hi = 0.5 * step, 2.5 * step
            (a1, a2), (b1, b2) = pair(_with(model, name, hi, coords), q), pair(_with(model, name, lo, coords), q)
            d1.append((a1 - b1) / (hi - lo))
            d2.append((a2 - b2) / (hi - lo))
    return h1, h2, torch.stack(d1), torch.stack(d2)


def ring_band(min_bin: int, max_bin: int, size: int = TILE) -> torch.Tensor:
    """``(size, size)`` 0/1 mask of the DFT bins (``torch.fft`` order) whose ring ``round(|k|)``
    lies in ``[min_bin, max_bin]``: the rings :class:`tdfd.dfd.FourierRatioDFD` reads (2 .. 13 at
    64 px, 0.2 cycles/px), whose information an estimator built on its ring features can reach.

    Example:
        >>> m = ring_band(2, 13)
        >>> int(m[0, 0]), int(m[0, 1]), int(m[0, 2]), int(m[0, 13]), int(m[0, 14]), int(m[9, 9]), int(m[10, 10])
        (0, 0, 1, 1, 0, 1, 0)
    """
    if not 0 <= min_bin <= max_bin:
        raise InputError(f"need 0 <= min_bin <= max_bin, got {min_bin}, {max_bin}")
    k = torch.fft.fftfreq(size, dtype=torch.float64) * size
    ring = torch.round(torch.sqrt(k[:, None] ** 2 + k[None, :] ** 2))
    return ((ring >= min_bin) & (ring <= max_bin)).double()


def plane_fisher(camera: Camera, sharp: torch.Tensor, depth_m: float, params: dict, nuisances: bool = True,
                 dq: float = 1e-3, band: torch.Tensor | None = None) -> torch.Tensor:
    """Fisher information matrix of each tile of a fronto-parallel plane.

    The parameters are ``q = 1/d`` (1/m) and, if ``nuisances``, the sample PSF's
    :data:`PSF_NUISANCES` coordinates. Per bin, with ``c_j = dH1/dtheta_j H2 - dH2/dtheta_j H1``,

        J_jk(u) = 2 |S(u)|^2 Re(c_j conj(c_k)) / (nu_2 |H1|^2 + nu_1 |H2|^2),

    summed over the independent half of the spectrum (the module docs' ``J`` is ``J_qq``).

    ``band`` (optional, :func:`ring_band`) keeps only those bins: the information within an
    estimator's frequency band. A stack of ``N`` bands ``(N, T, T)`` gives each band's
    information from one evaluation of the OTFs and their derivatives.

    Returns:
        ``(h, w, P, P)`` for the 64/32 grid's tiles (``(N, h, w, P, P)`` for ``N`` bands);
        ``P = 1`` without nuisances, else 6.
    """
    weight = _tile_weights(sharp, params)
    if band is not None:
        if band.dim() not in (2, 3) or band.shape[-2:] != weight.shape[-2:]:
            raise InputError(f"band must be ({TILE}, {TILE}) or (N, {TILE}, {TILE}), got {tuple(band.shape)}")
        weight = weight * band if band.dim() == 2 else weight[None] * band[:, None, None]
    return _fisher_at(camera, psf_model(params), 1.0 / depth_m, weight, nuisances, dq)


def sample_sensor(params: dict) -> tuple[SensorModel, float]:
    """The noise model of a ``data_synth`` sample's sensor (vignetting aside) and its output
    units per unit radiance (the slope of its mean response, far from clipping)."""
    sensor = SensorModel(full_well_e=params["full_well_e"], read_noise_e=params["read_noise_e"], bits=params["bits"],
                         black_level_dn=params["black_level_dn"], gain=params["gain"], exposure=params["exposure"])
    lo, hi = sensor.expected_mean(torch.tensor([0.0, 1e-3], dtype=torch.float64))
    return sensor, float(hi - lo) / 1e-3


def _tile_weights(sharp: torch.Tensor, params: dict) -> torch.Tensor:
    """Per tile and bin, ``2 |S(u)|^2 / nu``: ``(h, w, T, T)``, the texture's power over the
    tile's noise power (the part of :func:`plane_fisher` that does not depend on ``q``)."""
    sensor, scale = sample_sensor(params)
    x = sharp.double() * scale
    tiles = x.unfold(0, TILE, STRIDE).unfold(1, TILE, STRIDE)  # (h, w, T, T)
    mean = tiles.mean((-1, -2))
    var = sensor.expected_variance(mean / scale)  # output variance at the tile's mean level
    # frame 2 has the same mean level (blur keeps the mean); the two frames' noise is alike
    spec = torch.fft.fft2(tiles - mean[..., None, None]).abs() ** 2  # |S(u)|^2, DC removed
    nu = (TILE * TILE) * var
    return 2.0 * spec / nu[..., None, None]


def _fisher_at(camera: Camera, model: PSFModel, q: float, weight: torch.Tensor, nuisances: bool, dq: float
               ) -> torch.Tensor:
    """:func:`plane_fisher` of every tile as if at inverse depth ``q``, from :func:`_tile_weights`
    ``(..., T, T)`` (leading dimensions kept: several weightings of the same tiles, e.g. bands,
    share one OTF Jacobian)."""
    h1, h2, d1, d2 = otf_jacobian(camera, model, q, nuisances, dq)
    c = d1 * h2 - d2 * h1  # (P, T, T)
    cross = (c[:, None] * c.conj()[None]).real  # (P, P, T, T)
    inv = 1.0 / (h1.abs() ** 2 + h2.abs() ** 2).clamp_min(1e-300)
    return 0.5 * torch.einsum("...uv,jkuv->...jk", weight, cross * inv)  # a real tile's spectrum counts each bin twice


def tile_fisher(camera: Camera, sharp: torch.Tensor, tile_depth_m: torch.Tensor, params: dict, nuisances: bool = True,
                dq: float = 1e-3, node_step: float = 0.02) -> torch.Tensor:
    """:func:`plane_fisher` with a depth per tile: each tile as a fronto-parallel plane at its own depth.

    For scenes with depth structure (slanted planes, smooth surfaces, the faces of a
    piecewise-planar layout away from its edges) this is the information of a tile that is
    locally fronto-parallel at its true (window-weighted) depth: a reference, not a strict
    bound, since it leaves out the blur's variation across the tile. To first order the slant
    is odd about the tile centre and the depth even, so the two decouple and the slant as a
    nuisance costs little; a curved surface's relief inside the tile is ignored.

    The OTFs depend on ``q = 1/d`` alone, so they are computed on nodes spaced at most
    ``node_step`` (1/m) over the image's range of ``q`` and each tile's information is
    interpolated linearly in ``q`` between the two nodes around it (the texture weights, which
    do not depend on ``q``, are computed once).

    Args:
        camera, sharp, params, nuisances, dq: as for :func:`plane_fisher`.
        tile_depth_m: ``(h, w)`` each tile's depth in metres (the 64/32 grid of ``sharp``).
        node_step: largest spacing of the interpolation nodes in 1/m.

    Returns:
        ``(h, w, P, P)`` as :func:`plane_fisher`.

    Raises:
        InputError: ``tile_depth_m`` is not the grid's shape, or not finite and positive.
    """
    weight = _tile_weights(sharp, params)
    if tile_depth_m.shape != weight.shape[:2]:
        raise InputError(f"tile_depth_m {tuple(tile_depth_m.shape)} does not match the tile grid {tuple(weight.shape[:2])}")
    if not bool(torch.isfinite(tile_depth_m).all()) or not bool((tile_depth_m > 0).all()):
        raise InputError("tile_depth_m must be finite and positive")
    if not node_step > 0:
        raise InputError(f"node_step must be > 0, got {node_step}")
    q = 1.0 / tile_depth_m.double()
    q_lo, q_hi = float(q.min()), float(q.max())
    n = max(1, math.ceil((q_hi - q_lo) / node_step)) + 1 if q_hi > q_lo else 1
    nodes = torch.linspace(q_lo, q_hi, n, dtype=torch.float64) if n > 1 else torch.tensor([q_lo], dtype=torch.float64)
    model = psf_model(params)
    if n == 1:
        return _fisher_at(camera, model, q_lo, weight, nuisances, dq)
    pos = ((q - q_lo) / (q_hi - q_lo) * (n - 1)).clamp(0, n - 1)
    k = pos.floor().long().clamp(max=n - 2)  # each tile lies between nodes k and k + 1
    t = (pos - k)[..., None, None]
    p = 6 if nuisances else 1
    out = torch.zeros(*q.shape, p, p, dtype=torch.float64)
    for node in range(n):  # only the tiles next to a node need its information
        lower, upper = k == node, k == node - 1
        near = lower | upper
        if not bool(near.any()):
            continue
        f = _fisher_at(camera, model, float(nodes[node]), weight[near][:, None], nuisances, dq)[:, 0]
        w = torch.where(lower[near][:, None, None], 1.0 - t[near], t[near])
        out[near] += w * f
    return out


def psf_prior_variance(cfg: SynthConfig, camera: Camera) -> torch.Tensor:
    """Variance ``(5,)`` of each :data:`PSF_NUISANCES` coordinate over ``data_synth``'s draws
    (:func:`data_synth.params.draw_psf`): the spread that an estimator knows in advance."""
    moments = []  # (E kappa, E kappa^2) of each shape
    for shape in cfg.psf_shapes:
        if shape == "beta":
            b0, b1 = cfg.beta_range
            span = math.log(b1 / b0)
            moments.append(((1 / b0 - 1 / b1) / span, (1 / b0**2 - 1 / b1**2) / (2 * span)))
        else:
            k = 0.5 if shape == "gaussian" else 0.0 if shape == "pillbox" else 1.0 / float(shape)
            moments.append((k, k * k))
    mean_k = sum(m for m, _ in moments) / len(moments)
    var_k = sum(m2 for _, m2 in moments) / len(moments) - mean_k**2
    f_number = camera.focal_lengths_m[0] / camera.aperture_m
    lam = torch.linspace(*cfg.wavelength_range_m, 201, dtype=torch.float64)
    t = torch.tensor([diffraction_sigma_px(f_number, float(v), camera.pixel_pitch_m) ** 2 for v in lam])
    p = cfg.diffraction_prob
    var_t = p * float((t**2).mean()) - (p * float(t.mean())) ** 2
    pa = cfg.aberration_prob
    var_ast = pa * cfg.astigmatism_max**2 / 3.0 / 2.0  # a uniform in [0, max], angle uniform
    var_sph = pa * cfg.spherical_max**2 / 3.0
    return torch.tensor([var_k, var_t, var_ast, var_ast, var_sph], dtype=torch.float64)


def depth_variances(fisher: torch.Tensor, prior_var: torch.Tensor) -> dict[str, torch.Tensor]:
    """Cramér-Rao variances of ``q`` (1/m^2) of a plane's tiles and of the whole plane, five ways.

    Args:
        fisher: ``(h, w, 6, 6)`` from :func:`plane_fisher` (``q`` first, then the nuisances).
        prior_var: ``(5,)`` from :func:`psf_prior_variance`; its inverse is added to the
            nuisances' information (a Gaussian stand-in for ``data_synth``'s prior).

    Returns:
        ``tile_known`` ``(h, w)``: PSF known; ``tile_shared`` ``(h, w)``: depth per tile, PSF
        unknown but common to the image (learnt from its 16 disjoint tiles, each with its own
        depth); ``tile_unknown`` ``(h, w)``: PSF learnt from the tile alone; and for the whole
        plane (one depth, 16 disjoint tiles) ``plane_known`` and ``plane_unknown`` (scalars).
    """
    jqq, jqn = fisher[..., 0, 0], fisher[..., 0, 1:]
    disjoint = fisher[::2, ::2].reshape(-1, *fisher.shape[-2:])
    # nuisance information left once each disjoint tile's own depth is projected out
    left = disjoint[:, 1:, 1:] - disjoint[:, 1:, :1] * disjoint[:, :1, 1:] / disjoint[:, :1, :1].clamp_min(1e-300)
    cov_n = torch.linalg.inv(left.sum(0) + torch.diag(1.0 / prior_var))
    b = jqn / jqq.clamp_min(1e-300)[..., None]  # (h, w, 5)
    plane = disjoint.sum(0)
    return {
        "tile_known": 1.0 / jqq.clamp_min(1e-300),
        "tile_shared": 1.0 / jqq.clamp_min(1e-300) + torch.einsum("hwi,ij,hwj->hw", b, cov_n, b),
        "tile_unknown": _schur_variance(fisher, prior_var),
        "plane_known": 1.0 / plane[0, 0],
        "plane_unknown": _schur_variance(plane, prior_var),
    }


def _schur_variance(fisher: torch.Tensor, prior_var: torch.Tensor) -> torch.Tensor:
    """``[(J + prior)^-1]_qq`` as ``1 / (J_qq - J_qn (J_nn + prior)^-1 J_nq)``: finite (huge)
    for a tile without information, where the whole matrix would be singular."""
    jnn = fisher[..., 1:, 1:] + torch.diag(1.0 / prior_var)
    jnq = fisher[..., 1:, :1]
    lost = (jnq.transpose(-1, -2) @ torch.linalg.solve(jnn, jnq))[..., 0, 0]
    return 1.0 / (fisher[..., 0, 0] - lost).clamp_min(1e-300)


def median_at_bound(std: torch.Tensor) -> float:
    """Median of ``|e|`` over tiles whose errors ``e`` are normal with standard deviations ``std``.

    The score on this benchmark (a median over tiles) of an unbiased estimator that reaches
    the bound on every tile: the ``m`` at which the tiles' mean ``P(|e| <= m)`` is one half.

    Example:
        >>> round(median_at_bound(torch.tensor([1.0, 1.0])), 4)  # one normal: 0.6745 sigma
        0.6745
        >>> round(median_at_bound(torch.tensor([0.01] * 98 + [1e150] * 2)), 4)  # tiles with no information
        0.0069
    """
    std = std.double().flatten().clamp_min(1e-300)
    # an upper end that holds whatever the tail: at m = 5 s_75 three quarters of the
    # tiles (sigma <= s_75) each have P(|e| <= m) >= erf(5 / sqrt 2) ~ 1, so the mean is >= 0.75 > 1/2.
    # (A few tiles with no information have sigmas near 1e150; a 99th percentile start would put the
    # search out of reach of 100 halvings.)
    lo, hi = 0.0, 5.0 * float(std.quantile(0.75))
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        if float(torch.erf(mid / (std * math.sqrt(2.0))).mean()) < 0.5:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--samples", type=int, default=256, help="textured planes (the refinement benchmark's first N)")
    p.add_argument("--size", type=int, default=256, help="image side in px")
    p.add_argument("--model", default=str(ROOT / "models" / "reference"), help="model whose errors are compared ('' none)")
    p.add_argument("--no-write", action="store_true", help="print only; leave docs/ alone")
    args = p.parse_args(argv)
    torch.set_num_threads(2)
    camera = Camera.preset("reference")
    ev = EvalConfig(samples=args.samples, seed=BENCH_SEED, height=args.size, width=args.size)
    ds = DefocusPairDataset(size=args.size, camera=camera, seed=BENCH_SEED, tile=TILE, stride=STRIDE,
                            return_sharp=True, **ev.options)
    prior_var = psf_prior_variance(SynthConfig(), camera)
    rings = FourierRatioDFD(camera, tile=TILE, stride=STRIDE)  # the analytic estimator's default rings
    band = ring_band(rings.min_bin, rings.spectra.max_bin)
    every_and_band = torch.stack([torch.ones_like(band), band])  # both from one evaluation of the OTFs' derivatives
    t0 = time.perf_counter()
    rows = []  # per plane: depth, per-tile relative std (four ways), plane relative std (two ways)
    for i in tqdm(range(args.samples), desc="bound", mininterval=5.0):
        s = ds[i]
        prm = s["params"]
        if prm["layout"] != "plane":
            continue
        d = float(s["tile_depth"].median())
        every, in_band = plane_fisher(camera, s["sharp"][0], d, prm, band=every_and_band)
        var = depth_variances(every, prior_var)
        var["tile_band"] = depth_variances(in_band, prior_var)["tile_shared"]
        rel = {k: (v.sqrt() * d).flatten() for k, v in var.items()}  # std of q / q = relative depth std
        family = json.loads(prm["details"])["textures"][0]["family"]
        rows.append({"depth": d, "index": i, "family": family, **rel})
    wall = time.perf_counter() - t0
    keep = [r for r in rows if 0.3 <= r["depth"] <= 1.0]

    measured = None
    if args.model:
        measured = bench_tiles(DFDModel.load(args.model), args.samples, args.size)

    def pct(x: float) -> str:
        return f"{100 * x:.2f} %"

    def gather(sel: list[dict], key: str) -> torch.Tensor:
        return torch.cat([r[key] for r in sel])

    if measured is not None:  # per plane and tile, the signed relative depth errors
        tr = measured["true"].reshape(args.samples, -1)
        signed = (measured["refined"].reshape(args.samples, -1) - tr) / tr
        signed_analytic = (measured["analytic"].reshape(args.samples, -1) - tr) / tr

    def shared(errors: torch.Tensor, sel: list[dict]) -> torch.Tensor:
        """Per plane of ``sel``, the error every tile shares: |median signed tile error|."""
        return errors[torch.tensor([r["index"] for r in sel])].median(1).values.abs()

    table = []
    for lo, hi in BINS:
        sel = [r for r in keep if lo <= r["depth"] < hi or (hi == 1.0 and r["depth"] == 1.0)]
        if not sel:
            continue
        row = [f"{lo:.2f}-{hi:.2f}", len(sel)] + [pct(MEDIAN_ABS * float(gather(sel, k).median())) for k in VARIANTS]
        if measured is not None:
            t = measured["true"]
            m = (t >= lo) & ((t < hi) if hi < 1.0 else (t <= hi))
            row += [pct(float(depth_relative_error(measured[k], t)[m].median())) for k in ("refined", "analytic")]
            row.append(pct(float(shared(signed, sel).median())))
        table.append(row)
    families = []  # per texture family: where the refinement falls short of the bound
    if measured is not None:
        for name in sorted({r["family"] for r in keep}):
            sel = [r for r in keep if r["family"] == name]
            idx = torch.tensor([r["index"] for r in sel])
            refined, analytic = shared(signed, sel), shared(signed_analytic, sel)
            families.append([name, len(sel), pct(MEDIAN_ABS * float(gather(sel, "tile_shared").median())),
                             pct(MEDIAN_ABS * float(gather(sel, "tile_band").median())),
                             pct(float(signed[idx].abs().median())),
                             pct(MEDIAN_ABS * float(gather(sel, "plane_unknown").median())),
                             pct(float(refined.median())), pct(float(analytic.median())),
                             f"{int((refined > analytic + 0.05).sum())}"])
    summary: dict = {"planes": len(keep), "tiles": int(gather(keep, "tile_known").numel()), "wall_s": round(wall, 1)}
    for k in VARIANTS:
        std = gather(keep, k)
        summary[f"{k}_median"] = MEDIAN_ABS * float(std.median())
        summary[f"{k}_share_le_1pct"] = float((MEDIAN_ABS * std <= 0.01).double().mean())
        if k.startswith("tile"):
            summary[f"{k}_score_at_bound"] = median_at_bound(std)
    if measured is not None:
        tr = measured["true"]
        m = (tr >= 0.3) & (tr <= 1.0)
        for k in ("refined", "analytic"):
            summary[f"{k}_median"] = float(depth_relative_error(measured[k], tr)[m].median())
    print(json.dumps(summary, indent=2))
    header = ["distance (m)", "planes", *VARIANTS.values()]
    if measured is not None:
        header += ["refined, measured", "analytic, measured", "refined, shared per plane"]
    for row in table:
        print(" | ".join(str(v) for v in row))
    if args.no_write:
        return 0
    body = (
        f"The refinement benchmark's {len(keep)} held-out planes in 0.3-1.0 m ({summary['tiles']} tiles of 64 px, "
        f"first {args.samples} samples, seed {BENCH_SEED}, full realism; see `refinement`). For each plane the Fisher "
        "information that its two noisy frames carry about the inverse depth, with the sample's own PSF, the "
        "sensor's shot, read and quantisation noise at each tile's mean level, and the texture unknown per spatial "
        "frequency. Its Cramér-Rao bound, as a median absolute relative depth error (0.674 sigma), is what an "
        "unbiased estimator cannot beat. The PSF that `data_synth` draws for each sample (shape "
        "`kappa = 1/beta` between pillbox and Gaussian, diffraction, astigmatism, spherical aberration) is either "
        "known, or a nuisance that the estimator must learn from the frames, with `data_synth`'s spread of each "
        "parameter as prior information (a Gaussian of the same variance):\n\n"
        "- *per tile, PSF known*: one 64x64 tile's information, the PSF given;\n"
        "- *per tile, PSF shared by the image*: a depth per tile, the PSF unknown but common to the whole image and "
        "learnt from all its tiles (what a scene-agnostic estimator such as the CNN can at best do);\n"
        "- *per tile, PSF from the tile alone*: the tile's depth and PSF from that tile only;\n"
        f"- *per tile, PSF shared, the estimator's rings only*: as PSF shared, with only the bins of the analytic "
        f"estimator's rings ({rings.min_bin}-{rings.spectra.max_bin} bins, up to "
        f"{rings.spectra.max_bin / TILE:.2f} cycles/px), the information that a refinement of its ring features "
        "can reach;\n"
        "- *per plane*: one depth for the whole plane (16 disjoint tiles), which bounds only an estimator that "
        "assumes the whole view is one fronto-parallel plane.\n\n"
        "A common blur of both frames (the diffraction) drops out of their ratio and costs nothing. The bounds "
        "remain optimistic: the noise levels known; no clipping, vignetting, breathing, misregistration or frame "
        "gain jitter (a frame's gain is pinned by its mean level, which blur keeps). The PSFs are sampled "
        f"{SUPERSAMPLE}x per pixel and side, so that their derivatives in the shape are smooth (the renderer's "
        "pixel-centre samples of hard-edged shapes jump as pixels cross the edge); with the renderer's own "
        "sampling the PSF-known bound was 1.00 % rather than 1.05 %.\n\n"
        + markdown_table(header, table) + "\n\n"
        + ("*refined, shared per plane*: the median over the bin's planes of the refined estimate's |median "
           "signed tile error|, the error that every tile of a plane shares and that pooling its tiles cannot "
           "remove, beside the per-plane bounds.\n\n" if measured is not None else "")
        + "Medians over all tiles (per plane: over planes); *at the bound*: the median absolute error that an "
        "unbiased estimator reaching the bound on every tile would score on this benchmark (the median of the "
        "mixture of the tiles' normal errors):\n\n"
        + markdown_table(["bound", "median", "at the bound", "share <= 1 %"], [
            [name, pct(summary[f"{k}_median"]),
             pct(summary[f"{k}_score_at_bound"]) if k.startswith("tile") else "-",
             f"{100 * summary[f'{k}_share_le_1pct']:.0f} %"]
            for k, name in VARIANTS.items()]) + "\n"
    )
    if measured is not None:
        body += (f"\nMeasured on the same tiles (`{Path(args.model).name}`): refined {pct(summary['refined_median'])}, "
                 f"analytic {pct(summary['analytic_median'])}.\n")
        body += ("\nPer texture family (the plane's first texture): the bound per tile (PSF shared by the image; "
                 "all bins, and the analytic estimator's rings only) against the refined model's median error per "
                 "tile, and the bound per plane (PSF unknown) against the *shared* error of the refined and the "
                 "analytic estimates, the median over planes of |median signed tile error|, which pooling the "
                 "plane's tiles cannot remove; the last column counts the planes whose refined shared error exceeds "
                 "the analytic's by more than 5 points (the refinement moved the plane off the analytic estimate):\n\n"
                 + markdown_table(["family", "planes", "per tile: bound", "per tile: bound, rings", "per tile: refined",
                                   "per plane: bound", "per plane: refined, shared", "per plane: analytic, shared",
                                   "planes refined > analytic + 5 points"], families) + "\n")
    body += f"\nWall time: {wall:.0f} s.\n"
    update_section("bound", "Information bound on the refinement benchmark (Cramér-Rao)", body,
                   f".venv/bin/python -m benchmarks.bench_bound --samples {args.samples}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
