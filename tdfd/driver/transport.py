"""Byte transport for the Lens Driver 4 over any pyserial-like object.

:class:`SerialTransport` wraps an object with pyserial's ``read``/``write``/
``in_waiting``/``reset_input_buffer`` (a ``serial.Serial``, anything from
``serial.serial_for_url`` such as ``loop://`` or a pty path, or a test double). It never
opens a port; :func:`open_port` does, and only the port or URL the caller names.

Per command it drains stray input (logging what it finds: a late reply, or the
unsolicited error reply to a corrupted command that has no reply of its own), writes the
frame, and, only if the command has a reply, reads exactly as many bytes as can complete
a frame, each read bounded by the port's timeout. I/O failures of a vanished port become
:class:`~tdfd.errors.LensConnectionError`.
"""

from __future__ import annotations

import logging
from typing import Any

from ..errors import ChecksumError, ForbiddenCommandError, InputError, LensConnectionError, LensTimeoutError, ProtocolError
from .protocol import FORBIDDEN_PREFIX, ErrorFrame, Frame, FrameDecoder

try:  # pragma: no cover - termios is POSIX-only
    import termios

    _TERMIOS_ERRORS: tuple[type[BaseException], ...] = (termios.error,)
except ImportError:  # pragma: no cover
    _TERMIOS_ERRORS = ()

try:
    import serial

    _SERIAL_ERRORS: tuple[type[BaseException], ...] = (serial.SerialException,)
    _SERIAL_TIMEOUT: tuple[type[BaseException], ...] = (serial.SerialTimeoutException,)
except ImportError:  # pragma: no cover - pyserial is a dependency
    serial = None  # type: ignore[assignment]
    _SERIAL_ERRORS = ()
    _SERIAL_TIMEOUT = ()

__all__ = ["SerialTransport", "open_port", "DEFAULT_TIMEOUT_S", "DEFAULT_BAUDRATE"]

log = logging.getLogger(__name__)

#: default per-read timeout, seconds (public drivers use 0.1–1 s).
DEFAULT_TIMEOUT_S = 0.5
#: baud rate of the USB virtual COM port (the TTL UART variant runs at 38400).
DEFAULT_BAUDRATE = 115200

_IO_ERRORS = (OSError, *_SERIAL_ERRORS, *_TERMIOS_ERRORS)


def open_port(port_or_url: str, *, baudrate: int = DEFAULT_BAUDRATE, timeout_s: float = DEFAULT_TIMEOUT_S) -> Any:
    """Open the serial port (or pyserial URL) the user named: 8N1 at ``baudrate``.

    Args:
        port_or_url: a device path (``/dev/ttyACM0``, ``COM3``, a pty) or any
            ``serial_for_url`` URL (``loop://``, ``socket://host:port``, …).
        baudrate: 115200 for the USB port, 38400 for the TTL UART variant.
        timeout_s: read timeout, seconds.

    Raises:
        LensConnectionError: the port cannot be opened.
    """
    if serial is None:  # pragma: no cover
        raise LensConnectionError("pyserial is not installed")
    try:
        return serial.serial_for_url(
            port_or_url,
            baudrate=baudrate,
            bytesize=serial.EIGHTBITS,
            parity=serial.PARITY_NONE,
            stopbits=serial.STOPBITS_ONE,
            timeout=timeout_s,
            write_timeout=max(timeout_s, 0.5),
        )
    except _IO_ERRORS as exc:
        raise LensConnectionError(f"cannot open {port_or_url!r}: {exc}") from exc
    except ValueError as exc:  # bad URL or settings
        raise LensConnectionError(f"cannot open {port_or_url!r}: {exc}") from exc


class SerialTransport:
    """Command/reply exchange over a pyserial-like object.

    Args:
        port: an open pyserial-like object.
        timeout_s: how long one read may wait for bytes, seconds. Set on the port.
        owns_port: close ``port`` in :meth:`close`.

    Attributes:
        port: the wrapped object.
        timeout_s: the read timeout, seconds.
        drained: every stray byte drained so far (most recent last; capped at 4 KiB).
        stray_frames: frames decoded from drained input (capped at 64): late replies, or
            :class:`~tdfd.driver.protocol.ErrorFrame` answers to commands that have no
            reply of their own.
    """

    #: bytes read while waiting for one reply before giving up on a babbling port.
    MAX_REPLY_BYTES = 256

    def __init__(self, port: Any, *, timeout_s: float = DEFAULT_TIMEOUT_S, owns_port: bool = False) -> None:
        if not timeout_s > 0:
            raise InputError(f"timeout_s must be positive, got {timeout_s}")
        self.port = port
        self.timeout_s = float(timeout_s)
        self.owns_port = owns_port
        self.drained = b""
        self.stray_frames: list[Frame | ErrorFrame] = []
        self._decoder = FrameDecoder()
        self._closed = False
        self._configure_timeout()

    def _configure_timeout(self) -> None:
        try:
            if getattr(self.port, "timeout", self.timeout_s) != self.timeout_s:
                self.port.timeout = self.timeout_s
        except _IO_ERRORS as exc:
            raise LensConnectionError(f"cannot configure the port: {exc}") from exc

    # ------------------------------------------------------------------ raw I/O

    def _io(self, what: str, fn, *args):  # noqa: ANN001, ANN202
        if self._closed:
            raise LensConnectionError("transport is closed")
        try:
            return fn(*args)
        except _SERIAL_TIMEOUT as exc:
            raise LensTimeoutError(f"{what} timed out: {exc}") from exc
        except _IO_ERRORS as exc:
            raise LensConnectionError(f"serial port vanished during {what}: {exc}") from exc

    def drain(self) -> bytes:
        """Read and discard whatever is waiting on the input; return it.

        Called before each command. What it finds is logged, decoded (an ``E`` reply here
        is the answer to an earlier corrupted command) and kept in :attr:`drained` and
        :attr:`stray_frames`.
        """
        chunks = []
        for _ in range(64):  # bounded: a babbling port cannot hold us here
            waiting = self._io("drain", lambda: self.port.in_waiting)
            if not waiting:
                break
            chunks.append(bytes(self._io("drain", self.port.read, waiting)))
        self._io("drain", self.port.reset_input_buffer)
        pending = self._decoder.reset()
        data = pending + b"".join(chunks)
        if data:
            decoder = FrameDecoder()
            frames = decoder.feed(data)
            self.stray_frames = (self.stray_frames + frames)[-64:]
            self.drained = (self.drained + data)[-4096:]
            for frame in frames:
                if isinstance(frame, ErrorFrame):
                    log.warning("stray error reply drained (an earlier command was rejected): %s", frame.to_exception())
            log.warning("drained %d stray byte(s) before the command: %s", len(data), data[:64].hex(" "))
        return data

    def write(self, frame: bytes) -> None:
        """Write one command frame.

        Raises:
            ForbiddenCommandError: a frame starting with ``RESET``.
            LensConnectionError: the port vanished.
            LensTimeoutError: the write timed out.
        """
        frame = bytes(frame)
        if frame[: len(FORBIDDEN_PREFIX)].upper() == FORBIDDEN_PREFIX:
            raise ForbiddenCommandError("refusing to send RESET: it puts the Lens Driver 4 into firmware-update mode")
        log.debug("-> %s", frame.hex(" "))
        self._io("write", self.port.write, frame)
        flush = getattr(self.port, "flush", None)
        if flush is not None:
            self._io("flush", flush)

    def read_reply(self, expected_prefix: bytes) -> Frame:
        """Read until a reply with ``expected_prefix`` (or an error reply) is complete.

        Reads exactly :meth:`FrameDecoder.needed` bytes at a time, so it never waits for
        bytes a short error reply will not send; a read that comes back short (the
        port's timeout expired with bytes missing) ends the wait. Frames with another
        prefix (late replies to earlier commands) are logged and skipped. A port that
        babbles bytes without a valid reply is cut off after :attr:`MAX_REPLY_BYTES`.

        Args:
            expected_prefix: the reply prefix, e.g. ``b"A"``.

        Returns:
            The matching :class:`Frame`.

        Raises:
            DeviceErrorReply: the driver answered ``E`` + id or ``N``.
            ChecksumError: a reply-shaped frame with a bad CRC arrived.
            ProtocolError: more than :attr:`MAX_REPLY_BYTES` bytes without a valid reply.
            LensTimeoutError: no complete reply in time.
            LensConnectionError: the port vanished.
        """
        received = bytearray()
        while True:
            n = self._decoder.needed()
            chunk = bytes(self._io("read", self.port.read, n))
            received += chunk
            if chunk:
                log.debug("<- %s", chunk.hex(" "))
            for frame in self._decoder.feed(chunk):
                if isinstance(frame, ErrorFrame):
                    self._decoder.reset()
                    raise frame.to_exception()
                if frame.prefix == expected_prefix:
                    return frame
                log.warning("skipping a %r reply while waiting for %r (late reply?)", frame.prefix, expected_prefix)
            for error in self._decoder.pop_errors():
                if isinstance(error, ChecksumError):
                    self._decoder.reset()
                    raise error
                log.debug("%s", error)
            if len(received) > self.MAX_REPLY_BYTES:
                self._decoder.reset()
                raise ProtocolError(
                    f"no valid {expected_prefix!r} reply within {len(received)} bytes: {bytes(received[:32]).hex(' ')}…"
                )
            if len(chunk) < n:  # the port's read timeout expired
                pending = self._decoder.reset()
                raise LensTimeoutError(
                    f"no complete {expected_prefix!r} reply within {self.timeout_s:g} s"
                    + (f" (received {bytes(received[:32]).hex(' ')})" if received else " (nothing received)")
                    + (f", {len(pending)} byte(s) incomplete" if pending else "")
                )

    def exchange(self, frame: bytes, expected_prefix: bytes | None) -> Frame | None:
        """Drain, send one command and, only if it has one, read its reply.

        Args:
            frame: the command frame (from :mod:`tdfd.driver.protocol`).
            expected_prefix: the reply prefix, or ``None`` for a command without a reply
                (``Aw``, ``PwDA``): then nothing is read.

        Returns:
            The reply frame, or ``None``.
        """
        self.drain()
        self.write(frame)
        if expected_prefix is None:
            return None
        return self.read_reply(expected_prefix)

    def close(self) -> None:
        """Close the port if this transport owns it. Idempotent; never raises for a vanished port."""
        if self._closed:
            return
        self._closed = True
        if self.owns_port:
            try:
                self.port.close()
            except _IO_ERRORS as exc:  # pragma: no cover - closing a vanished port
                log.debug("closing the port: %s", exc)

    @property
    def closed(self) -> bool:
        """True after :meth:`close`."""
        return self._closed
