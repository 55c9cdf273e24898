"""Numbers on the wire: big-endian signed 16-bit fields and the unit conversions.

Current (raw = mA × 4095 / max_current_mA), the maximum-current register (mA × 100),
focal power (type A: (dpt + 5) × 200; types B/C/E: dpt × 200) and temperature (°C × 16,
4095 meaning no sensor). Nothing is clamped silently: out-of-range values raise
:class:`~tdfd.errors.LensRangeError`.
"""

from __future__ import annotations

import math
import struct

from ...errors import LensRangeError, UnsupportedFirmwareError

__all__ = [
    "pack_i16",
    "unpack_i16",
    "round_half_away",
    "current_ma_to_raw",
    "current_raw_to_ma",
    "max_current_raw_to_ma",
    "focal_power_dpt_to_raw",
    "focal_power_raw_to_dpt",
    "temperature_c_to_raw",
    "temperature_raw_to_c",
    "NO_TEMPERATURE_SENSOR_RAW",
    "CURRENT_RAW_LIMIT",
    "FOCAL_POWER_FIRMWARE_TYPES",
]

#: the largest current magnitude the 12-bit DAC accepts, in raw units.
CURRENT_RAW_LIMIT = 4095
#: temperature raw value that means "no sensor".
NO_TEMPERATURE_SENSOR_RAW = 4095
#: firmware types whose focal-power encoding the facts document: A with an offset of 5 dpt,
#: B/C/E without.
FOCAL_POWER_FIRMWARE_TYPES = {"A": 5.0, "B": 0.0, "C": 0.0, "E": 0.0}


def pack_i16(value: int) -> bytes:
    """Big-endian signed 16-bit.

    Raises:
        LensRangeError: outside -32768..32767.

    Examples:
        >>> pack_i16(-2).hex(" ")
        'ff fe'
    """
    value = int(value)
    if not -0x8000 <= value <= 0x7FFF:
        raise LensRangeError(f"{value} does not fit a signed 16-bit field")
    return struct.pack(">h", value)


def unpack_i16(data: bytes, offset: int = 0) -> int:
    """Big-endian signed 16-bit at ``offset``.

    Examples:
        >>> unpack_i16(b"\\xff\\xfe"), unpack_i16(b"\\x05\\x7a")
        (-2, 1402)
    """
    return struct.unpack_from(">h", data, offset)[0]


def round_half_away(x: float) -> int:
    """Round to the nearest integer, halves away from zero (not banker's rounding).

    Examples:
        >>> round_half_away(2.5), round_half_away(-2.5), round_half_away(1402.397)
        (3, -3, 1402)
    """
    return int(math.copysign(math.floor(abs(x) + 0.5), x))


def _finite(value: float, what: str) -> float:
    value = float(value)
    if not math.isfinite(value):
        raise LensRangeError(f"{what} must be finite, got {value}")
    return value


def current_ma_to_raw(current_ma: float, max_current_ma: float) -> int:
    """Current in mA to the raw DAC value: ``round(mA × 4095 / max_current_mA)``.

    Nothing is clamped silently: a current whose raw value exceeds ±4095 is an error.

    Args:
        current_ma: output current, mA (negative currents are allowed).
        max_current_ma: the driver's maximum output current, mA (``CrMA``).

    Raises:
        LensRangeError: non-finite input, non-positive maximum, or ``|raw| > 4095``.

    Examples:
        >>> current_ma_to_raw(100.0, 292.0), current_ma_to_raw(100.0, 292.84)
        (1402, 1398)
        >>> current_ma_to_raw(-100.0, 292.84)
        -1398
    """
    current_ma = _finite(current_ma, "current")
    max_current_ma = _finite(max_current_ma, "maximum current")
    if max_current_ma <= 0:
        raise LensRangeError(f"maximum current must be positive, got {max_current_ma} mA")
    raw = round_half_away(current_ma * CURRENT_RAW_LIMIT / max_current_ma)
    if abs(raw) > CURRENT_RAW_LIMIT:
        raise LensRangeError(
            f"current {current_ma} mA is outside ±{max_current_ma} mA (raw {raw} beyond ±{CURRENT_RAW_LIMIT})"
        )
    return raw


def current_raw_to_ma(raw: int, max_current_ma: float) -> float:
    """Raw DAC value to mA (inverse of :func:`current_ma_to_raw`).

    Examples:
        >>> round(current_raw_to_ma(4095, 292.84), 2)
        292.84
    """
    return int(raw) * float(max_current_ma) / CURRENT_RAW_LIMIT


def max_current_raw_to_ma(raw: int) -> float:
    """The maximum-current register (``CMA`` reply) in mA: value / 100.

    Examples:
        >>> max_current_raw_to_ma(29284)
        292.84
    """
    return int(raw) / 100.0


def _focal_offset(firmware_type: str) -> float:
    try:
        return FOCAL_POWER_FIRMWARE_TYPES[firmware_type]
    except KeyError:
        raise UnsupportedFirmwareError(
            f"focal-power encoding of firmware type {firmware_type!r} is not documented (known: A, B, C, E)"
        ) from None


def focal_power_dpt_to_raw(power_dpt: float, firmware_type: str) -> int:
    """Focal power to its raw encoding: ``(dpt + 5) × 200`` for type A, ``dpt × 200`` for B/C/E.

    Args:
        power_dpt: focal power, dioptres.
        firmware_type: ``H`` reply letter.

    Raises:
        LensRangeError: non-finite input or a raw value beyond 16 bits.
        UnsupportedFirmwareError: a firmware type without documented encoding.

    Examples:
        >>> focal_power_dpt_to_raw(3.0, "A"), focal_power_dpt_to_raw(3.0, "B")
        (1600, 600)
    """
    power_dpt = _finite(power_dpt, "focal power")
    raw = round_half_away((power_dpt + _focal_offset(firmware_type)) * 200.0)
    pack_i16(raw)  # range check
    return raw


def focal_power_raw_to_dpt(raw: int, firmware_type: str) -> float:
    """Raw focal power (``PD``/``MCA``/``PT`` replies) to dioptres.

    Examples:
        >>> focal_power_raw_to_dpt(1600, "A"), focal_power_raw_to_dpt(600, "C")
        (3.0, 3.0)
    """
    return int(raw) / 200.0 - _focal_offset(firmware_type)


def temperature_c_to_raw(temperature_c: float) -> int:
    """Temperature limit in °C to its raw encoding (°C × 16).

    Examples:
        >>> temperature_c_to_raw(20.0), temperature_c_to_raw(-10.5)
        (320, -168)
    """
    raw = round_half_away(_finite(temperature_c, "temperature") * 16.0)
    pack_i16(raw)
    return raw


def temperature_raw_to_c(raw: int) -> float | None:
    """Raw temperature (``TCA`` reply) to °C: raw × 0.0625; ``None`` for 4095 (no sensor).

    Examples:
        >>> temperature_raw_to_c(400), temperature_raw_to_c(4095) is None
        (25.0, True)
    """
    raw = int(raw)
    if raw == NO_TEMPERATURE_SENSOR_RAW:
        return None
    return raw * 0.0625
