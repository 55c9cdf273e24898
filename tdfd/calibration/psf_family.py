r"""The lens's PSF family (a Gaussian or a uniform disk) from calibration captures.

A lens's defocus PSF has one shape, fixed by its optics: a near-Gaussian blob where
aberrations and diffraction smooth it, a uniform disk (pillbox, the geometric blur of
paper eq. 3) where they do not. The autofocus controller that knows it fits that family
only (:class:`tdfd.autofocus.dfd.DFDController`, ``psf_family``): a periodic texture seen
through a disk can be explained by a Gaussian at a wrong power, and the other way round,
from two or three frames (docs/BENCHMARKS.md, reliability).

Several frames of one textured scene at known powers (a focus sweep, or pairs) decide it:
their cross-blur residual (:func:`tdfd.autofocus.cross_blur.cross_blur_focus`: each frame
blurred by the other's PSF gives the same image whatever the texture) is at its noise
floor for the lens's family at the scene's in-focus power, and well above it for the other
family at any power, once the frames span the disk's first MTF zero. Each square region of
the frames is searched on its own (``region`` px, so that depth may vary a little across
the scene) for its in-focus power within the scene's span of powers (a sweep brackets
focus), in steps of a quarter pixel of blur. The disk family has its own blur per dioptre, a
scale of the camera's ``M`` fitted on the central region (the calibrated ``mu`` is what the
Gaussian relative blur measures, about 0.8x a disk's RMS radius); the Gaussian's is 1. The
families' costs are summed over the regions and scenes, and a family is named only when the
other's total is at least ``min_ratio`` times its own and it fits more of the regions best.

A texture with detail at every scale (a printed random-noise chart) decides it best: on the
simulated bench (``python -m benchmarks.bench_psf_family``, 9-frame sweeps over +-3 px of
blur) band-limited charts name the right family in 3 of 4 sweeps per optics (the other family
up to 2.33x the cost; 1.01x on the chart left undecided), dead-leaves scenes in 2 of 4, and
no sweep names the wrong one.

Frames of a sweep differ by the lens's focus breathing: each frame is magnified back to
the scale of the scene's first frame (:func:`tdfd.breathing.magnify`) before the search.

Example:
    >>> import numpy as np, torch
    >>> from tdfd import Camera
    >>> from tdfd.optics.render import defocus_uniform
    >>> cam = Camera.preset("reference")
    >>> sharp = torch.from_numpy(np.random.default_rng(0).random((1, 1, 160, 160)))
    >>> focus, m = 2.2, cam.mu_px_per_m * cam.blur_scale_m_dpt
    >>> def frame(p):  # a disk of the thin lens's blur, sigma = M |P - P*|
    ...     s = torch.tensor([m * abs(p - focus)], dtype=torch.float64)
    ...     return defocus_uniform(sharp, s, "pillbox")[0, 0].numpy()
    >>> fit = psf_family_from_frames([[(frame(p), p) for p in (1.6, 1.9, 2.2, 2.5, 2.8)]], cam, region=128)
    >>> fit.family, fit.cost_ratio > 2
    ('pillbox', True)
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from ..autofocus.cross_blur import PSF_FAMILIES, cross_blur_focus, evenly_thinned
from ..autofocus.evidence import sigma_px_per_dpt
from ..autofocus.roi import Roi
from ..breathing import magnify
from ..camera import Camera
from ..errors import InputError
from .fit import group_scenes

__all__ = ["PsfFamilyFit", "psf_family_from_frames", "psf_family_from_captures", "MIN_FAMILY_RATIO",
           "MIN_FAMILY_FRAMES", "MAX_FAMILY_FRAMES", "MAX_FAMILY_REGIONS", "central_regions",
           "capture_scenes"]

log = logging.getLogger(__name__)

#: the other family's summed cost must be at least this many times the named family's (simulated
#: bench, ``benchmarks.bench_psf_family``: named in 10 of 16 sweeps, never the wrong family)
MIN_FAMILY_RATIO = 1.1
#: fewest frames of one scene (at distinct powers) that take part
MIN_FAMILY_FRAMES = 3
#: a longer sweep is thinned to this many frames, evenly in power (the search costs grow with the pairs)
MAX_FAMILY_FRAMES = 9
#: at most this many regions per scene, the central ones
MAX_FAMILY_REGIONS = 9
#: the search's coarse step in px of Gaussian blur sigma (its fine step a tenth of it)
SEARCH_STEP_PX = 0.25
#: the blur scales tried per family (times the camera's ``M``), then refined within one step (x ``SCALE_GRID ** (1/8)``)
SCALE_GRID = np.geomspace(0.5, 2.0, 9)
#: the scale is fitted on the frames blurred by at least this much (px of Gaussian sigma)
SCALE_MIN_BLUR_PX = 1.0


@dataclass(frozen=True)
class PsfFamilyFit:
    """What the captures say about the PSF family (:func:`psf_family_from_frames`).

    Attributes:
        family: ``"gaussian"`` or ``"pillbox"``, or ``None`` when neither fits
            ``min_ratio`` times better than the other (or no region could be searched).
        cost_ratio: the other family's summed cost over the better family's (1 or more;
            ``nan`` with no region).
        costs: each family's cost summed over the regions searched.
        regions: regions searched (their in-focus power inside the scene's span for both families).
        votes: per family, the regions it fitted best.
        in_focus_power_dpt: per family, the median over the regions of its best in-focus power.
        sigma_scale: per family, its RMS blur per dioptre over the camera's ``M`` (median over
            the scenes): a disk lens's calibrated ``mu`` is the Gaussian relative blur's, about
            0.8x its disk's (:func:`tdfd.autofocus.cross_blur.cross_blur_focus` ``sigma_scale``).
    """

    family: str | None
    cost_ratio: float
    costs: dict[str, float] = field(default_factory=dict)
    regions: int = 0
    votes: dict[str, int] = field(default_factory=dict)
    in_focus_power_dpt: dict[str, float] = field(default_factory=dict)
    sigma_scale: dict[str, float] = field(default_factory=dict)

    @property
    def family_sigma_scale(self) -> float:
        """The named family's blur scale (what a camera file's ``psf_sigma_scale`` holds); 1 without one."""
        return self.sigma_scale[self.family] if self.family is not None else 1.0

    def summary(self) -> dict[str, Any]:
        """JSON-ready numbers for a camera file's calibration provenance."""
        return {"family": self.family, "cost_ratio": self.cost_ratio, "costs": dict(self.costs),
                "regions": self.regions, "votes": dict(self.votes),
                "in_focus_power_dpt": dict(self.in_focus_power_dpt), "sigma_scale": dict(self.sigma_scale)}


def central_regions(shape: tuple[int, int], region: int, limit: int = MAX_FAMILY_REGIONS) -> list[Roi]:
    """Non-overlapping ``region`` px squares tiling the frame's centre, at most ``limit`` of
    them (the nearest the centre first)."""
    h, w = shape
    ny, nx = h // region, w // region
    y0, x0 = (h - ny * region) // 2, (w - nx * region) // 2
    rois = [Roi(x0 + j * region, y0 + i * region, region, region) for i in range(ny) for j in range(nx)]
    rois.sort(key=lambda r: (r.x + r.w / 2 - w / 2) ** 2 + (r.y + r.h / 2 - h / 2) ** 2)
    return rois[:limit]


def _fit_scale(search: Any, roi: Roi, family: str, frames: list, m: float) -> float:
    """``family``'s blur scale on ``roi``: the best of :data:`SCALE_GRID`, refined within one step
    on all frames, then refined again within one step on the frames blurred by at least
    :data:`SCALE_MIN_BLUR_PX` (near focus the pixel grid's own blur, a constant variance rather
    than a scale, biases it: on the simulated bench's seed-0 chart the disk's scale came out
    1.022 on all frames and 1.000 without them, in an ad-hoc check; alone, the far frames can
    trade the scale against the in-focus power)."""
    coarse = min(SCALE_GRID, key=lambda c: search(roi, family, c).cost)
    fits = [(c, search(roi, family, c)) for c in coarse * SCALE_GRID ** 0.125]
    scale, fit = min(fits, key=lambda cf: cf[1].cost)
    far = [fr for fr in frames if scale * m * abs(fr[1] - fit.power_dpt) >= SCALE_MIN_BLUR_PX]
    if len({p for _, p in far}) < MIN_FAMILY_FRAMES:
        return float(scale)
    return float(min(scale * SCALE_GRID ** 0.125, key=lambda c: search(roi, family, c, far).cost))


def psf_family_from_frames(scenes: Sequence[Sequence[tuple[np.ndarray, float]]], camera: Camera, *,
                           region: int = 128, magnification_per_dpt: float = 0.0,
                           min_ratio: float = MIN_FAMILY_RATIO, fixed_gaussian_scale: bool = True) -> PsfFamilyFit:
    """The PSF family that explains the frames of each scene best (module docstring).

    Args:
        scenes: per scene, its frames ``(image (H, W), power_dpt)`` at known (commanded) powers,
            all of one shape; a scene with fewer than :data:`MIN_FAMILY_FRAMES` distinct powers
            is left out, one with more than :data:`MAX_FAMILY_FRAMES` thinned evenly.
        camera: the calibrated camera (its ``M``, px of Gaussian sigma per dpt; the in-focus
            power is searched over each scene's own span of powers).
        region: side (px) of the square regions searched (at least 32).
        magnification_per_dpt: the lens's focus breathing, undone before the search.
        min_ratio: how many times better the named family must fit (at least 1).
        fixed_gaussian_scale: the Gaussian family's scale is 1 (the camera's ``mu`` is the
            Gaussian relative blur's); ``False`` fits it too (a check of ``mu``).

    Raises:
        InputError: no scene with enough frames, frames of different shapes within a scene,
            a region under 32 px or larger than the frames, or ``min_ratio < 1``.
    """
    if not region >= 32:
        raise InputError(f"region must be at least 32 px, got {region}")
    if not min_ratio >= 1:
        raise InputError(f"min_ratio must be at least 1, got {min_ratio}")
    usable = []
    for k, frames in enumerate(scenes):
        by_power = {round(float(p), 6): np.asarray(im, dtype=np.float64) for im, p in frames}
        if len(by_power) < MIN_FAMILY_FRAMES:
            log.info("scene %d: %d distinct powers, fewer than %d: not used for the PSF family", k, len(by_power),
                     MIN_FAMILY_FRAMES)
            continue
        shapes = {im.shape for im in by_power.values()}
        if len(shapes) != 1 or len(next(iter(shapes))) != 2:
            raise InputError(f"scene {k}: frames must be (H, W) of one shape, got {sorted(shapes)}")
        usable.append(evenly_thinned(sorted(by_power.items()), MAX_FAMILY_FRAMES))
    if not usable:
        raise InputError(f"the PSF family needs a scene with at least {MIN_FAMILY_FRAMES} frames at distinct powers")
    costs = {f: 0.0 for f in PSF_FAMILIES}
    votes = {f: 0 for f in PSF_FAMILIES}
    powers: dict[str, list[float]] = {f: [] for f in PSF_FAMILIES}
    scale_list: dict[str, list[float]] = {f: [] for f in PSF_FAMILIES}
    searched = 0
    for frames in usable:
        shape = frames[0][1].shape
        if min(shape) < region:
            raise InputError(f"region {region} px is larger than the frames {shape}")
        ref = 1.0 + magnification_per_dpt * frames[0][0]
        registered = [(im if not magnification_per_dpt else magnify(im, ref / (1.0 + magnification_per_dpt * p)), p)
                      for p, im in frames]
        span = (frames[0][0], frames[-1][0])  # a sweep brackets focus; steps of a quarter pixel of blur
        coarse = SEARCH_STEP_PX / sigma_px_per_dpt(camera)
        rois = central_regions(shape, region)

        def search(roi: Roi, family: str, scale: float, used: list = registered):
            return cross_blur_focus(used, camera, roi, span_dpt=span, shapes=(family,), coarse_dpt=coarse,
                                    fine_dpt=coarse / 10, sigma_scale=scale)

        for f in PSF_FAMILIES:  # each family's own blur scale, on the central region; the Gaussian's is 1
            # by construction (the calibrated mu is what the Gaussian relative blur measures), and a
            # scale error misleads the controller's fits (49 of 1000 declared out of focus on the
            # reliability benchmark with a Gaussian scale of 2.18, an ad-hoc run of an unstable fit)
            scale_list[f].append(1.0 if f == "gaussian" and fixed_gaussian_scale
                                 else _fit_scale(search, rois[0], f, registered, sigma_px_per_dpt(camera)))
        for roi in rois:
            fits = {f: search(roi, f, scale_list[f][-1]) for f in PSF_FAMILIES}
            if any(fit.at_edge for fit in fits.values()):
                continue
            searched += 1
            for f, fit in fits.items():
                costs[f] += fit.cost
                powers[f].append(fit.power_dpt)
            votes[min(fits, key=lambda f: fits[f].cost)] += 1
    if not searched:
        log.warning("no region of the captures has its in-focus power inside its scene's span of powers (a "
                    "sweep must bracket focus): PSF family not measured")
        return PsfFamilyFit(None, math.nan, costs, 0, votes, {}, {})
    best, other = sorted(PSF_FAMILIES, key=lambda f: costs[f])
    ratio = costs[other] / max(costs[best], 1e-300)
    family = best if ratio >= min_ratio and votes[best] > votes[other] else None
    log.info("PSF family: %s (the other fits %.2fx worse over %d regions; votes %s)", family, ratio, searched, votes)
    return PsfFamilyFit(family, float(ratio), costs, searched, votes,
                        {f: float(np.median(v)) for f, v in powers.items()},
                        {f: float(np.median(v)) for f, v in scale_list.items()})


def capture_scenes(frames: Sequence[Any], region: int) -> tuple[list[list[tuple[np.ndarray, float]]], int]:
    """Capture-folder frames grouped into scenes as the calibration does
    (:func:`tdfd.calibration.fit.group_scenes`: a scene's sweep and pair frames together), each a
    list of ``(image, power_dpt)``, and ``region`` shrunk to the frames' shorter side (a multiple
    of 32 px) on small frames."""
    scenes = []
    for s in group_scenes(frames):
        members = list(s.sweep) + [f for pair in s.pairs for f in pair]
        scenes.append([(f.image, f.power_dpt) for f in members])
    smallest = min((min(im.shape) for sc in scenes for im, _ in sc), default=region)
    return scenes, min(region, smallest // 32 * 32)


def psf_family_from_captures(frames: Sequence[Any], camera_file: Any, region: int = 128,
                             min_ratio: float = MIN_FAMILY_RATIO, fixed_gaussian_scale: bool = True) -> PsfFamilyFit:
    """:func:`psf_family_from_frames` on capture-folder frames (:class:`~tdfd.capture.folder.CaptureFrame`),
    grouped into scenes as the calibration does (:func:`tdfd.calibration.fit.group_scenes`: a
    scene's sweep and pair frames together), with the calibrated ``camera_file``'s camera and
    breathing. ``region`` shrinks to the frames' shorter side (a multiple of 32 px) on small frames.

    Raises:
        InputError: as :func:`psf_family_from_frames` (no scene with three powers, ...).
    """
    scenes, region = capture_scenes(frames, region)
    return psf_family_from_frames(scenes, camera_file.camera, region=region,
                                  magnification_per_dpt=camera_file.magnification_per_dpt, min_ratio=min_ratio,
                                  fixed_gaussian_scale=fixed_gaussian_scale)
