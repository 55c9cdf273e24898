"""Byte transport for the Lens Driver 4 over any pyserial-like object.

:class:`SerialTransport` wraps an object with pyserial's ``read``/``write``/
``in_waiting``/``reset_input_buffer`` (a ``serial.Serial``, anything from
``serial.serial_for_url`` such as ``loop://`` or a pty path, or a test double). It never
opens a port; :func:`open_port` does, and only the port or URL the caller names.

Per command it drains stray input (logging what it finds: a late reply, or the
unsolicited error reply to a corrupted command that has no reply of its own), writes the
frame, and, only if the command has a reply, reads exactly as many bytes as can complete
a frame, each read bounded by the port's timeout, decoding by the expected reply's length
(:class:`~tdfd.driver.protocol.ReplyReader`). I/O failures of a vanished port become
:class:`~tdfd.errors.LensConnectionError`.

Stale replies. The device answers commands in order, but a reply can arrive after its
query timed out, and draining before the next command cannot catch a reply that is still
on its way. So a query that ends without its reply (a timeout, an unreadable reply, an
``E 1``/``E 3`` answer that may belong to an earlier command) leaves the transport
*unsynchronised*: before the next command it sends a *fence*, a harmless query whose
reply prefix no owed reply has, and reads until the fence's reply arrives. Replies come
in order, so every late reply has arrived (and is discarded) or never will: the next
reply with a given prefix is the answer to the next query with that prefix.
"""

from __future__ import annotations

import logging
from typing import Any

from ..errors import ChecksumError, DeviceErrorReply, DriverError, ForbiddenCommandError, InputError, LensConnectionError, LensTimeoutError, ProtocolError
from . import protocol as p
from .protocol import FORBIDDEN_PREFIX, ErrorFrame, Frame, FrameDecoder, ReplyReader

try:  # pragma: no cover - termios is POSIX-only
    import termios

    _TERMIOS_ERRORS: tuple[type[BaseException], ...] = (termios.error,)
except ImportError:  # pragma: no cover
    _TERMIOS_ERRORS = ()

import serial  # pyserial: a dependency

_SERIAL_ERRORS: tuple[type[BaseException], ...] = (serial.SerialException,)
_SERIAL_TIMEOUT: tuple[type[BaseException], ...] = (serial.SerialTimeoutException,)

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
        unsynchronised: reply prefixes that may still arrive from queries that ended
            without their reply; non-empty means the next command is preceded by a fence.
        fences: fence queries sent so far.
    """

    #: bytes read while waiting for one reply before giving up on a babbling port.
    MAX_REPLY_BYTES = 256
    #: harmless queries used as fences, tried in this order (one whose reply prefix is owed is skipped).
    FENCE_COMMANDS: tuple[bytes, ...] = (
        p.encode_get_firmware_type(),
        p.encode_get_status(),
        p.encode_get_temperature(),
        p.encode_get_firmware_version(),
        p.encode_get_max_current(),
    )
    #: fences tried per exchange before it gives up with :class:`~tdfd.errors.LensTimeoutError`
    #: (the device class retries whole exchanges, so one fence per attempt bounds the time).
    FENCE_ATTEMPTS = 1

    def __init__(self, port: Any, *, timeout_s: float = DEFAULT_TIMEOUT_S, owns_port: bool = False) -> None:
        if not timeout_s > 0:
            raise InputError(f"timeout_s must be positive, got {timeout_s}")
        self.port = port
        self.timeout_s = float(timeout_s)
        self.owns_port = owns_port
        self.drained = b""
        self.stray_frames: list[Frame | ErrorFrame] = []
        self.unsynchronised: set[bytes] = set()
        self.fences = 0
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
        data = b"".join(chunks)
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

    def read_reply(self, expected_prefix: bytes, *, skip_errors: bool = False) -> Frame:
        """Read until the reply with ``expected_prefix`` (or an error reply) is complete.

        Decodes by the expected reply's length (:class:`~tdfd.driver.protocol.ReplyReader`),
        so a payload holding a shorter frame is never taken for that frame. Reads exactly
        :meth:`ReplyReader.needed` bytes at a time, so it never waits for bytes a short
        error reply will not send; a read that comes back short (the port's timeout
        expired with bytes missing) ends the wait. Frames with another prefix (late
        replies to earlier commands) are logged and skipped. A port that babbles bytes
        without a valid reply is cut off after :attr:`MAX_REPLY_BYTES`.

        Args:
            expected_prefix: the reply prefix, e.g. ``b"A"``.
            skip_errors: log and skip error replies instead of raising (fences: an error
                reply before the fence's reply may belong to an earlier command).

        Returns:
            The matching :class:`Frame`.

        Raises:
            DeviceErrorReply: the driver answered ``E`` + id or ``N``.
            ChecksumError: a reply with the expected prefix and a bad CRC arrived.
            ProtocolError: more than :attr:`MAX_REPLY_BYTES` bytes without a valid reply.
            LensTimeoutError: no complete reply in time.
            LensConnectionError: the port vanished.
        """
        reader = ReplyReader(expected_prefix)
        received = bytearray()
        while True:
            n = reader.needed()
            chunk = bytes(self._io("read", self.port.read, n))
            received += chunk
            if chunk:
                log.debug("<- %s", chunk.hex(" "))
            timed_out = len(chunk) < n  # the port's read timeout expired
            frames = reader.feed(chunk) + (reader.finish() if timed_out else [])
            for frame in frames:
                if isinstance(frame, ErrorFrame):
                    if not skip_errors:
                        raise frame.to_exception()
                    log.warning("skipping an error reply while waiting for %r: %s", expected_prefix, frame.to_exception())
                    continue
                if frame.prefix == expected_prefix:
                    return frame
                log.warning("skipping a %r reply while waiting for %r (late reply?)", frame.prefix, expected_prefix)
            for error in reader.errors:
                if isinstance(error, ChecksumError):
                    raise error
                log.debug("%s", error)
            reader.errors.clear()
            if len(received) > self.MAX_REPLY_BYTES:
                raise ProtocolError(
                    f"no valid {expected_prefix!r} reply within {len(received)} bytes: {bytes(received[:32]).hex(' ')}…"
                )
            if timed_out:
                raise LensTimeoutError(
                    f"no complete {expected_prefix!r} reply within {self.timeout_s:g} s"
                    + (f" (received {bytes(received[:32]).hex(' ')})" if received else " (nothing received)")
                )

    def resynchronise(self) -> None:
        """Send a fence and read until its reply, discarding every late reply before it.

        A fence is a harmless query (:attr:`FENCE_COMMANDS`) whose reply prefix is not
        among :attr:`unsynchronised`. The device answers in order, so once the fence's
        reply is in, no reply to an earlier query can still arrive: the set is cleared.
        A fence that fails adds its own prefix to the set; after :attr:`FENCE_ATTEMPTS`
        failures it raises that failure. With every fence's prefix owed (the device has
        been silent for several fences) it first waits until the line has been quiet
        for two read timeouts and takes every owed reply as lost: a reply later than
        that could still be mistaken for a fence's.

        Raises:
            LensTimeoutError: the fence was not answered in time.
            ChecksumError: the fence's reply was corrupted.
            ProtocolError: the port babbled without a valid fence reply.
            LensConnectionError: the port vanished.
        """
        last: DriverError | None = None
        for _ in range(self.FENCE_ATTEMPTS):
            fence = next((f for f in self.FENCE_COMMANDS if p.reply_prefix_for(f) not in self.unsynchronised), None)
            if fence is None:
                self._wait_quiet()
                self.unsynchronised.clear()
                fence = self.FENCE_COMMANDS[0]
            prefix = p.reply_prefix_for(fence)
            assert prefix is not None
            self.fences += 1
            log.info("resynchronising after a lost reply (owed: %s): fence %r", sorted(self.unsynchronised), prefix)
            self.drain()
            try:
                self.write(fence)
                self.read_reply(prefix, skip_errors=True)
            except (LensTimeoutError, ProtocolError) as exc:  # ProtocolError includes ChecksumError
                self.unsynchronised.add(prefix)  # a corrupted fence reply too: it may have been a stale one
                last = exc
                continue
            self.unsynchronised.clear()
            return
        assert last is not None
        raise last

    def _wait_quiet(self, quiet_reads: int = 2, max_reads: int = 16) -> None:
        """Read and discard until ``quiet_reads`` consecutive reads time out with nothing (bounded)."""
        log.warning("every fence's reply is owed (%s): waiting for a quiet line", sorted(self.unsynchronised))
        quiet = 0
        for _ in range(max_reads):
            data = bytes(self._io("read", self.port.read, self.MAX_REPLY_BYTES))
            quiet = 0 if data else quiet + 1
            if data:
                log.warning("discarding %d late byte(s): %s", len(data), data[:32].hex(" "))
            if quiet >= quiet_reads:
                return

    def exchange(self, frame: bytes, expected_prefix: bytes | None) -> Frame | None:
        """Resynchronise if needed, drain, send one command and, only if it has one, read its reply.

        A query that ends without its reply (timeout, babble, ``E 1``/``E 3``) marks its
        prefix as owed (:attr:`unsynchronised`), so the next exchange starts with a fence
        (:meth:`resynchronise`). ``E 2``/``E 4`` are the answer itself, and so is a reply
        with the expected prefix and a bad CRC (after a fence nothing else can carry it).

        Args:
            frame: the command frame (from :mod:`tdfd.driver.protocol`).
            expected_prefix: the reply prefix, or ``None`` for a command without a reply
                (``Aw``, ``PwDA``): then nothing is read.

        Returns:
            The reply frame, or ``None``.
        """
        if self.unsynchronised:
            self.resynchronise()
        self.drain()
        try:
            self.write(frame)
            if expected_prefix is None:
                return None
            return self.read_reply(expected_prefix)
        except DeviceErrorReply as exc:
            if exc.code in (1, 3) and expected_prefix is not None:
                self.unsynchronised.add(expected_prefix)
            raise
        except ChecksumError:
            raise
        except (LensTimeoutError, ProtocolError):
            if expected_prefix is not None:
                self.unsynchronised.add(expected_prefix)
            raise

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
