"""Splitting the byte stream a Lens Driver 4 receives into commands (the device's side).

Commands have no terminator: they are recognised by prefix and fixed length
(:data:`tdfd.driver.protocol.COMMANDS`, plus ``RESET`` so the emulator can refuse it
loudly). Bytes that cannot start a command are skipped up to the next plausible command
start; the device answers them with one ``E 3`` ("not recognised").
"""

from __future__ import annotations

import enum

from .. import protocol as p

__all__ = ["Piece", "split_command", "PARSE_TABLE"]

#: the emulator also recognises RESET (to refuse it loudly), which protocol.COMMANDS omits.
_RESET_SPEC = p.CommandSpec(p.FORBIDDEN_PREFIX, 0, None, crc=False)
#: every command shape the device recognises.
PARSE_TABLE: tuple[p.CommandSpec, ...] = (*p.COMMANDS.values(), _RESET_SPEC)


class Piece(enum.Enum):
    """What :func:`split_command` found at the start of the buffer."""

    COMMAND = "command"  #: a whole command frame (prefix and length; the CRC is not checked here)
    JUNK = "junk"  #: bytes that start no command
    PARTIAL = "partial"  #: the start of a command whose remaining bytes have not arrived


def _could_start_command(buf: bytes | bytearray, i: int) -> bool:
    rest = buf[i : i + 5]
    return any(spec.name[: len(rest)] == rest[: len(spec.name)] for spec in PARSE_TABLE)


def split_command(buf: bytes | bytearray) -> tuple[Piece, int]:
    """Classify the start of ``buf``.

    Args:
        buf: received bytes not yet consumed (non-empty).

    Returns:
        (what, length): a :attr:`Piece.COMMAND` of ``length`` bytes, ``length`` bytes of
        :attr:`Piece.JUNK`, or :attr:`Piece.PARTIAL` (length 0: wait for more bytes).

    Examples:
        >>> split_command(b"MMA\\x00\\x00Sr")
        (<Piece.COMMAND: 'command'>, 5)
        >>> split_command(b"Cr")
        (<Piece.PARTIAL: 'partial'>, 0)
        >>> split_command(b"\\x00\\x01Sr")
        (<Piece.JUNK: 'junk'>, 2)
    """
    partial = False
    for spec in PARSE_TABLE:
        name = spec.name
        if len(buf) < len(name):
            if name[: len(buf)] == buf:
                partial = True
        elif buf[: len(name)] == name:
            return (Piece.COMMAND, spec.length) if len(buf) >= spec.length else (Piece.PARTIAL, 0)
    if partial:
        return (Piece.PARTIAL, 0)
    j = 1
    while j < len(buf) and not _could_start_command(buf, j):
        j += 1
    return (Piece.JUNK, j)
