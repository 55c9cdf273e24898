"""The hardware capture rig: an Optotune lens driver plus an OpenCV camera.

Frames are stored as the camera delivers them (raw values, no scaling): the capture folder
wants linear sensor values, so put the camera in a raw / linear mode (gamma 1, fixed
exposure and gain, no sharpening) with its own tools. Colour frames are converted to one
channel (``cv2.COLOR_BGR2GRAY``), which is only right for a linear camera.

The port and the camera are opened only when named (:meth:`HardwareRig.open`); the rig
itself works on any objects with the :class:`~tdfd.driver.OptotuneLens` methods used here
and the ``cv2.VideoCapture`` surface (``grab``, ``read``, ``release``), so tests drive it
with the lens emulator on a pty and a fake camera.
"""

from __future__ import annotations

import logging
import time
from typing import Any, Callable

import numpy as np

from ..errors import InputError, TdfdError

__all__ = ["CameraCaptureError", "HardwareRig", "open_opencv_camera", "to_raw_gray"]

log = logging.getLogger(__name__)


class CameraCaptureError(TdfdError, RuntimeError):
    """The camera could not be opened or delivered no usable frame."""


def to_raw_gray(frame: Any) -> np.ndarray:
    """A camera frame as ``(H, W)`` uint8/uint16 raw values (colour converted to grey).

    Raises:
        CameraCaptureError: not an 8- or 16-bit image.
    """
    import cv2

    a = np.asarray(frame)
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[..., 0]
    elif a.ndim == 3 and a.shape[2] in (3, 4):
        a = cv2.cvtColor(np.ascontiguousarray(a[..., :3]), cv2.COLOR_BGR2GRAY)
    if a.ndim != 2 or a.dtype not in (np.uint8, np.uint16):
        raise CameraCaptureError(f"the camera delivered a {a.dtype} frame of shape {a.shape}; "
                                 "expected 8- or 16-bit grey or BGR")
    return np.ascontiguousarray(a)


def open_opencv_camera(source: str | int) -> Any:
    """Open ``cv2.VideoCapture`` on a device index (``0``, ``"0"``) or URL / file / pipeline.

    Raises:
        CameraCaptureError: the source cannot be opened.
    """
    import cv2

    src: str | int = int(source) if isinstance(source, str) and source.strip().isdigit() else source
    cap = cv2.VideoCapture(src)
    if not cap.isOpened():
        cap.release()
        raise CameraCaptureError(f"cannot open camera {source!r}")
    try:
        cap.set(cv2.CAP_PROP_BUFFERSIZE, 1)
    except cv2.error:  # pragma: no cover - backend dependent
        pass
    return cap


class HardwareRig:
    """Captures frames at commanded ECVFL powers with a real lens and camera.

    Args:
        lens: an :class:`~tdfd.driver.OptotuneLens` (connected); the rig switches it to
            focal-power mode.
        camera: a ``cv2.VideoCapture``-like object.
        settle_s: wait after each power command before the frame is taken, seconds.
        flush: frames grabbed and dropped before each capture (stale buffered frames).
        white_level: raw value of full scale written to the sidecars (``None``: the PNG's).
        sleep, clock: time functions (tests pass fakes).
    """

    def __init__(self, lens: Any, camera: Any, settle_s: float = 0.05, flush: int = 2,
                 white_level: float | None = None, sleep: Callable[[float], None] = time.sleep,
                 clock: Callable[[], float] = time.time) -> None:
        if settle_s < 0 or flush < 0:
            raise InputError("settle_s and flush must be >= 0")
        self.lens, self.camera = lens, camera
        self.settle_s, self.flush, self.white_level = float(settle_s), int(flush), white_level
        self.sleep, self.clock = sleep, clock
        self.limits = lens.set_focal_power_mode()

    @classmethod
    def open(cls, port: str, camera_source: str | int, **kwargs: Any) -> "HardwareRig":
        """Open the named serial port and camera (closed again if anything fails)."""
        from ..driver import OptotuneLens

        lens = OptotuneLens.open(port)
        cam = None
        try:
            cam = open_opencv_camera(camera_source)
            return cls(lens, cam, **kwargs)
        except BaseException:
            if cam is not None:
                cam.release()
            lens.close()
            raise

    def capture(self, commanded_dpt: float) -> tuple[np.ndarray, dict[str, Any]]:
        """Set the power, wait, read it back, take a fresh frame.

        Returns:
            ``(raw (H, W), sidecar dict)``: ``lens_power_dpt`` is the read-back power,
            plus ``temperature_c`` (when the lens has a sensor), ``time_s`` (Unix time of
            the frame) and ``white_level`` when given.

        Raises:
            DriverError: the lens refused or did not answer (typed, from tdfd.driver).
            CameraCaptureError: no frame.
        """
        self.lens.set_focal_power_dpt(float(commanded_dpt))
        self.sleep(self.settle_s)
        power = float(self.lens.get_focal_power_dpt())
        if abs(power - commanded_dpt) > 0.05:
            log.warning("lens reads back %.3f dpt after a command of %.3f dpt (not settled?)", power, commanded_dpt)
        for _ in range(self.flush):
            self.camera.grab()
        t = self.clock()
        ok, frame = self.camera.read()
        if not ok or frame is None:
            raise CameraCaptureError("the camera delivered no frame")
        meta: dict[str, Any] = {"lens_power_dpt": power, "time_s": float(t), "commanded_power_dpt": float(commanded_dpt)}
        temp = self.lens.get_temperature_c()
        if temp is not None:
            meta["temperature_c"] = float(temp)
        if self.white_level is not None:
            meta["white_level"] = float(self.white_level)
        return to_raw_gray(frame), meta

    def close(self) -> None:
        """Release the camera and close the lens port."""
        try:
            self.camera.release()
        finally:
            self.lens.close()
