"""The emulated Lens Driver 4 itself: registers, modes and the answer to every command.

:meth:`Emulator.handle` answers one complete command frame with the reply bytes
(byte-exact, CRCs included); :meth:`Emulator.feed` takes a raw byte stream (split by
:class:`~tdfd.driver.emulator.stream.CommandStream`) and returns the replies. The optics
(settling, temperature) are :class:`~tdfd.driver.emulator.optics.LensOptics`.

Behaviour (documented assumptions, not manufacturer data):

* Current mode: the optical power follows the current's calibrated power through the
  first-order filter, plus the (unfiltered) thermal drift.
* Focal-power mode: the driver compensates temperature, so the optical power follows the
  set-point through the filter. The reported limits are the powers reachable at every
  temperature between the user's temperature limits with currents inside the software
  current limits; type A clips them to its encodable −5…+15.475 dpt. A ``PwDA``
  set-point outside the limits is clipped and sets status bit 3.
* ``Aw`` acts only in current mode and ``PwDA`` only in focal-power mode (otherwise they
  are ignored); ``Start`` zeroes the current and selects current mode. ``RESET`` puts
  the emulator in firmware-update mode: it stops answering (a test can check
  :attr:`Emulator.reset_received`).
"""

from __future__ import annotations

import logging
import struct
import threading
import time
from collections import deque
from typing import Callable

from ...errors import InputError
from .. import protocol as p
from ..protocol import Mode, StatusFlags
from .optics import DEFAULT_SETTLING_TIME_S, Calibration, LensOptics, reachable_focal_power_raw
from .stream import CommandStream, Piece

__all__ = ["Emulator"]

log = logging.getLogger(__name__)

_FOCAL_POWER_COMMANDS = frozenset({"MwCA", "PwTA", "PwDA", "PrDA"})


class Emulator:
    """Device model of a Lens Driver 4 with an EL-10-30, speaking the protocol byte-exactly.

    Thread-safe: the pty server thread feeds it while a bench reads its state.

    Args:
        firmware_type: ``H`` reply letter. Focal-power commands answer ``E 2`` on types
            other than A, B, C, E.
        clock: callable returning the time in seconds; used for settling and temperature.
        settling_time_s: time for a focal-power step to settle within 1 %, seconds.
        calibration: focal power versus current and temperature.
        max_current_ma: maximum output current, mA (``CrMA``).
        current_limits_ma: (lower, upper) software current limits, mA (default ±maximum).
        temperature_c: initial lens temperature, °C.
        firmware_version: (major, minor, build, revision).
        serial_number: 8-byte lens serial number.
        device_id: 8-byte device id.
        lens_eeprom: False: the serial number reads as zeros and status bit 1 is set.
        temperature_sensor: False: ``TCA`` reads 4095 (no sensor).
        error_style: ``"E"`` answers a bad command CRC with ``E 1``, ``"N"`` with ``N\\r\\n``.
        unavailable: command names (e.g. ``{"MMA"}``) answered with ``E 2``.
        spec_temperature_c: product specification temperature range (status bit 5), °C.
    """

    def __init__(
        self,
        *,
        firmware_type: str = "A",
        clock: Callable[[], float] = time.monotonic,
        settling_time_s: float = DEFAULT_SETTLING_TIME_S,
        calibration: Calibration = Calibration(),
        max_current_ma: float = 292.84,
        current_limits_ma: tuple[float, float] | None = None,
        temperature_c: float = 25.0,
        firmware_version: tuple[int, int, int, int] = (1, 8, 2021, 0),
        serial_number: bytes = b"EL103001",
        device_id: bytes = b"LD4EMU01",
        lens_eeprom: bool = True,
        temperature_sensor: bool = True,
        error_style: str = "E",
        unavailable: frozenset[str] | set[str] | tuple[str, ...] = (),
        spec_temperature_c: tuple[float, float] = (-20.0, 65.0),
    ) -> None:
        if len(firmware_type) != 1 or not firmware_type.isalpha():
            raise InputError(f"firmware_type must be one letter, got {firmware_type!r}")
        if error_style not in ("E", "N"):
            raise InputError(f"error_style must be 'E' or 'N', got {error_style!r}")
        if settling_time_s < 0 or max_current_ma <= 0:
            raise InputError("settling_time_s must be >= 0 and max_current_ma > 0")
        self._lock = threading.RLock()
        self.firmware_type = firmware_type
        self.clock = clock
        self.calibration = calibration
        self.max_current_ma = float(max_current_ma)
        self.firmware_version = tuple(int(v) for v in firmware_version)
        self.serial_number = bytes(serial_number).ljust(8, b"\x00")[:8]
        self.device_id = bytes(device_id).ljust(8, b"\x00")[:8]
        self.lens_eeprom = lens_eeprom
        self.temperature_sensor = temperature_sensor
        self.error_style = error_style
        self.unavailable = frozenset(unavailable)
        self.spec_temperature_c = spec_temperature_c
        lo, hi = current_limits_ma if current_limits_ma is not None else (-self.max_current_ma, self.max_current_ma)
        self._current_limits_raw = (self._ma_to_raw(lo), self._ma_to_raw(hi))
        self._mode = Mode.CURRENT
        self._current_raw = 0
        self._setpoint_dpt: float | None = None
        self._temperature_limits_c: tuple[float, float] | None = None
        self._cannot_reach = False
        self.reset_received = False
        self._stream = CommandStream()
        #: (time, command name) of every well-formed command received, most recent last.
        self.command_log: deque[tuple[float, str]] = deque(maxlen=10000)
        self.command_count = 0
        self.optics = LensOptics(calibration, settling_time_s, self.clock(), temperature_c)

    # ------------------------------------------------------------------ conversions

    def _ma_to_raw(self, current_ma: float) -> int:
        raw = p.round_half_away(current_ma * p.CURRENT_RAW_LIMIT / self.max_current_ma)
        return max(-p.CURRENT_RAW_LIMIT, min(p.CURRENT_RAW_LIMIT, raw))

    def _raw_to_ma(self, raw: int) -> float:
        return p.current_raw_to_ma(raw, self.max_current_ma)

    @property
    def settling_time_s(self) -> float:
        """Time for a focal-power step to settle within 1 %, seconds."""
        return self.optics.settling_time_s

    @property
    def time_constant_s(self) -> float:
        """First-order time constant of the focal power, seconds (settling_time_s / ln 100)."""
        return self.optics.time_constant_s

    @property
    def focal_power_capable(self) -> bool:
        """Whether this firmware type has a documented focal-power encoding."""
        return self.firmware_type in p.FOCAL_POWER_FIRMWARE_TYPES

    # ------------------------------------------------------------------ state, read by a bench

    @property
    def mode(self) -> Mode:
        """The operating mode."""
        return self._mode

    @property
    def current_ma(self) -> float:
        """The output current, mA (in focal-power mode: the current the set-point needs now)."""
        with self._lock:
            return self._raw_to_ma(self._output_current_raw(self.clock()))

    @property
    def current_limits_ma(self) -> tuple[float, float]:
        """(lower, upper) software current limits, mA."""
        return (self._raw_to_ma(self._current_limits_raw[0]), self._raw_to_ma(self._current_limits_raw[1]))

    @property
    def temperature_limits_c(self) -> tuple[float, float] | None:
        """(lower, upper) temperature limits received with ``PwTA``, °C, or ``None``."""
        return self._temperature_limits_c

    @property
    def focal_power_setpoint_dpt(self) -> float | None:
        """The focal-power set-point in focal-power mode (after clipping), dpt; else ``None``."""
        return self._setpoint_dpt if self._mode == Mode.FOCAL_POWER else None

    @property
    def focal_power_limits_dpt(self) -> tuple[float, float]:
        """(min, max) focal power reported by ``MwCA``/``PwTA`` for the present limits, dpt."""
        with self._lock:
            lo, hi = self._focal_power_limits_raw(self.clock())
            return (p.focal_power_raw_to_dpt(lo, self._encoding()), p.focal_power_raw_to_dpt(hi, self._encoding()))

    @property
    def target_focal_power_dpt(self) -> float:
        """The optical focal power the lens settles to (thermal drift at the present temperature included), dpt."""
        with self._lock:
            return self.optics.target_at(self.clock())

    @property
    def focal_power_dpt(self) -> float:
        """The optical focal power now (by :attr:`clock`), dpt."""
        return self.focal_power_at(self.clock())

    def focal_power_at(self, t: float) -> float:
        """The optical focal power at time ``t`` on the emulator's clock, dpt (see :class:`LensOptics`)."""
        with self._lock:
            return self.optics.focal_power_at(t)

    def temperature_at(self, t: float) -> float:
        """Lens temperature at time ``t``, °C (first-order approach to the last target)."""
        with self._lock:
            return self.optics.temperature_at(t)

    @property
    def temperature_c(self) -> float:
        """Lens temperature now, °C."""
        return self.temperature_at(self.clock())

    def set_temperature(self, temperature_c: float, time_constant_s: float = 0.0) -> None:
        """Move the lens temperature towards ``temperature_c``, °C.

        Args:
            temperature_c: the new ambient temperature, °C.
            time_constant_s: first-order time constant of the change (0: at once), s.
        """
        with self._lock:
            self.optics.set_temperature(self.clock(), temperature_c, time_constant_s)

    @property
    def commands(self) -> list[str]:
        """Names of the well-formed commands received so far (most recent last)."""
        with self._lock:
            return [name for _, name in self.command_log]

    # ------------------------------------------------------------------ derived quantities

    def _encoding(self) -> str:
        return self.firmware_type if self.focal_power_capable else "B"

    def _focal_power_limits_raw(self, now: float) -> tuple[int, int]:
        temperatures = self._temperature_limits_c or (self.temperature_at(now),) * 2
        return reachable_focal_power_raw(self.calibration, self.current_limits_ma, temperatures, self._encoding())

    def _output_current_raw(self, now: float) -> int:
        if self._mode == Mode.FOCAL_POWER and self._setpoint_dpt is not None:
            ma = self.calibration.current_ma(self._setpoint_dpt, self.temperature_at(now))
            lo, hi = self._current_limits_raw
            return max(lo, min(hi, self._ma_to_raw(ma)))
        return self._current_raw

    def _status_flags(self, now: float) -> StatusFlags:
        flags = StatusFlags(0)
        if not self.lens_eeprom:
            flags |= StatusFlags.NO_OR_FAULTY_EEPROM
        if self._temperature_limits_c is None:
            flags |= StatusFlags.NO_TEMPERATURE_LIMITS
        if self._cannot_reach and self._mode == Mode.FOCAL_POWER:
            flags |= StatusFlags.CANNOT_REACH_FOCAL_POWER
        temp = self.temperature_at(now)
        if not self.spec_temperature_c[0] <= temp <= self.spec_temperature_c[1]:
            flags |= StatusFlags.TEMPERATURE_OUTSIDE_SPECIFICATION
        if self._temperature_limits_c is not None and not self._temperature_limits_c[0] <= temp <= self._temperature_limits_c[1]:
            flags |= StatusFlags.TEMPERATURE_OUTSIDE_USER_LIMITS
        return flags

    def _limits_payload(self, now: float) -> bytes:
        lo, hi = self._focal_power_limits_raw(now)
        return bytes([int(self._status_flags(now))]) + p.pack_i16(hi) + p.pack_i16(lo)

    # ------------------------------------------------------------------ the protocol

    def _error(self, code: int) -> bytes:
        if code == 1 and self.error_style == "N":
            return p.BARE_ERROR_REPLY
        return p.encode_error_reply(code)

    def handle(self, frame: bytes) -> bytes:
        """Answer one complete command frame.

        Args:
            frame: exactly one command, CRC included (``Start``/``RESET``: without).

        Returns:
            The reply bytes as the driver sends them; ``b""`` for a command without a
            reply (``Aw``, ``PwDA``) and for anything after ``RESET``.
        """
        frame = bytes(frame)
        with self._lock:
            if self.reset_received:
                return b""
            now = self.clock()
            if frame == p.FORBIDDEN_PREFIX:
                self.reset_received = True
                self.command_log.append((now, "RESET"))
                self.command_count += 1
                log.error("emulator received RESET: now in firmware-update mode, no more replies")
                return b""
            spec = p.command_spec_for(frame)
            if spec is None or len(frame) != spec.length:
                log.info("emulator: unrecognised command %s", frame[:16].hex(" "))
                return self._error(3)
            if spec.crc:
                body = frame[:-2]
                if p.crc16_arc(body) != int.from_bytes(frame[-2:], "little"):
                    log.info("emulator: bad command CRC in %s", frame.hex(" "))
                    return self._error(1)
            else:
                body = frame
            name = spec.name.decode()
            self.command_log.append((now, name))
            self.command_count += 1
            if name in self.unavailable or (name in _FOCAL_POWER_COMMANDS and not self.focal_power_capable):
                return self._error(2)
            return self._dispatch(name, body[len(spec.name) :], now)

    def _dispatch(self, name: str, args: bytes, now: float) -> bytes:  # noqa: C901 - one branch per command
        reply = p.encode_reply
        if name == "Start":
            self._mode = Mode.CURRENT
            self._current_raw = 0
            self._setpoint_dpt = None
            self.optics.retarget(now, self.calibration.power_dpt(0.0), False)
            return p.HANDSHAKE_REPLY
        if name == "H":
            return reply(b"H", self.firmware_type.encode("ascii"))
        if name == "V":
            return reply(b"V", struct.pack(">BBHH", *self.firmware_version))
        if name == "X":
            return reply(b"X", self.serial_number if self.lens_eeprom else bytes(8))
        if name == "IR":
            return reply(b"IR", self.device_id)
        if name == "Aw":
            raw = p.unpack_i16(args)
            lo, hi = self._current_limits_raw
            raw = max(lo, min(hi, raw))
            if self._mode != Mode.CURRENT:
                log.info("emulator: Aw ignored in %s mode", self._mode.name)
                return b""
            self._current_raw = raw
            self.optics.retarget(now, self.calibration.power_dpt(self._raw_to_ma(raw)), False)
            return b""
        if name == "Ar":
            return reply(b"A", p.pack_i16(self._output_current_raw(now)))
        if name == "CrMA":
            return reply(b"CMA", p.pack_i16(p.round_half_away(self.max_current_ma * 100.0)))
        if name == "CrUA":
            return reply(b"CUA", p.pack_i16(self._current_limits_raw[1]))
        if name == "CrLA":
            return reply(b"CLA", p.pack_i16(self._current_limits_raw[0]))
        if name == "MwDA":
            if self._mode == Mode.FOCAL_POWER:
                self._current_raw = self._output_current_raw(now)
            self._mode = Mode.CURRENT
            self._setpoint_dpt = None
            self.optics.retarget(now, self.calibration.power_dpt(self._raw_to_ma(self._current_raw)), False)
            return reply(b"MDA")
        if name == "MwCA":
            lo, hi = self._focal_power_limits_raw(now)
            enc = self._encoding()
            start = self.calibration.power_dpt(self._raw_to_ma(self._current_raw))
            if self._mode == Mode.FOCAL_POWER and self._setpoint_dpt is not None:
                start = self._setpoint_dpt
            self._setpoint_dpt = min(max(start, p.focal_power_raw_to_dpt(lo, enc)), p.focal_power_raw_to_dpt(hi, enc))
            self._cannot_reach = False
            self._mode = Mode.FOCAL_POWER
            self.optics.retarget(now, self._setpoint_dpt, True)
            return reply(b"MCA", self._limits_payload(now))
        if name == "MMA":
            return reply(b"MMA", bytes([int(self._mode)]))
        if name == "PwTA":
            upper, lower = p.unpack_i16(args, 0) / 16.0, p.unpack_i16(args, 2) / 16.0
            self._temperature_limits_c = (min(lower, upper), max(lower, upper))
            return reply(b"PT", self._limits_payload(now))
        if name == "PwDA":
            if self._mode != Mode.FOCAL_POWER:
                log.info("emulator: PwDA ignored in %s mode", self._mode.name)
                return b""
            raw = p.unpack_i16(args, 0)
            lo, hi = self._focal_power_limits_raw(now)
            self._cannot_reach = not lo <= raw <= hi
            enc = self._encoding()
            self._setpoint_dpt = p.focal_power_raw_to_dpt(max(lo, min(hi, raw)), enc)
            self.optics.retarget(now, self._setpoint_dpt, True)
            return b""
        if name == "PrDA":
            enc = self._encoding()
            if self._mode == Mode.FOCAL_POWER and self._setpoint_dpt is not None:
                power = self._setpoint_dpt
            else:
                power = self.calibration.power_dpt(self._raw_to_ma(self._current_raw), self.temperature_at(now))
            raw = p.round_half_away((power + p.FOCAL_POWER_FIRMWARE_TYPES[enc]) * 200.0)
            return reply(b"PD", p.pack_i16(max(-0x8000, min(0x7FFF, raw))))
        if name == "TCA":
            if not self.temperature_sensor:
                raw = p.NO_TEMPERATURE_SENSOR_RAW
            else:
                raw = max(-0x8000, min(0x7FFF, p.round_half_away(self.temperature_at(now) * 16.0)))
                if raw == p.NO_TEMPERATURE_SENSOR_RAW:
                    raw -= 1
            return reply(b"TCA", p.pack_i16(raw))
        if name == "Sr":
            return reply(b"S", bytes([int(self._status_flags(now)), 0, 0, 0]))
        raise AssertionError(f"unhandled command {name}")  # pragma: no cover - COMMANDS is exhaustive

    # ------------------------------------------------------------------ byte stream

    @property
    def pending(self) -> bytes:
        """Bytes of an incomplete command held back by :meth:`feed`."""
        return self._stream.pending

    def discard_partial(self) -> bytes:
        """Drop an incomplete buffered command (the server calls this after an idle gap)."""
        with self._lock:
            return self._stream.discard()

    def feed(self, data: bytes) -> list[bytes]:
        """Take received bytes; answer every complete command in them.

        Commands are recognised by prefix and length. Bytes that cannot start a command
        are skipped up to the next plausible command start and answered with one ``E 3``.

        Returns:
            The non-empty replies, in order.
        """
        replies: list[bytes] = []
        with self._lock:
            for piece, chunk in self._stream.feed(data):
                if self.reset_received:
                    self._stream.discard()
                    break
                if piece is Piece.COMMAND:
                    answer = self.handle(chunk)
                    if answer:
                        replies.append(answer)
                else:
                    log.info("emulator: unrecognised bytes %s", chunk[:32].hex(" "))
                    replies.append(self._error(3))
            if self.reset_received:
                self._stream.discard()
        return replies
