r"""The autofocus protocol: commands a controller issues, observations that answer them, and the run's result.

The bottom layer of :mod:`tdfd.autofocus`: plain data, no behaviour. A controller
(:class:`tdfd.autofocus.machine.StateMachine`) yields a :data:`Command`; whoever drives it
(a plant: the simulated bench or the real hardware) executes it and answers with the
matching :data:`Observation`:

==========================  ==========================================
command                     answered by
==========================  ==========================================
:class:`SetPower`           :class:`LensAck` or :class:`LensFault`
:class:`Capture`            :class:`Frame` or :class:`CaptureFault`
:class:`Estimate`           :class:`Estimation` or :class:`EstimateFault`
:class:`Done`               (the run is over: :class:`AFResult`)
==========================  ==========================================

:class:`Halt` may answer any command (the user interrupted, or a continuous run is over).
Times are seconds on the plant's clock; powers are ECVFL dioptres.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field
from typing import Union

import numpy as np

from ..errors import TdfdError

__all__ = [
    "ControllerError",
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
]


class ControllerError(TdfdError, RuntimeError):
    """The controller was driven wrongly (an observation that does not answer the last command)."""


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
    ``light`` names the assist-light pattern to expose with (the plant switches it on
    through its :class:`~tdfd.light.guard.LightGuard` for this exposure only); ``None``:
    unlit.
    """

    tag: str
    then_power_dpt: float | None = None
    settle_s: float = 0.0
    light: str | None = None


@dataclass(frozen=True)
class Estimate:
    """Run the depth estimator on ``(image_f1, image_f2)`` (frames at ``P_e1``, ``P_e2``).

    ``offset`` is the ``(row, column)`` of the images' origin in the frame when they are a
    crop around the ROI; ``optical_centre`` the ``(row, column)`` of the frame's centre in
    the images' pixels then (``None``: the images' own centre). An estimator that registers
    focus breathing registers about it (a crop off the optical centre also needs the
    breathing's translation; :func:`~tdfd.autofocus.interfaces.run_estimator`).
    """

    image_f1: np.ndarray
    image_f2: np.ndarray
    offset: tuple[int, int] = (0, 0)
    optical_centre: tuple[float, float] | None = None


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
        status: ``"focused"`` (focus declared), ``"unconfirmed"`` (the lens is at the DFD focus
            but no evidence confirmed it, and no fallback was allowed), ``"failed"``,
            ``"dry-run"`` or ``"halted"``.
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
        verified: result of the last verification frame, ``None`` if none was taken.
        evidence: what declared the focus: ``"uncertainty"`` (the estimate's own),
            ``"verification"`` (a verification frame), ``"refined"`` (the three-frame estimate:
            the model's and a failed verification frame's focus errors together, the lens moved
            there), ``"contrast"`` (a contrast-detect peak); ``None`` if focus was not declared.
        uncertainty_px: the DFD estimate's uncertainty as a blur radius (px), ``None`` without one.
        verify_error_dpt: the focus error the last verification frame measured (dpt).
        dfd_power_dpt: the in-focus power of the (last) DFD estimate, before any refinement (dpt).
        refine_count: further DFD steps taken after failed verifications.
        pair_agrees: the model's in-focus power lies in the interval the DFD pair allows
            without the model (``None`` if not checked).
        blur_measurements: relative-blur measurements the evidence took (each about 10 ms of
            CPU on the ROI; the simulated bench charges them to the time to focus).
        cross_blur_measurements: cross-blur focus searches the evidence took (about 25-35 ms
            each on the bench's ROI; charged likewise).
        pair_cross_blur_checks: 2-frame cross-blur searches of the DFD pair, one PSF family (the
            check of a known disk PSF: about a fifth of a 3-frame search; charged likewise).
        region_fits: one-region fits of a lit pair (the assist policy's step 3, 1.5-10 ms each;
            charged likewise).
        disk_region_fits: those of them made by the disk cross-blur (a lens told it is a disk,
            :mod:`tdfd.autofocus.region_cross_blur`; charged at their own cost).
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
    evidence: str | None = None
    uncertainty_px: float | None = None
    verify_error_dpt: float | None = None
    dfd_power_dpt: float | None = None
    refine_count: int = 0
    pair_agrees: bool | None = None
    blur_measurements: int = 0
    cross_blur_measurements: int = 0
    pair_cross_blur_checks: int = 0
    region_fits: int = 0
    disk_region_fits: int = 0
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
