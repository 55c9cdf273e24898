"""The package's exception types.

Every error tdfd raises on bad input or a hardware fault derives from :class:`TdfdError`,
and also from the builtin it refines (``ValueError``, ``TypeError``, ``TimeoutError``, …) so
callers can catch either.
"""

from __future__ import annotations

__all__ = [
    "TdfdError",
    "CameraError",
    "InputError",
    "ShapeError",
    "DTypeError",
    "NonFiniteError",
    "RangeError",
    "ModelError",
    "DriverError",
    "ProtocolError",
    "ChecksumError",
    "DeviceErrorReply",
    "LensTimeoutError",
    "LensConnectionError",
    "LensRangeError",
    "LensModeError",
    "LensStateError",
    "ForbiddenCommandError",
    "UnsupportedFirmwareError",
    "LightError",
    "LightSpecError",
    "LightConnectionError",
    "ModemLineError",
    "LightVerifyError",
    "LightCommandError",
    "LightSafetyError",
]


class TdfdError(Exception):
    """Base class of every error raised by tdfd."""


class CameraError(TdfdError, ValueError):
    """An invalid camera description (non-positive aperture, unknown preset, …)."""


class InputError(TdfdError, ValueError):
    """Input data that cannot be processed (base of the specific input errors)."""


class ShapeError(InputError):
    """A tensor or array of the wrong shape (rank, channel count, size smaller than a tile)."""


class DTypeError(TdfdError, TypeError):
    """A tensor or array of the wrong dtype."""


class NonFiniteError(InputError):
    """NaN or infinite values where finite numbers are required."""


class RangeError(InputError):
    """Values far outside their documented range (e.g. intensities outside [0, 1])."""


class ModelError(TdfdError, RuntimeError):
    """An ONNX model or checkpoint that is missing, corrupt or does not match the contract."""


class DriverError(TdfdError, RuntimeError):
    """Base class of lens-driver errors."""


class ProtocolError(DriverError):
    """Bytes from the lens driver that do not form a valid reply."""


class ChecksumError(ProtocolError):
    """A reply whose CRC-16/ARC does not match its payload."""


class DeviceErrorReply(DriverError):
    """The driver answered with an error frame (``E`` + id, or a bare ``N``).

    Attributes:
        code: the error id (1 CRC failed, 2 not available in this firmware type,
            3 not recognised, 4 lens incompatible; 1 for a bare ``N``).
    """

    MEANINGS = {
        1: "CRC check failed",
        2: "command not available in this firmware type",
        3: "command not recognised",
        4: "lens incompatible",
    }

    def __init__(self, code: int, message: str | None = None) -> None:
        self.code = int(code)
        super().__init__(message or f"device error {self.code}: {self.MEANINGS.get(self.code, 'unknown error')}")


class LensTimeoutError(DriverError, TimeoutError):
    """No (complete) reply from the lens driver within the timeout, after all retries."""


class LensConnectionError(DriverError, ConnectionError):
    """The serial port vanished or could not be used."""


class LensRangeError(DriverError, ValueError):
    """A requested current or focal power outside the lens's reported limits."""


class LensModeError(DriverError):
    """A command that does not act in the lens's present operating mode.

    For example setting a focal power while the driver is in current mode (``PwDA`` acts
    only in focal-power mode), or setting a current while it is in focal-power mode.
    """


class LensStateError(DriverError):
    """The device does not hold what was set: a set-point that still reads back otherwise after re-sending."""


class ForbiddenCommandError(DriverError, ValueError):
    """A command the driver refuses to send (``RESET``: firmware-update mode)."""


class UnsupportedFirmwareError(DriverError):
    """A firmware type whose encoding the protocol facts do not document (e.g. focal power on ``F``)."""


# ---------------------------------------------------------------------- assist light
class LightError(TdfdError, RuntimeError):
    """Base class of assist-light errors (:mod:`tdfd.light`)."""


class LightSpecError(InputError):
    """An ``--assist-light`` text that is not ``serial:PORT:rts``, ``serial:PORT:dtr`` or ``cmd:ON,OFF``."""


class LightConnectionError(LightError, ConnectionError):
    """The assist light's serial port does not exist, cannot be opened, or vanished."""


class ModemLineError(LightConnectionError):
    """The port refuses modem-line control (RTS/DTR).

    A pseudo-terminal, or a port that is not a serial adapter, answers the modem-line
    ioctls with ``OSError`` errno 25 (ENOTTY): usually the wrong port was named.
    """


class LightVerifyError(LightError):
    """The light's control line did not read back the state it was switched to."""


class LightCommandError(LightError):
    """A light command (``cmd:ON,OFF``) could not be run, timed out or exited non-zero."""


class LightSafetyError(LightError):
    """The light interlock refused to switch on, or switched the light off: the on-time
    cap per focus request or the duty-cycle cap was reached, or no light was named."""
