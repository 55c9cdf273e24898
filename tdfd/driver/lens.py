"""The device API of the Optotune Lens Driver 4: :class:`OptotuneLens`.

Typical use::

    from tdfd.driver import OptotuneLens

    with OptotuneLens.open("/dev/ttyACM0") as lens:     # handshake: the current drops to 0
        lens.set_current_ma(50.0)                      # DC current mode
        limits = lens.set_focal_power_mode()           # PwTA (temperature limits), then MwCA
        lens.set_focal_power_dpt(1.5, verify=True)     # range-checked, then read back (PrDA)
        print(lens.get_focal_power_dpt(), lens.get_temperature_c())

The driver's view of the device is verified, not assumed:

* :attr:`OptotuneLens.mode` is ``None`` (unknown) after a mode change (``MwDA``,
  ``MwCA``, ``Start``) whose reply was lost, and the mode is read (``MMA``) before the
  next set command relies on it.
* Set commands have no reply. With ``verify=True`` (per call, or for every call with
  ``OptotuneLens(..., verify=True)``) the set-point is read back (``Ar``/``PrDA``); a
  command the device rejected or never got is sent again, and one that still does not
  take raises :class:`~tdfd.errors.LensStateError`. :attr:`OptotuneLens.current_setpoint_ma`
  and :attr:`OptotuneLens.focal_power_setpoint_dpt` hold the set-point as last set
  (``None`` after a failure: unknown).
* A reply that arrives after its query timed out is never taken as the answer to a later
  query (the transport resynchronises with a fence query first), and replies are decoded
  by their expected length (see :mod:`tdfd.driver.transport`).

Every failure is a :class:`~tdfd.errors.DriverError` subclass: out-of-range set-points
:class:`~tdfd.errors.LensRangeError`, a command in the wrong mode
:class:`~tdfd.errors.LensModeError`, an ``E``/``N`` answer
:class:`~tdfd.errors.DeviceErrorReply`, silence :class:`~tdfd.errors.LensTimeoutError`
(after ``retries`` further attempts), a set-point that does not read back
:class:`~tdfd.errors.LensStateError`, a vanished port
:class:`~tdfd.errors.LensConnectionError`. ``RESET`` cannot be sent.
"""

from __future__ import annotations

import logging
import threading
from typing import Any

from ..errors import (
    DeviceErrorReply,
    DriverError,
    InputError,
    LensModeError,
    LensRangeError,
    LensStateError,
    ProtocolError,
)
from . import link
from . import protocol as p
from .focal_power import DEFAULT_TEMPERATURE_LIMITS_C, FocalPowerMode
from .protocol import FirmwareVersion, FocalPowerLimits, Frame, Mode, Status
from .transport import DEFAULT_BAUDRATE, DEFAULT_TIMEOUT_S, SerialTransport, open_port

__all__ = [
    "OptotuneLens",
    "DEFAULT_RETRIES",
    "DEFAULT_TEMPERATURE_LIMITS_C",
]

log = logging.getLogger(__name__)

#: further attempts after a timeout, a bad CRC, or an ``E 1`` (command CRC failed) or
#: ``E 3`` (not recognised: a corrupted prefix) answer; also the re-sends of a verified set.
DEFAULT_RETRIES = 2
#: commands that change the operating mode: a lost reply leaves the mode unknown.
_MODE_COMMANDS = (b"Start", b"MwDA", b"MwCA")


class OptotuneLens(FocalPowerMode):
    """An Optotune Lens Driver 4 with its lens (e.g. EL-10-30), over a serial port.

    Focal-power mode (temperature limits, ``MwCA``, ``PwDA``/``PrDA``) comes from
    :class:`~tdfd.driver.focal_power.FocalPowerMode`. The constructor does no I/O; :meth:`open` opens a named port and :meth:`connect`s.

    Args:
        port: an open pyserial-like object (``serial.Serial``, ``serial_for_url(...)``,
            a test double).
        timeout_s: time allowed for one reply, seconds.
        retries: further attempts for a command with a reply after a timeout, a bad
            reply CRC (or other unreadable reply), or an ``E 1``/``E 3`` answer (the
            command arrived corrupted). Commands without a reply are never retried and,
            unless verified, never read; a verified set is sent at most ``1 + retries`` times.
        owns_port: close ``port`` in :meth:`close`.
        verify: default of the ``verify`` argument of :meth:`set_current_ma` and
            :meth:`set_focal_power_dpt`: read every set-point back.

    Attributes:
        transport: the :class:`~tdfd.driver.transport.SerialTransport`.
        retries: see above.
        firmware_type: ``H`` reply letter, or ``None`` until read.
        max_current_ma: maximum output current (``CrMA``), mA, or ``None`` until read.
        current_limits_ma: (lower, upper) software current limits, mA, or ``None``.
        mode: the operating mode as last read or set, or ``None`` if unknown (never
            read, ``MMA`` unavailable, or a mode change whose reply was lost).
        current_setpoint_ma: the output current as last set (read back if verified), mA;
            ``None`` if unknown (after a failed set, a mode change, in focal-power mode).
        focal_power_setpoint_dpt: the focal power as last set (read back if verified),
            dpt; ``None`` if unknown or not in focal-power mode.
        verify: see above.
        focal_power_limits: the limits of the last ``MwCA`` reply, or ``None``.
        temperature_limits_c: (lower, upper) temperature limits last sent, °C, or ``None``.
    """

    #: accepted difference between a set-point and its read-back, raw units (one step: 0.005 dpt,
    #: about 0.07 mA): the facts do not say that ``Ar``/``PrDA`` return the set value exactly
    #: (the emulator does; tests/test_driver_hardware.py checks a real driver).
    READBACK_TOLERANCE_RAW = 1

    def __init__(
        self,
        port: Any,
        *,
        timeout_s: float = DEFAULT_TIMEOUT_S,
        retries: int = DEFAULT_RETRIES,
        owns_port: bool = False,
        verify: bool = False,
    ) -> None:
        if int(retries) < 0:
            raise InputError(f"retries must be >= 0, got {retries}")
        self.transport = SerialTransport(port, timeout_s=timeout_s, owns_port=owns_port)
        self.retries = int(retries)
        self.firmware_type: str | None = None
        self.max_current_ma: float | None = None
        self.current_limits_ma: tuple[float, float] | None = None
        self._current_limits_raw: tuple[int, int] | None = None
        self.mode: Mode | None = None
        self.current_setpoint_ma: float | None = None
        self.focal_power_setpoint_dpt: float | None = None
        self.verify = bool(verify)
        self._mode_readable = True
        self.focal_power_limits: FocalPowerLimits | None = None
        self.temperature_limits_c: tuple[float, float] | None = None
        self._lock = threading.RLock()

    # ------------------------------------------------------------------ life cycle

    @classmethod
    def open(
        cls,
        port_or_url: str,
        *,
        baudrate: int = DEFAULT_BAUDRATE,
        timeout_s: float = DEFAULT_TIMEOUT_S,
        retries: int = DEFAULT_RETRIES,
        handshake: bool = True,
        verify: bool = False,
    ) -> OptotuneLens:
        """Open the named port or pyserial URL and :meth:`connect`.

        Use as a context manager (``with OptotuneLens.open(port) as lens:``) so the port
        is closed. Note that the handshake zeroes the output current.

        Args:
            port_or_url: e.g. ``/dev/ttyACM0``, ``COM3``, an emulator's pty path.
            baudrate: 115200 (USB) or 38400 (TTL UART variant).
            timeout_s: time allowed for one reply, seconds.
            retries: see the class.
            handshake: send ``Start`` first.
            verify: read every set-point back (see the class).

        Raises:
            LensConnectionError: the port cannot be opened or vanished.
            DriverError: the device did not identify itself.
        """
        port = open_port(port_or_url, baudrate=baudrate, timeout_s=timeout_s)
        lens = cls(port, timeout_s=timeout_s, retries=retries, owns_port=True, verify=verify)
        try:
            lens.connect(handshake=handshake)
        except BaseException:
            lens.close()
            raise
        return lens

    def connect(self, *, handshake: bool = True) -> OptotuneLens:
        """Handshake (optional), then read firmware type, maximum current, current limits and mode.

        Args:
            handshake: send ``Start`` first (zeroes the output current).

        Returns:
            ``self``.
        """
        with self._lock:
            if handshake:
                self.handshake()
            self.get_firmware_type()
            self.get_max_current_ma()
            self.get_current_limits_ma()
            try:
                self.get_mode()
            except DeviceErrorReply as exc:  # MMA missing on some firmware: mode stays unknown
                log.warning("cannot read the operating mode: %s", exc)
                self.mode = None
                if exc.code == 2:
                    self._mode_readable = False
            log.info(
                "lens driver: firmware type %s, max current %.2f mA, current limits %s mA, mode %s",
                self.firmware_type,
                self.max_current_ma,
                self.current_limits_ma,
                self.mode.name if self.mode else "unknown",
            )
        return self

    def close(self) -> None:
        """Close the port if this lens opened it. Idempotent; the lens keeps its state."""
        self.transport.close()

    def __enter__(self) -> OptotuneLens:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        port = getattr(self.transport.port, "port", None) or type(self.transport.port).__name__
        return f"OptotuneLens({port!r}, firmware_type={self.firmware_type!r}, mode={self.mode.name if self.mode else None})"

    # ------------------------------------------------------------------ exchanges

    def _query(self, frame: bytes) -> Frame:
        """Send a command that has a reply, with retries (:func:`tdfd.driver.link.query`).

        If a mode-changing command (``Start``, ``MwDA``, ``MwCA``) fails, it may still have
        acted: the mode and set-points become unknown (``None``).
        """
        with self._lock:
            try:
                return link.query(self.transport, frame, self.retries)
            except DriverError as exc:
                if frame.startswith(_MODE_COMMANDS):
                    self._forget_mode(f"{bytes(frame[:5])!r} failed ({exc})")
                raise

    def _send(self, frame: bytes) -> None:
        """Send a command that has no reply, once (:func:`tdfd.driver.link.send`); read nothing."""
        with self._lock:
            link.send(self.transport, frame, self.retries)

    def _forget_mode(self, why: str) -> None:
        """The device may have changed mode without our knowing: mode and set-points unknown."""
        log.warning("%s: the operating mode is unknown until read again", why)
        self.mode = None
        self.focal_power_limits = None
        self.current_setpoint_ma = None
        self.focal_power_setpoint_dpt = None

    def _known_mode(self) -> Mode | None:
        """The mode, read (``MMA``) first if unknown and readable; ``None`` if it cannot be read."""
        if self.mode is None and self._mode_readable:
            try:
                self.get_mode()
            except DeviceErrorReply as exc:
                if exc.code != 2:
                    raise
                log.warning("cannot read the operating mode: %s", exc)
                self._mode_readable = False
        return self.mode

    # ------------------------------------------------------------------ identification

    def handshake(self) -> None:
        """Send ``Start`` and expect ``Ready``. The driver zeroes its output current and selects current mode."""
        with self._lock:
            self._query(p.encode_start())
            self.mode = Mode.CURRENT if self._mode_readable else None
            self.current_setpoint_ma = 0.0
            self.focal_power_setpoint_dpt = None

    def get_firmware_type(self) -> str:
        """Firmware type letter (``A``, ``B``, ``C``, ``E``, ``F``); also cached in :attr:`firmware_type`."""
        data = self._query(p.encode_get_firmware_type()).data
        letter = chr(data[0])
        if not letter.isalpha():
            raise ProtocolError(f"firmware type is not a letter: {data!r}")
        self.firmware_type = letter
        return letter

    def get_firmware_version(self) -> FirmwareVersion:
        """Firmware version (major, minor, build, revision)."""
        return p.parse_firmware_version(self._query(p.encode_get_firmware_version()))

    def get_serial_number(self) -> str:
        """The lens serial number (8 characters; empty without lens EEPROM)."""
        return _text(self._query(p.encode_get_serial_number()).data)

    def get_device_id(self) -> str:
        """The driver's device id (8 characters)."""
        return _text(self._query(p.encode_get_device_id()).data)

    # ------------------------------------------------------------------ current

    def get_max_current_ma(self) -> float:
        """Maximum output current, mA (default 292.84); also cached in :attr:`max_current_ma`."""
        raw = p.unpack_i16(self._query(p.encode_get_max_current()).data)
        if raw <= 0:
            raise ProtocolError(f"implausible maximum current register {raw}")
        self.max_current_ma = p.max_current_raw_to_ma(raw)
        return self.max_current_ma

    def get_current_limits_ma(self) -> tuple[float, float]:
        """(lower, upper) software current limits, mA; cached in :attr:`current_limits_ma`.

        The registers are read as raw current values (the ``Aw`` scale).
        """
        max_ma = self._max_current()
        lower = p.unpack_i16(self._query(p.encode_get_lower_current_limit()).data)
        upper = p.unpack_i16(self._query(p.encode_get_upper_current_limit()).data)
        if lower > upper:
            log.warning("lower current limit %d above upper %d: swapping", lower, upper)
            lower, upper = upper, lower
        self._current_limits_raw = (lower, upper)
        self.current_limits_ma = (p.current_raw_to_ma(lower, max_ma), p.current_raw_to_ma(upper, max_ma))
        return self.current_limits_ma

    def _max_current(self) -> float:
        return self.max_current_ma if self.max_current_ma is not None else self.get_max_current_ma()

    def set_current_ma(self, current_ma: float, *, verify: bool | None = None) -> None:
        """Set the output current (``Aw``; the driver sends no reply).

        Args:
            current_ma: output current, mA; negative currents are allowed.
            verify: read the current back (``Ar``) and re-send a command the device did
                not take (rejected as corrupted, or lost); ``None``: :attr:`verify`.
                Unverified, nothing is read and a rejected command goes unnoticed.

        Raises:
            LensRangeError: not finite, beyond the maximum current or the software limits.
            LensModeError: the driver is (or, read again, turns out to be) in another
                mode than current mode.
            LensStateError: verified, and the current still reads back otherwise after
                ``1 + retries`` sends.
        """
        verify = self.verify if verify is None else bool(verify)
        with self._lock:
            mode = self._known_mode()
            if mode is not None and mode != Mode.CURRENT:
                raise LensModeError(f"set_current_ma needs current mode, the driver is in {mode.name} mode: call set_current_mode()")
            max_ma = self._max_current()
            if self._current_limits_raw is None:
                self.get_current_limits_ma()
            raw = p.current_ma_to_raw(current_ma, max_ma)
            lower, upper = self._current_limits_raw  # type: ignore[misc]
            if not lower <= raw <= upper:
                lo_ma, hi_ma = self.current_limits_ma  # type: ignore[misc]
                raise LensRangeError(f"current {current_ma} mA outside the software limits [{lo_ma:.2f}, {hi_ma:.2f}] mA")
            self.current_setpoint_ma = None  # unknown until sent (and, if asked, read back)
            raw = self._set(p.encode_set_current(raw), p.encode_get_current(), raw, Mode.CURRENT, "current", verify)
            self.current_setpoint_ma = p.current_raw_to_ma(raw, max_ma)

    def _set(self, frame: bytes, readback: bytes, raw: int, mode: Mode, what: str, verify: bool) -> int:
        """Send a set command (no reply); with ``verify`` read it back (:meth:`_set_verified`).
        Returns the raw set-point as the device holds it (``raw`` when not verified)."""
        if verify:
            return self._set_verified(frame, readback, raw, mode, what)
        self._send(frame)
        return raw

    def _set_verified(self, frame: bytes, readback: bytes, raw: int, mode: Mode, what: str) -> int:
        """Send a set command, read the set-point back, re-send while it differs.

        Returns:
            The raw set-point read back (within :attr:`READBACK_TOLERANCE_RAW` of ``raw``).

        Raises:
            LensModeError: a mismatch, and the mode read again is not ``mode``.
            LensStateError: still a mismatch after ``1 + retries`` sends.
        """
        got = None
        for attempt in range(self.retries + 1):
            self._send(frame)
            got = p.unpack_i16(self._query(readback).data)
            if abs(got - raw) <= self.READBACK_TOLERANCE_RAW:
                return got
            log.warning("%s set-point reads back raw %d instead of %d (send %d of %d)", what, got, raw, attempt + 1, self.retries + 1)
            if self._mode_readable:
                self.mode = None
                read = self._known_mode()
                if read is not None and read != mode:
                    raise LensModeError(f"the driver is in {read.name} mode, the {what} set-point needs {mode.name} mode")
        raise LensStateError(f"the {what} set-point reads back raw {got} instead of {raw} after {self.retries + 1} sends")

    def get_current_ma(self) -> float:
        """The output current, mA."""
        raw = p.unpack_i16(self._query(p.encode_get_current()).data)
        return p.current_raw_to_ma(raw, self._max_current())

    # ------------------------------------------------------------------ modes

    def get_mode(self) -> Mode:
        """The operating mode (``MMA``); also cached in :attr:`mode`."""
        value = self._query(p.encode_get_mode()).data[0]
        try:
            self.mode = Mode(value)
        except ValueError:
            raise ProtocolError(f"unknown operating mode {value}") from None
        return self.mode

    def set_current_mode(self) -> None:
        """Switch to DC current mode (``MwDA``). The output current stays as it was (unknown here)."""
        with self._lock:
            self._query(p.encode_current_mode())
            self.mode = Mode.CURRENT
            self.current_setpoint_ma = None
            self.focal_power_setpoint_dpt = None

    # ------------------------------------------------------------------ monitoring

    def get_temperature_c(self) -> float | None:
        """Lens temperature, °C (``None``: no sensor)."""
        return p.temperature_raw_to_c(p.unpack_i16(self._query(p.encode_get_temperature()).data))

    def get_status(self) -> Status:
        """The four status bytes (``Sr``); ``.flags`` decodes status byte #1."""
        return p.parse_status(self._query(p.encode_get_status()))


def _text(data: bytes) -> str:
    return bytes(data).rstrip(b"\x00").decode("ascii", errors="replace")
