r"""The assist-light policy: active DFD for texture-less targets (paper sec. 2.1 and 4).

:class:`AssistedDFDController` is a :class:`~tdfd.autofocus.dfd.DFDController` that may ask
for frames lit by an assist light (``Capture(..., light=PATTERN)``); the plant switches
the light through its :class:`~tdfd.light.guard.LightGuard`, on for that exposure only.
The controller itself stays pure: it never touches a light.

One focus request with a light allowed, by default (``ambient_frame=False``):

1. ``f1`` **lit** at ``P_e1`` (the move to ``P_e2`` commanded at its exposure end, as in
   plain DFD), ``f2`` **lit** at ``P_e2``, estimate on the lit pair: two frames, so that a
   verification frame (lit too) still makes three. Every target is lit, textured ones as
   well (the pattern adds edges to a texture; measured: no lower in-focus rate).
2. **Lit-tile pooling**: the ROI depth is aggregated over the tiles with a cue in the lit
   pair only (:func:`~tdfd.autofocus.lit_tiles.pair_cue_mask`: a tile's contrast clear
   of the frame's noise floor; on a texture-less target that is where the pattern's
   edges are), so tiles without a cue give no depth, confident or not; no such tile in
   the ROI is a low-confidence estimate: contrast-detect AF takes over.
3. **One region fit** (``region_fit=True``, the default): when no tile with a cue lies on
   the ROI's outer ring of tiles (the pattern lies inside the ROI: a pattern, or a texture,
   that reaches the ROI's edge would be cut by the region), one Fourier-ratio fit over the
   ROI's central square of the lit pair (:func:`tdfd.dfd.region_fit.fit_region`, the
   paper's one region around the pattern; for a lens told it is a disk, the pair's disk
   cross-blur over that square, :func:`~tdfd.autofocus.region_cross_blur.fit_region_cross_blur`,
   which models it exactly) is fused with the pooled tiles as two correlated
   estimates (:func:`~tdfd.autofocus.lit_tiles.fuse_with_region`: the tiles' pixels are the
   region's, so the region's statistical error is their covariance); its uncertainty counts
   its statistics, ``mu``'s uncertainty and, for a lens not known to be Gaussian
   (``psf_family``), the Gaussian model's bias through a disk, so it carries the estimate
   near the distance the pair blurs equally and on a Gaussian lens, the tiles elsewhere.
   Only the depth changes; the trust rules read the tiles' confidence as before.

With the ambient frame (``ambient_frame=True``, implied by ``subtract_ambient``):

1. ``f1`` unlit at ``P_e1`` (the move to ``P_e2`` commanded at its exposure end). Its ROI
   texture over the noise floor (:func:`~tdfd.autofocus.sharpness.texture_snr`) decides:
2. textured (``>= light_texture_snr``, default 1.2): plain DFD goes on (``f2`` unlit, estimate, ...):
   the same frames, commands and result as without a light;
3. texture-less: ``f2`` **lit** at ``P_e2`` (then back to ``P_e1``), ``f1`` **lit** at
   ``P_e1``, estimate on the lit pair: three frames before any verification frame. The
   unlit ``f1`` is the ambient frame at the same lens power as the lit ``f1``:

   * **lit-tile pooling** over the tiles the pattern covers
     (:func:`~tdfd.autofocus.lit_tiles.lit_tile_mask` of lit minus ambient ``f1``);
   * **ambient subtraction** (``subtract_ambient=True``): the ambient ``f1`` is
     subtracted from both lit frames before estimation (exact for ``f1``, the same
     power; for ``f2`` it removes the ambient level, which a texture-less target's blur
     does not change).
4. If an unlit pair's estimate is not trusted (low confidence, step 2) and its ROI texture
   is weak (below ``retry_texture_snr`` x the noise floor), the light is tried once before
   contrast-detect AF: ``f2`` lit (the lens is at ``P_e2``), ``f1``
   lit, estimate, with both unlit frames as ambient. A lit estimate that is not trusted
   either falls back to contrast-detect AF as plain DFD does.

docs/BENCHMARKS.md (``assist_light``) measures both side by side: the ambient frame does
not pay for its frame (coherent light: 100 of 100 texture-less targets in focus with at most
3 frames without it, 82 with it taken, 77 with it subtracted).

``illumination=None`` (no light named) never asks for a lit frame: the controller is
then plain DFD. A dry run never lights (it does not move the lens either).

Example:
    >>> from tdfd import Camera
    >>> ctrl = AssistedDFDController(Camera.preset("reference"), illumination="coherent")
    >>> ctrl.illumination, ctrl.subtract_ambient, ctrl.ambient_frame
    ('coherent', False, False)
"""

from __future__ import annotations

import dataclasses
import logging
import math
from typing import Generator

import numpy as np

from ..camera import Camera
from ..region_fusion import DEFAULT_MU_UNCERTAINTY, RegionFit
from ..errors import InputError, TdfdError
from ..pair_check import SATURATION_LEVEL
from .aggregate import DepthAggregate, aggregate_depth
from .dfd import DFDController
from .evidence import estimate_uncertainty
from .lit_tiles import cue_touches_border, fuse_with_region, lit_tile_mask, pair_cue_mask, pool_lit_tiles, subtract_ambient
from .machine import Abort, Gen
from .messages import Command, Estimation, Frame, Observation, State
from .region_cross_blur import fit_region_cross_blur
from .roi import Roi, roi_tile_mask
from .sharpness import texture_snr

__all__ = ["AssistedDFDController", "LitPair", "REGION_MODELS"]

#: the region fit's model by its PSF family, as :meth:`AssistedDFDController.lit_summary` names it
REGION_MODELS = {"gaussian": "Gaussian Fourier ratio", "pillbox": "disk cross-blur"}

log = logging.getLogger(__name__)


#: Patterns that stay sharp at every distance (the coherent module, tdfd/illumination.py): a
#: contrast search lit with one peaks where the camera focuses. A projector's pattern is
#: blurred by its own defocus outside its depth of field, which flattens the contrast curve:
#: lit with it, the search declared a 0.36 m target at 1.08 px (bench_assist_light,
#: projector with the ambient frame subtracted), so its searches stay unlit.
SHARP_PATTERNS = frozenset({"coherent"})


@dataclasses.dataclass
class LitPair:
    """What the controller knows about the lit pair of the present focus cycle.

    Attributes:
        pattern: the light's pattern.
        ambient_f1: the unlit frame at ``P_e1`` (same power as the lit ``f1``), ``None``
            when the pair was lit without an ambient frame (``ambient_frame=False``).
        ambient_f2: the unlit frame at ``P_e2`` if one was taken, else ``None``.
        lit_f1: the lit frame at ``P_e1`` as captured (before any subtraction).
        lit_f2: the lit frame at ``P_e2`` as captured.
        lit_tiles: tiles the pattern covers inside the ROI (after estimation).
        roi_tiles: tiles of the ROI (after estimation).
        subtracted: the ambient frame was subtracted from the lit ones.
        reason: why the light was used.
        region: the region fit fused with the lit tiles (``None``: none).
        region_weight: its share of the fused estimate's weight in [0, 1].
    """

    pattern: str
    ambient_f1: Frame | None
    ambient_f2: Frame | None
    lit_f1: Frame | None = None
    lit_f2: Frame | None = None
    lit_tiles: int = 0
    roi_tiles: int = 0
    subtracted: bool = False
    reason: str = ""
    region: RegionFit | None = None
    region_weight: float = 0.0


class AssistedDFDController(DFDController):
    """DFD autofocus that switches an assist light on for texture-less targets (module docs).

    Args:
        camera: see :class:`~tdfd.autofocus.dfd.DFDController`.
        illumination: the pattern to ask for (``"coherent"``, ``"projector"`` on the bench;
            ``"on"`` for a real light), ``None``: no light (plain DFD).
        subtract_ambient: subtract the ambient frame from the lit ones before estimating.
        light_texture_snr: the unlit ``f1``'s ROI texture over the noise floor below which
            the pair is lit. A texture-less target reads about 1 (at most 1.08 over 60 bench
            targets with sensor noise); a textured one can read lower than the pair check's
            1.5 in ``f1`` alone when ``f1`` is blurred (a near target), and plain DFD does
            better on it than a lit pair, hence 1.2.
        retry_texture_snr: an unlit estimate that is not trusted is retried lit only if the
            pair's ROI texture over the noise floor is below this (a weak texture, where the
            pattern adds a cue); a strong texture that DFD still cannot read (a periodic one)
            goes to contrast AF as in plain DFD: measured on 100 textured bench targets, two
            stripes targets were focused at 1.2 and 1.7 px lit, in focus by contrast AF.
        lit_k_noise, lit_rel: thresholds of :func:`~tdfd.autofocus.lit_tiles.lit_tile_mask`.
        lit_min_confidence: ROI confidence needed from a lit estimate (default: the
            controller's ``min_confidence``). Measured on 100 texture-less bench targets
            with the shipped model: 0.01 instead of its 0.003 sends two right lit estimates
            (confidence 0.007) to contrast AF, which ends out of focus on them.
        ambient_pedestal: level added back after the subtraction (intensity units).
        region_fit: fuse one region fit over the ROI with the lit tiles (module docs, step 3).
            It does not register focus breathing: the bench and ``tdfd autofocus`` turn it
            off for an estimator that registers the pair (:func:`~tdfd.autofocus.estimators.estimator_breathing`).
        region_mu_uncertainty: the relative uncertainty of the camera's ``mu`` the region fit
            counts (default :data:`tdfd.region_fusion.DEFAULT_MU_UNCERTAINTY`; a known-distance
            calibration records its own, ``calibration.mu_relative_uncertainty``).
        ambient_frame: ``True``: the unlit ``f1`` probes the ROI's texture and is the
            ambient frame of the lit tiles (three frames before a verification frame);
            ``False``: with a light named, the DFD pair is lit from its first frame (two
            frames; a verification frame makes three), its lit tiles found in the lit
            frames themselves (:func:`~tdfd.autofocus.lit_tiles.pair_cue_mask`); textured
            targets are lit too. Default (``None``): the ambient frame is taken only when
            it is subtracted (``subtract_ambient``): measured on 100 texture-less bench
            targets it does not pay for its frame (docs/BENCHMARKS.md, ``assist_light``).
        lit_max_saturated: without the ambient frame, a lit pair with more than this fraction
            of the ROI's pixels saturated (at :data:`tdfd.pair_check.SATURATION_LEVEL`) in
            either frame is not estimated: the pattern on a bright texture clips, and
            clipped edges are no defocus cue (measured on 100 textured bench targets: with
            the check off, 3 declared out of focus); the pair is taken unlit from where the
            lens is (a clipped lit ``f1``: ``f2`` and ``f1`` unlit, one frame lost).
        **kwargs: :class:`~tdfd.autofocus.dfd.DFDController` options.

    Attributes:
        lit: the present cycle's :class:`LitPair` (``None`` if it ran unlit).
        lit_cycles: focus cycles that used the light.
    """

    def __init__(self, camera: Camera, *, illumination: str | None = None, subtract_ambient: bool = False,
                 light_texture_snr: float = 1.2, retry_texture_snr: float = 3.0,
                 lit_k_noise: float = 3.0, lit_rel: float = 0.05, lit_min_confidence: float | None = None,
                 ambient_pedestal: float = 0.02, ambient_frame: bool | None = None,
                 lit_max_saturated: float = 0.01, region_fit: bool = True,
                 region_mu_uncertainty: float = DEFAULT_MU_UNCERTAINTY, **kwargs) -> None:
        super().__init__(camera, **kwargs)
        if not (math.isfinite(region_mu_uncertainty) and 0 <= region_mu_uncertainty < 1):
            raise InputError(f"region_mu_uncertainty must be in [0, 1), got {region_mu_uncertainty}")
        self.region_fit, self.region_mu_uncertainty = bool(region_fit), float(region_mu_uncertainty)
        if illumination is not None and not isinstance(illumination, str):
            raise InputError(f"illumination must be a pattern name or None, got {illumination!r}")
        if lit_min_confidence is not None and not 0 <= lit_min_confidence <= 1:
            raise InputError(f"lit_min_confidence must be in [0, 1], got {lit_min_confidence}")
        if ambient_frame is None:
            ambient_frame = bool(subtract_ambient)
        if subtract_ambient and not ambient_frame:
            raise InputError("subtract_ambient needs the ambient frame (ambient_frame=True)")
        self.illumination = illumination
        self.ambient_frame = bool(ambient_frame)
        if not 0 <= lit_max_saturated <= 1:
            raise InputError(f"lit_max_saturated must be in [0, 1], got {lit_max_saturated}")
        self.lit_max_saturated = float(lit_max_saturated)
        self.lit_dropped: str | None = None
        self.subtract_ambient = bool(subtract_ambient)
        self.light_texture_snr = float(light_texture_snr)
        self.retry_texture_snr = float(retry_texture_snr)
        self.lit_k_noise, self.lit_rel = float(lit_k_noise), float(lit_rel)
        self.lit_min_confidence = lit_min_confidence
        self.ambient_pedestal = float(ambient_pedestal)
        self.lit: LitPair | None = None
        self.lit_cycles = 0
        self._unlit_pair: tuple[Frame, Frame] | None = None
        self._retry_lit = False
        self._retry_reason = ""
        self._base_min_confidence = self.min_confidence

    # ------------------------------------------------------------------ capture
    def _capture_pair(self, p1: float, p2: float) -> Generator[Command, Observation, tuple[Frame, Frame]]:
        """The DFD pair of this cycle: unlit, or lit for a texture-less target (module docs)."""
        self.lit = None
        self.min_confidence = self._base_min_confidence
        if self.illumination is None:
            pair = yield from super()._capture_pair(p1, p2)
            return pair
        if self._retry_lit and self._unlit_pair is not None:
            a1, a2 = self._unlit_pair  # the lens is still at P_e2 after the unlit f2
            self._retry_lit = False
            return (yield from self._lit_or_unlit(p1, p2, LitPair(self.illumination, a1, a2, reason=self._retry_reason)))
        self.lit_dropped = None
        if not self.ambient_frame:
            self._unlit_pair = None
            return (yield from self._lit_or_unlit(p1, p2, LitPair(self.illumination, None, None,
                                                                  reason="a light named: the pair is lit")))
        self.state = State.MOVE_F1
        yield from self._set_power(p1)
        self.state = State.CAPTURE_F1
        f1, _ = yield from self._capture("f1", then_power_dpt=p2)
        roi = self._roi_for(f1.image.shape[-2:])
        try:
            snr = texture_snr(f1.image, roi)
        except InputError as exc:  # a tiny ROI: no texture check, plain DFD
            log.info("no texture check before the light: %s", exc)
            snr = math.inf
        if snr >= self.light_texture_snr:
            self.state = State.CAPTURE_F2
            f2, _ = yield from self._capture("f2")
            self._unlit_pair = (f1, f2)
            return f1, f2
        reason = f"texture-less target: ROI contrast {snr:.2f}x the noise floor in f1 (below {self.light_texture_snr:g}x)"
        log.info("%s: lighting the DFD pair (%s)", reason, self.illumination)
        self._unlit_pair = None
        return (yield from self._lit_or_unlit(p1, p2, LitPair(self.illumination, f1, None, reason=reason)))

    def _lit_or_unlit(self, p1: float, p2: float, lit: LitPair
                      ) -> Generator[Command, Observation, tuple[Frame, Frame]]:
        """The lit pair; if the light refuses or fails (a cap, a broken light), plain DFD's unlit pair."""
        try:
            return (yield from self._lit_pair(p1, p2, lit))
        except Abort as exc:
            if exc.status != "failed" or "light" not in exc.reason.lower():
                raise  # a halt, or a lens / camera failure: not the light's
            log.warning("no lit frames (%s): going on unlit", exc.reason)
            self.lit = None
            self.min_confidence = self._base_min_confidence
            self.result.fallback_reason = f"assist light unavailable: {exc.reason}"
            pair = yield from super()._capture_pair(p1, p2)
            self._unlit_pair = None  # the light is not tried again in this cycle
            return pair

    def _lit_pair(self, p1: float, p2: float, lit: LitPair) -> Generator[Command, Observation, tuple[Frame, Frame]]:
        """After an ambient ``f1``: ``f2`` lit at ``P_e2`` (where the lens is), then ``f1`` lit at
        ``P_e1``; without one: ``f1`` lit at ``P_e1``, then ``f2`` lit at ``P_e2`` (plain DFD's order)."""
        self.lit = lit
        self.lit_cycles += 1
        if lit.ambient_f1 is None:
            self.state = State.MOVE_F1
            yield from self._set_power(p1)
            self.state = State.CAPTURE_F1
            f1, _ = yield from self._capture("f1 lit", then_power_dpt=p2, light=lit.pattern)
            if self._clips(f1):  # the lens is at P_e2: the unlit pair from there, one frame lost
                return (yield from self._unlit_from_p2(p1))
            self.state = State.CAPTURE_F2
            f2, _ = yield from self._capture("f2 lit", light=lit.pattern)
            if self._clips(f2):
                return (yield from self._unlit_from_p2(p1))
        else:
            self.state = State.CAPTURE_F2
            f2, _ = yield from self._capture("f2 lit", then_power_dpt=p1, light=lit.pattern)
            self.state = State.CAPTURE_F1
            f1, _ = yield from self._capture("f1 lit", light=lit.pattern)
        lit.lit_f1, lit.lit_f2 = f1, f2
        if self.lit_min_confidence is not None:
            self.min_confidence = float(self.lit_min_confidence)
        if self.subtract_ambient and lit.ambient_f1 is not None:
            lit.subtracted = True
            amb1 = lit.ambient_f1.image
            amb2 = lit.ambient_f2.image if lit.ambient_f2 is not None else amb1
            f1 = dataclasses.replace(f1, image=subtract_ambient(f1.image, amb1, self.ambient_pedestal))
            f2 = dataclasses.replace(f2, image=subtract_ambient(f2.image, amb2, self.ambient_pedestal))
        return f1, f2

    def _clips(self, frame: Frame) -> bool:
        """A lit frame clips more than ``lit_max_saturated`` of the ROI (then the pair is taken unlit)."""
        clipped = float(np.mean(self._roi_for(frame.image.shape[-2:]).crop(frame.image) >= SATURATION_LEVEL))
        if clipped <= self.lit_max_saturated:
            return False
        self.lit_dropped = (f"the lit frame {frame.tag!r} clips {100 * clipped:.1f} % of the ROI (over "
                            f"{100 * self.lit_max_saturated:g} %): the pair is taken unlit")
        log.info("%s", self.lit_dropped)
        return True

    def _unlit_from_p2(self, p1: float) -> Generator[Command, Observation, tuple[Frame, Frame]]:
        """The unlit DFD pair with the lens at ``P_e2``: ``f2`` there (then ``P_e1``), ``f1``."""
        self.lit = None
        self.state = State.CAPTURE_F2
        f2, _ = yield from self._capture("f2", then_power_dpt=p1)
        self.state = State.CAPTURE_F1
        f1, _ = yield from self._capture("f1")
        return f1, f2

    # ------------------------------------------------------------------ ROI depth
    def _aggregate(self, obs: Estimation, roi: Roi, offset: tuple[int, int]
                   ) -> tuple[DepthAggregate, np.ndarray]:
        """The ROI depth and the tiles it pooled; for a lit pair, the tiles the pattern covers only."""
        mask = roi_tile_mask(roi, obs.depth_m.shape, obs.tile, obs.stride, offset)
        lit = self.lit
        if lit is None or lit.lit_f1 is None:
            return aggregate_depth(obs.depth_m, obs.confidence, mask), mask
        h, w = obs.depth_m.shape
        y0, x0 = offset
        y1, x1 = y0 + (h - 1) * obs.stride + obs.tile, x0 + (w - 1) * obs.stride + obs.tile
        box = (..., slice(y0, y1), slice(x0, x1))
        if lit.ambient_f1 is not None:
            covered = lit_tile_mask(lit.lit_f1.image[box], lit.ambient_f1.image[box], obs.tile, obs.stride,
                                    self.lit_k_noise, self.lit_rel)
        else:
            assert lit.lit_f2 is not None
            covered = pair_cue_mask(lit.lit_f1.image[box], lit.lit_f2.image[box], obs.tile, obs.stride,
                                    self.lit_k_noise, self.lit_rel)
        agg, pooled = pool_lit_tiles(obs.depth_m, obs.confidence, covered, mask)
        lit.roi_tiles, lit.lit_tiles = int(mask.sum()), int(pooled.sum())
        log.info("lit pair (%s): the pattern covers %d of the ROI's %d tiles", lit.pattern, lit.lit_tiles, lit.roi_tiles)
        if (self.region_fit and lit.lit_f2 is not None and agg.inliers > 0 and math.isfinite(agg.inverse_depth)
                and not cue_touches_border(pooled, mask)):
            try:
                region = self._fit_region(roi.crop(lit.lit_f1.image), roi.crop(lit.lit_f2.image),
                                          (lit.lit_f1.power_dpt, lit.lit_f2.power_dpt))
            except TdfdError as exc:  # a small ROI, odd frames, no minimum in range: the tiles alone
                log.info("no region fit: %s", exc)
                return agg, pooled
            # a standard deviation: the model's Laplace scale counts sqrt(2) times (FocusUncertainty.std_dpt)
            sigma = estimate_uncertainty(agg, obs.confidence, pooled, self.camera, self.confidence_scale).std_dpt
            self.result.region_fits += 1
            self.result.disk_region_fits += region.fit_family == "pillbox"
            fused, lit.region_weight = fuse_with_region(agg, sigma, region)
            lit.region = region
            log.info("region fit %.4f +- %.4f dpt, lit tiles %.4f +- %.4f dpt: fused %.4f dpt (region weight %.2f)",
                     region.inverse_depth, region.sigma_dpt, agg.inverse_depth, sigma, fused.inverse_depth,
                     lit.region_weight)
            return fused, pooled
        return agg, pooled

    def _fit_region(self, crop_f1: np.ndarray, crop_f2: np.ndarray, powers_dpt: tuple[float, float]) -> RegionFit:
        """Step 3's region fit: for a lens told it is a disk, the pair's disk cross-blur
        (:func:`~tdfd.autofocus.region_cross_blur.fit_region_cross_blur`, exact for it); else the
        Gaussian Fourier ratio (:func:`tdfd.dfd.region_fit.fit_region`, the paper's)."""
        if self.psf_family == "pillbox":
            return fit_region_cross_blur(crop_f1, crop_f2, powers_dpt, self.camera, psf_family="pillbox",
                                         sigma_scale=self.psf_sigma_scale, mu_uncertainty=self.region_mu_uncertainty)
        from ..dfd.region_fit import fit_region  # torch: loaded only when a lit pair is fitted

        return fit_region(crop_f1, crop_f2, self.camera, psf_family=self.psf_family,
                          mu_uncertainty=self.region_mu_uncertainty)

    def _verify_light(self) -> str | None:
        """A verification frame is compared with the DFD pair: lit like it (an unlit frame of a
        texture-less target shows nothing to compare)."""
        return self.lit.pattern if self.lit is not None else None

    # ------------------------------------------------------------------ fallback
    def _contrast(self, centre_dpt: float | None) -> Gen:
        """Before contrast-detect AF takes over from an untrusted unlit estimate, try the light once."""
        weak = (self.result.texture_snr is None or not math.isfinite(self.result.texture_snr)
                or self.result.texture_snr < self.retry_texture_snr)
        if (centre_dpt is None and self.illumination is not None and self.lit is None and not self.dry_run
                and self._unlit_pair is not None and weak):
            self._retry_reason = self.result.fallback_reason or "DFD not trusted"
            log.info("%s: retrying with the light (%s) before contrast-detect AF", self._retry_reason, self.illumination)
            self.result.fallback_reason = None
            self.result.refocus_count -= 1  # the same focus request, not a new cycle
            self._retry_lit = True
            yield from self._dfd_once()
            return
        yield from super()._contrast(centre_dpt)

    def _contrast_light(self) -> str | None:
        """The pair was lit with a pattern that stays sharp at every distance: the contrast
        search's frames are lit like it (on a texture-less target the pattern is all there is
        to see); else unlit (:data:`SHARP_PATTERNS`)."""
        return self.lit.pattern if self.lit is not None and self.lit.pattern in SHARP_PATTERNS else None

    def lit_summary(self) -> dict:
        """What the light did in the last cycle (for reports): pattern, tiles, subtraction."""
        if self.lit is None:
            return {"light": None, "lit_dropped": self.lit_dropped}
        return {"light": self.lit.pattern, "lit_tiles": self.lit.lit_tiles, "roi_tiles": self.lit.roi_tiles,
                "ambient_subtracted": self.lit.subtracted, "light_reason": self.lit.reason,
                "lit_cycles": self.lit_cycles, "region_weight": round(self.lit.region_weight, 3),
                "region_model": None if self.lit.region is None else REGION_MODELS[self.lit.region.fit_family]}


# the hooks this policy overrides or uses in DFDController / StateMachine:
#   DFDController._capture_pair(p1, p2) -> (f1, f2): the capture steps of one cycle;
#   DFDController._aggregate(obs, roi, offset) -> (DepthAggregate, mask): the ROI depth and its tiles;
#   DFDController._verify_light() -> pattern or None: the light of the verification frames;
#   DFDController._contrast_light() -> pattern or None: the light of the fall-back contrast search;
#   StateMachine._capture(tag, then_power_dpt=None, light=None): Capture(..., light=...).

