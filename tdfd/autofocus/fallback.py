"""When the DFD policy cannot declare focus: the contrast-detect fall-back
(:class:`ContrastFallback`, mixed into :class:`~tdfd.autofocus.dfd.DFDController`).

:meth:`ContrastFallback._not_confirmed` hands a DFD focus that its evidence did not confirm
(:mod:`~tdfd.autofocus.declaration`) to a contrast search around it
(:class:`~tdfd.autofocus.contrast.ContrastSearch`), or ends the run ``"unconfirmed"`` with
``fallback=False``; :meth:`ContrastFallback._contrast` runs the search (also where the model
has no opinion) and declares its peak only when the peak rises ``contrast_min_peak`` above the
scan's least sharp frame and, with the lens's PSF family known, the scan frames' own cross-blur
focus (:mod:`~tdfd.autofocus.cross_blur`) does not put focus elsewhere
(:meth:`ContrastFallback._contrast_contradicted`): a periodic texture through a disk shows
contrast peaks on the MTF's side lobes.

The mixin reads the controller's ``fallback``, ``contrast_kwargs``, ``contrast_min_peak``,
``cross_blur``, ``psf_family``, ``psf_sigma_scale``, ``cross_blur_min_contrast`` and
``verify_tolerance_px``, and uses the state machine's ``_set_power`` and the controller's
``_contrast_light``, ``_roi_for``, ``_credible`` and ``_unique``.
"""

from __future__ import annotations

import logging
from typing import Generator

from ..errors import InputError
from .contrast import ContrastSearch
from .cross_blur import cross_blur_focus, evenly_thinned
from .evidence import blur_px_per_dpt, working_powers_dpt
from .machine import Gen
from .messages import Command, Frame, Observation, State
from .roi import Roi

__all__ = ["ContrastFallback", "CONTRAST_CHECK_FRAMES"]

log = logging.getLogger(__name__)

#: at most this many of a contrast search's frames check its peak (15 frame pairs)
CONTRAST_CHECK_FRAMES = 6


class ContrastFallback:
    """The contrast-detect fall-back of :class:`~tdfd.autofocus.dfd.DFDController` (see the
    module docstring for the attributes and methods of the controller it uses)."""

    def _not_confirmed(self, reason: str, power: float, pair: tuple[Frame, Frame]
                       ) -> Generator[Command, Observation, tuple[Frame, Frame] | None]:
        """The DFD focus could not be confirmed: a contrast-detect search around it, or no declaration."""
        if not self.fallback:
            self._undeclared(reason)
            return None
        self._add_reason(reason)  # after why the estimate came without the model (the pair's own), if it did
        # around the estimate: a scan of the whole range did no better on the reliability benchmark
        # (9 declared out of focus in 1000 against 8; both are the contrast search's false peaks on
        # low-frequency textures) and costs more frames
        log.warning("%s: contrast-detect AF decides around %.3f dpt", reason, power)
        yield from self._contrast(power)
        return None

    def _add_reason(self, reason: str) -> None:
        """Append ``reason`` to the result's fall-back reasons."""
        prior = self.result.fallback_reason
        self.result.fallback_reason = f"{prior}; {reason}" if prior else reason

    def _undeclared(self, reason: str) -> None:
        """The run ends without a declaration (the lens where it was last sent), saying why."""
        self._add_reason(reason)
        log.warning("%s: focus not declared", reason)
        self.result.status = "unconfirmed"
        self.result.t_focus_s = None

    def _contrast(self, centre_dpt: float | None) -> Gen:
        """The contrast search (around ``centre_dpt``, else over the whole range), its peak declared
        unless it hardly rises above the noise or the scan frames' cross-blur focus contradicts it
        (:meth:`_contrast_contradicted`: the lens then goes to that focus, nothing declared)."""
        self.state = State.CONTRAST
        kwargs = dict(self.contrast_kwargs)
        kwargs.setdefault("light", self._contrast_light())
        if centre_dpt is not None:  # a local search around the DFD answer
            kwargs.setdefault("span_dpt", (centre_dpt - 0.6, centre_dpt + 0.6))
        search = ContrastSearch(self.camera, roi=self.roi, **kwargs)
        peak = yield from search.search(self)
        frame_hw = search.frames[-1][0].shape[-2:] if search.frames else None
        elsewhere = None if frame_hw is None else self._contrast_contradicted(search.frames, peak, self._roi_for(frame_hw))
        power = self.check_power(peak if elsewhere is None else elsewhere)
        self.state = State.MOVE_FOCUS
        ack = yield from self._set_power(power)
        self.result.method = "contrast"
        self.result.power_dpt = power
        self.result.history.append((ack.ready_s, power, None))
        if elsewhere is not None:  # a side-lobe peak: the lens is at the frames' focus, nothing declared
            self._undeclared(f"the contrast peak is contradicted by its frames' cross-blur focus {power:.3f} dpt "
                             "(the lens is there)")
            return
        values = [v for _, v in search.samples]
        if values and not max(values) >= self.contrast_min_peak * min(values) > 0:
            # a peak that hardly rises above the scan's least sharp frame is sensor noise, not focus
            self._undeclared(f"no contrast peak: the sharpest frame is {max(values) / max(min(values), 1e-300):.3f}x "
                             f"the least sharp (below {self.contrast_min_peak:g}x)")
            return
        self._declare(ack.ready_s, "contrast")

    def _contrast_contradicted(self, frames: list, peak: float, roi: Roi) -> float | None:
        """With the PSF family known, the contrast search's frames (up to :data:`CONTRAST_CHECK_FRAMES`,
        evenly in power) checked by their cross-blur focus: returns that focus when it is credible
        (not at its span's edge, within the working powers, a cost contrast of at least
        ``cross_blur_min_contrast``) and farther than the verification tolerance from the contrast
        ``peak``, as is its runner-up unless the focus is unique (:meth:`_unique`); else ``None``.
        A periodic texture through a disk shows contrast peaks away from focus (the MTF's side
        lobes), which a contrast search can take for focus (fresh seed 29, trial 79: checkers at
        6 px). Charged as one 3-frame search per three frame pairs."""
        if not (self.cross_blur and self.psf_family is not None and len({p for _, p in frames}) >= 3):
            return None
        frames = evenly_thinned(sorted(frames, key=lambda fp: fp[1]), CONTRAST_CHECK_FRAMES)
        pairs = len(frames) * (len(frames) - 1) // 2
        self.result.cross_blur_measurements += -(-pairs // 3)
        try:
            cb = cross_blur_focus(frames, self.camera, roi, shapes=self._psf_families(), sigma_scale=self.psf_sigma_scale)
        except InputError as exc:
            log.info("no cross-blur check of the contrast peak: %s", exc)
            return None
        tol = self.verify_tolerance_px / blur_px_per_dpt(self.camera)
        log.info("contrast peak %.3f dpt; the scan frames' cross-blur focus %.3f dpt (contrast %.3f, runner-up %.3f dpt "
                 "at %.2fx, edge %s)", peak, cb.power_dpt, cb.contrast, cb.runner_up_power_dpt, cb.runner_up_ratio,
                 cb.at_edge)
        if (self._credible(cb, working_powers_dpt(self.camera)) and abs(cb.power_dpt - peak) > tol
                and (self._unique(cb, tol) or abs(cb.runner_up_power_dpt - peak) > tol)):
            return cb.power_dpt
        return None
