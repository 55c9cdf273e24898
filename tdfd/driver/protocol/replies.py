"""Reply types and their parsers: frames, error frames, modes, status flags, limits.

The decoders that find frames in a byte stream are in :mod:`.decoder`.
"""

from __future__ import annotations

import enum
import struct
from dataclasses import dataclass

from ...errors import DeviceErrorReply
from .framing import BARE_ERROR_REPLY, CRLF, HANDSHAKE_REPLY, crc16_arc
from .units import focal_power_raw_to_dpt
from .units import pack_i16  # noqa: F401 - the doctests use it

__all__ = [
    "Frame",
    "ErrorFrame",
    "Mode",
    "StatusFlags",
    "Status",
    "FirmwareVersion",
    "FocalPowerLimits",
    "encode_reply",
    "encode_error_reply",
    "parse_firmware_version",
    "parse_focal_power_limits",
    "parse_status",
]


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
    return body + crc16_arc(body).to_bytes(2, "little") + CRLF


def encode_error_reply(code: int) -> bytes:
    """Build an ``E`` + id error reply.

    Examples:
        >>> encode_error_reply(3).hex(" ")
        '45 03 ... 0d 0a'
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
