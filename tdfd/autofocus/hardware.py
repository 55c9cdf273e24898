"""The real-hardware autofocus loop: OpenCV capture plus the Lens Driver 4 over serial.

:class:`HardwarePlant` executes the controller's commands on a real camera and lens with
wall-clock time; the controllers are the same state machines the simulated bench drives.

Camera notes (read before trusting a depth):

* DFD needs **linear** intensity (CONTRACT.md section 2: raw value / white level, no
  gamma). Consumer webcams deliver gamma-encoded, auto-exposed, auto-white-balanced,
  often sharpened video. Put the camera in raw / linear mode (gamma 1, sharpening off,
  fixed exposure and gain) through its own tools; ``--linearise`` undoes an sRGB gamma
  as a fallback, which is only approximate.
* The model was built for one camera description (its ONNX metadata: aperture, sensor
  distance, pixel pitch, ECVFL powers, ``mu``). Frames from other optics give wrong depths.
* OpenCV offers no exposure-end event, so the move to the second ECVFL power is commanded
  after the first frame has been read (one read-out later than the bench models), and
  the settling wait is a sleep; buffered frames are discarded before each capture so the
  frame used was exposed after the lens settled.

Dry run (``dry_run=True``): frames are captured and the model run, but the lens is never
moved (no handshake, which would zero its current; no set-points). The depth is only
meaningful if the lens already sits at the powers the frames need; the run reports what
it *would* command.
"""

from __future__ import annotations

import logging
import time
from typing import Any, Callable

import numpy as np

from ..camera import Camera
from ..errors import InputError, TdfdError
from ..frames import raw_to_linear, srgb_to_linear
from ..light.guard import DEFAULT_LIMITS, LightGuard, LightLimits, exposure
from .assist import AssistedDFDController
from .contrast import ContrastController
from .dfd import DFDController
from .estimators import estimator_breathing, suggested_confidence_scale, suggested_min_confidence
from .interfaces import Estimator, run_estimator
from .lens_command import command_lens
from .machine import StateMachine, drive
from .messages import (
    AFResult,
    Capture,
    CaptureFault,
    Estimate,
    Estimation,
    EstimateFault,
    Frame,
    Halt,
    LensAck,
    LensFault,
    SetPower,
)
from .roi import Roi

__all__ = ["CaptureError", "OpenCVCamera", "HardwarePlant", "frame_to_linear", "run_hardware", "drive_to_halt",
           "HARDWARE_TEMPERATURE_LIMITS_C"]

log = logging.getLogger(__name__)

#: temperature limits (°C) sent before focal-power mode on real hardware.
HARDWARE_TEMPERATURE_LIMITS_C = (15.0, 40.0)


class CaptureError(TdfdError, RuntimeError):
    """The capture device could not be opened or delivered no frame.

    (Not :class:`tdfd.errors.CameraError`, which is about an invalid camera *description*.)
    """


def frame_to_linear(frame: np.ndarray, white_level: float | None = None, linearise: bool = False,
                    name: str = "camera frame") -> np.ndarray:
    """A captured frame as ``(H, W)`` float32 in [0, 1] (:func:`tdfd.frames.raw_to_linear`'s policy).

    Args:
        frame: ``(H, W)`` or ``(H, W, 3)`` BGR, uint8 / uint16 / float.
        white_level: raw value of white (default: 255 for uint8, 65535 for uint16, 1 for floats).
        linearise: undo an sRGB gamma (only if the camera cannot deliver linear data).
        name: the frame's name in error messages.

    Raises:
        RangeError: values above the white level (a wrong ``white_level``); never clipped
            silently. The plants report it as a capture fault.

    Example:
        >>> frame_to_linear(np.full((2, 2), 255, np.uint8)).tolist()
        [[1.0, 1.0], [1.0, 1.0]]
    """
    import cv2

    a = np.asarray(frame)
    if a.ndim == 3:
        a = cv2.cvtColor(a[..., :3], cv2.COLOR_BGR2GRAY) if a.shape[2] >= 3 else a[..., 0]
    x = raw_to_linear(a, white_level, name)
    if linearise:
        x = srgb_to_linear(x)
    return x.astype(np.float32)


class OpenCVCamera:
    """A camera through ``cv2.VideoCapture``.

    Args:
        source: a device index (``0``, ``"0"``) or a URL / file / GStreamer pipeline.
        white_level: raw value of white (see :func:`frame_to_linear`).
        linearise: undo an sRGB gamma.
        flush: frames grabbed and discarded before each capture (stale buffered frames).
        crop: read-out window in frame pixels (``None``: the whole frame).

    Raises:
        CaptureError: the source cannot be opened.
    """

    def __init__(self, source: str | int, white_level: float | None = None, linearise: bool = False, flush: int = 2,
                 crop: Roi | None = None) -> None:
        import cv2

        src: str | int = int(source) if isinstance(source, str) and source.strip().isdigit() else source
        self.cap = cv2.VideoCapture(src)
        if not self.cap.isOpened():
            raise CaptureError(f"cannot open camera {source!r}")
        try:
            self.cap.set(cv2.CAP_PROP_BUFFERSIZE, 1)
        except cv2.error:  # pragma: no cover - backend dependent
            pass
        self.source, self.white_level, self.linearise = source, white_level, linearise
        self.flush, self.crop = int(flush), crop

    def read(self) -> np.ndarray:
        """One fresh frame as ``(H, W)`` float32 linear intensity in [0, 1].

        Raises:
            CaptureError: no frame.
        """
        for _ in range(self.flush):
            self.cap.grab()
        ok, frame = self.cap.read()
        if not ok or frame is None:
            raise CaptureError(f"camera {self.source!r} delivered no frame")
        x = frame_to_linear(frame, self.white_level, self.linearise, name=f"camera {self.source!r} frame")
        return self.crop.crop(x) if self.crop is not None else x

    def close(self) -> None:
        """Release the capture device."""
        self.cap.release()


class HardwarePlant:
    """Executes controller commands on a real camera and lens (wall-clock time).

    Args:
        camera: frames source with ``read() -> (H, W) float32``.
        lens: an :class:`~tdfd.driver.OptotuneLens` in focal-power mode, or ``None`` (dry run).
        estimator: depth estimator.
        duration_s: end a continuous run after this long (s); ``None``: until interrupted.
        clock: time source (s).
        sleep: sleep function (s).
        readback: read every set-point back (``PrDA``; ``PwDA`` has no reply, so a lost
            command is only caught this way); costs about 2 ms per command.
        light_guard: the guarded assist light; a lit ``Capture`` has it on for that frame's
            read only (``None``: no light named, a lit capture fails).
    """

    def __init__(self, camera: Any, lens: Any | None, estimator: Estimator | None, duration_s: float | None = None,
                 clock: Callable[[], float] = time.monotonic, sleep: Callable[[float], None] = time.sleep,
                 readback: bool = True, light_guard: LightGuard | None = None) -> None:
        self.camera, self.lens, self.estimator = camera, lens, estimator
        self.clock, self.sleep = clock, sleep
        self.t0 = clock()
        self.duration_s = duration_s
        self.readback = readback
        self.lens_ready = self.t0
        self.power_dpt = float("nan")  # last commanded power
        self.halt_requested = False
        self.light_guard = light_guard

    def now(self) -> float:
        return self.clock()

    def should_halt(self) -> bool:
        if self.halt_requested:
            return True
        return self.duration_s is not None and self.clock() - self.t0 >= self.duration_s

    def _command(self, power_dpt: float, settle_s: float) -> LensAck | LensFault:
        t = self.clock()
        if self.lens is None:
            return LensFault(power_dpt, "no lens (dry run)", t)
        try:
            sent = command_lens(self.lens, power_dpt, verify=self.readback, clock=self.clock)
        except TdfdError as exc:
            return LensFault(power_dpt, f"{type(exc).__name__}: {exc}", self.clock())
        self.lens_ready = sent + settle_s
        self.power_dpt = float(power_dpt)
        return LensAck(power_dpt, t, self.lens_ready)

    def set_power(self, cmd: SetPower) -> LensAck | LensFault:
        return self._command(cmd.power_dpt, cmd.settle_s)

    def capture(self, cmd: Capture) -> Frame | CaptureFault:
        wait = self.lens_ready - self.clock()
        if wait > 0:
            self.sleep(wait)
        start, power = self.clock(), self.power_dpt
        try:
            with exposure(self.light_guard, cmd.light):  # a lit frame: the light on for this read only
                image = self.camera.read()
        except TdfdError as exc:
            lens = self._command(cmd.then_power_dpt, cmd.settle_s) if cmd.then_power_dpt is not None else None
            return CaptureFault(cmd.tag, str(exc), self.clock(), lens=lens)
        end = self.clock()
        lens = self._command(cmd.then_power_dpt, cmd.settle_s) if cmd.then_power_dpt is not None else None
        return Frame(image, power, start, end, end, cmd.tag, lens=lens)

    def estimate(self, cmd: Estimate) -> Estimation | EstimateFault:
        if self.estimator is None:
            return EstimateFault("no depth estimator", self.clock())
        t0 = self.clock()
        try:
            depth, conf = run_estimator(self.estimator, cmd)
        except TdfdError as exc:
            return EstimateFault(f"{type(exc).__name__}: {exc}", self.clock())
        t1 = self.clock()
        return Estimation(np.asarray(depth), np.asarray(conf), self.estimator.tile, self.estimator.stride, t_s=t1,
                          elapsed_s=t1 - t0)


def run_hardware(port: str | None, camera_source: str | int, estimator: Estimator | None, *, method: str = "dfd",
                 roi: Roi | None = None, verify: bool | str = "auto", dry_run: bool = False, continuous: bool = False,
                 duration_s: float | None = None, settle_s: float = 0.015, linearise: bool = False,
                 white_level: float | None = None,
                 temperature_limits_c: tuple[float, float] = HARDWARE_TEMPERATURE_LIMITS_C,
                 contrast: dict | None = None, camera: Any | None = None, lens: Any | None = None,
                 min_confidence: float | None = None, max_uncertainty_px: float = 0.25, light: Any | None = None,
                 illumination: str | None = None, light_limits: LightLimits = DEFAULT_LIMITS,
                 psf_family: str | None = None, psf_sigma_scale: float = 1.0,
                 region_mu_uncertainty: float | None = None) -> AFResult:
    """Autofocus once (or continuously) on real hardware.

    Args:
        port: the Lens Driver 4's serial port or pyserial URL (``None`` only for a dry run).
        camera_source: OpenCV device index or URL.
        estimator: depth estimator (its camera gives the capture powers); ``None`` for contrast.
        method: ``"dfd"`` or ``"contrast"``.
        roi: region of interest in frame pixels.
        verify, continuous: see :class:`~tdfd.autofocus.dfd.DFDController`.
        dry_run: capture and estimate without touching the lens.
        duration_s: length of a continuous run (s); ``None``: until Ctrl-C.
        settle_s: settling wait after each lens command (s).
        linearise, white_level: see :func:`frame_to_linear`.
        temperature_limits_c: sent before focal-power mode.
        contrast: contrast-search options.
        min_confidence: ROI-confidence threshold (default: the estimator's suggestion).
        max_uncertainty_px: see :class:`~tdfd.autofocus.dfd.DFDController`.
        camera, lens: already-open objects to use instead of opening ``camera_source`` / ``port``.
        light: the assist light the user named (an open :class:`~tdfd.light.base.AssistLight`,
            see :func:`tdfd.light.open_light`), used by DFD through a
            :class:`~tdfd.light.guard.LightGuard` on :func:`time.monotonic` (watchdog on) when the
            target is texture-less; ``None``: never lit. The caller closes it.
        illumination: ``"none"`` keeps a named light off; any other value (or ``None``)
            lets DFD use it. Needs ``light``.
        light_limits: the light's on-time and duty caps.
        psf_family, psf_sigma_scale: the lens's PSF family and its blur scale (a calibrated camera
            file's), see :class:`~tdfd.autofocus.dfd.DFDController`; ``None``: unknown.
        region_mu_uncertainty: the relative uncertainty of ``mu`` the assist light's region fit
            counts (a calibrated camera file's ``calibration.mu_relative_uncertainty``, see
            :class:`~tdfd.autofocus.assist.AssistedDFDController`); ``None``: its default.

    Returns:
        The :class:`~tdfd.autofocus.messages.AFResult`; lens and camera faults end up in it
        (``status="failed"``), they are not raised.

    Raises:
        CaptureError: the camera cannot be opened.
        LensConnectionError: the port cannot be opened.
        InputError: inconsistent options.
    """
    from ..driver import OptotuneLens

    if method not in ("dfd", "contrast"):
        raise InputError(f"method must be 'dfd' or 'contrast', got {method!r}")
    if method == "dfd" and estimator is None:
        raise InputError("DFD needs a depth estimator (--model)")
    if port is None and lens is None and not dry_run:
        raise InputError("give the lens's serial port (--port), or use --dry-run")
    if illumination is not None and light is None:
        raise InputError("--illumination on hardware needs the light named with --assist-light")
    pattern = None if light is None or illumination == "none" else light.patterns[0]
    own_cam = camera is None
    cam = camera if camera is not None else OpenCVCamera(camera_source, white_level=white_level, linearise=linearise)
    own_lens = lens is None and port is not None
    try:
        limits = None
        if own_lens:
            lens = OptotuneLens.open(port, handshake=not dry_run)  # the handshake zeroes the current: not in a dry run
        if lens is not None and not dry_run:
            fp = lens.set_focal_power_mode(temperature_limits_c)
            limits = (fp.min_dpt, fp.max_dpt)
        elif lens is not None:
            try:
                log.info("dry run: lens at %.3f dpt (not moved)", lens.get_focal_power_dpt())
            except TdfdError as exc:
                log.warning("dry run: cannot read the lens: %s", exc)
        optics = estimator.camera if estimator is not None else Camera.preset("reference")
        ctrl: StateMachine
        if method == "dfd":
            dfd_kwargs = dict(roi=roi, settle_s=settle_s, verify=verify, dry_run=dry_run, continuous=continuous,
                              power_limits_dpt=limits, contrast=contrast, grid=(estimator.tile, estimator.stride),
                              confidence_scale=suggested_confidence_scale(estimator),
                              max_uncertainty_px=max_uncertainty_px, psf_family=psf_family,
                              psf_sigma_scale=psf_sigma_scale,
                              min_confidence=suggested_min_confidence(estimator) if min_confidence is None
                              else min_confidence)
            region = {} if region_mu_uncertainty is None else {"region_mu_uncertainty": region_mu_uncertainty}
            ctrl = (AssistedDFDController(optics, illumination=pattern, region_fit=estimator_breathing(estimator) == 0.0,
                                          **region, **dfd_kwargs) if pattern is not None
                    else DFDController(optics, **dfd_kwargs))
        else:
            if dry_run:
                raise InputError("a contrast-detect search must move the lens: no dry run")
            ctrl = ContrastController(optics, roi=roi, settle_s=settle_s, power_limits_dpt=limits, **(contrast or {}))
        guard = LightGuard(light, light_limits) if pattern is not None else None
        plant = HardwarePlant(cam, None if dry_run else lens, estimator, duration_s=duration_s if continuous else None,
                              light_guard=guard)
        try:
            try:
                return drive(ctrl, plant)
            except KeyboardInterrupt:
                plant.halt_requested = True
                return drive_to_halt(ctrl, plant)
        finally:
            if guard is not None:  # off on every exit path (the exposure blocks did it already)
                guard.force_off("end of the focus request")
    finally:
        if own_lens and lens is not None:
            lens.close()
        if own_cam:
            cam.close()


def drive_to_halt(ctrl: StateMachine, plant: HardwarePlant) -> AFResult:
    """After Ctrl-C: end the controller's run cleanly with a :class:`Halt`."""
    if ctrl.done:
        return ctrl.result
    cmd = ctrl.step(Halt(plant.now()))
    return cmd.result  # type: ignore[union-attr]
