r"""Contrast-detect autofocus: the baseline DFD is measured against, and DFD's fallback.

A search over the ECVFL focal power that maximises a sharpness measure of the ROI,
driven through the same command/observation protocol as the DFD controller
(:mod:`tdfd.autofocus.controller`), so the bench counts its frames, lens moves and time
the same way.

Two strategies:

* ``"scan"`` (default, coarse-to-fine): a coarse scan at ``step_dpt`` spacing across
  the span, starting from the end nearer to the lens's present power; each move to the
  next scan point is commanded at the end of the previous exposure (pipelined, like a
  real contrast-AF loop). The scan stops early once the sharpness has fallen below
  ``stop_ratio`` of the best on two frames after it. The peak is refined by fitting a
  parabola to ``log(sharpness)`` through the best point and its neighbours; optionally
  (``fine=True``) one more frame at the refined power confirms it (kept only if sharper).
* ``"golden"``: golden-section search on ``[lo, hi]`` down to ``tol_dpt``; every
  evaluation waits for the previous frame (no pipelining).

Sharpness measures (on the ROI, normalised by the squared mean intensity so the
exposure does not matter): ``"laplacian"`` (variance of the 3x3 Laplacian of a lightly
smoothed image) and ``"tenengrad"`` (mean squared Sobel gradient).

Example:
    >>> import numpy as np
    >>> rng = np.random.default_rng(0)
    >>> sharp = rng.random((64, 64)).astype(np.float32)
    >>> import cv2
    >>> blurred = cv2.GaussianBlur(sharp, (0, 0), 2.0)
    >>> sharpness(sharp) > sharpness(blurred)
    True
"""

from __future__ import annotations

import logging
import math
from typing import TYPE_CHECKING, Generator, Sequence

import numpy as np

from ..camera import Camera
from ..errors import InputError
from .controller import (
    AFResult,
    Command,
    Observation,
    Roi,
    State,
    StateMachine,
    in_focus_power_dpt,
)

if TYPE_CHECKING:  # pragma: no cover
    pass

__all__ = ["sharpness", "texture_snr", "pair_texture_snr", "noise_variance", "ContrastSearch", "ContrastController", "MEASURES"]

log = logging.getLogger(__name__)

MEASURES = ("laplacian", "tenengrad")


def sharpness(image: np.ndarray, roi: Roi | None = None, measure: str = "laplacian") -> float:
    """Sharpness of the ROI of a frame (dimensionless, higher is sharper).

    Args:
        image: ``(H, W)`` linear intensity.
        roi: region (default: the whole frame).
        measure: ``"laplacian"`` or ``"tenengrad"``.

    Returns:
        The measure divided by the squared mean intensity of the ROI.
    """
    import cv2

    if measure not in MEASURES:
        raise InputError(f"sharpness measure must be one of {MEASURES}, got {measure!r}")
    img = np.asarray(image, dtype=np.float32)
    if img.ndim != 2:
        raise InputError(f"image must be (H, W), got {img.shape}")
    if roi is not None:
        img = roi.crop(img)
    mean = float(img.mean())
    norm = max(mean * mean, 1e-12)
    if measure == "laplacian":
        smooth = cv2.GaussianBlur(img, (5, 5), 0.8, borderType=cv2.BORDER_REFLECT)
        lap = cv2.Laplacian(smooth, cv2.CV_32F, ksize=3, borderType=cv2.BORDER_REFLECT)
        return float(lap[2:-2, 2:-2].var()) / norm
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3, borderType=cv2.BORDER_REFLECT)
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3, borderType=cv2.BORDER_REFLECT)
    return float((gx[1:-1, 1:-1] ** 2 + gy[1:-1, 1:-1] ** 2).mean()) / norm


def noise_variance(image: np.ndarray) -> float:
    """Robust white-noise variance of a frame (intensity units squared).

    From the median absolute deviation of the diagonal second difference
    ``x[i,j] - x[i+1,j] - x[i,j+1] + x[i+1,j+1]`` (variance ``4 s^2`` for white noise of
    variance ``s^2``), whose pass band holds little of a defocused image's signal.
    """
    x = np.asarray(image, dtype=np.float64)
    d = x[:-1, :-1] - x[1:, :-1] - x[:-1, 1:] + x[1:, 1:]
    mad = float(np.median(np.abs(d - np.median(d))))
    return (mad / 0.6745) ** 2 / 4.0


_DOG_CACHE: dict[tuple[float, float], tuple[np.ndarray, float]] = {}


def texture_snr(image: np.ndarray, roi: Roi | None = None, sigmas_px: tuple[float, float] = (1.0, 2.0),
                noise_var: float | None = None) -> float:
    """Band-pass contrast of the ROI relative to the noise floor (dimensionless; ~1 for a texture-less target).

    The variance of a difference-of-Gaussians (``sigmas_px``, periods of about 6-12 px)
    divided by what white noise of variance ``noise_var`` would give through the same
    filter. A texture-less or uniformly lit target reads about 1; usable texture reads
    several times more. ``noise_var`` defaults to :func:`noise_variance` of the ROI itself,
    which a sharp pixel-scale texture inflates: pass the estimate of a blurrier frame of
    the same scene when there is one (:func:`pair_texture_snr`).

    Args:
        image: ``(H, W)`` linear intensity.
        roi: region (default: the whole frame).
        sigmas_px: the two Gaussian widths (px).
        noise_var: the noise variance (intensity units squared).

    Example:
        >>> rng = np.random.default_rng(0)
        >>> flat = 0.5 + 0.01 * rng.standard_normal((96, 96))
        >>> import cv2
        >>> textured = flat + cv2.GaussianBlur(0.2 * rng.random((96, 96)), (0, 0), 2.0)
        >>> texture_snr(flat) < 1.5 < texture_snr(textured)
        True
    """
    import cv2

    img = np.asarray(image, dtype=np.float32)
    if roi is not None:
        img = roi.crop(img)
    key = (float(sigmas_px[0]), float(sigmas_px[1]))
    if key not in _DOG_CACHE:
        half = int(math.ceil(4 * max(key)))
        g1 = cv2.getGaussianKernel(2 * half + 1, key[0])
        g2 = cv2.getGaussianKernel(2 * half + 1, key[1])
        dog = (g1 @ g1.T - g2 @ g2.T).astype(np.float32)
        _DOG_CACHE[key] = (dog, float((dog.astype(np.float64) ** 2).sum()))
    dog, gain = _DOG_CACHE[key]
    half = dog.shape[0] // 2
    if min(img.shape) <= 2 * half + 2:
        raise InputError(f"ROI {img.shape} too small for the texture measure (needs > {2 * half + 2} px)")
    band = cv2.filter2D(img, cv2.CV_32F, dog, borderType=cv2.BORDER_REFLECT)[half:-half, half:-half]
    nv = noise_variance(img) if noise_var is None else float(noise_var)
    return float(band.astype(np.float64).var() / max(nv * gain, 1e-20))


def pair_texture_snr(image_f1: np.ndarray, image_f2: np.ndarray, roi: Roi | None = None) -> float:
    """:func:`texture_snr` of the more textured frame of a DFD pair, against the smaller
    noise estimate of the two (the blurrier frame's is the least inflated by texture).

    Example:
        >>> rng = np.random.default_rng(1)
        >>> a, b = (0.5 + 0.01 * rng.standard_normal((96, 96)) for _ in range(2))
        >>> pair_texture_snr(a, b) < 1.5
        True
    """
    x1, x2 = (np.asarray(im, dtype=np.float32) for im in (image_f1, image_f2))
    if roi is not None:
        x1, x2 = roi.crop(x1), roi.crop(x2)
    nv = min(noise_variance(x1), noise_variance(x2))
    return max(texture_snr(x1, noise_var=nv), texture_snr(x2, noise_var=nv))


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
    """A contrast-detect focus search, run inside a :class:`~tdfd.autofocus.controller.StateMachine`.

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
    """

    def __init__(self, camera: Camera, roi: Roi | None = None, strategy: str = "scan", measure: str = "laplacian",
                 span_dpt: tuple[float, float] | None = None, margin_dpt: float = 0.15, step_dpt: float = 0.4,
                 stop_ratio: float = 0.6, fine: bool = False, tol_dpt: float = 0.15) -> None:
        if strategy not in ("scan", "golden"):
            raise InputError(f"contrast strategy must be 'scan' or 'golden', got {strategy!r}")
        if measure not in MEASURES:
            raise InputError(f"sharpness measure must be one of {MEASURES}, got {measure!r}")
        if step_dpt <= 0 or tol_dpt <= 0:
            raise InputError("step_dpt and tol_dpt must be > 0")
        self.camera, self.roi, self.strategy, self.measure = camera, roi, strategy, measure
        if span_dpt is None:
            near, far = camera.depth_range_m
            span_dpt = (in_focus_power_dpt(camera, far) - margin_dpt, in_focus_power_dpt(camera, near) + margin_dpt)
        lo, hi = sorted(float(v) for v in span_dpt)
        self.span_dpt = (lo, hi)
        self.step_dpt, self.stop_ratio, self.fine, self.tol_dpt = float(step_dpt), float(stop_ratio), bool(fine), float(tol_dpt)
        self.samples: list[tuple[float, float]] = []  # (power_dpt, sharpness) in capture order

    def _span(self, machine: StateMachine) -> tuple[float, float]:
        lo, hi = self.span_dpt
        if machine.power_limits_dpt is not None:
            lo, hi = max(lo, machine.power_limits_dpt[0]), min(hi, machine.power_limits_dpt[1])
            if lo > hi:
                raise InputError(f"the contrast search span {self.span_dpt} lies outside the lens range {machine.power_limits_dpt}")
        return lo, hi

    def _measure(self, frame) -> float:
        roi = (self.roi or Roi.centre(frame.image.shape[-2:])).clip(frame.image.shape[-2:])
        s = sharpness(frame.image, roi, self.measure)
        self.samples.append((frame.power_dpt, s))
        return s

    def search(self, machine: StateMachine) -> Generator[Command, Observation, float]:
        """The search as a sub-generator of ``machine``; returns the best power (dpt).

        The lens is left wherever the search last moved it; the caller commands the
        returned power.
        """
        machine.state = State.CONTRAST
        self.samples = []
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
        yield from machine._set_power(float(powers[0]))
        values: list[float] = []
        for i, p in enumerate(powers):
            nxt = float(powers[i + 1]) if i + 1 < len(powers) else None
            frame, _ = yield from machine._capture("contrast", then_power_dpt=nxt)
            values.append(self._measure(frame))
            best = int(np.argmax(values))
            if i - best >= 2 and values[-1] < self.stop_ratio * values[best] and values[-2] < values[best]:
                log.debug("contrast scan: stopping after %d frames (peak passed)", i + 1)
                break
        best = int(np.argmax(values))
        p_best = _refine_peak([float(p) for p in powers[: len(values)]], values, best, self.step_dpt)
        if self.fine and abs(p_best - float(powers[best])) > 1e-6:
            yield from machine._set_power(p_best)
            frame, _ = yield from machine._capture("contrast")
            if self._measure(frame) < values[best]:
                p_best = float(powers[best])
        log.info("contrast scan: peak at %.3f dpt after %d frames", p_best, len(self.samples))
        return p_best

    def _golden(self, machine: StateMachine) -> Generator[Command, Observation, float]:
        lo, hi = self._span(machine)
        g = (math.sqrt(5.0) - 1.0) / 2.0
        a, b = lo, hi
        c, d = b - g * (b - a), a + g * (b - a)

        def evaluate(p: float) -> Generator[Command, Observation, float]:
            yield from machine._set_power(p)
            frame, _ = yield from machine._capture("contrast")
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
            :class:`~tdfd.autofocus.controller.StateMachine`.
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
        res.power_dpt, res.status, res.t_focus_s = power, "focused", ack.ready_s
        res.history.append((ack.ready_s, power, None))
