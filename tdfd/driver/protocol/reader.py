"""Finding the reply to one command by its expected length (sans I/O).

:class:`~tdfd.driver.protocol.decoder.FrameDecoder` takes the earliest complete frame
anywhere in the buffer, which suits input of unknown origin (drained bytes), but a valid
reply whose payload holds a shorter complete frame (``X`` + ``AN\\r\\nBCDE``, or a device id
holding ``Ready\\r\\n``) would be decoded as that inner frame. :class:`ReplyReader` knows
which reply it waits for: a position that starts with the expected prefix is read to the
expected length and decided there (valid, or a bad CRC) before anything inside it is
looked at; every other frame found (a late reply, an error reply) is consumed whole, by
its own length. Only bytes that can start no frame are skipped one at a time.
"""

from __future__ import annotations

from ...errors import ChecksumError, ProtocolError
from .framing import BARE_ERROR_REPLY, CRLF, HANDSHAKE_REPLY, REPLY_DATA_LENGTHS, crc16_arc, reply_length
from .replies import ErrorFrame, Frame

__all__ = ["ReplyReader"]

# (key, total length, carries a CRC); "Ready" and "N" are whole frames without CRC
_OTHER_KEYS: tuple[tuple[bytes, int, bool], ...] = tuple(
    [(prefix, reply_length(prefix), True) for prefix in REPLY_DATA_LENGTHS]
    + [(HANDSHAKE_REPLY, len(HANDSHAKE_REPLY), False), (BARE_ERROR_REPLY, len(BARE_ERROR_REPLY), False)]
)


class ReplyReader:
    """Incremental reader of the reply to one command, decoding by the expected length.

    Feed it the bytes that arrive after the command; :meth:`feed` returns the frames
    found, in order: the expected reply, error replies (``E`` + id, ``N``) and other
    complete frames (late replies to earlier commands), each consumed whole. A frame
    with the expected prefix whose CR LF is in place but whose CRC is wrong is consumed
    whole too and recorded as a :class:`~tdfd.errors.ChecksumError` (:attr:`errors`).
    :meth:`feed` never raises.

    Args:
        expected_prefix: the reply prefix awaited (``b"A"``, ``b"X"``, ``b"Ready"``, …).

    Attributes:
        expected_prefix: as given.
        errors: checksum failures of frames with the expected prefix, and a
            :class:`~tdfd.errors.ProtocolError` per run of discarded bytes.
        discarded: bytes discarded as forming no frame.

    Examples:
        >>> r = ReplyReader(b"X")
        >>> body = b"X" + b"AN\\r\\nBCDE"  # a serial number holding a bare error reply
        >>> r.feed(body + crc16_arc(body).to_bytes(2, "little") + b"\\r\\n")
        [Frame(prefix=b'X', data=b'AN\\r\\nBCDE')]
        >>> ReplyReader(b"X").feed(b"N\\r\\n")
        [ErrorFrame(code=1, bare=True)]
    """

    #: at most this many recorded errors are kept.
    MAX_ERRORS = 64

    def __init__(self, expected_prefix: bytes) -> None:
        expected_prefix = bytes(expected_prefix)
        if expected_prefix == b"Ready":
            self._expected = (HANDSHAKE_REPLY, len(HANDSHAKE_REPLY), False)
        elif expected_prefix in REPLY_DATA_LENGTHS and expected_prefix != b"E":
            self._expected = (expected_prefix, reply_length(expected_prefix), True)
        else:
            raise ProtocolError(f"no reply with prefix {expected_prefix!r} is known")
        self.expected_prefix = expected_prefix
        self._keys = (self._expected, *(k for k in _OTHER_KEYS if k[0] != self._expected[0]))
        self._buf = bytearray()
        self._junk = bytearray()
        self.errors: list[ProtocolError] = []
        self.discarded = 0

    @property
    def pending(self) -> bytes:
        """Bytes held back as the start of a possible frame."""
        return bytes(self._buf)

    def _record(self, error: ProtocolError) -> None:
        if len(self.errors) < self.MAX_ERRORS:
            self.errors.append(error)

    def _flush_junk(self) -> None:
        if self._junk:
            self._record(ProtocolError(f"discarded {len(self._junk)} byte(s) that form no reply: {bytes(self._junk[:32]).hex(' ')}"))
            self._junk.clear()

    def _step(self, final: bool) -> tuple[str, object, int]:
        """Decide the start of the buffer: ("frame", frame, n), ("bad", error, n), ("wait", None, need) or ("junk", None, 1)."""
        buf = self._buf
        avail = len(buf)
        need = None
        for key, length, has_crc in self._keys:
            probe = bytes(buf[: min(len(key), avail)])
            if key[: len(probe)] != probe:
                continue
            if avail < length:  # could still become this frame
                if not final:
                    need = length - avail if need is None else min(need, length - avail)
                    if key == self._expected[0]:
                        break  # the expected reply is decided at its own length, nothing inside it first
                continue
            if not has_crc:  # Ready\r\n, N\r\n: the key is the whole frame
                frame = Frame(b"Ready", b"") if key == HANDSHAKE_REPLY else ErrorFrame(1, bare=True)
                return ("frame", frame, length)
            if bytes(buf[length - 2 : length]) != CRLF:
                continue
            body = bytes(buf[: length - 4])
            got = int.from_bytes(buf[length - 4 : length - 2], "little")
            want = crc16_arc(body)
            if got != want:
                error = ChecksumError(
                    f"bad CRC in {key!r} reply {bytes(buf[:length]).hex(' ')}: got {got:#06x}, expected {want:#06x}"
                )
                return ("bad", error, length)
            data = body[len(key) :]
            return ("frame", ErrorFrame(data[0]) if key == b"E" else Frame(key, data), length)
        if need is not None:
            return ("wait", None, need)
        return ("junk", None, 1)

    def _run(self, final: bool) -> list[Frame | ErrorFrame]:
        frames: list[Frame | ErrorFrame] = []
        while self._buf:
            kind, obj, n = self._step(final)
            if kind == "wait":
                break
            if kind == "junk":
                self._junk += self._buf[:1]
                del self._buf[:1]
                self.discarded += 1
                continue
            self._flush_junk()
            if kind == "bad":
                if bytes(self._buf[: len(self._expected[0])]) == self._expected[0]:
                    self._record(obj)  # type: ignore[arg-type]
                del self._buf[:n]  # a frame-shaped thing with a bad CRC: consumed whole
                continue
            del self._buf[:n]
            frames.append(obj)  # type: ignore[arg-type]
        self._flush_junk()
        return frames

    def feed(self, data: bytes) -> list[Frame | ErrorFrame]:
        """Add received bytes; return the frames they complete, in order."""
        self._buf += bytes(data)
        return self._run(final=False)

    def finish(self) -> list[Frame | ErrorFrame]:
        """No more bytes will come (the read timed out): decode what is left.

        Positions that could only have become a longer frame are skipped, so a complete
        short frame behind them (an error reply after a stray byte) is still found.
        """
        frames = self._run(final=True)
        self._buf.clear()
        return frames

    def needed(self) -> int:
        """Fewest further bytes that could complete a frame at the start of the buffer (at least 1).

        With nothing pending, the length of the shortest frame (3, ``N\\r\\n``). Reading
        exactly this many bytes never waits for bytes a shorter reply will not send,
        except where a stray byte looks like the start of the expected reply.
        """
        if not self._buf:
            return len(BARE_ERROR_REPLY)
        kind, _, n = self._step(final=False)
        return max(1, n) if kind == "wait" else 1
