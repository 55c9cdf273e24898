"""An emulated Optotune Lens Driver 4 with an EL-10-30 lens, served on a pseudo-terminal.

Three layers:

* :class:`Emulator`, the device model. :meth:`Emulator.handle` answers one complete
  command frame with the reply bytes (byte-exact, CRCs included);
  :meth:`Emulator.feed` takes a raw byte stream, buffers partial commands (commands have
  no terminator: they are recognised by prefix and fixed length) and returns the replies.
  It keeps the state a bench needs: mode, current, focal-power set-point, temperature,
  limits, firmware type, and the *optical* focal power over time
  (:meth:`Emulator.focal_power_at`).
* :class:`Faults`, seeded fault injection on replies: bad CRC, dropped, late, garbage
  before the reply, and a disconnect after a number of commands.
* :class:`EmulatorServer`, which serves an :class:`Emulator` on a pty from a background
  thread; ``.port`` is the slave device path, usable with ``serial.Serial(path)`` or
  :meth:`tdfd.driver.OptotuneLens.open`.
* :class:`EmulatorSerial`, an in-process pyserial-like port wired straight to an
  :class:`Emulator` (no pty, no thread): ``OptotuneLens(EmulatorSerial(device))``.

Optical model (documented assumptions, not manufacturer data):

* Calibration (:class:`Calibration`): at the reference temperature (25 °C) the focal
  power is ``-1.5 dpt + current_mA × 5/290 dpt/mA`` (−1.5 dpt at 0 mA, +3.5 dpt at
  290 mA, as an EL-10-30-C); without compensation it drops 0.067 dpt/°C above 25 °C.
* Current mode: the optical power follows the current's calibrated power through the
  first-order filter, plus the (unfiltered) thermal drift.
* Focal-power mode: the driver compensates temperature, so the optical power follows the
  set-point through the filter. The reported limits are the powers reachable at every
  temperature between the user's temperature limits with currents inside the software
  current limits; type A clips them to its encodable −5…+15.475 dpt. A ``PwDA``
  set-point outside the limits is clipped and sets status bit 3.
* Settling: first order with time constant ``settling_time_s / ln(100)``: a step is
  within 1 % of its size ``settling_time_s`` (default 15 ms) after the command arrives.
  Times are read from the injectable ``clock`` (default :func:`time.monotonic`), so a
  simulated bench can run the lens on simulated time.
* ``Aw`` acts only in current mode and ``PwDA`` only in focal-power mode (otherwise they
  are ignored); ``Start`` zeroes the current and selects current mode. ``RESET`` puts
  the emulator in firmware-update mode: it stops answering (a test can check
  :attr:`Emulator.reset_received`).

Example:
    >>> from tdfd.driver import protocol as p
    >>> t = [0.0]
    >>> lens = Emulator(clock=lambda: t[0])
    >>> lens.handle(p.encode_start())
    b'Ready\\r\\n'
    >>> lens.handle(p.encode_set_current(p.current_ma_to_raw(100.0, 292.84)))
    b''
    >>> lens.focal_power_at(0.0), round(lens.target_focal_power_dpt, 4)
    (-1.5, 0.2237)
    >>> step = lens.target_focal_power_dpt - lens.focal_power_at(0.0)
    >>> round((lens.target_focal_power_dpt - lens.focal_power_at(0.015)) / step, 6)  # 1 % left after 15 ms
    0.01
"""

from __future__ import annotations

import bisect
import logging
import math
import os
import random
import select
import struct
import threading
import time
from collections import deque
from dataclasses import dataclass, field, fields
from typing import Callable

from ..errors import DriverError, InputError
from . import protocol as p
from .protocol import Mode, StatusFlags

__all__ = ["Calibration", "Emulator", "Faults", "EmulatorServer", "EmulatorSerial", "DEFAULT_SETTLING_TIME_S"]

log = logging.getLogger(__name__)

#: time for a focal-power step to settle within 1 %, seconds (EL-10-30: about 15 ms).
DEFAULT_SETTLING_TIME_S = 0.015


@dataclass(frozen=True)
class Calibration:
    """Linear focal power of the emulated lens versus current and temperature.

    ``power = offset_dpt + slope_dpt_per_ma × current_mA
    + temperature_coefficient_dpt_per_c × (temperature_C − reference_temperature_c)``.

    Examples:
        >>> c = Calibration()
        >>> c.power_dpt(0.0), round(c.power_dpt(290.0), 6)
        (-1.5, 3.5)
        >>> round(c.current_ma(c.power_dpt(123.0, 35.0), 35.0), 9)
        123.0
    """

    offset_dpt: float = -1.5
    slope_dpt_per_ma: float = 5.0 / 290.0
    temperature_coefficient_dpt_per_c: float = -0.067
    reference_temperature_c: float = 25.0

    def drift_dpt(self, temperature_c: float) -> float:
        """Power change from the reference temperature at fixed current, dpt."""
        return self.temperature_coefficient_dpt_per_c * (temperature_c - self.reference_temperature_c)

    def power_dpt(self, current_ma: float, temperature_c: float | None = None) -> float:
        """Focal power at ``current_ma`` and ``temperature_c`` (default: reference), dpt."""
        t = self.reference_temperature_c if temperature_c is None else temperature_c
        return self.offset_dpt + self.slope_dpt_per_ma * current_ma + self.drift_dpt(t)

    def current_ma(self, power_dpt: float, temperature_c: float | None = None) -> float:
        """Current giving ``power_dpt`` at ``temperature_c`` (default: reference), mA."""
        t = self.reference_temperature_c if temperature_c is None else temperature_c
        return (power_dpt - self.offset_dpt - self.drift_dpt(t)) / self.slope_dpt_per_ma


# the emulator also recognises RESET (to refuse it loudly), which protocol.COMMANDS omits
_RESET_SPEC = p.CommandSpec(p.FORBIDDEN_PREFIX, 0, None, crc=False)
_PARSE_TABLE: tuple[p.CommandSpec, ...] = (*p.COMMANDS.values(), _RESET_SPEC)
_FOCAL_POWER_COMMANDS = frozenset({"MwCA", "PwTA", "PwDA", "PrDA"})
_TYPE_A_RANGE_RAW = (0, 4095)  # −5 … +15.475 dpt
_HISTORY_MAX = 20000


def _could_start_command(buf: bytes | bytearray, i: int) -> bool:
    rest = buf[i : i + 5]
    return any(spec.name[: len(rest)] == rest[: len(spec.name)] for spec in _PARSE_TABLE)


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
        self.settling_time_s = float(settling_time_s)
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
        self._buf = bytearray()
        #: (time, command name) of every well-formed command received, most recent last.
        self.command_log: deque[tuple[float, str]] = deque(maxlen=10000)
        self.command_count = 0
        now = self.clock()
        self._temperature = (now, float(temperature_c), float(temperature_c), 0.0)  # t0, T0, target, tau
        target = self.calibration.power_dpt(0.0)
        self._seg_t: list[float] = [now]
        self._seg: list[tuple[float, float, float, bool]] = [(now, target, target, False)]  # t0, p0, target, compensated

    # ------------------------------------------------------------------ conversions

    def _ma_to_raw(self, current_ma: float) -> int:
        raw = p.round_half_away(current_ma * p.CURRENT_RAW_LIMIT / self.max_current_ma)
        return max(-p.CURRENT_RAW_LIMIT, min(p.CURRENT_RAW_LIMIT, raw))

    def _raw_to_ma(self, raw: int) -> float:
        return p.current_raw_to_ma(raw, self.max_current_ma)

    @property
    def time_constant_s(self) -> float:
        """First-order time constant of the focal power, seconds (settling_time_s / ln 100)."""
        return self.settling_time_s / math.log(100.0)

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
            now = self.clock()
            _, _, target, compensated = self._seg[-1]
            return target + (0.0 if compensated else self.calibration.drift_dpt(self.temperature_at(now)))

    @property
    def focal_power_dpt(self) -> float:
        """The optical focal power now (by :attr:`clock`), dpt."""
        return self.focal_power_at(self.clock())

    def focal_power_at(self, t: float) -> float:
        """The optical focal power at time ``t`` on the emulator's clock, dpt.

        Exact for the first-order model: past times use the recorded set-point history
        (the last 20000 changes), times after the last command extrapolate the settling.
        Before the first record it is the initial power.
        """
        with self._lock:
            k = bisect.bisect_right(self._seg_t, t) - 1
            if k < 0:
                t0, p0, _, compensated = self._seg[0]
                filtered = p0
            else:
                t0, p0, target, compensated = self._seg[k]
                filtered = self._settle(p0, target, t - t0)
            return filtered + (0.0 if compensated else self.calibration.drift_dpt(self.temperature_at(t)))

    def _settle(self, p0: float, target: float, dt: float) -> float:
        tau = self.time_constant_s
        if tau <= 0.0:
            return target
        return target + (p0 - target) * math.exp(-max(dt, 0.0) / tau)

    def _retarget(self, t: float, target: float, compensated: bool) -> None:
        last_t = self._seg_t[-1]
        if t < last_t:
            log.warning("emulator clock went backwards (%.6f < %.6f): restarting the focal-power history", t, last_t)
            t0, p0, old_target, _ = self._seg[-1]
            now_p = self._settle(p0, old_target, 0.0)
            self._seg_t, self._seg = [t], [(t, now_p, now_p, compensated)]
            last_t = t
        k = len(self._seg) - 1
        t0, p0, old_target, _ = self._seg[k]
        p_now = self._settle(p0, old_target, t - t0)
        self._seg_t.append(t)
        self._seg.append((t, p_now, target, compensated))
        if len(self._seg) > _HISTORY_MAX:
            del self._seg_t[: _HISTORY_MAX // 2]
            del self._seg[: _HISTORY_MAX // 2]

    def temperature_at(self, t: float) -> float:
        """Lens temperature at time ``t``, °C (first-order approach to the last target)."""
        with self._lock:
            t0, temp0, target, tau = self._temperature
            if t < t0:
                return temp0
            if tau <= 0.0:
                return target
            return target + (temp0 - target) * math.exp(-(t - t0) / tau)

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
            now = self.clock()
            self._temperature = (now, self.temperature_at(now), float(temperature_c), float(time_constant_s))

    @property
    def commands(self) -> list[str]:
        """Names of the well-formed commands received so far (most recent last)."""
        with self._lock:
            return [name for _, name in self.command_log]

    # ------------------------------------------------------------------ derived quantities

    def _encoding(self) -> str:
        return self.firmware_type if self.focal_power_capable else "B"

    def _focal_power_limits_raw(self, now: float) -> tuple[int, int]:
        lo_ma, hi_ma = self.current_limits_ma
        if self._temperature_limits_c is not None:
            t_lo, t_hi = self._temperature_limits_c
        else:
            t_lo = t_hi = self.temperature_at(now)
        c = self.calibration
        enc = self._encoding()
        lo = math.ceil((c.power_dpt(lo_ma, t_lo) + p.FOCAL_POWER_FIRMWARE_TYPES[enc]) * 200.0 - 1e-9)
        hi = math.floor((c.power_dpt(hi_ma, t_hi) + p.FOCAL_POWER_FIRMWARE_TYPES[enc]) * 200.0 + 1e-9)
        if enc == "A":
            lo, hi = max(lo, _TYPE_A_RANGE_RAW[0]), min(hi, _TYPE_A_RANGE_RAW[1])
        lo, hi = max(lo, -0x8000), min(hi, 0x7FFF)
        return (lo, max(lo, hi))

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
            self._retarget(now, self.calibration.power_dpt(0.0), False)
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
            self._retarget(now, self.calibration.power_dpt(self._raw_to_ma(raw)), False)
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
            self._retarget(now, self.calibration.power_dpt(self._raw_to_ma(self._current_raw)), False)
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
            self._retarget(now, self._setpoint_dpt, True)
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
            self._retarget(now, self._setpoint_dpt, True)
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
        return bytes(self._buf)

    def discard_partial(self) -> bytes:
        """Drop an incomplete buffered command (the server calls this after an idle gap)."""
        with self._lock:
            dropped = bytes(self._buf)
            self._buf.clear()
            if dropped:
                log.info("emulator: discarded incomplete command %s", dropped.hex(" "))
            return dropped

    def feed(self, data: bytes) -> list[bytes]:
        """Take received bytes; answer every complete command in them.

        Commands are recognised by prefix and length. Bytes that cannot start a command
        are skipped up to the next plausible command start and answered with one ``E 3``.

        Returns:
            The non-empty replies, in order.
        """
        replies: list[bytes] = []
        with self._lock:
            self._buf += bytes(data)
            while self._buf:
                if self.reset_received:
                    self._buf.clear()
                    break
                buf = self._buf
                matched = None
                partial = False
                for spec in _PARSE_TABLE:
                    name = spec.name
                    if len(buf) < len(name):
                        if name[: len(buf)] == buf:
                            partial = True
                    elif buf[: len(name)] == name:
                        matched = spec
                        break
                if matched is not None:
                    if len(buf) < matched.length:
                        break
                    frame = bytes(buf[: matched.length])
                    del buf[: matched.length]
                    answer = self.handle(frame)
                    if answer:
                        replies.append(answer)
                    continue
                if partial:
                    break
                j = 1
                while j < len(buf) and not _could_start_command(buf, j):
                    j += 1
                log.info("emulator: unrecognised bytes %s", bytes(buf[:j][:32]).hex(" "))
                del buf[:j]
                replies.append(self._error(3))
        return replies


@dataclass
class Faults:
    """Seeded fault injection on the emulator's replies (and the port itself).

    Probabilities are per reply and independent; a probability of 1 always fires. Set
    ``limit`` to stop after that many injected faults (e.g. ``Faults(drop=1, limit=1)``
    drops exactly the next reply). Replace or mutate the server's faults at run time.

    Attributes:
        bad_crc: probability of corrupting a reply's CRC (a ``Ready`` reply: its text).
        drop: probability of not sending a reply.
        late: probability of delaying a reply (and those queued after it) by ``late_s``.
        garbage: probability of sending 1…``garbage_max_bytes`` random bytes before a reply.
        late_s: delay of a late reply, seconds.
        garbage_max_bytes: most garbage bytes at once.
        disconnect_after: close the pty after this many further commands (0: at the
            next opportunity); ``None``: never.
        limit: most faults to inject (disconnect excluded); ``None``: no limit.
        seed: seed of :attr:`rng`.
        rng: the random generator (``random.Random(seed)``).
        injected: faults injected so far.
    """

    bad_crc: float = 0.0
    drop: float = 0.0
    late: float = 0.0
    garbage: float = 0.0
    late_s: float = 0.3
    garbage_max_bytes: int = 8
    disconnect_after: int | None = None
    limit: int | None = None
    seed: int = 0
    rng: random.Random = field(init=False, repr=False, compare=False)
    injected: int = field(default=0, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        for name in ("bad_crc", "drop", "late", "garbage"):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise InputError(f"fault probability {name} must be in [0, 1], got {value}")
        if self.late_s < 0 or self.garbage_max_bytes < 1:
            raise InputError("late_s must be >= 0 and garbage_max_bytes >= 1")
        self.rng = random.Random(self.seed)

    @classmethod
    def parse(cls, specs: list[str] | tuple[str, ...], seed: int = 0) -> Faults:
        """Build from ``NAME=VALUE`` strings (the CLI's ``--fault``).

        Examples:
            >>> Faults.parse(["drop=0.5", "late_s=0.1", "disconnect_after=3"])
            Faults(bad_crc=0.0, drop=0.5, late=0.0, garbage=0.0, late_s=0.1, garbage_max_bytes=8, disconnect_after=3, limit=None, seed=0)
        """
        kinds = {f.name: f.type for f in fields(cls) if f.init}
        values: dict[str, object] = {"seed": seed}
        for spec in specs:
            name, sep, value = spec.partition("=")
            name = name.strip().replace("-", "_")
            if not sep or name not in kinds:
                raise InputError(f"bad fault {spec!r}: use NAME=VALUE with NAME one of {', '.join(kinds)}")
            kind = str(kinds[name])
            if value.strip().lower() in ("none", ""):
                values[name] = None
            elif "int" in kind:
                values[name] = int(value)
            else:
                values[name] = float(value)
        return cls(**values)  # type: ignore[arg-type]

    def _roll(self, probability: float) -> bool:
        if probability <= 0.0 or (self.limit is not None and self.injected >= self.limit):
            return False
        hit = probability >= 1.0 or self.rng.random() < probability
        if hit:
            self.injected += 1
        return hit

    def apply(self, reply: bytes) -> tuple[bytes | None, float]:
        """Decide the fate of one reply.

        Returns:
            (bytes to send or ``None`` if dropped, delay in seconds).
        """
        if self._roll(self.drop):
            log.info("fault: dropping reply %s", reply.hex(" "))
            return None, 0.0
        out = bytes(reply)
        if self._roll(self.bad_crc):
            corrupted = bytearray(out)
            index = len(out) - 4 if out not in (p.HANDSHAKE_REPLY, p.BARE_ERROR_REPLY) else 0
            corrupted[max(index, 0)] ^= 0x5A
            out = bytes(corrupted)
            log.info("fault: bad CRC %s", out.hex(" "))
        delay = 0.0
        if self._roll(self.late):
            delay = self.late_s
            log.info("fault: reply late by %.3f s", delay)
        if self._roll(self.garbage):
            n = self.rng.randint(1, self.garbage_max_bytes)
            junk = bytes(self.rng.randrange(256) for _ in range(n))
            out = junk + out
            log.info("fault: %d garbage byte(s) before the reply", n)
        return out, delay


class EmulatorServer:
    """Serve an :class:`Emulator` on a pseudo-terminal from a background thread.

    Example::

        with EmulatorServer() as srv:
            lens = OptotuneLens.open(srv.port)
            lens.set_current_ma(100.0)
            srv.device.focal_power_at(srv.device.clock() + 0.02)

    Args:
        device: the model to serve (default: a new :class:`Emulator` from ``device_kwargs``).
        faults: fault injection (default: none). Replace at run time via :attr:`faults`.
        partial_timeout_s: an incomplete command older than this is discarded, seconds.
        **device_kwargs: passed to :class:`Emulator` when ``device`` is not given.

    Attributes:
        device: the :class:`Emulator`.
        port: the pty slave path (``/dev/pts/N``) once started, else ``None``.
    """

    def __init__(
        self,
        device: Emulator | None = None,
        *,
        faults: Faults | None = None,
        partial_timeout_s: float = 0.25,
        **device_kwargs: object,
    ) -> None:
        if device is not None and device_kwargs:
            raise TypeError("pass either device or Emulator keyword arguments, not both")
        self.device = device if device is not None else Emulator(**device_kwargs)  # type: ignore[arg-type]
        self._faults = faults if faults is not None else Faults()
        self.partial_timeout_s = float(partial_timeout_s)
        self.port: str | None = None
        self._lock = threading.Lock()
        self._master: int | None = None
        self._slave: int | None = None
        self._wake: tuple[int, int] | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._disconnect_requested = threading.Event()
        self._disconnected = threading.Event()
        self._commands_since_faults = 0

    # ------------------------------------------------------------------ control

    @property
    def faults(self) -> Faults:
        """The active :class:`Faults`; assigning restarts the ``disconnect_after`` count."""
        return self._faults

    @faults.setter
    def faults(self, faults: Faults) -> None:
        with self._lock:
            self._faults = faults
            self._commands_since_faults = 0
        self._poke()

    @property
    def disconnected(self) -> bool:
        """True once the pty was closed by a disconnect."""
        return self._disconnected.is_set()

    @property
    def running(self) -> bool:
        """True while the serving thread runs."""
        return self._thread is not None and self._thread.is_alive()

    def start(self) -> EmulatorServer:
        """Open the pty (raw mode on both ends) and start serving. Returns ``self``."""
        import tty

        if self._thread is not None:
            raise DriverError("EmulatorServer already started")
        master, slave = os.openpty()
        tty.setraw(master)
        tty.setraw(slave)
        os.set_blocking(master, False)
        self._master, self._slave = master, slave
        self.port = os.ttyname(slave)
        self._wake = os.pipe()
        self._thread = threading.Thread(target=self._serve, name=f"lens-emulator {self.port}", daemon=True)
        self._thread.start()
        log.info("lens emulator serving on %s", self.port)
        return self

    def _poke(self) -> None:
        if self._wake is not None:
            try:
                os.write(self._wake[1], b"x")
            except OSError:
                pass

    def disconnect(self) -> None:
        """Close the pty now: the client sees its port vanish."""
        self._disconnect_requested.set()
        self._poke()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._disconnected.wait(2.0)

    def stop(self) -> None:
        """Stop serving and close everything. Idempotent."""
        self._stop.set()
        self._poke()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(5.0)
        self._close_pty()
        if self._wake is not None:
            for fd in self._wake:
                try:
                    os.close(fd)
                except OSError:
                    pass
            self._wake = None

    def wait(self, timeout: float | None = None) -> bool:
        """Block until the serving thread ends (stop or disconnect); True if it did."""
        if self._thread is None:
            return True
        self._thread.join(timeout)
        return not self._thread.is_alive()

    def __enter__(self) -> EmulatorServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # ------------------------------------------------------------------ the thread

    def _close_pty(self) -> None:
        with self._lock:
            for attr in ("_master", "_slave"):
                fd = getattr(self, attr)
                if fd is not None:
                    try:
                        os.close(fd)
                    except OSError:
                        pass
                    setattr(self, attr, None)

    def _write(self, data: bytes) -> None:
        master = self._master
        if master is None:
            return
        view = memoryview(data)
        while view:
            try:
                n = os.write(master, view)
            except BlockingIOError:
                log.warning("lens emulator: pty full (client not reading), dropping %d byte(s)", len(view))
                return
            except OSError as exc:
                log.warning("lens emulator: write failed: %s", exc)
                return
            view = view[n:]

    def _wait_delivered(self, timeout_s: float = 0.5) -> None:
        """Give the client up to ``timeout_s`` to read what was written (the pty drops it on close)."""
        try:
            import fcntl
            import termios

            deadline = time.monotonic() + timeout_s
            quiet_since = None
            while self._slave is not None and time.monotonic() < deadline:
                waiting = struct.unpack("i", fcntl.ioctl(self._slave, termios.FIONREAD, b"\0\0\0\0"))[0]
                now = time.monotonic()
                if waiting:
                    quiet_since = None
                elif quiet_since is None:
                    quiet_since = now
                elif now - quiet_since >= 0.02:  # the pty moves bytes asynchronously: want a quiet spell
                    return
                time.sleep(0.002)
        except (ImportError, OSError):  # pragma: no cover - non-Linux ptys
            pass

    def _do_disconnect(self) -> None:
        log.warning("lens emulator: disconnecting %s", self.port)
        self._close_pty()
        self._disconnected.set()

    def _serve(self) -> None:
        out: deque[tuple[float, bytes]] = deque()
        last_rx = 0.0
        assert self._master is not None and self._wake is not None
        master, wake = self._master, self._wake[0]
        try:
            while not self._stop.is_set():
                if self._disconnect_requested.is_set() or (
                    self._faults.disconnect_after is not None
                    and self._commands_since_faults >= self._faults.disconnect_after
                ):
                    while out and out[0][0] <= time.monotonic():
                        self._write(out.popleft()[1])
                    self._wait_delivered()
                    self._do_disconnect()
                    return
                now = time.monotonic()
                while out and out[0][0] <= now:
                    self._write(out.popleft()[1])
                timeout = 0.05
                if out:
                    timeout = min(timeout, max(0.0, out[0][0] - now))
                if self.device.pending:
                    timeout = min(timeout, max(0.0, last_rx + self.partial_timeout_s - now))
                readable, _, _ = select.select([master, wake], [], [], timeout)
                if wake in readable:
                    os.read(wake, 512)
                if master in readable:
                    try:
                        data = os.read(master, 4096)
                    except BlockingIOError:
                        data = b""
                    except OSError as exc:
                        log.warning("lens emulator: read failed: %s", exc)
                        data = b""
                    if data:
                        last_rx = time.monotonic()
                        before = self.device.command_count
                        replies = self.device.feed(data)
                        now = time.monotonic()
                        with self._lock:
                            faults = self._faults
                            self._commands_since_faults += self.device.command_count - before
                            for reply in replies:
                                sent, delay = faults.apply(reply)
                                if sent is None:
                                    continue
                                due = now + delay
                                if out:
                                    due = max(due, out[-1][0])
                                out.append((due, sent))
                elif self.device.pending and time.monotonic() - last_rx >= self.partial_timeout_s:
                    self.device.discard_partial()
        except Exception:  # pragma: no cover - keep a bench informative if the model breaks
            log.exception("lens emulator thread failed")
            self._do_disconnect()


class EmulatorSerial:
    """An in-process, pyserial-like port wired to an :class:`Emulator` (no pty, no thread).

    Replies become readable as soon as the command is written (late ones after
    ``late_s`` of wall-clock time); :class:`Faults` apply as on the pty. After an injected
    disconnect every call raises ``serial.SerialException`` like a vanished port.

    Args:
        device: the model (default: a new :class:`Emulator`).
        faults: fault injection (default: none).
        timeout: read timeout, seconds (as pyserial's ``timeout``).

    Example:
        >>> from tdfd.driver import OptotuneLens
        >>> lens = OptotuneLens(EmulatorSerial()).connect()
        >>> lens.set_current_ma(50.0); round(lens.get_current_ma(), 1)
        50.0
    """

    def __init__(self, device: Emulator | None = None, *, faults: Faults | None = None, timeout: float | None = 0.5) -> None:
        self.device = device if device is not None else Emulator()
        self.timeout = timeout
        self.port = "emulator://"
        self.is_open = True
        self._out: deque[tuple[float, bytes]] = deque()
        self._rx = bytearray()
        self._vanished = False
        self.faults = faults if faults is not None else Faults()

    @property
    def faults(self) -> Faults:
        """The active :class:`Faults`; assigning restarts the ``disconnect_after`` count."""
        return self._faults

    @faults.setter
    def faults(self, faults: Faults) -> None:
        self._faults = faults
        self._commands = 0

    def _due_to_vanish(self) -> bool:
        after = self._faults.disconnect_after
        return after is not None and self._commands >= after and not self._rx and not self._out

    def _check(self) -> None:
        import serial

        if not self._vanished and self._due_to_vanish():
            self._vanished = True
            log.warning("emulator port: disconnecting (injected fault)")
        if self._vanished:
            raise serial.SerialException("device disconnected (injected fault)")
        if not self.is_open:
            raise serial.PortNotOpenError()

    def _collect(self) -> None:
        now = time.monotonic()
        while self._out and self._out[0][0] <= now:
            self._rx += self._out.popleft()[1]

    @property
    def in_waiting(self) -> int:
        """Bytes readable now."""
        self._check()
        self._collect()
        return len(self._rx)

    def write(self, data: bytes) -> int:
        """Feed bytes to the device; queue its (faulted) replies."""
        self._check()
        before = self.device.command_count
        replies = self.device.feed(bytes(data))
        self._commands += self.device.command_count - before
        now = time.monotonic()
        for reply in replies:
            sent, delay = self._faults.apply(reply)
            if sent is not None:
                due = max(now + delay, self._out[-1][0] if self._out else 0.0)
                self._out.append((due, sent))
        return len(data)

    def read(self, size: int = 1) -> bytes:
        """Up to ``size`` bytes, waiting at most :attr:`timeout` for late ones."""
        self._check()
        deadline = time.monotonic() + (self.timeout if self.timeout is not None else 3600.0)
        self._collect()
        while len(self._rx) < size and self._out:
            wait = min(self._out[0][0], deadline) - time.monotonic()
            if wait <= 0 and time.monotonic() >= deadline:
                break
            time.sleep(max(wait, 0.0))
            self._collect()
        out = bytes(self._rx[:size])
        del self._rx[:size]
        return out

    def reset_input_buffer(self) -> None:
        """Discard readable bytes."""
        self._check()
        self._collect()
        self._rx.clear()

    def flush(self) -> None:
        """Nothing to flush."""
        self._check()

    def close(self) -> None:
        """Close (idempotent)."""
        self.is_open = False
