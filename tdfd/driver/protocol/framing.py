"""Framing of the Lens Driver 4 protocol: CRC-16/ARC, the command table and reply lengths.

Every command except the ``Start`` handshake carries a CRC-16/ARC, low byte first, and no
terminator. Every reply is ``prefix + payload + CRC + CR LF``, except ``Ready\\r\\n`` and
the bare error reply ``N\\r\\n``. ``RESET`` (firmware-update mode) is absent from the
table and :func:`with_crc` refuses it.
"""

from __future__ import annotations

from dataclasses import dataclass

from ...errors import ForbiddenCommandError, ProtocolError

__all__ = [
    "crc16_arc",
    "with_crc",
    "FORBIDDEN_PREFIX",
    "CommandSpec",
    "COMMANDS",
    "REPLY_DATA_LENGTHS",
    "HANDSHAKE",
    "HANDSHAKE_REPLY",
    "BARE_ERROR_REPLY",
    "CRLF",
    "reply_prefix_for",
    "reply_length",
    "command_spec_for",
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
#: every reply ends in CR LF.
CRLF = b"\r\n"


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
        >>> reply_prefix_for(b"Ar\\x00\\x00\\xb4\\x27")
        b'A'
        >>> reply_prefix_for(b"Aw\\x04\\xb2\\x26\\x93") is None
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
