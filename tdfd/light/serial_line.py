r"""A light keyed from a USB-serial adapter's modem line (RTS or DTR), through pyserial.

Wiring: a laser-diode driver's enable input, or a relay driver, on the adapter's RTS or
DTR output. The light is **on while the line is asserted** (pyserial ``rts = True``), so a
closed port (Linux drops both lines on the last close, ``HUPCL``), a pulled adapter or a
dead host leave it off. Nothing else is sent on the port.

Works on any pyserial object (a ``serial.Serial``, anything from ``serial_for_url``:
``loop://``, a pty, ...). :func:`open_serial_line` opens the port the user named with the
keyed line already at its off level: pyserial would otherwise assert RTS and DTR when it
opens a port. (The Linux tty layer itself raises both lines when a tty is opened, until
pyserial's first ioctl microseconds later; a laser driver with an enable delay of a
millisecond or more does not emit in that glitch.)

**Read-back after every switch** (``readback="auto"`` picks the first that exists):

* ``"loopback"``: the loop partner of the line, CTS for RTS and DSR for DTR. pyserial's
  ``loop://`` loops RTS to CTS and DTR to DSR; on hardware, a wire from the keyed line
  (or the driver's "laser on" output) back to CTS/DSR.
* ``"modem"``: the port's modem-control register (``TIOCMGET`` on a POSIX tty), i.e.
  what the adapter's driver holds on the line.
* ``"none"``: no read-back (logged once).

A pseudo-terminal or a port that is not a serial adapter refuses the modem-line ioctls
with ``OSError`` errno 25 (ENOTTY): reported as :class:`~tdfd.errors.ModemLineError`,
which names the port (usually the wrong one was given).

Example:
    >>> import serial
    >>> port = serial.serial_for_url("loop://", do_not_open=True); port.rts = False; port.open()
    >>> light = SerialLineLight(port, "rts")
    >>> light.on(); port.cts, light.is_on
    (True, True)
    >>> light.off(); port.cts, light.is_on
    (False, False)
"""

from __future__ import annotations

import errno
import logging
import struct
from typing import Any

from ..errors import InputError, LightConnectionError, LightVerifyError, ModemLineError
from .base import AssistLight

try:  # pragma: no cover - POSIX only
    import fcntl
    import termios
except ImportError:  # pragma: no cover
    fcntl = termios = None  # type: ignore[assignment]

import serial  # pyserial: a dependency

_SERIAL_ERRORS: tuple[type[BaseException], ...] = (serial.SerialException,)

__all__ = ["SerialLineLight", "open_serial_line", "LINES", "READBACKS"]

log = logging.getLogger(__name__)

#: the modem output lines a light can be keyed from, and their loop-back partners.
LINES = {"rts": "cts", "dtr": "dsr"}
#: read-back modes (see the module documentation).
READBACKS = ("auto", "loopback", "modem", "none")
_TIOCM_BIT = {"rts": 0x004, "dtr": 0x002}  # TIOCM_RTS, TIOCM_DTR (Linux, BSD, macOS)


def _check_line(line: str) -> str:
    key = str(line).lower()
    if key not in LINES:
        raise InputError(f"the light's modem line must be 'rts' or 'dtr', got {line!r}")
    return key


def _port_name(port: Any) -> str:
    return str(getattr(port, "port", None) or getattr(port, "name", None) or type(port).__name__)


def _is_loop(port: Any) -> bool:
    return str(getattr(port, "port", "") or "").startswith("loop://")


def open_serial_line(port: str, line: str) -> Any:
    """Open the serial port (or pyserial URL) the user named, with ``line`` de-asserted.

    Raises:
        LightConnectionError: the port does not exist or cannot be opened.
        InputError: ``line`` is not ``rts`` or ``dtr``.
    """
    key = _check_line(line)
    try:
        p = serial.serial_for_url(port, do_not_open=True)
        setattr(p, key, False)  # applied by open(): the light stays off
        p.open()
    except ValueError as exc:  # a malformed URL
        raise LightConnectionError(f"cannot open the assist-light port {port!r}: {exc}") from exc
    except (OSError, *_SERIAL_ERRORS) as exc:
        raise LightConnectionError(f"cannot open the assist-light port {port!r}: {exc}") from exc
    return p


class SerialLineLight(AssistLight):
    """An on/off light on a serial port's RTS or DTR line.

    Args:
        port: an open pyserial-like object (see :func:`open_serial_line`).
        line: ``"rts"`` or ``"dtr"``.
        readback: ``"auto"``, ``"loopback"``, ``"modem"`` or ``"none"`` (module docs).
        owns_port: close the port in :meth:`close`.

    Raises:
        InputError: unknown line or read-back mode.
        ModemLineError: the port refuses modem-line control (switching the line off on
            construction is the first test).
    """

    def __init__(self, port: Any, line: str = "rts", readback: str = "auto", owns_port: bool = False) -> None:
        super().__init__()
        self.port, self.line = port, _check_line(line)
        if readback not in READBACKS:
            raise InputError(f"readback must be one of {', '.join(READBACKS)}, got {readback!r}")
        self.owns_port = bool(owns_port)
        self.name = f"serial:{_port_name(port)}:{self.line}"
        if readback == "auto":
            readback = "loopback" if _is_loop(port) else "modem" if self._fd() is not None else "none"
        self.readback = readback
        if readback == "none":
            log.warning("light %s: no read-back of the line (wire it back to %s for one)", self.name,
                        LINES[self.line].upper())
        self._switch_off()  # a known state, and the first test that the port takes modem-line control

    # ------------------------------------------------------------------ line I/O
    def _fd(self) -> int | None:
        if fcntl is None:  # pragma: no cover
            return None
        fd = getattr(self.port, "fd", None)
        return fd if isinstance(fd, int) and fd >= 0 else None

    def _wrap(self, what: str, fn, *args):  # noqa: ANN001, ANN202
        try:
            return fn(*args)
        except OSError as exc:
            if exc.errno == errno.ENOTTY:
                raise ModemLineError(
                    f"{_port_name(self.port)} refuses {what} (errno 25, not a serial adapter with modem lines: "
                    f"a pseudo-terminal or the wrong port?)") from exc
            raise LightConnectionError(f"assist-light port {_port_name(self.port)} failed during {what}: {exc}") from exc
        except _SERIAL_ERRORS as exc:  # pragma: no cover - SerialException is an OSError in pyserial 3.5
            raise LightConnectionError(f"assist-light port {_port_name(self.port)} failed during {what}: {exc}") from exc

    def _set_line(self, level: bool) -> None:
        self._wrap(f"setting {self.line.upper()}", setattr, self.port, self.line, bool(level))

    def read_line(self) -> bool | None:
        """The keyed line's state as read back, ``None`` without a read-back.

        Raises:
            ModemLineError, LightConnectionError: the read-back failed.
        """
        if self.readback == "loopback":
            partner = LINES[self.line]
            return bool(self._wrap(f"reading {partner.upper()}", getattr, self.port, partner))
        if self.readback == "modem":
            fd = self._fd()
            if fd is None:
                raise LightConnectionError(f"{_port_name(self.port)} has no file descriptor to read its modem lines")
            raw = self._wrap("reading the modem lines", fcntl.ioctl, fd, termios.TIOCMGET, struct.pack("I", 0))
            return bool(struct.unpack("I", raw)[0] & _TIOCM_BIT[self.line])
        return None

    def _verify(self, level: bool) -> None:
        got = self.read_line()
        if got is not None and got != level:
            raise LightVerifyError(f"light {self.name}: {self.line.upper()} reads back {'on' if got else 'off'} "
                                   f"after switching it {'on' if level else 'off'} (read-back: {self.readback})")

    # ------------------------------------------------------------------ AssistLight
    def _switch_on(self, pattern: str) -> None:
        self._set_line(True)
        self._verify(True)

    def _switch_off(self) -> None:
        self._set_line(False)
        self._verify(False)

    def _release(self) -> None:
        if self.owns_port:
            try:
                self.port.close()
            except (OSError, *_SERIAL_ERRORS) as exc:  # closing a vanished port: nothing left to switch
                log.warning("closing the assist-light port %s: %s", _port_name(self.port), exc)
