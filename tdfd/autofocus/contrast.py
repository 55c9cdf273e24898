r"""Contrast-detect autofocus: the baseline DFD is measured against, and DFD's fallback.

A search over the ECVFL focal power that maximises a sharpness measure of the ROI
(:func:`tdfd.autofocus.sharpness.sharpness`), driven through the same command/observation
protocol as the DFD controller (:mod:`tdfd.autofocus.messages`,
:class:`tdfd.autofocus.machine.StateMachine`), so the bench counts its frames, lens moves
and time the same way.

Two strategies:

* ``"scan"`` (default, coarse-to-fine): a coarse scan at ``step_dpt`` spacing across
  the span, starting from the end nearer to the lens's present power; each move to the
  next scan point is commanded at the end of the previous exposure (pipelined, like a
  real contrast-AF loop). The scan stops early once the sharpness has fallen below
  ``stop_ratio`` of the best on two frames after it. The peak is refined by fitting a
  parabola to ``log(sharpness)`` through the best point and its neighbours; optionally
  (``fine=True``) one more frame at the refined power confirms it (kept only if sharper).
  A sharpest frame at an edge of the span is no peak (the sharpness may rise beyond it):
  the scan then goes on outwards, one step at a time, up to ``range_dpt`` (default: the
  camera's working range), until the peak is passed or the range ends (``extend=True``).
* ``"golden"``: golden-section search on ``[lo, hi]`` down to ``tol_dpt``; every
  evaluation waits for the previous frame (no pipelining).
"""

from __future__ import annotations

import logging
import math
from typing import Generator, Sequence

import numpy as np

from ..camera import Camera
from ..errors import InputError
from .evidence import blur_px_per_dpt, working_powers_dpt
from .machine import StateMachine
from .messages import AFResult, Command, Observation, State
from .roi import Roi
from .sharpness import MEASURES, sharpness

__all__ = ["ContrastSearch", "ContrastController"]

log = logging.getLogger(__name__)


def _parabola_peak(x: tuple[float, float, float], y: tuple[float, float, float]) -> float | None:
    """Vertex of the parabola through three points (``None`` if it is not a maximum)."""
    (x0, x1, x2), (y0, y1, y2) = x, y
    d = (x0 - x1) * (x0 - x2) * (x1 - x2)
    if d == 0:
        return None
    a = (x2 * (y1 - y0) + x1 * (y0 - y2) + x0 * (y2 - y1)) / d
    b = (x2 * x2 * (y0 - y1) + x1 * x1 * (y2 - y0) + x0 * x0 * (y1 - y2)) / d
    if a >= 0:
        return None
    return -b / (2 * a)


def _refine_peak(powers: Sequence[float], values: Sequence[float], best: int, step: float) -> float:
    """Sub-sample peak: vertex of the parabola through ``log(sharpness)`` of three neighbouring samples.

    The three samples are centred on the best one, shifted inwards at an edge of the
    scanned set; the vertex is kept only if it is a maximum within half a step of the
    three samples' span, else the best sample's power is returned.
    """
    if len(powers) < 3:
        return float(powers[best])
    order = np.argsort(powers)
    xs = [float(powers[i]) for i in order]
    ys = [math.log(max(float(values[i]), 1e-30)) for i in order]
    k = int(np.where(order == best)[0][0])
    k = min(max(k, 1), len(xs) - 2)
    x, y = tuple(xs[k - 1 : k + 2]), tuple(ys[k - 1 : k + 2])
    vertex = _parabola_peak(x, y)  # type: ignore[arg-type]
    if vertex is None or not (min(x) - 0.5 * step <= vertex <= max(x) + 0.5 * step):
        return float(powers[best])
    return float(vertex)


class ContrastSearch:
    """A contrast-detect focus search, run inside a :class:`~tdfd.autofocus.machine.StateMachine`.

    Args:
        camera: camera description; the default span covers its working range.
        roi: region whose sharpness is maximised (default: the centred half of the frame).
        strategy: ``"scan"`` (coarse-to-fine) or ``"golden"`` (golden-section).
        measure: sharpness measure (see :func:`sharpness`).
        span_dpt: ``(lo, hi)`` ECVFL powers searched (dpt); default: the in-focus powers of
            the camera's depth range widened by ``margin_dpt``.
        margin_dpt: widening of the default span on each side (dpt).
        step_dpt: coarse scan spacing (dpt).
        stop_ratio: the scan stops once two frames after the best are below
            ``stop_ratio`` times its sharpness.
        fine: capture one more frame at the refined peak (scan strategy).
        tol_dpt: final bracket width of the golden-section search (dpt).
        light: the assist-light pattern every search frame is lit with (``Capture(..., light=)``;
            the plant's light guard enforces its limits); ``None``: unlit frames.
        fine_scan_px: a camera whose blur changes by more than this (geometric radius, px)
            over one ``step_dpt`` has a depth of field the coarse scan cannot resolve (the
            4x-binned paper camera: 9 px per 0.4 dpt); the scan strategy then scans again
            around its peak, one step wide, in steps of ``fine_scan_px / 2`` px of blur, and
            takes that scan's peak. 0 disables; the reference camera (1.1 px per step) never
            takes it.
        extend: scan on beyond an edge of ``span_dpt`` where the sharpest frame lies at it
            (scan strategy; a local search around a DFD estimate that missed by more than
            its span would otherwise declare the edge: on the reliability benchmark all
            three contrast declarations out of focus were such edges).
        range_dpt: ``(lo, hi)`` the furthest an extended scan goes (dpt); default: the
            in-focus powers of the camera's depth range widened by ``margin_dpt``.
    """

    def __init__(self, camera: Camera, roi: Roi | None = None, strategy: str = "scan", measure: str = "laplacian",
                 span_dpt: tuple[float, float] | None = None, margin_dpt: float = 0.15, step_dpt: float = 0.4,
                 stop_ratio: float = 0.6, fine: bool = False, tol_dpt: float = 0.15, light: str | None = None,
                 fine_scan_px: float = 2.0, extend: bool = True, range_dpt: tuple[float, float] | None = None) -> None:
        if strategy not in ("scan", "golden"):
            raise InputError(f"contrast strategy must be 'scan' or 'golden', got {strategy!r}")
        if measure not in MEASURES:
            raise InputError(f"sharpness measure must be one of {MEASURES}, got {measure!r}")
        if step_dpt <= 0 or tol_dpt <= 0:
            raise InputError("step_dpt and tol_dpt must be > 0")
        self.camera, self.roi, self.strategy, self.measure = camera, roi, strategy, measure
        working = working_powers_dpt(camera, margin_dpt)
        lo, hi = sorted(float(v) for v in (working if span_dpt is None else span_dpt))
        self.span_dpt = (lo, hi)
        r_lo, r_hi = sorted(float(v) for v in (working if range_dpt is None else range_dpt))
        if not all(math.isfinite(v) for v in (lo, hi, r_lo, r_hi)):
            raise InputError(f"contrast search span {span_dpt} and range {range_dpt} must be finite")
        self.range_dpt = (min(r_lo, lo), max(r_hi, hi))
        self.extend = bool(extend)
        self.step_dpt, self.stop_ratio, self.fine, self.tol_dpt = float(step_dpt), float(stop_ratio), bool(fine), float(tol_dpt)
        self.light, self.fine_scan_px = light, float(fine_scan_px)
        if self.fine_scan_px < 0:
            raise InputError(f"fine_scan_px must be >= 0, got {fine_scan_px}")
        self.samples: list[tuple[float, float]] = []  # (power_dpt, sharpness) in capture order
        self.frames: list[tuple[np.ndarray, float]] = []  # (image, power_dpt) in capture order

    def _span(self, machine: StateMachine, span: tuple[float, float] | None = None) -> tuple[float, float]:
        """``span`` (default ``span_dpt``) within the lens's power limits."""
        lo, hi = span or self.span_dpt
        if machine.power_limits_dpt is not None:
            lo, hi = max(lo, machine.power_limits_dpt[0]), min(hi, machine.power_limits_dpt[1])
            if lo > hi:
                raise InputError(f"the contrast search span {(lo, hi)} lies outside the lens range {machine.power_limits_dpt}")
        return lo, hi

    def _measure(self, frame) -> float:
        roi = (self.roi or Roi.centre(frame.image.shape[-2:])).clip(frame.image.shape[-2:])
        s = sharpness(frame.image, roi, self.measure)
        self.samples.append((frame.power_dpt, s))
        self.frames.append((frame.image, frame.power_dpt))
        return s

    def search(self, machine: StateMachine) -> Generator[Command, Observation, float]:
        """The search as a sub-generator of ``machine``; returns the best power (dpt).

        The lens is left wherever the search last moved it; the caller commands the
        returned power.
        """
        machine.state = State.CONTRAST
        self.samples, self.frames = [], []
        if self.strategy == "golden":
            return (yield from self._golden(machine))
        return (yield from self._scan(machine))

    def _scan(self, machine: StateMachine) -> Generator[Command, Observation, float]:
        lo, hi = self._span(machine)
        n = max(2, int(math.ceil((hi - lo) / self.step_dpt - 1e-9)) + 1)
        powers = list(np.linspace(lo, hi, n))
        here = machine._lens_power
        if here is not None and abs(here - hi) < abs(here - lo):
            powers.reverse()
        values = yield from self._sweep(machine, powers, stop_early=True)
        powers = [float(p) for p in powers[: len(values)]]
        if self.extend:
            yield from self._extend(machine, powers, values)
        best = int(np.argmax(values))
        p_best = _refine_peak(powers, values, best, self.step_dpt)
        if self.fine and abs(p_best - float(powers[best])) > 1e-6:
            yield from machine._set_power(p_best)
            frame, _ = yield from machine._capture("contrast", light=self.light)
            if self._measure(frame) < values[best]:
                p_best = float(powers[best])
        px_per_dpt = blur_px_per_dpt(self.camera)
        if self.fine_scan_px > 0 and px_per_dpt * self.step_dpt > self.fine_scan_px:
            p_best = yield from self._fine_scan(machine, p_best, px_per_dpt)
        log.info("contrast scan: peak at %.3f dpt after %d frames", p_best, len(self.samples))
        return p_best

    def _sweep(self, machine: StateMachine, powers: Sequence[float], stop_early: bool, before: float | None = None
               ) -> Generator[Command, Observation, list[float]]:
        """One frame at each of ``powers`` in order (each move commanded at the previous
        exposure's end) and its sharpness; with ``stop_early`` the sweep ends once two frames
        after the best have fallen below ``stop_ratio`` of it (the peak is passed). ``before``:
        the sharpness of the frame just before ``powers[0]`` (a sweep that continues a scan)."""
        yield from machine._set_power(float(powers[0]))
        seen = [] if before is None else [float(before)]
        for i in range(len(powers)):
            nxt = float(powers[i + 1]) if i + 1 < len(powers) else None
            frame, _ = yield from machine._capture("contrast", then_power_dpt=nxt, light=self.light)
            seen.append(self._measure(frame))
            best = int(np.argmax(seen))
            if (stop_early and len(seen) - 1 - best >= 2 and seen[-1] < self.stop_ratio * seen[best]
                    and seen[-2] < seen[best]):
                log.debug("contrast scan: stopping after %d frames (peak passed)", i + 1)
                break
        return seen if before is None else seen[1:]

    def _extend(self, machine: StateMachine, powers: list[float], values: list[float]
                ) -> Generator[Command, Observation, None]:
        """While the sharpest frame lies at an edge of the scanned powers and ``range_dpt``
        goes on beyond it, scan on outwards from that edge (``powers`` and ``values`` grow)."""
        r_lo, r_hi = self._span(machine, self.range_dpt)
        while True:
            best = int(np.argmax(values))
            top, bottom = max(powers), min(powers)
            if powers[best] >= top and top < r_hi - 1e-6:
                n = int(math.ceil((r_hi - top) / self.step_dpt - 1e-9))
                outward = [min(r_hi, top + self.step_dpt * k) for k in range(1, n + 1)]
            elif powers[best] <= bottom and bottom > r_lo + 1e-6:
                n = int(math.ceil((bottom - r_lo) / self.step_dpt - 1e-9))
                outward = [max(r_lo, bottom - self.step_dpt * k) for k in range(1, n + 1)]
            else:
                return
            log.info("contrast scan: the sharpest frame (%.3f dpt) is at the edge of the scanned %.3f..%.3f dpt: "
                     "scanning on outwards", powers[best], bottom, top)
            more = yield from self._sweep(machine, outward, stop_early=True, before=values[best])
            powers += outward[: len(more)]
            values += more

    def _fine_scan(self, machine: StateMachine, centre: float, px_per_dpt: float) -> Generator[Command, Observation, float]:
        """A second scan one coarse step wide around ``centre``, in steps of half
        ``fine_scan_px`` of blur: the coarse peak of a shallow depth of field is off by up to
        half a step (several px of blur)."""
        lo, hi = self._span(machine, self.range_dpt if self.extend else None)
        a, b = max(lo, centre - 0.5 * self.step_dpt), min(hi, centre + 0.5 * self.step_dpt)
        step = 0.5 * self.fine_scan_px / px_per_dpt
        n = max(3, int(math.ceil((b - a) / step - 1e-9)) + 1)
        powers = [float(p) for p in np.linspace(a, b, n)]
        values = yield from self._sweep(machine, powers, stop_early=False)
        best = int(np.argmax(values))
        return _refine_peak(powers, values, best, (b - a) / (n - 1))

    def _golden(self, machine: StateMachine) -> Generator[Command, Observation, float]:
        lo, hi = self._span(machine)
        g = (math.sqrt(5.0) - 1.0) / 2.0
        a, b = lo, hi
        c, d = b - g * (b - a), a + g * (b - a)

        def evaluate(p: float) -> Generator[Command, Observation, float]:
            yield from machine._set_power(p)
            frame, _ = yield from machine._capture("contrast", light=self.light)
            return self._measure(frame)

        fc = yield from evaluate(c)
        fd = yield from evaluate(d)
        while b - a > self.tol_dpt:
            if fc >= fd:
                b, d, fd = d, c, fc
                c = b - g * (b - a)
                fc = yield from evaluate(c)
            else:
                a, c, fc = c, d, fd
                d = a + g * (b - a)
                fd = yield from evaluate(d)
        pts = sorted(self.samples)
        k = int(np.argmax([s for _, s in pts]))
        p_best = _refine_peak([p for p, _ in pts], [s for _, s in pts], k, max(self.tol_dpt, self.step_dpt))
        log.info("contrast golden-section: peak at %.3f dpt after %d frames", p_best, len(self.samples))
        return float(p_best)


class ContrastController(StateMachine):
    """Contrast-detect autofocus as a state machine (the baseline, ``--method contrast``).

    Args:
        camera: camera description (span of the search).
        roi: region of interest in frame pixels (default: the centred half).
        settle_s, lens_retries, capture_retries, power_limits_dpt: see
            :class:`~tdfd.autofocus.machine.StateMachine`.
        **search: keyword arguments of :class:`ContrastSearch` (strategy, measure, ...).
    """

    def __init__(self, camera: Camera, *, roi: Roi | None = None, settle_s: float = 0.015, lens_retries: int = 2,
                 capture_retries: int = 1, power_limits_dpt: tuple[float, float] | None = None, **search) -> None:
        super().__init__(settle_s, lens_retries, capture_retries, power_limits_dpt)
        self.camera, self.roi = camera, roi
        self.search_kwargs = search
        ContrastSearch(camera, roi=roi, **search)  # validate the options now

    def _initial_method(self) -> str:
        return "contrast"

    def _run(self) -> Generator[Command, Observation, None]:
        search = ContrastSearch(self.camera, roi=self.roi, **self.search_kwargs)
        power = yield from search.search(self)
        power = self.check_power(power)
        self.state = State.MOVE_FOCUS
        ack = yield from self._set_power(power)
        res: AFResult = self.result
        res.power_dpt, res.status, res.t_focus_s, res.evidence = power, "focused", ack.ready_s, "contrast"
        res.history.append((ack.ready_s, power, None))
