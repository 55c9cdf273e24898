r"""The DFD autofocus controller: a pure state machine (observation in, command out).

The controller never touches hardware, threads or clocks. Whoever drives it (the
simulated bench, :mod:`tdfd.autofocus.bench`, or the real-hardware loop,
:mod:`tdfd.autofocus.hardware`) executes each :class:`Command` and answers with an
:class:`Observation`::

    ctrl = DFDController(camera)
    cmd = ctrl.start()
    while not isinstance(cmd, Done):
        cmd = ctrl.step(plant.execute(cmd))     # see :func:`drive`
    print(cmd.result)

One single-shot DFD focus (paper sec. 3, "focal length as the varying parameter"):

1. ``SetPower(P_e1)``, ``Capture("f1", then_power_dpt=P_e2)``: the first frame once the
   lens has settled; the move to ``P_e2`` is commanded at the end of its exposure.
2. ``Capture("f2")`` once the lens has settled at ``P_e2``.
3. ``Estimate(f1, f2)``: the depth model (ONNX runtime, or any :class:`Estimator`).
4. ROI aggregation (:func:`aggregate_depth`): confidence-weighted median of inverse
   depth, then a trimmed weighted mean of the inliers.
5. In-focus power ``P_e = 1/d_o + 1/d_s - 1/f0`` (CONTRACT section 1), checked against
   the lens's range (clamped only with an explicit error in the result).
6. ``SetPower(P_e)``; focus is reached when the lens has settled.
7. Optionally ``Capture("verify")``: the ROI sharpness at ``P_e`` must not fall below
   that of the DFD pair, else a contrast-detect search around ``P_e`` takes over.

When the ROI confidence is too low (a texture-less target) the controller says so
(log and :attr:`AFResult.fallback_reason`) and falls back to the contrast-detect search
of :mod:`tdfd.autofocus.contrast`. Lens faults are retried (``lens_retries``), then the
run ends with ``status="failed"`` and the reason; the loop itself never raises for a
hardware fault.

Example:
    >>> import numpy as np
    >>> from tdfd import Camera
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

import enum
import logging
import math
from dataclasses import dataclass, field
from typing import Any, Generator, Optional, Protocol, Sequence, Union, runtime_checkable

import numpy as np

from ..camera import Camera
from ..errors import InputError, TdfdError

__all__ = [
    "ControllerError",
    "Roi",
    "roi_tile_mask",
    "roi_crop_box",
    "DepthAggregate",
    "aggregate_depth",
    "in_focus_power_dpt",
    "Estimator",
    "LensLike",
    "SetPower",
    "Capture",
    "Estimate",
    "Done",
    "Command",
    "LensAck",
    "LensFault",
    "Frame",
    "CaptureFault",
    "Estimation",
    "EstimateFault",
    "Halt",
    "Observation",
    "State",
    "AFResult",
    "Plant",
    "StateMachine",
    "DFDController",
    "drive",
]

log = logging.getLogger(__name__)


class ControllerError(TdfdError, RuntimeError):
    """The controller was driven wrongly (an observation that does not answer the last command)."""


# ------------------------------------------------------------------------------ ROI
@dataclass(frozen=True)
class Roi:
    """A rectangular region of interest in frame pixels.

    Args:
        x: left column (px).
        y: top row (px).
        w: width (px).
        h: height (px).
    """

    x: int
    y: int
    w: int
    h: int

    def __post_init__(self) -> None:
        if self.w <= 0 or self.h <= 0 or self.x < 0 or self.y < 0:
            raise InputError(f"ROI must have x, y >= 0 and w, h > 0, got {self}")

    @classmethod
    def parse(cls, text: str) -> "Roi":
        """Parse ``"x,y,w,h"`` (pixels)."""
        try:
            x, y, w, h = (int(round(float(v))) for v in text.split(","))
        except ValueError:
            raise InputError(f"ROI must be 'x,y,w,h' in pixels, got {text!r}") from None
        return cls(x, y, w, h)

    @classmethod
    def centre(cls, frame_hw: tuple[int, int], fraction: float = 0.5) -> "Roi":
        """The centred ROI covering ``fraction`` of each side of a ``(H, W)`` frame."""
        hh, ww = frame_hw
        h, w = max(1, int(round(hh * fraction))), max(1, int(round(ww * fraction)))
        return cls((ww - w) // 2, (hh - h) // 2, w, h)

    def clip(self, frame_hw: tuple[int, int]) -> "Roi":
        """The ROI clipped to a ``(H, W)`` frame.

        Raises:
            InputError: if the ROI lies entirely outside the frame.
        """
        hh, ww = frame_hw
        x0, y0 = min(self.x, ww), min(self.y, hh)
        x1, y1 = min(self.x + self.w, ww), min(self.y + self.h, hh)
        if x1 <= x0 or y1 <= y0:
            raise InputError(f"ROI {self} lies outside the {hh}x{ww} frame")
        return Roi(x0, y0, x1 - x0, y1 - y0)

    def crop(self, image: np.ndarray) -> np.ndarray:
        """``image[..., y:y+h, x:x+w]`` (clipped to the image)."""
        r = self.clip(image.shape[-2:])
        return image[..., r.y : r.y + r.h, r.x : r.x + r.w]

    def __str__(self) -> str:
        return f"{self.x},{self.y},{self.w},{self.h}"


def _tile_range(start: int, length: int, n: int, tile: int, stride: int) -> tuple[int, int]:
    """First and last tile index (inclusive) whose centre lies in the pixels ``start … start + length - 1``.

    Pixel ``k`` spans ``[k - 0.5, k + 0.5)``; tile ``i``'s centre is ``i*stride + (tile-1)/2``.
    """
    c0 = (tile - 1) / 2.0
    lo = max(0, math.ceil((start - 0.5 - c0) / stride))
    hi = min(n - 1, math.ceil((start + length - 0.5 - c0) / stride) - 1)
    if hi < lo:  # no centre inside: the tile nearest to the middle
        k = min(max(int(round((start + (length - 1) / 2.0 - c0) / stride)), 0), n - 1)
        return k, k
    return lo, hi


def roi_tile_mask(roi: Roi | None, grid_hw: tuple[int, int], tile: int, stride: int,
                  offset: tuple[int, int] = (0, 0)) -> np.ndarray:
    """Boolean ``(h, w)`` mask of the tiles whose centre lies inside ``roi``.

    Tile ``(i, j)`` covers rows ``offset[0] + i*stride … + tile - 1`` of the frame
    (CONTRACT.md section 2; ``offset`` is the origin of a crop the grid was computed on).
    If no tile centre falls inside a small ROI, the tile whose centre is nearest to the
    ROI centre is used. ``roi=None`` selects every tile.

    Example:
        >>> int(roi_tile_mask(Roi(64, 64, 64, 64), (5, 5), 64, 32).sum())
        4
    """
    gh, gw = grid_hw
    if roi is None:
        return np.ones((gh, gw), bool)
    r0, r1 = _tile_range(roi.y - offset[0], roi.h, gh, tile, stride)
    c0, c1 = _tile_range(roi.x - offset[1], roi.w, gw, tile, stride)
    mask = np.zeros((gh, gw), bool)
    mask[r0 : r1 + 1, c0 : c1 + 1] = True
    return mask


def roi_crop_box(roi: Roi, frame_hw: tuple[int, int], tile: int, stride: int) -> tuple[int, int, int, int]:
    """The smallest grid-aligned crop ``(y0, y1, x0, x1)`` holding every tile of :func:`roi_tile_mask`.

    Running the estimator on ``frame[y0:y1, x0:x1]`` gives exactly those tiles (the crop
    starts on a multiple of ``stride``), at a fraction of the full frame's cost.

    Example:
        >>> roi_crop_box(Roi(80, 64, 160, 128), (256, 320), 64, 32)
        (32, 192, 64, 256)
    """
    from ..grid import grid_shape

    gh, gw = grid_shape(frame_hw[0], frame_hw[1], tile, stride)
    r0, r1 = _tile_range(roi.y, roi.h, gh, tile, stride)
    c0, c1 = _tile_range(roi.x, roi.w, gw, tile, stride)
    return r0 * stride, r1 * stride + tile, c0 * stride, c1 * stride + tile


# ------------------------------------------------------------------------ aggregation
@dataclass(frozen=True)
class DepthAggregate:
    """A robust depth for a region of the tile grid.

    Attributes:
        depth_m: aggregated object distance (m); ``inf`` if the inverse depth is <= 0.
        inverse_depth: aggregated ``1/d_o`` (1/m, i.e. dioptres of defocus).
        confidence: mean tile confidence over the region, in [0, 1].
        spread_dpt: confidence-weighted standard deviation of the inliers' inverse depth (1/m).
        tiles: tiles in the region.
        inliers: tiles kept after trimming.
    """

    depth_m: float
    inverse_depth: float
    confidence: float
    spread_dpt: float
    tiles: int
    inliers: int


def _weighted_median(values: np.ndarray, weights: np.ndarray) -> float:
    order = np.argsort(values, kind="stable")
    v, w = values[order], weights[order]
    cum = np.cumsum(w)
    half = 0.5 * cum[-1]
    k = int(np.searchsorted(cum, half))
    # average the two middle values when the half-weight falls exactly on a boundary
    if k + 1 < len(v) and math.isclose(cum[k], half, rel_tol=1e-12, abs_tol=0.0):
        return float(0.5 * (v[k] + v[k + 1]))
    return float(v[min(k, len(v) - 1)])


def aggregate_depth(depth_m: np.ndarray, confidence: np.ndarray, mask: np.ndarray | None = None, *,
                    trim_sigmas: float = 3.0, min_trim_dpt: float = 0.05) -> DepthAggregate:
    r"""Confidence-weighted, outlier-robust depth of a region of the tile grid.

    Works in inverse depth ``q = 1/d_o``, where blur and the in-focus power are linear
    (paper eq. 4). First the confidence-weighted median ``q_med`` and the weighted median
    absolute deviation ``MAD``; tiles with ``|q - q_med| > max(trim_sigmas * 1.4826 MAD,
    min_trim_dpt)`` are dropped; the result is the confidence-weighted mean of the rest.

    Args:
        depth_m: ``(h, w)`` depth per tile in metres (> 0; non-finite tiles are ignored).
        confidence: ``(h, w)`` confidence per tile in [0, 1].
        mask: ``(h, w)`` boolean region (default: every tile).
        trim_sigmas: inlier half-width in robust standard deviations.
        min_trim_dpt: lower bound of the inlier half-width in 1/m.

    Returns:
        A :class:`DepthAggregate`. With zero total confidence the unweighted median is used
        and ``confidence`` is 0.

    Raises:
        InputError: shapes disagree or the region holds no finite tile.

    Example:
        >>> d = np.full((3, 3), 0.5); d[0, 0] = 5.0          # one wild outlier
        >>> c = np.full((3, 3), 0.8); c[1, 1] = 0.0
        >>> a = aggregate_depth(d, c)
        >>> round(a.depth_m, 6), a.inliers, a.tiles
        (0.5, 8, 9)
    """
    depth_m = np.asarray(depth_m, dtype=np.float64)
    confidence = np.asarray(confidence, dtype=np.float64)
    if depth_m.shape != confidence.shape or depth_m.ndim != 2:
        raise InputError(f"depth and confidence must be (h, w) of one shape, got {depth_m.shape} and {confidence.shape}")
    if mask is None:
        mask = np.ones(depth_m.shape, bool)
    elif mask.shape != depth_m.shape:
        raise InputError(f"mask shape {mask.shape} differs from the grid {depth_m.shape}")
    sel = mask & np.isfinite(depth_m) & (depth_m > 0) & np.isfinite(confidence)
    n = int(mask.sum())
    if not sel.any():
        raise InputError("the region holds no tile with a finite, positive depth")
    q = 1.0 / depth_m[sel]
    w = np.clip(confidence[sel], 0.0, 1.0)
    mean_conf = float(np.clip(np.where(np.isfinite(confidence[mask]), confidence[mask], 0.0), 0, 1).mean())
    if w.sum() <= 0:
        w = np.ones_like(q)
        mean_conf = 0.0
    med = _weighted_median(q, w)
    mad = _weighted_median(np.abs(q - med), w)
    half = max(trim_sigmas * 1.4826 * mad, min_trim_dpt)
    keep = np.abs(q - med) <= half
    wk, qk = w[keep], q[keep]
    qa = float(np.sum(wk * qk) / np.sum(wk)) if wk.sum() > 0 else med
    spread = float(np.sqrt(np.sum(wk * (qk - qa) ** 2) / np.sum(wk))) if wk.sum() > 0 else 0.0
    return DepthAggregate(depth_m=1.0 / qa if qa > 0 else math.inf, inverse_depth=qa, confidence=mean_conf,
                          spread_dpt=spread, tiles=n, inliers=int(keep.sum()))


def in_focus_power_dpt(camera: Camera, depth_m: float) -> float:
    """ECVFL power that focuses an object at ``depth_m`` metres: ``1/d_o + 1/d_s - 1/f0``.

    ``depth_m = inf`` gives the power that focuses at infinity.
    """
    if math.isinf(depth_m) and depth_m > 0:
        return 1.0 / camera.sensor_distance_m - camera.fixed_power_dpt
    return camera.in_focus_power_dpt(depth_m)


# ------------------------------------------------------------------------- protocols
@runtime_checkable
class Estimator(Protocol):
    """Two frames in, depth and confidence on the tile grid out.

    Attributes:
        camera: the camera the estimator was built for (its two ECVFL powers).
        tile: tile size (px).
        stride: tile stride (px).
    """

    camera: Camera
    tile: int
    stride: int

    def __call__(self, image_f1: np.ndarray, image_f2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(H, W)`` float32 linear intensity in [0, 1] each -> ``(depth_m, confidence)``, each ``(h, w)``."""
        ...


@runtime_checkable
class LensLike(Protocol):
    """The part of :class:`tdfd.driver.OptotuneLens` the autofocus loop uses."""

    def set_focal_power_dpt(self, power_dpt: float) -> None: ...

    def get_focal_power_dpt(self) -> float: ...


# -------------------------------------------------------------------------- commands
@dataclass(frozen=True)
class SetPower:
    """Command the ECVFL to ``power_dpt`` dioptres; the lens is usable ``settle_s`` later."""

    power_dpt: float
    settle_s: float


@dataclass(frozen=True)
class Capture:
    """Capture the next frame whose exposure starts after the lens has settled.

    If ``then_power_dpt`` is given, the lens is commanded there as soon as the exposure
    ends (camera exposure-end event), overlapping settling with the frame read-out.
    """

    tag: str
    then_power_dpt: float | None = None
    settle_s: float = 0.0


@dataclass(frozen=True)
class Estimate:
    """Run the depth estimator on ``(image_f1, image_f2)`` (frames at ``P_e1``, ``P_e2``).

    ``offset`` is the ``(row, column)`` of the images' origin in the frame when they are a
    crop around the ROI.
    """

    image_f1: np.ndarray
    image_f2: np.ndarray
    offset: tuple[int, int] = (0, 0)


@dataclass(frozen=True)
class Done:
    """The run has ended; ``result`` says how."""

    result: "AFResult"


Command = Union[SetPower, Capture, Estimate, Done]


# ---------------------------------------------------------------------- observations
@dataclass(frozen=True)
class LensAck:
    """The lens accepted ``power_dpt`` at time ``t_s``; it is settled at ``ready_s`` (seconds)."""

    power_dpt: float
    t_s: float
    ready_s: float


@dataclass(frozen=True)
class LensFault:
    """Commanding ``power_dpt`` failed (after the driver's own retries)."""

    power_dpt: float
    error: str
    t_s: float = 0.0


@dataclass(frozen=True)
class Frame:
    """A captured frame.

    Attributes:
        image: ``(H, W)`` float32 linear intensity in [0, 1].
        power_dpt: the ECVFL power requested for it (dioptres).
        t_start_s, t_end_s: exposure start and end (s).
        t_ready_s: when the frame reached the host (s).
        tag: the :class:`Capture` tag.
        lens: the answer to ``then_power_dpt`` (``None`` if none was asked).
    """

    image: np.ndarray
    power_dpt: float
    t_start_s: float
    t_end_s: float
    t_ready_s: float
    tag: str
    lens: LensAck | LensFault | None = None


@dataclass(frozen=True)
class CaptureFault:
    """No frame could be captured."""

    tag: str
    error: str
    t_s: float = 0.0
    lens: LensAck | LensFault | None = None


@dataclass(frozen=True)
class Estimation:
    """Depth estimator output on the tile grid.

    Attributes:
        depth_m: ``(h, w)`` metres.
        confidence: ``(h, w)`` in [0, 1].
        tile, stride: the grid (px).
        t_s: time the result was available (s).
        elapsed_s: compute time charged for it (s).
    """

    depth_m: np.ndarray
    confidence: np.ndarray
    tile: int
    stride: int
    t_s: float = 0.0
    elapsed_s: float = 0.0


@dataclass(frozen=True)
class EstimateFault:
    """The estimator failed (bad frames, missing model)."""

    error: str
    t_s: float = 0.0


@dataclass(frozen=True)
class Halt:
    """Stop now (continuous mode: the run is over; any mode: the user interrupted)."""

    t_s: float = 0.0


Observation = Union[LensAck, LensFault, Frame, CaptureFault, Estimation, EstimateFault, Halt]


class State(enum.Enum):
    """Where a controller is."""

    IDLE = "idle"
    MOVE_F1 = "move to P_e1"
    CAPTURE_F1 = "capture f1"
    CAPTURE_F2 = "capture f2"
    ESTIMATE = "estimate"
    MOVE_FOCUS = "move to focus"
    VERIFY = "verify"
    CONTRAST = "contrast search"
    TRACK = "track"
    DONE = "done"


@dataclass
class AFResult:
    """How an autofocus run ended.

    Attributes:
        status: ``"focused"``, ``"failed"``, ``"dry-run"`` or ``"halted"``.
        method: ``"dfd"`` or ``"contrast"`` (the method that set the final power).
        power_dpt: final commanded ECVFL power (dpt), ``None`` if none.
        estimated_depth_m: DFD depth of the ROI (m), ``None`` without an estimate.
        confidence: ROI confidence of the last estimate, ``None`` without one.
        frames: frames captured.
        lens_commands: lens set-point commands sent (retries included).
        t_start_s: time of the first command (s).
        t_focus_s: time focus was reached (lens settled at the final power, or the
            verification frame was evaluated), ``None`` if never.
        fallback_reason: why DFD handed over to contrast-detect AF, ``None`` if it did not.
        error: why the run failed, ``None`` if it did not.
        clamped: the in-focus power was outside the lens range and was clamped.
        texture_snr: ROI band-pass contrast over the noise floor in the sharper DFD frame.
        verified: result of the verification frame, ``None`` if not verified.
        refocus_count: DFD cycles run (continuous mode counts every re-estimate).
        history: ``(t_s, power_dpt, depth_m)`` of every focus decision (continuous mode).
    """

    status: str = "failed"
    method: str = "dfd"
    power_dpt: float | None = None
    estimated_depth_m: float | None = None
    confidence: float | None = None
    frames: int = 0
    lens_commands: int = 0
    t_start_s: float | None = None
    t_focus_s: float | None = None
    fallback_reason: str | None = None
    error: str | None = None
    clamped: bool = False
    texture_snr: float | None = None
    verified: bool | None = None
    refocus_count: int = 0
    history: list[tuple[float, float, float | None]] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        """``True`` if focus was reached (or a dry run completed)."""
        return self.status in ("focused", "dry-run")

    @property
    def time_to_focus_s(self) -> float | None:
        """``t_focus_s - t_start_s`` in seconds, ``None`` if focus was not reached."""
        if self.t_focus_s is None or self.t_start_s is None:
            return None
        return self.t_focus_s - self.t_start_s


# ---------------------------------------------------------------------- base machine
class _Abort(Exception):
    """Raised inside a controller generator to end the run with ``status="failed"``."""

    def __init__(self, reason: str, status: str = "failed") -> None:
        super().__init__(reason)
        self.reason, self.status = reason, status


Gen = Generator[Command, Observation, Any]


class StateMachine:
    """Generator-backed state machine: :meth:`start` gives the first command, :meth:`step` the next.

    Subclasses implement :meth:`_run`, a generator that yields commands and receives the
    observations answering them. It shares the counting (frames, lens commands, time) and
    the fault handling (bounded retries of lens commands) in helper generators.

    Args:
        settle_s: lens settling time waited after each power command (s).
        lens_retries: further attempts after a lens fault before the run fails.
        capture_retries: further attempts after a failed capture before the run fails.
        power_limits_dpt: the lens's ``(min, max)`` focal power (dpt), ``None`` if unknown.
    """

    def __init__(self, settle_s: float = 0.015, lens_retries: int = 2, capture_retries: int = 1,
                 power_limits_dpt: tuple[float, float] | None = None) -> None:
        if settle_s < 0 or lens_retries < 0 or capture_retries < 0:
            raise InputError("settle_s, lens_retries and capture_retries must be >= 0")
        self.settle_s = float(settle_s)
        self.lens_retries, self.capture_retries = int(lens_retries), int(capture_retries)
        self.power_limits_dpt = None if power_limits_dpt is None else (float(power_limits_dpt[0]), float(power_limits_dpt[1]))
        self.state = State.IDLE
        self.result = AFResult()
        self._gen: Gen | None = None
        self._pending: Command | None = None
        self._last_t = 0.0
        self._lens_power: float | None = None

    # -------------------------------------------------------------- public protocol
    def start(self, t_s: float | None = None) -> Command:
        """Begin a run and return the first command.

        Args:
            t_s: time of the focus request (s); default: the time of the first observation.
        """
        self.state = State.IDLE
        self.result = AFResult(method=self._initial_method(), t_start_s=t_s)
        self._gen = self._wrapped()
        return self._advance(None, first=True)

    def step(self, observation: Observation) -> Command:
        """Feed the observation that answers the last command; return the next command.

        Raises:
            ControllerError: the run has not started or has ended, or the observation does
                not answer the pending command.
        """
        if self._gen is None or isinstance(self._pending, Done):
            raise ControllerError("the controller is not running: call start()")
        if not isinstance(observation, Halt):
            self._check_answer(observation)
        return self._advance(observation)

    @property
    def done(self) -> bool:
        """``True`` once :class:`Done` has been returned."""
        return isinstance(self._pending, Done)

    # -------------------------------------------------------------- internals
    def _initial_method(self) -> str:
        return "dfd"

    def _check_answer(self, obs: Observation) -> None:
        cmd = self._pending
        ok = {
            SetPower: (LensAck, LensFault),
            Capture: (Frame, CaptureFault),
            Estimate: (Estimation, EstimateFault),
        }
        expected = ok.get(type(cmd), ())
        if not isinstance(obs, expected):
            raise ControllerError(f"{type(obs).__name__} does not answer {type(cmd).__name__} (state {self.state.value})")

    def _advance(self, obs: Observation | None, first: bool = False) -> Command:
        assert self._gen is not None
        cmd = next(self._gen) if first else self._gen.send(obs)  # type: ignore[arg-type]
        self._pending = cmd
        if isinstance(cmd, Done):
            self.state = State.DONE
        return cmd

    def _wrapped(self) -> Gen:
        try:
            yield from self._run()
        except _Abort as exc:
            self.result.status = exc.status
            if exc.status == "failed":
                self.result.error = exc.reason
                log.error("autofocus failed: %s", exc.reason)
        yield Done(self.result)

    def _run(self) -> Gen:  # pragma: no cover - abstract
        raise NotImplementedError
        yield  # noqa: unreachable

    def _note_time(self, t: float) -> None:
        self._last_t = t
        if self.result.t_start_s is None:
            self.result.t_start_s = t

    def _halt(self, obs: Observation) -> None:
        if isinstance(obs, Halt):
            self._note_time(obs.t_s)
            raise _Abort("halted", status="halted")

    def check_power(self, power_dpt: float) -> float:
        """Clamp ``power_dpt`` into the lens range, recording an explicit error if it was outside."""
        if self.power_limits_dpt is None:
            return power_dpt
        lo, hi = self.power_limits_dpt
        if lo <= power_dpt <= hi:
            return power_dpt
        clamped = min(max(power_dpt, lo), hi)
        self.result.clamped = True
        msg = f"in-focus power {power_dpt:.3f} dpt outside the lens range [{lo:.3f}, {hi:.3f}] dpt: clamped to {clamped:.3f} dpt"
        self.result.error = msg
        log.error(msg)
        return clamped

    # helper generators ---------------------------------------------------------
    def _set_power(self, power_dpt: float) -> Generator[Command, Observation, LensAck]:
        """``SetPower`` with bounded retries; aborts the run if the lens keeps failing."""
        last = ""
        for attempt in range(self.lens_retries + 1):
            self.result.lens_commands += 1
            obs = yield SetPower(power_dpt, self.settle_s)
            self._halt(obs)
            if isinstance(obs, LensAck):
                self._note_time(obs.t_s)
                self._lens_power = obs.power_dpt
                return obs
            assert isinstance(obs, LensFault)
            self._note_time(obs.t_s)
            last = obs.error
            log.warning("lens command %.3f dpt failed (attempt %d of %d): %s", power_dpt, attempt + 1,
                        self.lens_retries + 1, last)
        raise _Abort(f"lens did not accept {power_dpt:.3f} dpt after {self.lens_retries + 1} attempts: {last}")

    def _capture(self, tag: str, then_power_dpt: float | None = None
                 ) -> Generator[Command, Observation, tuple[Frame, LensAck | None]]:
        """``Capture`` with bounded retries; a failed ``then`` move is retried with ``SetPower``."""
        last = ""
        for attempt in range(self.capture_retries + 1):
            if then_power_dpt is not None:
                self.result.lens_commands += 1
            obs = yield Capture(tag, then_power_dpt, self.settle_s)
            self._halt(obs)
            self.result.frames += 1 if isinstance(obs, Frame) else 0
            lens = obs.lens
            if isinstance(obs, CaptureFault):
                self._note_time(obs.t_s)
                last = obs.error
                log.warning("capture %r failed (attempt %d of %d): %s", tag, attempt + 1, self.capture_retries + 1, last)
                if isinstance(lens, LensAck):  # the lens moved anyway: do not move it again
                    self._lens_power = lens.power_dpt
                    then_power_dpt = None
                continue
            assert isinstance(obs, Frame)
            self._note_time(obs.t_ready_s)
            ack: LensAck | None = None
            if then_power_dpt is not None:
                if isinstance(lens, LensAck):
                    ack = lens
                    self._lens_power = lens.power_dpt
                else:  # the exposure-end command failed: retry it as a plain SetPower
                    reason = lens.error if isinstance(lens, LensFault) else "no answer"
                    log.warning("lens command %.3f dpt after %r failed: %s", then_power_dpt, tag, reason)
                    ack = yield from self._set_power(then_power_dpt)
            return obs, ack
        raise _Abort(f"no frame for {tag!r} after {self.capture_retries + 1} attempts: {last}")


# ---------------------------------------------------------------------- DFD machine
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
            (:func:`tdfd.autofocus.contrast.pair_texture_snr`, about 1 for a texture-less
            target) in the more textured frame of the DFD pair, below which the target
            counts as texture-less and contrast-detect AF takes over; 0 disables the check.
        fallback: run the contrast-detect search when DFD is not trusted (else fail).
        contrast: keyword arguments of :class:`tdfd.autofocus.contrast.ContrastSearch`
            for the fallback search.
        continuous: keep tracking after focusing: live frames at focus are watched, and
            DFD is re-run when their ROI sharpness drops by ``refocus_drop`` or every
            ``refocus_interval_s``; the run ends on a :class:`Halt` observation.
        refocus_drop: relative sharpness drop that triggers a re-estimate.
        refocus_interval_s: longest time between re-estimates in continuous mode (s).
        dry_run: capture and estimate without moving the lens; ends with ``status="dry-run"``.
        lens_retries, capture_retries, power_limits_dpt: see :class:`StateMachine`.
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
        from .contrast import sharpness

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
            self.state = State.MOVE_F1
            yield from self._set_power(p1)
            self.state = State.CAPTURE_F1
            f1, _ = yield from self._capture("f1", then_power_dpt=p2)
            self.state = State.CAPTURE_F2
            f2, _ = yield from self._capture("f2")
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
            raise _Abort(f"depth estimation failed: {obs.error}")
        assert isinstance(obs, Estimation)
        self._note_time(obs.t_s)
        mask = roi_tile_mask(roi, obs.depth_m.shape, obs.tile, obs.stride, offset)
        agg = aggregate_depth(obs.depth_m, obs.confidence, mask)
        self.last_aggregate = agg
        res.confidence = agg.confidence
        res.estimated_depth_m = agg.depth_m
        log.info("DFD: ROI depth %.4f m (1/d %.3f 1/m, spread %.3f 1/m), confidence %.3f, %d/%d tiles",
                 agg.depth_m, agg.inverse_depth, agg.spread_dpt, agg.confidence, agg.inliers, agg.tiles)
        from .contrast import pair_texture_snr

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
                raise _Abort(reason, status="dry-run")
            if not self.fallback:
                raise _Abort(reason)
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
            raise _Abort("dry run", status="dry-run")
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

    def _contrast(self, centre_dpt: float | None) -> Gen:
        from .contrast import ContrastSearch

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


# ---------------------------------------------------------------------------- driving
@runtime_checkable
class Plant(Protocol):
    """What executes commands: the simulated bench or the real camera + lens."""

    def set_power(self, cmd: SetPower) -> LensAck | LensFault: ...

    def capture(self, cmd: Capture) -> Frame | CaptureFault: ...

    def estimate(self, cmd: Estimate) -> Estimation | EstimateFault: ...

    def should_halt(self) -> bool: ...

    def now(self) -> float: ...


def drive(controller: StateMachine, plant: Plant, max_steps: int = 100_000) -> AFResult:
    """Run ``controller`` against ``plant`` until it is done and return its result.

    Hardware faults arrive as :class:`LensFault` / :class:`CaptureFault` /
    :class:`EstimateFault` observations (the plant converts exceptions); the controller
    decides to retry or fail. ``plant.should_halt()`` ends a continuous run.

    Raises:
        ControllerError: more than ``max_steps`` commands (a controller bug).
    """
    cmd = controller.start(plant.now())
    for _ in range(max_steps):
        if isinstance(cmd, Done):
            return cmd.result
        if plant.should_halt():
            cmd = controller.step(Halt(plant.now()))
            continue
        if isinstance(cmd, SetPower):
            obs: Observation = plant.set_power(cmd)
        elif isinstance(cmd, Capture):
            obs = plant.capture(cmd)
        elif isinstance(cmd, Estimate):
            obs = plant.estimate(cmd)
        else:  # pragma: no cover
            raise ControllerError(f"unknown command {cmd!r}")
        cmd = controller.step(obs)
    raise ControllerError(f"controller did not finish within {max_steps} commands")
