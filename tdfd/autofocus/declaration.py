r"""When the DFD policy declares focus: the evidence steps after the lens has moved to the
model's in-focus power (:class:`FocusDeclaration`, mixed into
:class:`~tdfd.autofocus.dfd.DFDController`).

Focus is declared only on the controller's own evidence (:mod:`tdfd.autofocus.evidence`):

* ``"uncertainty"`` (2 frames): the estimate's uncertainty maps to at most
  ``max_uncertainty_px`` of blur, its power focuses a depth within the camera's range (the
  model's confidence is calibrated there only), and the DFD pair's own relative blur,
  measured without the model (:func:`~tdfd.autofocus.evidence.pair_focus_interval`),
  allows its power;
* ``"verification"`` (3 frames): a ``Capture("verify")`` frame at that power is confirmed
  by its relative blur against the pair (:func:`~tdfd.autofocus.evidence.verify_focus`);
* ``"refined"`` (3 frames): the verification frame failed, but its measured focus error,
  weighted with the model's where the two agree
  (:func:`~tdfd.autofocus.evidence.combine_focus_error`), or alone where the model is too
  uncertain to take part and the frame's references agree among themselves, is known well
  enough, or the three frames' cross-blur focus (:mod:`~tdfd.autofocus.cross_blur`) is sure
  of it (not at its span's edge, the two PSF families agree or one fits clearly better, and
  its cost curve has a contrast of at least ``cross_blur_min_contrast``): the lens moves
  there (a relative-blur estimate the cross-blur focus contradicts is not declared);
* otherwise the lens moves by the measured error and verifies again (``refine_steps``),
  never to a power outside :func:`~tdfd.autofocus.evidence.working_powers_dpt`, then
  :meth:`~tdfd.autofocus.fallback.ContrastFallback._not_confirmed` hands over to the contrast search (or ends
  ``"unconfirmed"``).

A verification does not pass where the three frames' cross-blur focus is sure and lies
farther than the tolerance from the lens's power (it then is the three-frame estimate).
Neither a verification nor a three-frame estimate is declared at a power the frames'
sharpness order rules out (:func:`~tdfd.autofocus.sharpness_order.sharpness_bracket`: no
blur model, so it holds where the relative blur's Gaussian model is misled), except a
cross-blur focus that a disk fits clearly better than any Gaussian (a disk's MTF reversals
on a periodic texture can make a blurrier frame look sharper and the order exclude the
truth). Where the
model has no opinion on a textured ROI, :meth:`FocusDeclaration._pair_estimate` moves to
the DFD pair's own model-free in-focus power (its relative blur's, else its cross-blur
focus) and the same steps follow without the model; a three-frame estimate that follows the
pair's cross-blur focus must confirm it within the verification tolerance.

Told the lens's PSF family (``psf_family``, ``psf_sigma_scale``: a calibrated camera file's),
the cross-blur searches fit that family only; a cross-blur focus is then sure only as its cost
curve's one clear minimum (:meth:`FocusDeclaration._unique`; a known disk's stands outside the
sharpness order, as a clear disk fit does), any credible one (not at an edge,
within the working powers, not flat) farther than the tolerance vetoes a verification pass,
and through a disk the pair's check of a 2-frame declaration is its own disk cross-blur focus
(:meth:`FocusDeclaration._pair_cross_blur_agrees`).

The mixin reads the controller's thresholds (``max_uncertainty_px``, ``agree_px``,
``verify_tolerance_px``, ``verify_z``, ``shape_range``, ``combine_gate``, ``refine_z``,
``refine_max_uncertainty_px``, ``refine_steps``, ``verify``, ``fallback``, ``cross_blur``,
``cross_blur_family_ratio``, ``cross_blur_min_contrast``, ``psf_family``, ``psf_sigma_scale``) and uses the
state machine's ``_capture`` / ``_set_power`` and the controller's ``_contrast`` and
``_verify_light``.
"""

from __future__ import annotations

import logging
import math
from dataclasses import replace
from typing import Generator

from ..errors import InputError
from .evidence import (FocusEstimate, FocusUncertainty, blur_px_per_dpt, combine_focus_error, pair_focus_interval,
                       verify_focus, working_powers_dpt)
from .messages import Command, Frame, Observation, State
from .cross_blur import PSF_FAMILIES, CrossBlurFocus, cross_blur_focus
from .sharpness_order import sharpness_bracket
from .roi import Roi

__all__ = ["FocusDeclaration"]

log = logging.getLogger(__name__)


class FocusDeclaration:
    """The declaration steps of :class:`~tdfd.autofocus.dfd.DFDController` (see the module
    docstring for the attributes and methods of the controller they use)."""

    def _declare_or_verify(self, target: float, power: float, ready_s: float, unc: FocusUncertainty,
                           f1: Frame, f2: Frame, roi: Roi, *, anchored: bool = False
                           ) -> Generator[Command, Observation, tuple[Frame, Frame] | None]:
        """The lens has settled at ``power`` (the model's in-focus power ``target``, ready at
        ``ready_s``): declare focus on the estimate's uncertainty, or verify (module docstring).
        ``anchored``: ``target`` is the pair's own cross-blur focus, which a three-frame estimate
        must confirm within the verification tolerance (no model to arbitrate between the two).

        Returns:
            The DFD pair, or ``None`` if the contrast search set the focus.
        """
        res = self.result
        confident = unc.blur_px <= self.max_uncertainty_px
        near_p, far_p = working_powers_dpt(self.camera, margin_dpt=0.0)
        if confident and not near_p <= target <= far_p:
            # a depth outside the camera's range: the model extrapolates, its confidence was never calibrated there
            log.info("DFD estimate %.3f dpt outside the in-focus powers of the depth range (%.3f..%.3f dpt): verify",
                     target, near_p, far_p)
            confident = False
        slack = self.agree_px / blur_px_per_dpt(self.camera)
        if confident and self.psf_family == "pillbox":  # a second opinion: the pair's own disk cross-blur focus
            res.pair_agrees = self._pair_cross_blur_agrees(f1, f2, roi, target, slack)
            confident = res.pair_agrees
        elif confident:  # a second opinion: the pair's own relative blur must allow the model's power
            try:
                res.blur_measurements += 1
                lo, hi = pair_focus_interval(f1.image, f1.power_dpt, f2.image, f2.power_dpt, self.camera, roi,
                                             shape_range=self.shape_range)
            except InputError as exc:
                lo, hi = math.inf, -math.inf
                log.info("no pair check: %s", exc)
            res.pair_agrees = bool(math.isfinite(lo) and math.isfinite(hi) and lo - slack <= target <= hi + slack)
            confident = res.pair_agrees
            log.info("DFD pair without the model: in-focus power %.3f..%.3f dpt; the model's %.3f dpt %s", lo, hi,
                     target, "agrees" if confident else "DISAGREES")
            if confident and self.psf_family is None and self.pair_disk_check:
                res.pair_agrees = confident = self._pair_clear_disk_agrees(f1, f2, roi, target, slack)
        log.info("DFD uncertainty: %.2f px of blur (model %.3f dpt, tiles %.3f dpt): %s", unc.blur_px, unc.model_dpt,
                 unc.spread_dpt, "declare" if confident and self.verify != "always" else "verify")
        if confident and self.verify != "always":
            self._declare(ready_s, "uncertainty")
            return f1, f2
        if self.verify == "never":
            reason = (f"DFD uncertainty {unc.blur_px:.2f} px above {self.max_uncertainty_px:g} px and no "
                      "verification frame allowed")
            return (yield from self._not_confirmed(reason, power, (f1, f2)))
        references = [(f1.image, f1.power_dpt), (f2.image, f2.power_dpt)]
        tol = self.verify_tolerance_px / blur_px_per_dpt(self.camera)
        lo_w, hi_w = working_powers_dpt(self.camera)  # a goal or a step must focus a target of the range
        lo_p, hi_p = lo_w, hi_w
        if self.power_limits_dpt is not None:
            lo_p, hi_p = max(lo_p, self.power_limits_dpt[0]), min(hi_p, self.power_limits_dpt[1])
        for step in range(self.refine_steps + 1):
            self.state = State.VERIFY
            fv, _ = yield from self._capture("verify", light=self._verify_light())
            check = verify_focus(fv.image, fv.power_dpt, references, self.camera, roi,
                                 tolerance_dpt=tol, z=self.verify_z, shape_range=self.shape_range)
            res.verify_error_dpt = check.error_dpt
            res.blur_measurements += len(check.estimates)
            log.info("verify %d at %.3f dpt: focus error %+.3f +- %.3f dpt: %s", step + 1, power, check.error_dpt,
                     check.sigma_dpt, "ok" if check.passed else check.reason)
            references.append((fv.image, fv.power_dpt))
            lo_s, hi_s = sharpness_bracket(references, roi)  # the powers the frames' sharpness order allows
            if check.passed and not lo_s - tol <= power <= hi_s + tol:
                check = replace(check, passed=False, consistent=False,
                                reason=f"the frames' sharpness order puts focus at {lo_s:.3f}..{hi_s:.3f} dpt")
                log.info("verify %d: %s", step + 1, check.reason)
            cross = None  # the frames' cross-blur focus and whether it is sure
            if self.cross_blur and (check.passed or (step == 0 and self.combine_gate > 0)):
                cross = self._cross_blur(references, roi, (lo_s, hi_s), tol, (lo_p, hi_p))
                focus, sure, credible = cross
                # a sure focus elsewhere; with the family known, any credible one (a periodic texture's
                # frames may leave two powers, one of them the lens's: the verification cannot tell)
                if (check.passed and (sure or (credible and self.psf_family is not None))
                        and abs(focus.power_dpt - power) > tol):
                    check = replace(check, passed=False, reason=f"the frames' cross-blur focus is {focus.power_dpt:.3f} dpt")
                    log.info("verify %d: %s", step + 1, check.reason)
            if check.passed:
                res.verified = True
                self._declare(fv.t_ready_s, "verification")
                return f1, f2
            res.verified = False
            if step == 0 and self.combine_gate > 0:
                # the three-frame estimate: the model's (from the pair) and the verification frame's, weighted;
                # when the model is too uncertain to take part, the verification frame's alone if its own
                # references agree (three relative blurs, two unknowns: a consistency check of its own);
                # when the two disagree, one of them is wrong: no estimate, a further step
                model_part = unc.blur_px <= self.refine_max_uncertainty_px
                est = combine_focus_error(check, unc.sigma_dpt, gate=self.combine_gate) if model_part else None
                if (not model_part and check.consistent and len(check.estimates) >= 3
                        and math.isfinite(check.error_dpt)):
                    est = FocusEstimate(check.error_dpt, check.sigma_dpt, math.nan)
                goal = None if est is None else power - est.error_dpt
                if goal is not None:
                    if not lo_s <= goal <= hi_s:
                        log.info("three-frame estimate %.3f dpt: the frames' sharpness order puts focus at %.3f..%.3f dpt",
                                 goal, lo_s, hi_s)
                        est = goal = None
                ok = est is not None and goal is not None and self.refine_z * est.sigma_dpt <= tol and lo_p <= goal <= hi_p
                source = ("the verification frame's alone" if est is None or math.isnan(est.discrepancy)
                          else f"{est.discrepancy:.1f} sigma between model and verification")
                if cross is not None:
                    goal, ok, est, source = self._cross_blur_step(cross, power, goal, ok, est, tol, source)
                if ok and anchored and abs(goal - target) > tol:
                    # the pair's focus and the three frames' disagree: one of them is wrong, a further step
                    log.info("three-frame estimate %.3f dpt: the pair's own cross-blur focus %.3f dpt disagrees",
                             goal, target)
                    ok = False
                if ok:
                    log.info("three-frame estimate: focus error %+.3f +- %.3f dpt (%s): declared at %.3f dpt",
                             est.error_dpt, est.sigma_dpt, source, goal)
                    res.refine_count += 1
                    if abs(goal - power) >= 0.005:
                        self.state = State.MOVE_FOCUS
                        ack = yield from self._set_power(goal)
                        t_declare = ack.ready_s
                        res.history.append((ack.ready_s, goal, None))
                    else:
                        t_declare = fv.t_ready_s
                    res.power_dpt = goal
                    self._declare(t_declare, "refined")
                    return f1, f2
            if step == self.refine_steps or not (check.consistent and math.isfinite(check.error_dpt)):
                break
            if not lo_w <= power - check.error_dpt <= hi_w:
                # a power that focuses no target of the camera's range: the measurement is wrong (a periodic
                # texture through a disk PSF past its first MTF zero), not the lens
                check = replace(check, reason=f"{check.reason}; the step to {power - check.error_dpt:.3f} dpt leaves "
                                              f"the working powers {lo_w:.3f}..{hi_w:.3f} dpt")
                break
            power = self.check_power(power - check.error_dpt)  # a further DFD step with the verification frame
            res.refine_count += 1
            self.state = State.MOVE_FOCUS
            ack = yield from self._set_power(power)
            res.power_dpt = power
            res.history.append((ack.ready_s, power, None))
        return (yield from self._not_confirmed(f"verification failed: {check.reason}", power, (f1, f2)))

    def _cross_blur(self, references: list, roi: Roi, order: tuple[float, float], tol: float,
                    limits: tuple[float, float]) -> tuple[CrossBlurFocus, bool, bool]:
        """The cross-blur focus of all frames so far (:func:`~tdfd.autofocus.cross_blur.cross_blur_focus`,
        a Gaussian or a disk PSF) and whether it is sure: not at its span's edge, inside the
        sharpness order's bracket ``order`` and the powers ``limits``, a cost curve with a contrast of
        at least ``cross_blur_min_contrast`` (so far: credible), the other family within ``tol`` or
        fitting ``cross_blur_family_ratio`` x worse, and with the family known, no runner-up
        elsewhere (:meth:`_unique`). Returns ``(focus, sure, credible)``."""
        self.result.cross_blur_measurements += 1
        cb = cross_blur_focus(references, self.camera, roi, shapes=self._psf_families(),
                              sigma_scale=self.psf_sigma_scale)
        lo_s, hi_s = order
        log.info("cross-blur focus %.3f dpt (%s, contrast %.3f; the other family %.3f dpt, %.2fx the cost; runner-up "
                 "%.3f dpt, %.2fx; edge %s), sharpness order %.3f..%.3f dpt", cb.power_dpt, cb.shape, cb.contrast,
                 cb.other_power_dpt, cb.other_cost_ratio, cb.runner_up_power_dpt, cb.runner_up_ratio, cb.at_edge,
                 lo_s, hi_s)
        clear_disk = cb.shape == "pillbox" and cb.other_cost_ratio >= self.cross_blur_family_ratio
        credible = self._credible(cb, limits)
        sure = (credible and self._unique(cb, tol)
                and (abs(cb.other_power_dpt - cb.power_dpt) <= tol or cb.other_cost_ratio >= self.cross_blur_family_ratio)
                # a disk's MTF has zeros and reversals: on a periodic texture a blurrier frame can look
                # sharper, so the sharpness order is no evidence against a clear disk fit
                and (lo_s <= cb.power_dpt <= hi_s or clear_disk))
        return cb, sure, credible

    @staticmethod
    def _cross_blur_step(cross: tuple[CrossBlurFocus, bool, bool], power: float, goal: float | None, ok: bool,
                         est: FocusEstimate | None, tol: float, source: str
                         ) -> tuple[float | None, bool, FocusEstimate | None, str]:
        """A sure cross-blur focus ``cross`` (:meth:`_cross_blur`) is the three-frame estimate; an
        unsure one lets a relative-blur three-frame estimate ``goal`` stand only within ``tol`` of its
        focus. Returns ``(goal, ok, est, source)``."""
        cb, sure, _ = cross
        if sure:
            return cb.power_dpt, True, FocusEstimate(power - cb.power_dpt, 0.0, math.nan), f"cross-blur, {cb.shape} PSF"
        if ok and goal is not None and abs(goal - cb.power_dpt) > tol:
            log.info("three-frame estimate %.3f dpt: the cross-blur focus disagrees", goal)
            return goal, False, est, source
        return goal, ok, est, source

    def _pair_estimate(self, f1: Frame, f2: Frame, roi: Roi, reason: str
                       ) -> Generator[Command, Observation, tuple[Frame, Frame] | None | bool]:
        """The model has no opinion on a textured ROI (``reason``): the lens moves to the
        in-focus power the DFD pair's own relative blur gives (the centre of
        :func:`~tdfd.autofocus.evidence.pair_focus_interval`, no model), else to the pair's own
        cross-blur focus (not at its span's edge, with a cost contrast of at least
        ``cross_blur_min_contrast``), and verification frames decide, the model taking no part
        (then as :meth:`_declare_or_verify`, ``anchored`` after a cross-blur focus). Returns
        ``False`` without a move when neither gives a power within the working powers (the
        caller searches by contrast)."""
        res = self.result
        lo_w, hi_w = working_powers_dpt(self.camera)
        try:
            res.blur_measurements += 1
            lo, hi = pair_focus_interval(f1.image, f1.power_dpt, f2.image, f2.power_dpt, self.camera, roi,
                                         shape_range=self.shape_range)
        except InputError as exc:
            log.info("no pair estimate: %s", exc)
            lo, hi = math.nan, math.nan
        target = 0.5 * (lo + hi)
        if not (math.isfinite(target) and lo_w <= target <= hi_w):
            log.info("the DFD pair's own in-focus power %.3f dpt is unusable", target)
            if not self.cross_blur:
                return False
            # the pair's cross-blur focus: a place to take the verification frame from (two frames
            # are half the time over 1 px wrong on periodic textures; the three frames' one decides)
            res.cross_blur_measurements += 1
            cb = self._pair_cross_blur(f1, f2, roi)
            if cb is None:
                return False
            log.info("the pair's cross-blur focus %.3f dpt (%s, contrast %.3f, edge %s)", cb.power_dpt, cb.shape,
                     cb.contrast, cb.at_edge)
            if not self._credible(cb, (lo_w, hi_w)):
                return False
            target, lo, hi = cb.power_dpt, math.nan, math.nan
        log.warning("%s: the DFD pair's own in-focus power %.3f dpt (%s) instead, to be verified", reason, target,
                    f"{lo:.3f}..{hi:.3f}" if math.isfinite(lo + hi) else "cross-blur")
        power = self.check_power(target)
        res.method, res.dfd_power_dpt = "dfd", power
        self.state = State.MOVE_FOCUS
        ack = yield from self._set_power(power)
        res.power_dpt = power
        res.history.append((ack.ready_s, power, None))
        no_model = FocusUncertainty(math.inf, math.inf, math.inf, math.inf, math.inf)
        return (yield from self._declare_or_verify(target, power, ack.ready_s, no_model, f1, f2, roi,
                                                   anchored=not math.isfinite(lo + hi)))

    def _psf_families(self) -> tuple[str, ...]:
        """The PSF families the cross-blur searches fit: the lens's, when the controller knows it."""
        return PSF_FAMILIES if self.psf_family is None else (self.psf_family,)

    def _pair_cross_blur(self, f1: Frame, f2: Frame, roi: Roi) -> CrossBlurFocus | None:
        """The DFD pair's own cross-blur focus (the known family's, else both), ``None`` (logged)
        where the frames allow none."""
        try:
            return cross_blur_focus([(f1.image, f1.power_dpt), (f2.image, f2.power_dpt)], self.camera, roi,
                                    shapes=self._psf_families(), sigma_scale=self.psf_sigma_scale)
        except InputError as exc:
            log.info("no cross-blur focus of the DFD pair: %s", exc)
            return None

    def _credible(self, cb: CrossBlurFocus, limits: tuple[float, float] | None = None) -> bool:
        """A cross-blur focus to act on or to object with: not at its span's edge, a cost curve with
        a contrast of at least ``cross_blur_min_contrast`` (frames that differ by little more than
        their noise single no power out), and within the powers ``limits`` when given."""
        return (not cb.at_edge and cb.contrast >= self.cross_blur_min_contrast
                and (limits is None or limits[0] <= cb.power_dpt <= limits[1]))

    def _unique(self, cb: CrossBlurFocus, tol: float) -> bool:
        """With the PSF family known, a cross-blur focus must be the cost curve's only clear minimum:
        its runner-up lies within ``tol`` or costs ``cross_blur_family_ratio`` x more. (Unknown, the
        other family's fit plays that part: the family rule of :meth:`_cross_blur`.)"""
        return (self.psf_family is None or abs(cb.runner_up_power_dpt - cb.power_dpt) <= tol
                or cb.runner_up_ratio >= self.cross_blur_family_ratio)

    def _pair_cross_blur_agrees(self, f1: Frame, f2: Frame, roi: Roi, target: float, slack: float) -> bool:
        """The 2-frame check with a known disk PSF: the DFD pair's own cross-blur focus (that family
        only, no model) is sure (not at its span's edge, a cost contrast of at least
        ``cross_blur_min_contrast``, its curve's one clear minimum: :meth:`_unique`) and within
        ``slack`` of the model's power ``target``. The relative blur's Gaussian fit is no check
        here: on a periodic texture a disk's MTF reversals mislead it and the model alike
        (docs/BENCHMARKS.md, reliability)."""
        self.result.pair_cross_blur_checks += 1
        cb = self._pair_cross_blur(f1, f2, roi)
        if cb is None:
            return False
        agrees = self._credible(cb) and self._unique(cb, slack) and abs(cb.power_dpt - target) <= slack
        log.info("DFD pair's disk cross-blur focus %.3f dpt (contrast %.3f, runner-up %.3f dpt at %.2fx, edge %s); "
                 "the model's %.3f dpt %s", cb.power_dpt, cb.contrast, cb.runner_up_power_dpt, cb.runner_up_ratio,
                 cb.at_edge, target, "agrees" if agrees else "DISAGREES")
        return agrees

    def _pair_clear_disk_agrees(self, f1: Frame, f2: Frame, roi: Roi, target: float, slack: float) -> bool:
        """The 2-frame check with the family unknown, after the relative blur's: the DFD pair's own
        cross-blur focus over both families (:meth:`_pair_cross_blur`). When a disk explains the
        pair best and the search is credible (:meth:`_credible`), the model's power must also lie within
        ``slack`` of the disk's focus: through a disk a periodic texture misleads the relative
        blur's Gaussian fit and an untold model alike (docs/BENCHMARKS.md, reliability: checkers at
        0.306 m, the model and the relative blur at 2.29 dpt, the disk's focus 3.27 dpt, the truth
        3.27 dpt, the Gaussian 1.07x the disk's cost). A pair a Gaussian explains best leaves the
        relative blur's verdict. Tried and left out (docs/BENCHMARKS.md, reliability): asking the
        disk also when it fits within 1.5x of a better Gaussian (seeds 0-4: 96.9 % in focus within 3
        frames, 2 declared out of focus, against 97.4 % and 0), and asking the disk's focus to be
        its cost curve's one clear minimum (seeds 20-29: 96.8 % within 3 frames against 97.1 %, the
        same 3 declared out of focus: stripes through a disk at 0.9 m fool a verification frame too)."""
        self.result.pair_cross_blur_checks += 1
        cb = self._pair_cross_blur(f1, f2, roi)
        if cb is None or not self._credible(cb) or cb.shape != "pillbox":
            return True
        disk = cb.power_dpt
        agrees = abs(disk - target) <= slack
        log.info("DFD pair's cross-blur focus: a disk at %.3f dpt (the Gaussian %.2fx the cost; runner-up %.3f dpt at "
                 "%.2fx); the model's %.3f dpt %s", disk, cb.other_cost_ratio, cb.runner_up_power_dpt,
                 cb.runner_up_ratio, target, "agrees" if agrees else "DISAGREES")
        return agrees

    def _declare(self, t_s: float, evidence: str) -> None:
        """Focus is declared: the lens sits at ``result.power_dpt`` and ``evidence`` says why."""
        self.result.status = "focused"
        self.result.evidence = evidence
        self.result.t_focus_s = t_s
