"""Command encoders: one function per Lens Driver 4 command, each returning the whole frame.

There is no encoder for ``RESET``.
"""

from __future__ import annotations

from ...errors import LensRangeError
from .framing import HANDSHAKE, with_crc
from .units import CURRENT_RAW_LIMIT, pack_i16
from .units import current_ma_to_raw, focal_power_dpt_to_raw, temperature_c_to_raw  # noqa: F401 - the doctests use them

__all__ = [
    "encode_start",
    "encode_get_firmware_type",
    "encode_get_firmware_version",
    "encode_get_serial_number",
    "encode_get_device_id",
    "encode_set_current",
    "encode_get_current",
    "encode_get_max_current",
    "encode_get_upper_current_limit",
    "encode_get_lower_current_limit",
    "encode_current_mode",
    "encode_focal_power_mode",
    "encode_get_mode",
    "encode_set_temperature_limits",
    "encode_set_focal_power",
    "encode_get_focal_power",
    "encode_get_temperature",
    "encode_get_status",
]


def encode_start() -> bytes:
    """``Start``: the handshake (no CRC). The driver answers ``Ready\\r\\n`` and zeroes the current.

    Examples:
        >>> encode_start()
        b'Start'
    """
    return HANDSHAKE


def encode_get_firmware_type() -> bytes:
    """``H``: firmware type; reply ``H`` + one ASCII letter.

    Examples:
        >>> encode_get_firmware_type()[:1]
        b'H'
    """
    return with_crc(b"H")


def encode_get_firmware_version() -> bytes:
    """``V``: firmware version; reply ``V`` + major u8 + minor u8 + build u16 + revision u16."""
    return with_crc(b"V")


def encode_get_serial_number() -> bytes:
    """``X``: lens serial number; reply ``X`` + 8 bytes (zeros without lens EEPROM)."""
    return with_crc(b"X")


def encode_get_device_id() -> bytes:
    """``IR`` + 8 zero bytes: device id; reply ``IR`` + 8 bytes.

    Examples:
        >>> len(encode_get_device_id())
        12
    """
    return with_crc(b"IR" + bytes(8))


def encode_set_current(raw: int) -> bytes:
    """``Aw`` + i16: set the output current (no reply on success).

    Args:
        raw: DAC value from :func:`current_ma_to_raw`, -4095..4095.

    Raises:
        LensRangeError: ``|raw| > 4095``.

    Examples:
        >>> encode_set_current(0x04B2).hex(" ")
        '41 77 04 b2 26 93'
    """
    raw = int(raw)
    if abs(raw) > CURRENT_RAW_LIMIT:
        raise LensRangeError(f"raw current {raw} beyond ±{CURRENT_RAW_LIMIT}")
    return with_crc(b"Aw" + pack_i16(raw))


def encode_get_current() -> bytes:
    """``Ar`` + ``00 00``: read the current; reply ``A`` + i16 raw."""
    return with_crc(b"Ar\x00\x00")


def encode_get_max_current() -> bytes:
    """``CrMA`` + ``00 00``: maximum output current; reply ``CMA`` + i16 (mA × 100)."""
    return with_crc(b"CrMA\x00\x00")


def encode_get_upper_current_limit() -> bytes:
    """``CrUA`` + ``00 00``: upper software current limit; reply ``CUA`` + i16 (raw current)."""
    return with_crc(b"CrUA\x00\x00")


def encode_get_lower_current_limit() -> bytes:
    """``CrLA`` + ``00 00``: lower software current limit; reply ``CLA`` + i16 (raw current)."""
    return with_crc(b"CrLA\x00\x00")


def encode_current_mode() -> bytes:
    """``MwDA``: switch to DC current mode; reply ``MDA``."""
    return with_crc(b"MwDA")


def encode_focal_power_mode() -> bytes:
    """``MwCA``: switch to focal-power mode; reply ``MCA`` + status u8 + max i16 + min i16.

    Send :func:`encode_set_temperature_limits` first.
    """
    return with_crc(b"MwCA")


def encode_get_mode() -> bytes:
    """``MMA``: operating mode; reply ``MMA`` + mode u8 (see :class:`Mode`)."""
    return with_crc(b"MMA")


def encode_set_temperature_limits(upper_raw: int, lower_raw: int) -> bytes:
    """``PwTA`` + upper i16 + lower i16 (°C × 16); reply ``PT`` + status u8 + max i16 + min i16.

    Examples:
        >>> encode_set_temperature_limits(temperature_c_to_raw(40), temperature_c_to_raw(20))[:8]
        b'PwTA\\x02\\x80\\x01@'
    """
    return with_crc(b"PwTA" + pack_i16(upper_raw) + pack_i16(lower_raw))


def encode_set_focal_power(raw: int) -> bytes:
    """``PwDA`` + i16 + ``00 00``: set the focal power (no reply; acts only in focal-power mode).

    Examples:
        >>> encode_set_focal_power(focal_power_dpt_to_raw(3.0, "A")).hex(" ")
        '50 77 44 41 06 40 00 00 30 2c'
    """
    return with_crc(b"PwDA" + pack_i16(raw) + b"\x00\x00")


def encode_get_focal_power() -> bytes:
    """``PrDA`` + four zero bytes: read the focal power; reply ``PD`` + i16 raw."""
    return with_crc(b"PrDA" + bytes(4))


def encode_get_temperature() -> bytes:
    """``TCA``: lens temperature; reply ``TCA`` + i16 (× 0.0625 °C)."""
    return with_crc(b"TCA")


def encode_get_status() -> bytes:
    """``Sr``: status; reply ``S`` + 4 status bytes."""
    return with_crc(b"Sr")
