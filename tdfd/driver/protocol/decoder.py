"""Finding reply frames in received bytes: one complete frame, or a resynchronising stream.

A candidate frame starts with a known reply prefix, has that prefix's fixed length, ends
in CR LF and (except ``Ready``/``N``) carries a matching CRC. Frames are never found by
splitting on newlines: a payload or CRC byte can be ``0x0A``.
"""

from __future__ import annotations

from collections import deque

from ...errors import ChecksumError, ProtocolError
from .framing import BARE_ERROR_REPLY, CRLF, HANDSHAKE_REPLY, REPLY_DATA_LENGTHS, crc16_arc, reply_length
from .replies import ErrorFrame, Frame

__all__ = ["decode_frame", "FrameDecoder"]

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
        if buf[i + length - 2 : i + length] != CRLF:
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
