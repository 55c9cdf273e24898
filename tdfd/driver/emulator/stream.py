"""Splitting the byte stream a Lens Driver 4 receives into commands (the device's side).

Commands have no terminator: they are recognised by prefix and fixed length
(:data:`tdfd.driver.protocol.COMMANDS`, plus ``RESET`` so the emulator can refuse it
loudly). Bytes that cannot start a command are skipped up to the next plausible command
start; the device answers them with one ``E 3`` ("not recognised").
"""

from __future__ import annotations

import enum
import logging
from collections.abc import Iterator

from .. import protocol as p

log = logging.getLogger(__name__)

__all__ = ["Piece", "split_command", "CommandStream", "PARSE_TABLE"]

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


class CommandStream:
    """The device's input buffer: received bytes in, whole commands and junk out.

    Examples:
        >>> stream = CommandStream()
        >>> [(piece.name, chunk) for piece, chunk in stream.feed(b"\\x00MMA\\x00\\x00Cr")]
        [('JUNK', b'\\x00'), ('COMMAND', b'MMA\\x00\\x00')]
        >>> stream.pending
        b'Cr'
    """

    def __init__(self) -> None:
        self._buf = bytearray()

    @property
    def pending(self) -> bytes:
        """Bytes of an incomplete command held back."""
        return bytes(self._buf)

    def discard(self) -> bytes:
        """Drop the held-back bytes; return them."""
        dropped = bytes(self._buf)
        self._buf.clear()
        if dropped:
            log.info("emulator: discarded incomplete command %s", dropped.hex(" "))
        return dropped

    def feed(self, data: bytes) -> Iterator[tuple[Piece, bytes]]:
        """Add received bytes; yield each whole command or run of junk, in order.

        Each piece leaves the buffer before it is yielded; what stays is an incomplete
        command (:attr:`pending`).
        """
        self._buf += bytes(data)
        while self._buf:
            piece, length = split_command(self._buf)
            if piece is Piece.PARTIAL:
                return
            chunk = bytes(self._buf[:length])
            del self._buf[:length]
            yield piece, chunk
