r"""The lens's whole defocus PSF from a focus sweep: shape, diffraction, astigmatism, spherical aberration.

:mod:`tdfd.calibration.psf_family` names the family (Gaussian or disk); a real lens's PSF is
neither exactly. The likelihood stage (:mod:`tdfd.dfd.likelihood_stage`) told the PSF's
diffraction and aberrations reaches what a model-based fit can (docs/BENCHMARKS.md, section
``likelihood_stage``: 1.24 % per tile with the PSF known against 1.48 % with its shape profiled
over the families); this module measures that PSF as a user can: from a focus sweep of a
textured target, the frames at known (commanded) ECVFL powers ``P_i``.

**The model.** One :class:`~tdfd.optics.aberrated_psf.PSFModel`: the power-exponential profile
``exp(-(r/alpha)^beta)`` between Gaussian (``beta = 2``) and disk (``beta -> inf``), an
astigmatic stretch ``a`` along an axis ``theta`` that swaps across focus, a spherical weight
``s`` of the blur's sign, and a blur scale ``k``: the RMS radius is ``k M (P - P*)`` (paper eq. 7
generalised), ``M`` the camera's px per dioptre, so the camera's ``mu`` keeps its meaning and
``k`` says how far the lens's RMS blur departs from it (1 where ``mu`` was calibrated on this
PSF; about 1.25 for a disk lens whose ``mu`` the Gaussian relative blur calibrated, as the
family's ``psf_sigma_scale``).

**What it cannot see, and need not.** A blur common to every frame, whatever the focus (the
diffraction of the aperture, the pixel's own area), multiplies both terms of the cross residual
and its noise spectrum alike, so it cancels from the likelihood: a sweep does not measure it, and
the likelihood stage, which fits the same residual, does not depend on it (up to its taper's
leakage). The fit reports no diffraction (``diffraction_px = 0``).

**The likelihood.** For every pair of frames ``(i, j)`` of a region in focus at ``P*``, the
cross residual ``k_j * f_i - k_i * f_j`` (:mod:`tdfd.dfd.cross_residual`) is texture-free at
the true PSF and ``P*``; its mean per-bin Whittle NLL over the band, with the tapered
residual's expected periodogram, summed over the pairs and regions, is minimised over the PSF's
parameters (shared) and each region's ``P*`` (its own: a chart need not be fronto-parallel) by
the simplex method (:mod:`tdfd.calibration.nelder_mead`), started from the best of a grid of
shapes and diffractions. The frames of one sweep share their exposure, so their noise is one
unknown variance, which the minimum does not depend on. Frames that straddle focus tell the
aberrations' signs apart: a sweep must bracket focus.

Example:
    >>> import numpy as np, torch
    >>> from tdfd import Camera
    >>> from tdfd.optics.aberrated_psf import PSFModel
    >>> from tdfd.optics.render import defocus_uniform
    >>> cam = Camera.preset("reference")
    >>> lens = PSFModel(5.0, 0.5, astigmatism=0.1, astigmatism_angle=0.4, spherical=-0.2)
    >>> g = torch.Generator().manual_seed(0)
    >>> sharp = torch.rand(1, 1, 150, 150, generator=g, dtype=torch.float64)
    >>> m, focus = cam.mu_px_per_m * cam.blur_scale_m_dpt, 2.2
    >>> def frame(p):
    ...     k = lens.kernels(torch.tensor([m * (p - focus)], dtype=torch.float64), 21)[0]
    ...     return torch.nn.functional.conv2d(sharp, k[None, None])[0, 0].numpy()
    >>> fit = psf_model_from_frames([[(frame(p), p) for p in (1.8, 2.0, 2.2, 2.4, 2.6)]], cam, region=96)
    >>> h = fit.hypothesis
    >>> round(fit.beta, 1), round(h.astigmatism, 2), round(h.astigmatism_angle, 2), round(h.spherical, 2)
    (5.0, 0.1, 0.4, -0.2)
    >>> round(fit.in_focus_power_dpt[0], 3)
    2.2
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np
import torch

from ..autofocus.cross_blur import evenly_thinned
from ..autofocus.evidence import sigma_px_per_dpt
from ..breathing import magnify
from ..camera import Camera
from ..dfd.cross_residual import band_weight, kernel_spectra, taper_lag_weight, tapered_power, tukey_window
from ..dfd.psf_hypotheses import PsfHypothesis
from ..errors import InputError
from .nelder_mead import nelder_mead
from .psf_family import MIN_FAMILY_FRAMES, capture_scenes, central_regions

__all__ = ["PsfModelFit", "psf_model_from_frames", "psf_model_from_captures", "MAX_MODEL_FRAMES", "MAX_MODEL_REGIONS",
           "MAX_ABERRATION"]

log = logging.getLogger(__name__)

#: a longer sweep is thinned to this many frames, evenly in power (the cost grows with the pairs)
MAX_MODEL_FRAMES = 7
#: at most this many regions per scene, the central ones
MAX_MODEL_REGIONS = 4
#: the largest astigmatism and |spherical| the fit considers (the PSF model's own limit is 0.5)
MAX_ABERRATION = 0.45
#: the shape parameter ``u = 2 / beta``: 1 Gaussian, 0 disk; at or below this the disk itself
U_DISK = 1.0 / 16.0
#: and its upper end (``beta = 1``, a Laplacian-like profile)
U_MAX = 2.0
#: the start grid of shapes (``u``)
START_SHAPES = (0.0, 0.25, 0.5, 0.75, 1.0, 1.5)
#: the PSF's parameters in the fit's vector (the regions' in-focus powers follow)
N_PSF = 5
#: the blur scale ``k`` (the PSF's RMS blur over the camera's) the fit considers: ``|log k|`` at most this
MAX_LOG_SCALE = math.log(2.0)
#: the start grid's blur scales (a disk lens whose ``mu`` the Gaussian relative blur calibrated: about 1.25)
START_SCALES = (1.0, 1.25)
#: the band of the likelihood (cycles/px), as the likelihood stage's
BAND = 0.25
#: the in-focus power's start search: steps of this many px of blur over the scene's span
START_STEP_PX = 0.25


@dataclass(frozen=True)
class PsfModelFit:
    """The PSF a focus sweep says the lens has (:func:`psf_model_from_frames`).

    Attributes:
        hypothesis: the PSF, as the likelihood stage takes it.
        cost: the fit's mean NLL per pair over the regions, in units of the frames' own noise
            variance (unknown; about that variance at the truth: only ratios of costs mean anything).
        family_cost_ratio: the plain Gaussian's or disk's cost, the better (no aberration, at
            the start's ``P*``), over the fit's: how much the measured PSF explains beyond the
            family (1 or more).
        in_focus_power_dpt: each region's in-focus power (commanded dpt).
        regions: regions fitted; frames: frames of the scenes fitted (after averaging and thinning).
        evaluations: likelihood evaluations; converged: whether the simplex converged.
    """

    hypothesis: PsfHypothesis
    cost: float
    family_cost_ratio: float
    in_focus_power_dpt: list[float] = field(default_factory=list)
    regions: int = 0
    frames: int = 0
    evaluations: int = 0
    converged: bool = False

    @property
    def beta(self) -> float:
        """The profile's exponent (2 Gaussian, ``inf`` disk)."""
        return self.hypothesis.model().beta

    def to_dict(self) -> dict[str, Any]:
        """The PSF as a camera file's ``psf_model`` holds it (:meth:`PsfHypothesis.from_dict` reads it)."""
        return self.hypothesis.to_dict()

    def summary(self) -> dict[str, Any]:
        """JSON-ready numbers for a camera file's calibration provenance."""
        return {"psf_model": self.to_dict(), "cost": self.cost, "family_cost_ratio": self.family_cost_ratio,
                "in_focus_power_dpt": list(self.in_focus_power_dpt), "regions": self.regions, "frames": self.frames,
                "evaluations": self.evaluations, "converged": self.converged}


def _hypothesis(x: np.ndarray) -> PsfHypothesis | None:
    """The PSF of the fit's parameters ``(u, a cos 2 theta, a sin 2 theta, s, log k)``; ``None`` outside their box."""
    u, ac, as_, s, log_k = (float(v) for v in x[:N_PSF])
    a = math.hypot(ac, as_)
    if not (0.0 <= u <= U_MAX and a < MAX_ABERRATION and abs(s) < MAX_ABERRATION and abs(log_k) <= MAX_LOG_SCALE):
        return None
    shape: str | float = "pillbox" if u <= U_DISK else ("gaussian" if u == 1.0 else 2.0 / u)
    return PsfHypothesis(shape, 0.0, a, 0.5 * math.atan2(as_, ac) % math.pi if a > 0 else 0.0, s, math.exp(log_k))


class _Region:
    """One region's frames, spectra and the fixed geometry of its residuals."""

    def __init__(self, frames: list[np.ndarray], powers: list[float], kernel: int) -> None:
        y = torch.from_numpy(np.stack(frames)).to(torch.float64)
        self.powers = torch.tensor(powers, dtype=torch.float64)
        self.shape = tuple(y.shape[-2:])
        self.spectra = torch.fft.rfft2(y)
        self.kernel = kernel
        half = kernel // 2
        self.crop = (half, self.shape[0] - half, half, self.shape[1] - half)
        mh, mw = self.crop[1] - self.crop[0], self.crop[3] - self.crop[2]
        taper = tukey_window(mh, mw)
        self.taper = taper / float((taper ** 2).mean().sqrt())
        self.weight = band_weight(mh, mw, BAND)
        self.lag_weight = taper_lag_weight(self.taper)  # once per region, not per evaluation
        n = len(frames)
        self.pairs = torch.tensor([(i, j) for i in range(n) for j in range(i + 1, n)], dtype=torch.long)

    def cost(self, hyp: PsfHypothesis, m: float, focus: float) -> float:
        """The mean per-bin NLL of every pair, summed (unit noise)."""
        sigma = m * (self.powers - focus)
        k = hyp.kernels(sigma, self.kernel)
        spec = kernel_spectra(k, self.shape)
        i, j = self.pairs[:, 0], self.pairs[:, 1]
        r = torch.fft.irfft2(spec[j] * self.spectra[i] - spec[i] * self.spectra[j], s=self.shape)
        y0, y1, x0, x1 = self.crop
        mh, mw = y1 - y0, x1 - x0
        big_r = torch.fft.rfft2(r[:, y0:y1, x0:x1] * self.taper)
        a = tapered_power(k, self.lag_weight)  # each kernel's |K|^2 through the taper
        terms = big_r.abs() ** 2 / (mh * mw) / (a[j] + a[i]).clamp_min(1e-300)
        return float(((terms * self.weight).sum((-1, -2)) / self.weight.sum()).sum())


def _usable_scenes(scenes: Sequence[Sequence[tuple[np.ndarray, float]]]) -> list[list[tuple[float, np.ndarray]]]:
    """Per scene with three distinct powers or more: its frames averaged per power, sorted and
    thinned to :data:`MAX_MODEL_FRAMES` (``(power, image)``)."""
    usable = []
    for k, frames in enumerate(scenes):
        groups: dict[float, list[np.ndarray]] = {}
        for im, p in frames:
            groups.setdefault(round(float(p), 6), []).append(np.asarray(im, dtype=np.float64))
        shapes = {im.shape for ims in groups.values() for im in ims}
        if len(shapes) != 1 or len(next(iter(shapes))) != 2:
            raise InputError(f"scene {k}: frames must be (H, W) of one shape, got {sorted(shapes)}")
        if len(groups) < MIN_FAMILY_FRAMES:
            log.info("scene %d: %d distinct powers, fewer than %d: not used for the PSF model", k, len(groups),
                     MIN_FAMILY_FRAMES)
            continue
        by_power = {p: np.mean(ims, axis=0) for p, ims in groups.items()}  # repeated frames: less noise
        if not all(np.isfinite(im).all() for im in by_power.values()):
            raise InputError(f"scene {k}: a frame has non-finite pixels")
        usable.append(evenly_thinned(sorted(by_power.items()), MAX_MODEL_FRAMES))
    if not usable:
        raise InputError(f"the PSF model needs a scene with at least {MIN_FAMILY_FRAMES} frames at distinct powers")
    return usable


def psf_model_from_frames(scenes: Sequence[Sequence[tuple[np.ndarray, float]]], camera: Camera, *,
                          region: int = 128, magnification_per_dpt: float = 0.0, max_regions: int = MAX_MODEL_REGIONS,
                          max_evaluations: int = 600) -> PsfModelFit:
    """The lens PSF that explains the frames of each scene best (module docstring).

    Args:
        scenes: per scene, its frames ``(image (H, W), power_dpt)`` at known (commanded) powers,
            one exposure, all of one shape; frames at one power are averaged (the fit's precision
            grows with the frames: the PSF's shape is a small effect against the noise of one
            frame); a scene with fewer than three distinct powers is left out, one with more than
            :data:`MAX_MODEL_FRAMES` thinned evenly. Linear frames; a black level cancels in the
            cross residual.
        camera: the calibrated camera (its ``M``, px of blur per dioptre).
        region: side (px) of the square regions fitted (at least 64).
        magnification_per_dpt: the lens's focus breathing, undone before the fit.
        max_regions: regions per scene, the central ones.
        max_evaluations: the simplex's budget of likelihood evaluations.

    Raises:
        InputError: no scene with three powers, frames of different shapes or non-finite ones,
            a region under 64 px or larger than the frames, a sweep too wide for the regions or
            one that brackets focus in no region, a bad budget.
    """
    if not region >= 64:
        raise InputError(f"region must be at least 64 px, got {region}")
    if not max_regions >= 1 or not max_evaluations >= 50:
        raise InputError(f"need max_regions >= 1 and max_evaluations >= 50, got {max_regions}, {max_evaluations}")
    m = sigma_px_per_dpt(camera)
    usable = _usable_scenes(scenes)
    regions: list[_Region] = []
    spans: list[tuple[float, float]] = []
    for frames in usable:
        powers = [p for p, _ in frames]
        shape = frames[0][1].shape
        if min(shape) < region:
            raise InputError(f"region {region} px is larger than the frames {shape}")
        ref = 1.0 + magnification_per_dpt * powers[0]
        images = [im if not magnification_per_dpt else magnify(im, ref / (1.0 + magnification_per_dpt * p))
                  for p, im in frames]
        # the kernels hold the blur of a P* at the span's centre plus a pixel (a sweep centred on focus);
        # a P* far off-centre truncates the outer frames' kernels (each renormalised)
        blur = m * (max(powers) - min(powers)) / 2 + 1.0
        kernel = PsfHypothesis("pillbox", 0.0, MAX_ABERRATION, 0.0, MAX_ABERRATION).kernel_size(blur)
        if kernel > region // 2:
            raise InputError(f"the sweep spans {blur:.1f} px of blur: its kernels ({kernel} px) need regions of at "
                             f"least {2 * kernel} px, got {region}")
        for roi in central_regions(shape, region, max_regions):
            crops = [im[roi.y: roi.y + roi.h, roi.x: roi.x + roi.w] for im in images]
            scale = float(np.mean(crops[0]))
            if not scale > 0:
                raise InputError("a region of the sweep has no light (mean <= 0)")
            regions.append(_Region([c / scale for c in crops], powers, kernel))
            spans.append((min(powers), max(powers)))
    gauss = PsfHypothesis("gaussian")
    focus = [_start_focus(r, gauss, m, span) for r, span in zip(regions, spans)]
    edge = START_STEP_PX / m  # a focus at the span's end: the sweep does not bracket it there
    inside = [k for k, (p, (a, b)) in enumerate(zip(focus, spans)) if a + edge < p < b - edge]
    if len(inside) < len(regions):
        log.warning("%d of %d regions have their focus at their sweep's end (a sweep must bracket focus): left out",
                    len(regions) - len(inside), len(regions))
    if not inside:
        raise InputError("no region's focus lies inside its sweep: a sweep for the PSF model must bracket focus")
    regions, spans, focus = [regions[k] for k in inside], [spans[k] for k in inside], [focus[k] for k in inside]
    starts = [np.array([u, 0.0, 0.0, 0.0, math.log(k)]) for u in START_SHAPES for k in START_SCALES]
    start_costs = [sum(r.cost(_hypothesis(x), m, p) for r, p in zip(regions, focus)) for x in starts]
    family = min(c for x, c in zip(starts, start_costs) if x[0] in (0.0, 1.0) and x[4] == 0.0)
    x0 = np.concatenate([starts[int(np.argmin(start_costs))], np.array(focus)])
    total0 = min(start_costs)
    lo, hi = np.array([s[0] for s in spans]), np.array([s[1] for s in spans])

    def objective(x: np.ndarray) -> float:
        hyp = _hypothesis(x)
        p = x[N_PSF:]
        if hyp is None or (p < lo).any() or (p > hi).any():
            return math.inf
        return sum(r.cost(hyp, m, float(pp)) for r, pp in zip(regions, p)) / total0

    step = np.concatenate([[0.2, 0.05, 0.05, 0.1, 0.05], np.full(len(regions), 0.1 / m)])
    res = nelder_mead(objective, x0, step, max_evaluations=max_evaluations, x_tol=1e-3, f_tol=1e-6)
    res2 = nelder_mead(objective, res.x, step / 4, max_evaluations=max(50, max_evaluations // 3), x_tol=1e-4,
                       f_tol=1e-7)  # a restart: the simplex may have collapsed on a ridge
    best = res2 if res2.value <= res.value else res
    hyp = _hypothesis(best.x)
    cost = best.value * total0
    n_pairs = sum(len(r.pairs) for r in regions)
    fit = PsfModelFit(hyp, cost / n_pairs, family / cost, [float(v) for v in best.x[N_PSF:]], len(regions),
                      sum(len(f) for f in usable), len(starts) + res.evaluations + res2.evaluations, res2.converged)
    log.info("PSF model: %s (the best family fits %.3fx worse over %d regions, %d evaluations)", fit.to_dict(),
             fit.family_cost_ratio, fit.regions, fit.evaluations)
    return fit


def _start_focus(region: _Region, hyp: PsfHypothesis, m: float, span: tuple[float, float]) -> float:
    """The region's in-focus power under ``hyp``: the best of a grid over the span, refined by a parabola."""
    step = START_STEP_PX / m
    grid = np.arange(span[0], span[1] + step / 2, step)
    costs = np.array([region.cost(hyp, m, float(p)) for p in grid])
    k = int(np.argmin(costs))
    if 0 < k < len(grid) - 1:
        c0, c1, c2 = costs[k - 1: k + 2]
        den = c0 - 2 * c1 + c2
        if den > 0:
            return float(grid[k] + 0.5 * step * (c0 - c2) / den)
    return float(grid[k])


def psf_model_from_captures(frames: Sequence[Any], camera_file: Any, region: int = 128, **kwargs: Any) -> PsfModelFit:
    """:func:`psf_model_from_frames` on capture-folder frames (:class:`~tdfd.capture.folder.CaptureFrame`),
    grouped into scenes as the calibration does (a scene's sweep and pair frames together), with
    the calibrated ``camera_file``'s camera and breathing; ``region`` shrinks to the frames'
    shorter side (a multiple of 32 px) on small frames.

    Raises:
        InputError: as :func:`psf_model_from_frames`.
    """
    scenes, region = capture_scenes(frames, region)
    return psf_model_from_frames(scenes, camera_file.camera, region=region,
                                 magnification_per_dpt=camera_file.magnification_per_dpt, **kwargs)
