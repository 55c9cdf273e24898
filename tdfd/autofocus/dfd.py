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
3. ``Estimate(f1, f2)``: the depth model (ONNX runtime, or any :class:`Estimator`).
4. ROI aggregation (:func:`tdfd.autofocus.aggregate.aggregate_depth`): confidence-weighted median of inverse
   depth, then a trimmed weighted mean of the inliers.
5. In-focus power ``P_e = 1/d_o + 1/d_s - 1/f0`` (CONTRACT section 1), checked against
   the lens's range (clamped only with an explicit error in the result).
6. ``SetPower(P_e)``; focus is reached when the lens has settled.
7. Optionally ``Capture("verify")``: the ROI sharpness at ``P_e`` must not fall below
   that of the DFD pair, else a contrast-detect search around ``P_e`` takes over.

When the ROI confidence is too low (a texture-less target) the controller says so
(log and :attr:`~tdfd.autofocus.messages.AFResult.fallback_reason`) and falls back to the contrast-detect search
of :mod:`tdfd.autofocus.contrast`. Lens faults are retried (``lens_retries``), then the
run ends with ``status="failed"`` and the reason; the loop itself never raises for a
hardware fault.

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
    >>> cmd = ctrl.step(Frame(img, 2.7, 0.033, 0.034, 0.035, "f2")); type(cmd).__name__
    'Estimate'
    >>> depth = np.full((2, 2), 0.5, np.float32); conf = np.full((2, 2), 0.9, np.float32)
    >>> cmd = ctrl.step(Estimation(depth, conf, tile=64, stride=32, t_s=0.04))
    >>> type(cmd).__name__, round(cmd.power_dpt, 6)
    ('SetPower', 2.0)
    >>> done = ctrl.step(LensAck(cmd.power_dpt, t_s=0.041, ready_s=0.056))
    >>> done.result.status, done.result.frames, done.result.lens_commands
    ('focused', 2, 3)
"""

from __future__ import annotations

import logging
import math
from typing import Generator

import numpy as np

from ..camera import Camera
from ..errors import InputError
from .aggregate import DepthAggregate, aggregate_depth
from .contrast import ContrastSearch
from ..camera import in_focus_power_dpt
from .machine import Abort, Gen, StateMachine
from .messages import Command, Estimate, Estimation, EstimateFault, Frame, Observation, State
from .roi import Roi, roi_crop_box, roi_tile_mask
from .sharpness import pair_texture_snr, sharpness

__all__ = ["DFDController"]

log = logging.getLogger(__name__)


class DFDController(StateMachine):
    """Single-shot (or continuous) depth-from-defocus autofocus.

    Args:
        camera: the camera the depth model was built for (its ``lens_powers_dpt`` are the
            capture pair; its thin-lens constants give the in-focus power).
        roi: region of interest in frame pixels; ``None``: the centred half of the frame.
        settle_s: lens settling time (s) waited after every power command.
        verify: capture one more frame at the in-focus power and check its sharpness.
        min_confidence: mean ROI confidence below which DFD is not trusted and
            contrast-detect AF takes over (the scale is the estimator's: see
            :func:`tdfd.autofocus.estimators.suggested_min_confidence`).
        min_texture_snr: the ROI's band-pass contrast over the noise floor
            (:func:`tdfd.autofocus.sharpness.pair_texture_snr`, about 1 for a texture-less
            target) in the more textured frame of the DFD pair, below which the target
            counts as texture-less and contrast-detect AF takes over; 0 disables the check.
        fallback: run the contrast-detect search when DFD is not trusted (else fail).
        contrast: keyword arguments of :class:`tdfd.autofocus.contrast.ContrastSearch`
            for the fallback search.
        continuous: keep tracking after focusing: live frames at focus are watched, and
            DFD is re-run when their ROI sharpness drops by ``refocus_drop`` or every
            ``refocus_interval_s``; the run ends on a :class:`~tdfd.autofocus.messages.Halt` observation.
        refocus_drop: relative sharpness drop that triggers a re-estimate.
        refocus_interval_s: longest time between re-estimates in continuous mode (s).
        dry_run: capture and estimate without moving the lens; ends with ``status="dry-run"``.
        lens_retries, capture_retries, power_limits_dpt: see :class:`~tdfd.autofocus.machine.StateMachine`.
        verify_tolerance: the verification frame passes if its ROI sharpness is at least
            ``(1 - verify_tolerance)`` times the sharper of the DFD pair.
        grid: the estimator's ``(tile, stride)``; when given, only the grid-aligned crop
            around the ROI (:func:`roi_crop_box`) is sent for estimation.
    """

    def __init__(self, camera: Camera, *, roi: Roi | None = None, settle_s: float = 0.015, verify: bool = False,
                 min_confidence: float = 0.01, min_texture_snr: float = 1.5, fallback: bool = True,
                 contrast: dict | None = None,
                 continuous: bool = False, refocus_drop: float = 0.25, refocus_interval_s: float = 0.5,
                 dry_run: bool = False, lens_retries: int = 2, capture_retries: int = 1,
                 power_limits_dpt: tuple[float, float] | None = None, verify_tolerance: float = 0.1,
                 grid: tuple[int, int] | None = None) -> None:
        super().__init__(settle_s, lens_retries, capture_retries, power_limits_dpt)
        self.grid = None if grid is None else (int(grid[0]), int(grid[1]))
        if not 0 <= min_confidence <= 1:
            raise InputError(f"min_confidence must be in [0, 1], got {min_confidence}")
        self.camera, self.roi, self.verify = camera, roi, bool(verify)
        self.min_confidence, self.fallback = float(min_confidence), bool(fallback)
        self.min_texture_snr = float(min_texture_snr)
        self.contrast_kwargs = dict(contrast or {})
        self.continuous, self.refocus_drop = bool(continuous), float(refocus_drop)
        self.refocus_interval_s, self.dry_run = float(refocus_interval_s), bool(dry_run)
        self.verify_tolerance = float(verify_tolerance)
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
        if self.dry_run:
            self.state = State.CAPTURE_F1
            f1, _ = yield from self._capture("f1")
            self.state = State.CAPTURE_F2
            f2, _ = yield from self._capture("f2")
        else:
            f1, f2 = yield from self._capture_pair(p1, p2)
        self.state = State.ESTIMATE
        roi = self._roi_for(f1.image.shape[-2:])
        offset = (0, 0)
        im1, im2 = f1.image, f2.image
        if self.grid is not None and min(f1.image.shape[-2:]) >= self.grid[0]:
            y0, y1, x0, x1 = roi_crop_box(roi, f1.image.shape[-2:], *self.grid)
            im1, im2, offset = im1[..., y0:y1, x0:x1], im2[..., y0:y1, x0:x1], (y0, x0)
        obs = yield Estimate(im1, im2, offset)
        self._halt(obs)
        if isinstance(obs, EstimateFault):
            self._note_time(obs.t_s)
            raise Abort(f"depth estimation failed: {obs.error}")
        assert isinstance(obs, Estimation)
        self._note_time(obs.t_s)
        agg = self._aggregate(obs, roi, offset)
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
            log.warning("%s: falling back to contrast-detect AF", reason)
            yield from self._contrast(None)
            return None
        target = in_focus_power_dpt(self.camera, agg.depth_m)
        power = self.check_power(target)
        res.method = "dfd"
        if self.dry_run:
            res.power_dpt = power
            res.t_focus_s = obs.t_s
            raise Abort("dry run", status="dry-run")
        self.state = State.MOVE_FOCUS
        ack = yield from self._set_power(power)
        res.power_dpt = power
        res.status = "focused"
        res.t_focus_s = ack.ready_s
        res.history.append((ack.ready_s, power, agg.depth_m))
        if self.verify:
            self.state = State.VERIFY
            fv, _ = yield from self._capture("verify")
            s1, s2, sv = self._sharpness(f1.image), self._sharpness(f2.image), self._sharpness(fv.image)
            res.t_focus_s = fv.t_ready_s
            res.verified = bool(sv >= (1.0 - self.verify_tolerance) * max(s1, s2))
            log.info("verify: sharpness %.4g at %.3f dpt vs %.4g / %.4g in the DFD pair: %s", sv, power, s1, s2,
                     "ok" if res.verified else "FAILED")
            if not res.verified:
                res.fallback_reason = (f"verification failed: sharpness {sv:.4g} at {power:.3f} dpt below the DFD "
                                       f"pair's {max(s1, s2):.4g}")
                log.warning("%s: refining with contrast-detect AF", res.fallback_reason)
                yield from self._contrast(power)
                return None
        return f1, f2

    def _capture_pair(self, p1: float, p2: float) -> Generator[Command, Observation, tuple[Frame, Frame]]:
        """The DFD pair of one cycle: ``P_e1``, ``f1`` (then ``P_e2``), ``f2`` (a policy above may light it)."""
        self.state = State.MOVE_F1
        yield from self._set_power(p1)
        self.state = State.CAPTURE_F1
        f1, _ = yield from self._capture("f1", then_power_dpt=p2)
        self.state = State.CAPTURE_F2
        f2, _ = yield from self._capture("f2")
        return f1, f2

    def _aggregate(self, obs: Estimation, roi: Roi, offset: tuple[int, int]) -> DepthAggregate:
        """The ROI depth from the estimate on the tile grid (a policy above may pool other tiles)."""
        mask = roi_tile_mask(roi, obs.depth_m.shape, obs.tile, obs.stride, offset)
        return aggregate_depth(obs.depth_m, obs.confidence, mask)

    def _contrast(self, centre_dpt: float | None) -> Gen:
        self.state = State.CONTRAST
        kwargs = dict(self.contrast_kwargs)
        if centre_dpt is not None:  # a local search around the DFD answer
            kwargs.setdefault("span_dpt", (centre_dpt - 0.6, centre_dpt + 0.6))
        search = ContrastSearch(self.camera, roi=self.roi, **kwargs)
        power = yield from search.search(self)
        power = self.check_power(power)
        self.state = State.MOVE_FOCUS
        ack = yield from self._set_power(power)
        self.result.method = "contrast"
        self.result.power_dpt = power
        self.result.status = "focused"
        self.result.t_focus_s = ack.ready_s
        self.result.history.append((ack.ready_s, power, None))

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
