r"""The DFD autofocus policy: :class:`DFDController`, a pure state machine (observation in, command out).

The controller never touches hardware, threads or clocks. Whoever drives it (the
simulated bench, :mod:`tdfd.autofocus.sim`, or the real-hardware loop,
:mod:`tdfd.autofocus.hardware`) executes each :class:`Command` and answers with an
:data:`~tdfd.autofocus.messages.Observation` (:mod:`tdfd.autofocus.messages`)::

    ctrl = DFDController(camera)
    cmd = ctrl.start()
    while not isinstance(cmd, Done):
        cmd = ctrl.step(plant.execute(cmd))     # see :func:`tdfd.autofocus.machine.drive`
    print(cmd.result)

One single-shot DFD focus (paper sec. 3, "focal length as the varying parameter"):

1. ``SetPower(P_e1)``, ``Capture("f1", then_power_dpt=P_e2)``: the first frame once the
   lens has settled; the move to ``P_e2`` is commanded at the end of its exposure.
2. ``Capture("f2")`` once the lens has settled at ``P_e2``.
   A pair that is no DFD pair (identical frames: the lens did not move; a black, much
   darker or saturated frame; :func:`tdfd.pair_check.pair_problem`) is a capture fault:
   the pair is taken again (``capture_retries``), then the run fails and says why; no
   depth is ever taken from it.
3. ``Estimate(f1, f2)``: the depth model (ONNX runtime, or any :class:`Estimator`).
4. ROI aggregation (:func:`tdfd.autofocus.aggregate.aggregate_depth`): confidence-weighted median of inverse
   depth, then a trimmed weighted mean of the inliers.
5. In-focus power ``P_e = 1/d_o + 1/d_s - 1/f0`` (CONTRACT section 1), checked against
   the lens's range (clamped only with an explicit error in the result).
6. ``SetPower(P_e)``.
7. Focus is declared only on the controller's own evidence (:mod:`tdfd.autofocus.evidence`;
   the steps are :mod:`tdfd.autofocus.declaration`'s): the estimate's uncertainty and the
   DFD pair's own relative blur (2 frames), a ``Capture("verify")`` frame at ``P_e``, or the
   three frames' estimate after a failed verification (still 3 frames); otherwise further
   DFD steps, then a contrast-detect search around ``P_e`` (or, with ``fallback=False``, the
   run ends ``"unconfirmed"``); a search without a peak declares nothing.
   :attr:`~tdfd.autofocus.messages.AFResult.evidence` says which evidence declared the focus.

A texture-less ROI is said so (log, :attr:`~tdfd.autofocus.messages.AFResult.fallback_reason`)
and searched by contrast (:mod:`tdfd.autofocus.contrast`); a textured one the model has no
opinion on first gets the DFD pair's own model-free in-focus power, verified
(``pair_fallback``). Lens faults are retried (``lens_retries``), then the run ends with
``status="failed"`` and the reason; the loop itself never raises for a hardware fault.

Example:
    >>> import numpy as np
    >>> from tdfd import Camera
    >>> from tdfd.autofocus.messages import Estimation, Frame, LensAck
    >>> cam = Camera.preset("reference")
    >>> ctrl = DFDController(cam, settle_s=0.015)
    >>> cmd = ctrl.start(); type(cmd).__name__, cmd.power_dpt
    ('SetPower', 1.7)
    >>> cmd = ctrl.step(LensAck(1.7, t_s=0.0, ready_s=0.015)); type(cmd).__name__, cmd.tag
    ('Capture', 'f1')
    >>> img = (0.25 + 0.5 * (np.indices((96, 96)).sum(0) // 8 % 2)).astype(np.float32)  # a checkerboard
    >>> cmd = ctrl.step(Frame(img, 1.7, 0.016, 0.017, 0.018, "f1", lens=LensAck(2.7, 0.017, 0.032)))
    >>> cmd.tag
    'f2'
    >>> img2 = img + np.random.default_rng(0).normal(0, 0.002, img.shape).astype(np.float32)  # sensor noise
    >>> cmd = ctrl.step(Frame(img2, 2.7, 0.033, 0.034, 0.035, "f2")); type(cmd).__name__
    'Estimate'
    >>> depth = np.full((2, 2), 1 / 2.2, np.float32); conf = np.full((2, 2), 0.9, np.float32)
    >>> cmd = ctrl.step(Estimation(depth, conf, tile=64, stride=32, t_s=0.04))
    >>> type(cmd).__name__, round(cmd.power_dpt, 6)
    ('SetPower', 2.2)
    >>> done = ctrl.step(LensAck(cmd.power_dpt, t_s=0.041, ready_s=0.056))
    >>> done.result.status, done.result.evidence, done.result.frames, done.result.lens_commands
    ('focused', 'uncertainty', 2, 3)

    (Both frames show the checkerboard equally blurred, so the pair's own relative blur
    puts the focus midway between 1.7 and 2.7 dpt; the confident estimate agrees.)
"""

from __future__ import annotations

import logging
import math
from typing import Generator

import numpy as np

from ..camera import Camera, in_focus_power_dpt
from ..errors import DTypeError, InputError
from ..pair_check import pair_problem
from .aggregate import DepthAggregate, aggregate_depth
from .cross_blur import PSF_FAMILIES
from .declaration import FocusDeclaration
from .fallback import ContrastFallback
from .evidence import estimate_uncertainty
from .machine import Abort, Gen, StateMachine
from .messages import Command, Estimate, Estimation, EstimateFault, Frame, Observation, State
from .roi import Roi, roi_crop_box, roi_tile_mask
from .sharpness import pair_texture_snr, sharpness

__all__ = ["DFDController"]

log = logging.getLogger(__name__)


class DFDController(FocusDeclaration, ContrastFallback, StateMachine):
    """Single-shot (or continuous) depth-from-defocus autofocus.

    Args:
        camera: the camera the depth model was built for (its ``lens_powers_dpt`` are the
            capture pair; its thin-lens constants give the in-focus power).
        roi: region of interest in frame pixels; ``None``: the centred half of the frame.
        settle_s: lens settling time (s) waited after every power command.
        verify: when to take a verification frame at the in-focus power (:func:`verify_focus`):
            ``"auto"`` (default) only when the estimate's uncertainty is above
            ``max_uncertainty_px``, ``"always"`` (``True``), ``"never"`` (``False``: focus is
            declared on the uncertainty alone, else not confirmed).
        max_uncertainty_px: focus is declared without a verification frame when the
            estimate's uncertainty (:func:`estimate_uncertainty`: the model's predicted
            error and the tiles' disagreement) is at most this blur radius (px).
        confidence_scale: the estimator's ``b0`` (relative error at confidence 0.5, see
            :func:`tdfd.autofocus.estimators.suggested_confidence_scale`).
        verify_tolerance_px: the verification frame passes when its focus error, plus
            ``verify_z`` standard uncertainties, is at most this blur radius (px).
        verify_z, shape_range: see :func:`tdfd.autofocus.evidence.verify_focus`; the shape
            factor's range (1.0-2.0) spans what a uniform disk's blur gives the Gaussian fit on
            the bench's textures (1.1-2.0, median 1.35: docs/BENCHMARKS.md, ``reliability``).
        agree_px: without a verification frame, the model's in-focus power must also lie
            within this blur radius (px) of the interval the DFD pair allows on its own
            (:func:`tdfd.autofocus.evidence.pair_focus_interval`).
        refine_steps: after a failed verification, this many further DFD steps (move by the
            focus error the verification measured, verify again) before the contrast search.
        combine_gate: after a failed first verification, the model's estimate and the
            verification frame's are combined (:func:`~tdfd.autofocus.evidence.combine_focus_error`)
            when they lie within this many combined standard uncertainties (when they do not,
            one of the two is wrong: a further step follows); 0 disables the three-frame
            estimate.
        refine_z: the combined estimate is declared (after moving the lens to it) when
            ``refine_z`` of its standard uncertainties are within ``verify_tolerance_px``.
        refine_max_uncertainty_px: only a model estimate at most this uncertain (px) takes
            part in the combined estimate; a less certain one leaves the verification
            frame's own measured error as the three-frame estimate, if its references agree.
        contrast_min_peak: the contrast fall-back declares its peak only when the sharpest
            frame of the search is at least this many times the least sharp (else the run
            ends ``"unconfirmed"``: a texture-less target shows only noise).
        min_confidence: mean ROI confidence below which DFD is not trusted and
            contrast-detect AF takes over (the scale is the estimator's: see
            :func:`tdfd.autofocus.estimators.suggested_min_confidence`).
        min_texture_snr: the ROI's band-pass contrast over the noise floor
            (:func:`tdfd.autofocus.sharpness.pair_texture_snr`, about 1 for a texture-less
            target) in the more textured frame of the DFD pair, below which the target
            counts as texture-less and contrast-detect AF takes over; 0 disables the check.
        fallback: run the contrast-detect search when DFD is not trusted or its focus is not
            confirmed (else the run fails, or ends ``"unconfirmed"`` with the lens at the DFD
            focus and no focus declared).
        contrast: keyword arguments of the fallback :class:`~tdfd.autofocus.contrast.ContrastSearch`.
        continuous: keep tracking after focusing: live frames at focus are watched, and
            DFD is re-run when their ROI sharpness drops by ``refocus_drop`` or every
            ``refocus_interval_s``; the run ends on a :class:`~tdfd.autofocus.messages.Halt` observation.
        refocus_drop, refocus_interval_s: relative sharpness drop that triggers a re-estimate;
            longest time between re-estimates in continuous mode (s).
        dry_run: capture and estimate without moving the lens; ends with ``status="dry-run"``.
        lens_retries, capture_retries, power_limits_dpt: see :class:`~tdfd.autofocus.machine.StateMachine`.
        grid: the estimator's ``(tile, stride)``: only the grid-aligned crop around the ROI is sent.
        pair_fallback, pair_min_texture_snr: no model opinion on an ROI textured this many times
            the noise: verify the pair's own in-focus power first (``_pair_estimate``).
        cross_blur, cross_blur_family_ratio, cross_blur_min_contrast: after a failed verification
            the three frames' cross-blur focus is the three-frame estimate where the Gaussian and
            disk fits agree or the other fits this many times worse, and its cost curve's
            contrast is at least the minimum; it vetoes a verification or a relative-blur
            three-frame estimate it contradicts (module
            :mod:`~tdfd.autofocus.declaration`, which also uses the pair's own cross-blur focus).
        psf_family: the lens's PSF family when it is known (``"gaussian"`` or ``"pillbox"``, e.g.
            a camera file's ``psf_family`` measured by ``tdfd calibrate``): the cross-blur
            searches fit that family only, and with a disk the DFD pair's check of a 2-frame
            declaration is its disk cross-blur focus. ``None`` (default): both are tried.
        pair_disk_check: with the family unknown, a 2-frame declaration also asks the pair's own
            cross-blur focus over both families: where a disk fits the pair best, the model's power
            must agree with its focus (:meth:`_pair_clear_disk_agrees`). Off by default: on 5000
            reliability targets (seeds 0-4, 10-19, 20-29) it cut the declarations of focus at 2 px or
            more of blur from 6 to 2 but not their count at 1 px (10 to 9, within the trajectories'
            noise), and its search on every 2-frame declaration raised the autofocus benchmark's
            median bench time from 66.3 to 79.0 ms (target 70 ms). Calibrating the family is the
            remedy that costs nothing per request (``psf_family``).
        psf_sigma_scale: that family's RMS blur per dioptre over the camera's (a camera file's
            ``psf_sigma_scale``; 1 without a family).
    """

    def __init__(self, camera: Camera, *, roi: Roi | None = None, settle_s: float = 0.015, verify: bool | str = "auto",
                 min_confidence: float = 0.01, min_texture_snr: float = 1.5, fallback: bool = True,
                 contrast: dict | None = None,
                 continuous: bool = False, refocus_drop: float = 0.25, refocus_interval_s: float = 0.5,
                 dry_run: bool = False, lens_retries: int = 2, capture_retries: int = 1,
                 power_limits_dpt: tuple[float, float] | None = None, grid: tuple[int, int] | None = None,
                 max_uncertainty_px: float = 0.25, confidence_scale: float = 0.01, verify_tolerance_px: float = 0.8,
                 verify_z: float = 2.0, shape_range: tuple[float, float] = (1.0, 2.0), refine_steps: int = 1,
                 agree_px: float = 0.5, combine_gate: float = 2.0, refine_z: float = 2.5,
                 refine_max_uncertainty_px: float = 1.0, contrast_min_peak: float = 1.1,
                 pair_fallback: bool = True, pair_min_texture_snr: float = 3.0, cross_blur: bool = True,
                 cross_blur_family_ratio: float = 1.5, cross_blur_min_contrast: float = 0.1, pair_disk_check: bool = False,
                 psf_family: str | None = None, psf_sigma_scale: float = 1.0) -> None:
        super().__init__(settle_s, lens_retries, capture_retries, power_limits_dpt)
        self.grid = None if grid is None else (int(grid[0]), int(grid[1]))
        if not 0 <= min_confidence <= 1:
            raise InputError(f"min_confidence must be in [0, 1], got {min_confidence}")
        modes = {True: "always", False: "never", "auto": "auto", "always": "always", "never": "never"}
        if not isinstance(verify, (bool, str)) or verify not in modes:
            raise InputError(f"verify must be 'auto', 'always', 'never' or a bool, got {verify!r}")
        if not (max_uncertainty_px >= 0 and verify_tolerance_px > 0 and confidence_scale > 0 and refine_steps >= 0):
            raise InputError("need max_uncertainty_px >= 0, verify_tolerance_px > 0, confidence_scale > 0, "
                             "refine_steps >= 0")
        self.camera, self.roi, self.verify = camera, roi, modes[verify]
        self.max_uncertainty_px, self.confidence_scale = float(max_uncertainty_px), float(confidence_scale)
        self.verify_tolerance_px, self.verify_z = float(verify_tolerance_px), float(verify_z)
        self.shape_range = (float(shape_range[0]), float(shape_range[1]))
        self.refine_steps, self.agree_px = int(refine_steps), float(agree_px)
        self.pair_disk_check = bool(pair_disk_check)
        if not (combine_gate >= 0 and refine_z > 0 and refine_max_uncertainty_px >= 0 and contrast_min_peak >= 1):
            raise InputError("need combine_gate >= 0, refine_z > 0, refine_max_uncertainty_px >= 0, "
                             "contrast_min_peak >= 1")
        self.contrast_min_peak = float(contrast_min_peak)
        self.combine_gate, self.refine_z = float(combine_gate), float(refine_z)
        self.refine_max_uncertainty_px = float(refine_max_uncertainty_px)
        self.min_confidence, self.fallback = float(min_confidence), bool(fallback)
        if not (pair_min_texture_snr >= 0 and cross_blur_family_ratio >= 1 and cross_blur_min_contrast >= 0):
            raise InputError("need pair_min_texture_snr >= 0, cross_blur_family_ratio >= 1, cross_blur_min_contrast >= 0, "
                             f"got {pair_min_texture_snr}, {cross_blur_family_ratio}, {cross_blur_min_contrast}")
        self.pair_fallback, self.pair_min_texture_snr = bool(pair_fallback), float(pair_min_texture_snr)
        self.cross_blur, self.cross_blur_family_ratio = bool(cross_blur), float(cross_blur_family_ratio)
        self.cross_blur_min_contrast = float(cross_blur_min_contrast)
        if psf_family not in (None, *PSF_FAMILIES):
            raise InputError(f"psf_family must be None or one of {PSF_FAMILIES}, got {psf_family!r}")
        if not (0.2 <= psf_sigma_scale <= 5.0 and (psf_family is not None or psf_sigma_scale == 1.0)):
            raise InputError(f"psf_sigma_scale must be in [0.2, 5] and 1 without a psf_family, got {psf_sigma_scale}")
        self.psf_family, self.psf_sigma_scale = psf_family, float(psf_sigma_scale)
        self.min_texture_snr = float(min_texture_snr)
        self.contrast_kwargs = dict(contrast or {})
        self.continuous, self.refocus_drop = bool(continuous), float(refocus_drop)
        self.refocus_interval_s, self.dry_run = float(refocus_interval_s), bool(dry_run)
        self.last_aggregate: DepthAggregate | None = None

    def _roi_for(self, frame_hw: tuple[int, int]) -> Roi:
        return (self.roi or Roi.centre(frame_hw)).clip(frame_hw)

    def _sharpness(self, image: np.ndarray) -> float:
        return sharpness(image, self._roi_for(image.shape[-2:]), self.contrast_kwargs.get("measure", "laplacian"))

    def _run(self) -> Gen:
        while True:
            frames = yield from self._dfd_once()
            if not self.continuous or self.result.status != "focused":
                return
            yield from self._track(frames)

    def _dfd_once(self) -> Generator[Command, Observation, tuple[Frame, Frame] | None]:
        """One DFD focus; returns the DFD pair (``None`` if contrast AF set the focus)."""
        p1, p2 = self.camera.lens_powers_dpt
        res = self.result
        res.refocus_count += 1
        for attempt in range(self.capture_retries + 1):
            if self.dry_run:
                self.state = State.CAPTURE_F1
                f1, _ = yield from self._capture("f1")
                self.state = State.CAPTURE_F2
                f2, _ = yield from self._capture("f2")
            else:
                f1, f2 = yield from self._capture_pair(p1, p2)
            problem = self._pair_problem(f1, f2)
            if problem is None:
                break
            log.warning("capture fault (pair %d of %d): %s", attempt + 1, self.capture_retries + 1, problem)
        else:
            raise Abort(f"capture fault: {problem}; no depth taken from this pair")
        self.state = State.ESTIMATE
        roi = self._roi_for(f1.image.shape[-2:])
        offset = (0, 0)
        im1, im2 = f1.image, f2.image
        if self.grid is not None and min(f1.image.shape[-2:]) >= self.grid[0]:
            y0, y1, x0, x1 = roi_crop_box(roi, f1.image.shape[-2:], *self.grid)
            im1, im2, offset = im1[..., y0:y1, x0:x1], im2[..., y0:y1, x0:x1], (y0, x0)
        centre = None
        if offset != (0, 0) or im1.shape[-2:] != f1.image.shape[-2:]:  # a crop: where the frame's centre lies in it
            H, W = f1.image.shape[-2:]
            centre = ((H - 1) / 2.0 - offset[0], (W - 1) / 2.0 - offset[1])
        obs = yield Estimate(im1, im2, offset, centre)
        self._halt(obs)
        if isinstance(obs, EstimateFault):
            self._note_time(obs.t_s)
            raise Abort(f"depth estimation failed: {obs.error}")
        assert isinstance(obs, Estimation)
        self._note_time(obs.t_s)
        agg, mask = self._aggregate(obs, roi, offset)
        self.last_aggregate = agg
        res.confidence = agg.confidence
        res.estimated_depth_m = agg.depth_m
        log.info("DFD: ROI depth %.4f m (1/d %.3f 1/m, spread %.3f 1/m), confidence %.3f, %d/%d tiles",
                 agg.depth_m, agg.inverse_depth, agg.spread_dpt, agg.confidence, agg.inliers, agg.tiles)
        snr = math.inf
        if self.min_texture_snr > 0:
            try:
                snr = pair_texture_snr(f1.image, f2.image, roi)
            except InputError as exc:  # a tiny ROI: rely on the confidence alone
                log.info("no texture check: %s", exc)
        res.texture_snr = snr
        reason = None
        if snr < self.min_texture_snr:
            reason = (f"texture-less target: ROI contrast {snr:.2f}x the noise floor (below {self.min_texture_snr:g}x), "
                      f"DFD confidence {agg.confidence:.3f}")
        elif agg.confidence < self.min_confidence or not math.isfinite(agg.inverse_depth) or agg.inverse_depth <= 0:
            reason = (f"DFD confidence {agg.confidence:.3f} below {self.min_confidence:.3f} over the ROI "
                      f"(ROI contrast {snr:.1f}x the noise floor)")
        if reason is not None:
            if self.dry_run:
                res.fallback_reason = reason
                raise Abort(reason, status="dry-run")
            if not self.fallback:
                raise Abort(reason)
            res.fallback_reason = reason
            if self.pair_fallback and snr >= self.pair_min_texture_snr and self.verify != "never":
                outcome = yield from self._pair_estimate(f1, f2, roi, reason)
                if outcome is not False:
                    return outcome
            log.warning("%s: falling back to contrast-detect AF", reason)
            yield from self._contrast(None)
            return None
        target = in_focus_power_dpt(self.camera, agg.depth_m)
        unc = estimate_uncertainty(agg, obs.confidence, mask, self.camera, self.confidence_scale)
        res.uncertainty_px = unc.blur_px
        power = self.check_power(target)
        res.method = "dfd"
        res.dfd_power_dpt = power
        if self.dry_run:
            res.power_dpt = power
            res.t_focus_s = obs.t_s
            raise Abort("dry run", status="dry-run")
        self.state = State.MOVE_FOCUS
        ack = yield from self._set_power(power)
        res.power_dpt = power
        res.history.append((ack.ready_s, power, agg.depth_m))
        return (yield from self._declare_or_verify(target, power, ack.ready_s, unc, f1, f2, roi))

    def _verify_light(self) -> str | None:
        """The light a verification frame is taken under: the DFD pair's (it is compared with
        that pair), none for plain DFD (a policy above that lights the pair overrides this)."""
        return None

    def _contrast_light(self) -> str | None:
        """The light the fall-back contrast search's frames are taken under: none for plain DFD
        (a policy above that lights the pair overrides this)."""
        return None

    @staticmethod
    def _pair_problem(f1: Frame, f2: Frame) -> str | None:
        """Why the two frames are no DFD pair (:func:`tdfd.pair_check.pair_problem`: identical
        frames, a black, much darker or saturated frame), or ``None``. Such a pair is a capture
        fault: no estimator is asked to vouch for it."""
        try:
            return pair_problem(f1.image, f2.image)
        except (InputError, DTypeError) as exc:  # frames of different shapes or dtypes
            return str(exc)

    def _capture_pair(self, p1: float, p2: float) -> Generator[Command, Observation, tuple[Frame, Frame]]:
        """The DFD pair of one cycle: ``P_e1``, ``f1`` (then ``P_e2``), ``f2`` (a policy above may light it)."""
        self.state = State.MOVE_F1
        yield from self._set_power(p1)
        self.state = State.CAPTURE_F1
        f1, _ = yield from self._capture("f1", then_power_dpt=p2)
        self.state = State.CAPTURE_F2
        f2, _ = yield from self._capture("f2")
        return f1, f2

    def _aggregate(self, obs: Estimation, roi: Roi, offset: tuple[int, int]
                   ) -> tuple[DepthAggregate, np.ndarray]:
        """The ROI depth from the estimate on the tile grid, and the ``(h, w)`` mask of the
        tiles it pooled (a policy above may pool other tiles)."""
        mask = roi_tile_mask(roi, obs.depth_m.shape, obs.tile, obs.stride, offset)
        return aggregate_depth(obs.depth_m, obs.confidence, mask), mask

    def _track(self, pair: tuple[Frame, Frame] | None) -> Gen:
        """Continuous mode: watch live frames at focus; re-run DFD when they blur or periodically."""
        self.state = State.TRACK
        reference: float | None = None
        last_focus = self.result.t_focus_s or self._last_t
        while True:
            frame, _ = yield from self._capture("live")
            s = self._sharpness(frame.image)
            if reference is None:
                reference = s
                continue
            reference = max(reference, s)
            dropped = s < (1.0 - self.refocus_drop) * reference
            stale = frame.t_ready_s - last_focus >= self.refocus_interval_s
            if dropped or stale:
                log.info("continuous: re-estimating (%s)", "sharpness dropped" if dropped else "periodic")
                self.state = State.MOVE_F1
                yield from self._dfd_once()
                if self.result.status != "focused":
                    return
                self.state = State.TRACK
                reference, last_focus = None, self.result.t_focus_s or self._last_t
