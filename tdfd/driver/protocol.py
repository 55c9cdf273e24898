"""The Optotune Lens Driver 4 serial protocol, sans I/O.

Pure functions and a feed-based decoder; nothing here touches a port. The facts this
module encodes (see ``shared/optotune-lens-driver-4.md``):

* Every command except the ``Start`` handshake carries a CRC-16/ARC, low byte first.
  Commands have no terminator.
* Every reply is ``prefix + payload + CRC (low byte first) + CR LF``, except the handshake
  reply ``Ready\\r\\n`` and the bare error reply ``N\\r\\n`` which carry no CRC.
* Multi-byte numbers are big-endian and signed 16-bit unless stated.
* Replies are binary: a payload or CRC byte can be ``0x0A``, so frames are found by their
  known prefix and fixed length, never by splitting on newlines.

``RESET`` (firmware-update mode) has no builder and :func:`with_crc` refuses it.

Examples:
    >>> hex(crc16_arc(b"123456789"))
    '0xbb3d'
    >>> encode_set_current(current_ma_to_raw(100.0, 292.0)).hex(" ")
    '41 77 05 7a 26 95'
    >>> decoder = FrameDecoder()
    >>> decoder.feed(b"\\x00junk" + bytes.fromhex("41 05 7a") + crc16_arc(bytes.fromhex("41 05 7a")).to_bytes(2, "little") + b"\\r\\n")
    [Frame(prefix=b'A', data=b'\\x05z')]
"""

from __future__ import annotations

import enum
import math
import struct
from collections import deque
from dataclasses import dataclass

from ..errors import (
    ChecksumError,
    DeviceErrorReply,
    ForbiddenCommandError,
    LensRangeError,
    ProtocolError,
    UnsupportedFirmwareError,
)

__all__ = [
    # checksum and framing
    "crc16_arc",
    "with_crc",
    "FORBIDDEN_PREFIX",
    "CommandSpec",
    "COMMANDS",
    "REPLY_DATA_LENGTHS",
    "HANDSHAKE",
    "HANDSHAKE_REPLY",
    "BARE_ERROR_REPLY",
    "reply_prefix_for",
    "reply_length",
    "command_spec_for",
    # numbers
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
    # command builders
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
    # replies
    "Frame",
    "ErrorFrame",
    "Mode",
    "StatusFlags",
    "Status",
    "FirmwareVersion",
    "FocalPowerLimits",
    "encode_reply",
    "encode_error_reply",
    "decode_frame",
    "FrameDecoder",
    "parse_firmware_version",
    "parse_focal_power_limits",
    "parse_status",
]

# --------------------------------------------------------------------------- checksum


def _make_crc_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
        table.append(crc)
    return tuple(table)


_CRC_TABLE = _make_crc_table()


def crc16_arc(data: bytes) -> int:
    """CRC-16/ARC of ``data``: reflected polynomial 0xA001, initial value 0, no final XOR.

    Args:
        data: the bytes to check.

    Returns:
        The checksum, 0 to 0xFFFF. The driver sends it low byte first.

    Examples:
        >>> hex(crc16_arc(b"123456789"))
        '0xbb3d'
        >>> hex(crc16_arc(b"Start"))
        '0xa5ea'
        >>> crc16_arc(b"")
        0
    """
    crc = 0
    for byte in bytes(data):
        crc = (crc >> 8) ^ _CRC_TABLE[(crc ^ byte) & 0xFF]
    return crc


#: no frame may start with this: ``RESET`` puts the driver into firmware-update mode.
FORBIDDEN_PREFIX = b"RESET"


def _refuse_forbidden(payload: bytes) -> None:
    if bytes(payload[: len(FORBIDDEN_PREFIX)]).upper() == FORBIDDEN_PREFIX:
        raise ForbiddenCommandError("refusing to send RESET: it puts the Lens Driver 4 into firmware-update mode")


def with_crc(payload: bytes) -> bytes:
    """Append the CRC-16/ARC of ``payload``, low byte first.

    Args:
        payload: command (or reply) bytes.

    Returns:
        ``payload`` followed by its two CRC bytes.

    Raises:
        ForbiddenCommandError: for a payload starting with ``RESET``.

    Examples:
        >>> with_crc(bytes.fromhex("41 77 04 B2")).hex(" ")
        '41 77 04 b2 26 93'
        >>> with_crc(b"RESET")
        Traceback (most recent call last):
        ...
        tdfd.errors.ForbiddenCommandError: refusing to send RESET: it puts the Lens Driver 4 into firmware-update mode
    """
    payload = bytes(payload)
    _refuse_forbidden(payload)
    return payload + crc16_arc(payload).to_bytes(2, "little")


# --------------------------------------------------------------------------- command table


@dataclass(frozen=True)
class CommandSpec:
    """The shape of one command.

    Attributes:
        name: the command prefix, e.g. ``b"Aw"``.
        arg_length: bytes of arguments after the prefix (before the CRC).
        reply_prefix: prefix of the reply payload, or ``None`` for a command that has no
            reply on success.
        crc: whether the command carries a CRC (all but ``Start``).
    """

    name: bytes
    arg_length: int
    reply_prefix: bytes | None
    crc: bool = True

    @property
    def length(self) -> int:
        """Length of the whole command frame in bytes, CRC included."""
        return len(self.name) + self.arg_length + (2 if self.crc else 0)


#: every command of the facts table, by prefix. ``RESET`` is deliberately absent.
COMMANDS: dict[bytes, CommandSpec] = {
    spec.name: spec
    for spec in (
        CommandSpec(b"Start", 0, b"Ready", crc=False),
        CommandSpec(b"H", 0, b"H"),
        CommandSpec(b"V", 0, b"V"),
        CommandSpec(b"X", 0, b"X"),
        CommandSpec(b"IR", 8, b"IR"),
        CommandSpec(b"Aw", 2, None),
        CommandSpec(b"Ar", 2, b"A"),
        CommandSpec(b"CrMA", 2, b"CMA"),
        CommandSpec(b"CrUA", 2, b"CUA"),
        CommandSpec(b"CrLA", 2, b"CLA"),
        CommandSpec(b"MwDA", 0, b"MDA"),
        CommandSpec(b"MwCA", 0, b"MCA"),
        CommandSpec(b"MMA", 0, b"MMA"),
        CommandSpec(b"PwTA", 4, b"PT"),
        CommandSpec(b"PwDA", 4, None),
        CommandSpec(b"PrDA", 4, b"PD"),
        CommandSpec(b"TCA", 0, b"TCA"),
        CommandSpec(b"Sr", 0, b"S"),
    )
}

#: payload length (after the prefix, before CRC and CR LF) of every CRC-carrying reply.
#: ``E`` is the error reply; the prefixes form a prefix-free set.
REPLY_DATA_LENGTHS: dict[bytes, int] = {
    b"H": 1,
    b"V": 6,
    b"X": 8,
    b"IR": 8,
    b"A": 2,
    b"CMA": 2,
    b"CUA": 2,
    b"CLA": 2,
    b"MDA": 0,
    b"MCA": 5,
    b"MMA": 1,
    b"PT": 5,
    b"PD": 2,
    b"TCA": 2,
    b"S": 4,
    b"E": 1,
}

#: the handshake command and its reply (neither carries a CRC).
HANDSHAKE = b"Start"
HANDSHAKE_REPLY = b"Ready\r\n"
#: the bare error reply some documents show for a CRC failure.
BARE_ERROR_REPLY = b"N\r\n"
_CRLF = b"\r\n"


def command_spec_for(frame: bytes) -> CommandSpec | None:
    """The :class:`CommandSpec` whose prefix starts ``frame``, or ``None``.

    Examples:
        >>> command_spec_for(b"CrMA\\x00\\x00xx").reply_prefix
        b'CMA'
        >>> command_spec_for(b"Q") is None
        True
    """
    for name, spec in COMMANDS.items():
        if frame.startswith(name):
            return spec
    return None


def reply_prefix_for(frame: bytes) -> bytes | None:
    """Prefix of the reply a command frame expects (``None``: no reply on success).

    Raises:
        ProtocolError: for bytes that start no known command.

    Examples:
        >>> reply_prefix_for(encode_get_current())
        b'A'
        >>> reply_prefix_for(encode_set_current(0)) is None
        True
    """
    spec = command_spec_for(frame)
    if spec is None:
        raise ProtocolError(f"not a Lens Driver 4 command: {bytes(frame[:8])!r}")
    return spec.reply_prefix


def reply_length(prefix: bytes) -> int:
    """Total length in bytes of a reply with this prefix (CRC and CR LF included).

    Examples:
        >>> reply_length(b"A"), reply_length(b"Ready"), reply_length(b"N"), reply_length(b"E")
        (7, 7, 3, 6)
    """
    if prefix == b"Ready":
        return len(HANDSHAKE_REPLY)
    if prefix == b"N":
        return len(BARE_ERROR_REPLY)
    return len(prefix) + REPLY_DATA_LENGTHS[prefix] + 4


# --------------------------------------------------------------------------- numbers

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


# --------------------------------------------------------------------------- builders


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


# --------------------------------------------------------------------------- replies


@dataclass(frozen=True)
class Frame:
    """One valid reply.

    Attributes:
        prefix: the reply prefix (``b"A"``, ``b"CMA"``, ``b"Ready"``, …).
        data: the payload after the prefix, without CRC and CR LF.
    """

    prefix: bytes
    data: bytes

    def to_bytes(self) -> bytes:
        """The frame as sent on the wire."""
        if self.prefix == b"Ready":
            return HANDSHAKE_REPLY
        return encode_reply(self.prefix, self.data)


@dataclass(frozen=True)
class ErrorFrame:
    """An error reply: ``E`` + id (CRC, CR LF), or a bare ``N\\r\\n`` (reported as id 1).

    Attributes:
        code: 1 CRC failed, 2 not available in this firmware type, 3 not recognised,
            4 lens incompatible.
        bare: True for the bare ``N`` form.
    """

    code: int
    bare: bool = False

    def to_exception(self) -> DeviceErrorReply:
        """The matching :class:`~tdfd.errors.DeviceErrorReply`."""
        return DeviceErrorReply(self.code)

    def to_bytes(self) -> bytes:
        """The frame as sent on the wire."""
        return BARE_ERROR_REPLY if self.bare else encode_error_reply(self.code)


def encode_reply(prefix: bytes, data: bytes = b"") -> bytes:
    """Build a reply frame (the emulator's side): ``prefix + data + CRC + CR LF``.

    Examples:
        >>> encode_reply(b"MDA").hex(" ")
        '4d 44 41 ... 0d 0a'
    """
    body = bytes(prefix) + bytes(data)
    return body + crc16_arc(body).to_bytes(2, "little") + _CRLF


def encode_error_reply(code: int) -> bytes:
    """Build an ``E`` + id error reply.

    Examples:
        >>> decode_frame(encode_error_reply(3))
        ErrorFrame(code=3, bare=False)
    """
    return encode_reply(b"E", bytes([int(code) & 0xFF]))


class Mode(enum.IntEnum):
    """Operating modes reported by ``MMA``."""

    CURRENT = 1
    SINE = 2
    TRIANGLE = 3
    RECTANGLE = 4
    FOCAL_POWER = 5
    ANALOG = 6
    POSITION = 7


class StatusFlags(enum.IntFlag):
    """Bits of status byte #1 (also the status byte of the ``MCA`` and ``PT`` replies)."""

    NOT_ALL_HARDWARE_AVAILABLE = 1 << 0
    NO_OR_FAULTY_EEPROM = 1 << 1
    NO_TEMPERATURE_LIMITS = 1 << 2
    CANNOT_REACH_FOCAL_POWER = 1 << 3
    FOCAL_POWER_INVERSION = 1 << 4
    TEMPERATURE_OUTSIDE_SPECIFICATION = 1 << 5
    FOCAL_POWER_OUTSIDE_GUARANTEED_RANGE = 1 << 6
    TEMPERATURE_OUTSIDE_USER_LIMITS = 1 << 7


@dataclass(frozen=True)
class Status:
    """The ``Sr`` reply.

    The facts number the status bytes but do not say in which order they are sent; this
    package takes status byte #1 to be the first byte after ``S`` (the emulator does the
    same). ``raw`` keeps all four bytes.

    Attributes:
        raw: the four status bytes as received.
    """

    raw: bytes

    @property
    def flags(self) -> StatusFlags:
        """Status byte #1 decoded."""
        return StatusFlags(self.raw[0])


@dataclass(frozen=True)
class FirmwareVersion:
    """The ``V`` reply."""

    major: int
    minor: int
    build: int
    revision: int

    def __str__(self) -> str:
        return f"{self.major}.{self.minor}.{self.build}.{self.revision}"


@dataclass(frozen=True)
class FocalPowerLimits:
    """The ``MCA`` or ``PT`` reply: focal-power range the driver guarantees.

    Attributes:
        status: the status byte of the reply.
        min_dpt: lower focal-power limit, dioptres.
        max_dpt: upper focal-power limit, dioptres.
    """

    status: StatusFlags
    min_dpt: float
    max_dpt: float


def parse_firmware_version(frame: Frame) -> FirmwareVersion:
    """Decode a ``V`` reply.

    Examples:
        >>> str(parse_firmware_version(Frame(b"V", bytes([3, 6, 0, 15, 0, 1]))))
        '3.6.15.1'
    """
    major, minor, build, revision = struct.unpack(">BBHH", frame.data)
    return FirmwareVersion(major, minor, build, revision)


def parse_focal_power_limits(frame: Frame, firmware_type: str) -> FocalPowerLimits:
    """Decode an ``MCA`` or ``PT`` reply (status u8, max i16, min i16).

    Examples:
        >>> parse_focal_power_limits(Frame(b"MCA", bytes([0]) + pack_i16(3000) + pack_i16(0)), "A")
        FocalPowerLimits(status=<StatusFlags: 0>, min_dpt=-5.0, max_dpt=10.0)
    """
    status, max_raw, min_raw = struct.unpack(">Bhh", frame.data)
    return FocalPowerLimits(
        StatusFlags(status),
        focal_power_raw_to_dpt(min_raw, firmware_type),
        focal_power_raw_to_dpt(max_raw, firmware_type),
    )


def parse_status(frame: Frame) -> Status:
    """Decode an ``S`` reply.

    Examples:
        >>> parse_status(Frame(b"S", bytes([4, 0, 0, 0]))).flags
        <StatusFlags.NO_TEMPERATURE_LIMITS: 4>
    """
    return Status(bytes(frame.data))


# --------------------------------------------------------------------------- decoding

_CANDIDATES: tuple[tuple[bytes, int, bool], ...] = tuple(
    [(p, reply_length(p), True) for p in REPLY_DATA_LENGTHS]
    + [(HANDSHAKE_REPLY, len(HANDSHAKE_REPLY), False), (BARE_ERROR_REPLY, len(BARE_ERROR_REPLY), False)]
)
_MIN_FRAME = min(length for _, length, _ in _CANDIDATES)

_VALID, _PARTIAL, _BAD_CRC, _INVALID = range(4)


def _classify(buf: bytes | bytearray, i: int) -> tuple[int, object, int]:
    """Classify the bytes at ``buf[i:]``: (kind, frame or error, length or bytes needed)."""
    avail = len(buf) - i
    result: tuple[int, object, int] = (_INVALID, None, 0)
    for key, length, has_crc in _CANDIDATES:
        probe = buf[i : i + min(len(key), avail)]
        if key[: len(probe)] != probe:
            continue
        if avail < len(key):
            # the bytes so far are a prefix of the key: they could still become this frame
            need = length - avail
            if result[0] != _PARTIAL or need < result[2]:
                result = (_PARTIAL, None, need)
            continue
        if not has_crc:  # Ready\r\n, N\r\n: the key is the whole frame
            frame: Frame | ErrorFrame = Frame(b"Ready", b"") if key == HANDSHAKE_REPLY else ErrorFrame(1, bare=True)
            return (_VALID, frame, length)
        if avail < length:
            need = length - avail
            if result[0] != _PARTIAL or need < result[2]:
                result = (_PARTIAL, None, need)
            continue
        body = bytes(buf[i : i + length - 4])
        if buf[i + length - 2 : i + length] != _CRLF:
            continue
        got = int.from_bytes(buf[i + length - 4 : i + length - 2], "little")
        want = crc16_arc(body)
        if got != want:
            err = ChecksumError(f"bad CRC in {key!r} reply {bytes(buf[i:i + length]).hex(' ')}: got {got:#06x}, expected {want:#06x}")
            if result[0] == _INVALID:
                result = (_BAD_CRC, err, length)
            continue
        data = body[len(key) :]
        if key == b"E":
            return (_VALID, ErrorFrame(data[0]), length)
        return (_VALID, Frame(key, data), length)
    return result


def decode_frame(data: bytes) -> Frame | ErrorFrame:
    """Decode exactly one complete reply frame.

    Args:
        data: the whole frame, CRC and CR LF included.

    Returns:
        A :class:`Frame`, or an :class:`ErrorFrame` for an ``E``/``N`` error reply.

    Raises:
        ChecksumError: CR LF in place but the CRC does not match.
        ProtocolError: anything else that is not exactly one known frame.

    Examples:
        >>> decode_frame(b"Ready\\r\\n")
        Frame(prefix=b'Ready', data=b'')
        >>> decode_frame(b"N\\r\\n")
        ErrorFrame(code=1, bare=True)
        >>> decode_frame(b"A\\x05\\x7a\\x00\\x00\\r\\n")
        Traceback (most recent call last):
        ...
        tdfd.errors.ChecksumError: bad CRC in b'A' reply 41 05 7a 00 00 0d 0a: got 0x0000, expected 0x...
    """
    data = bytes(data)
    kind, obj, length = _classify(data, 0)
    if kind == _VALID and length == len(data):
        return obj  # type: ignore[return-value]
    if kind == _BAD_CRC and length == len(data):
        raise obj  # type: ignore[misc]
    if kind == _PARTIAL:
        raise ProtocolError(f"incomplete reply ({len(data)} bytes, {length} more needed): {data.hex(' ')}")
    if kind == _VALID:
        raise ProtocolError(f"{len(data) - length} bytes after a complete reply: {data.hex(' ')}")
    raise ProtocolError(f"not a Lens Driver 4 reply: {data[:32].hex(' ')}")


class FrameDecoder:
    """Incremental reply decoder that resynchronises after garbage.

    Feed it whatever bytes arrive; it returns the complete frames found. It never splits
    on newlines: a candidate frame starts with a known reply prefix, has that prefix's
    fixed length, ends in CR LF and (except ``Ready``/``N``) carries a matching CRC. The
    earliest position where a complete valid frame starts wins; bytes before it are
    discarded as garbage, and so is anything that cannot start a frame. A candidate whose
    CR LF is in place but whose CRC is wrong is discarded too and recorded as a
    :class:`~tdfd.errors.ChecksumError` (see :meth:`pop_errors`).

    :meth:`feed` never raises.

    Attributes:
        discarded: total number of bytes discarded so far.

    Examples:
        >>> d = FrameDecoder()
        >>> d.feed(b"\\xffRea")
        []
        >>> d.needed()
        4
        >>> d.feed(b"dy\\r\\nN\\r\\n")
        [Frame(prefix=b'Ready', data=b''), ErrorFrame(code=1, bare=True)]
        >>> d.discarded
        1
    """

    #: at most this many recorded errors are kept.
    MAX_ERRORS = 64

    def __init__(self) -> None:
        self._buf = bytearray()
        self._errors: deque[ProtocolError] = deque(maxlen=self.MAX_ERRORS)
        self.discarded = 0

    @property
    def pending(self) -> bytes:
        """Bytes held back as the start of a possible frame."""
        return bytes(self._buf)

    def reset(self) -> bytes:
        """Forget the pending bytes and recorded errors; return the pending bytes."""
        pending = bytes(self._buf)
        self._buf.clear()
        self._errors.clear()
        return pending

    def pop_errors(self) -> list[ProtocolError]:
        """Return and forget the errors recorded since the last call."""
        errors = list(self._errors)
        self._errors.clear()
        return errors

    def needed(self) -> int:
        """Fewest further bytes that could complete a frame (at least 1).

        The minimum over every pending position that could still start a frame; with
        nothing pending, the length of the shortest frame (3, ``N\\r\\n``). A reader that
        reads exactly this many bytes never waits for bytes that a shorter reply (an error
        frame, or a real reply after a garbage byte that looked like a longer prefix) will
        not send.
        """
        if not self._buf:
            return _MIN_FRAME
        needs = [need for kind, _, need in (_classify(self._buf, i) for i in range(len(self._buf))) if kind == _PARTIAL]
        return max(1, min(needs)) if needs else 1

    def _discard(self, n: int) -> None:
        if n <= 0:
            return
        dropped = bytes(self._buf[:n])
        # record checksum failures among the dropped positions (CR LF in place, CRC wrong)
        for i in range(n):
            kind, obj, _ = _classify(self._buf, i)
            if kind == _BAD_CRC:
                self._errors.append(obj)  # type: ignore[arg-type]
        self._errors.append(ProtocolError(f"discarded {n} byte(s) that form no reply: {dropped[:32].hex(' ')}"))
        del self._buf[:n]
        self.discarded += n

    def feed(self, data: bytes) -> list[Frame | ErrorFrame]:
        """Add received bytes; return the frames completed by them, in order.

        Args:
            data: any bytes (possibly empty, partial frames, garbage).

        Returns:
            :class:`Frame` and :class:`ErrorFrame` objects.
        """
        self._buf += bytes(data)
        frames: list[Frame | ErrorFrame] = []
        while self._buf:
            first_partial = None
            found = None
            for i in range(len(self._buf)):
                kind, obj, length = _classify(self._buf, i)
                if kind == _VALID:
                    found = (i, obj, length)
                    break
                if kind == _PARTIAL and first_partial is None:
                    first_partial = i
            if found is None:
                self._discard(len(self._buf) if first_partial is None else first_partial)
                break
            i, obj, length = found
            self._discard(i)
            del self._buf[:length]
            frames.append(obj)  # type: ignore[arg-type]
        return frames
