"""The Optotune Lens Driver 4 serial protocol, sans I/O.

One idea per module, all re-exported here:

* :mod:`.framing`: CRC-16/ARC, the command table, reply prefixes and lengths.
* :mod:`.units`: 16-bit fields and unit conversions (mA, dpt, °C).
* :mod:`.commands`: one encoder per command.
* :mod:`.replies`: reply types (frames, error frames, modes, status) and their parsers.
* :mod:`.decoder`: decoding one frame, and the resynchronising stream decoder for input
  of unknown origin.
* :mod:`.reader`: finding the reply to one command by its expected length.

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

# the error types stay reachable as attributes of this module, as before it became a package
from ...errors import (  # noqa: F401
    ChecksumError,
    DeviceErrorReply,
    ForbiddenCommandError,
    LensRangeError,
    ProtocolError,
    UnsupportedFirmwareError,
)
from .commands import (
    encode_current_mode,
    encode_focal_power_mode,
    encode_get_current,
    encode_get_device_id,
    encode_get_firmware_type,
    encode_get_firmware_version,
    encode_get_focal_power,
    encode_get_lower_current_limit,
    encode_get_max_current,
    encode_get_mode,
    encode_get_serial_number,
    encode_get_status,
    encode_get_temperature,
    encode_get_upper_current_limit,
    encode_set_current,
    encode_set_focal_power,
    encode_set_temperature_limits,
    encode_start,
)
from .decoder import (
    decode_frame,
    FrameDecoder,
)
from .framing import (
    BARE_ERROR_REPLY,
    command_spec_for,
    COMMANDS,
    CommandSpec,
    crc16_arc,
    CRLF,
    FORBIDDEN_PREFIX,
    HANDSHAKE,
    HANDSHAKE_REPLY,
    REPLY_DATA_LENGTHS,
    reply_length,
    reply_prefix_for,
    with_crc,
)
from .reader import ReplyReader
from .replies import (
    encode_error_reply,
    encode_reply,
    ErrorFrame,
    FirmwareVersion,
    FocalPowerLimits,
    Frame,
    Mode,
    parse_firmware_version,
    parse_focal_power_limits,
    parse_status,
    Status,
    StatusFlags,
)
from .units import (
    current_ma_to_raw,
    CURRENT_RAW_LIMIT,
    current_raw_to_ma,
    focal_power_dpt_to_raw,
    FOCAL_POWER_FIRMWARE_TYPES,
    focal_power_raw_to_dpt,
    max_current_raw_to_ma,
    NO_TEMPERATURE_SENSOR_RAW,
    pack_i16,
    round_half_away,
    temperature_c_to_raw,
    temperature_raw_to_c,
    unpack_i16,
)

from . import commands, decoder, framing, reader, replies, units  # noqa: E402 - their __all__ make this one

#: every public name of the protocol's modules (framing and CRC, numbers, command builders,
#: replies, the stream decoder and the reply reader).
__all__ = [*framing.__all__, *units.__all__, *commands.__all__, *replies.__all__, *decoder.__all__, *reader.__all__]
