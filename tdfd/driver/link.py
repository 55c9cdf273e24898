"""Bounded retries over the transport: which failures are worth another attempt.

* :func:`query` sends a command that has a reply and retries it after a timeout, an
  unreadable reply (bad CRC, babble) or an ``E 1``/``E 3`` answer (the command arrived
  corrupted: bad CRC, mangled prefix). ``E 2``/``E 4`` are answers: retrying cannot help.
* :func:`send` sends a command that has no reply exactly once, after the transport has
  resynchronised (retried) if a reply was lost before. A set command is never repeated
  here: only a read-back (:class:`~tdfd.driver.lens.OptotuneLens`, ``verify=True``) can
  tell whether it took.

Each attempt of a query after a failure starts with the transport's fence
(:meth:`~tdfd.driver.transport.SerialTransport.resynchronise`), so the time a query can
take is bounded by ``(1 + retries)`` round trips of two commands.
"""

from __future__ import annotations

import logging

from ..errors import DeviceErrorReply, LensTimeoutError, ProtocolError
from . import protocol as p
from .protocol import Frame
from .transport import SerialTransport

__all__ = ["query", "send", "TRANSMISSION_ERRORS"]

log = logging.getLogger(__name__)

#: device error ids that a command corrupted on the wire produces, so that retrying can help.
TRANSMISSION_ERRORS = (1, 3)


def query(transport: SerialTransport, frame: bytes, retries: int) -> Frame:
    """Send a command that has a reply and return the reply; up to ``retries`` further attempts.

    Args:
        transport: the transport.
        frame: the command frame (from :mod:`tdfd.driver.protocol`).
        retries: further attempts after a timeout, an unreadable reply, ``E 1`` or ``E 3``.

    Raises:
        LensTimeoutError, ChecksumError, ProtocolError, DeviceErrorReply: the last
            failure, after all attempts (``E 2``/``E 4`` at once).
        LensConnectionError: the port vanished (never retried).
    """
    prefix = p.reply_prefix_for(frame)
    if prefix is None:
        raise ProtocolError(f"{bytes(frame[:8])!r} has no reply: use send()")
    spec = p.command_spec_for(frame)
    name = spec.name.decode() if spec is not None else repr(bytes(frame[:8]))
    last: Exception | None = None
    for attempt in range(retries + 1):
        try:
            return transport.exchange(frame, prefix)  # type: ignore[return-value]
        except (LensTimeoutError, ProtocolError) as exc:  # ProtocolError includes ChecksumError
            last = exc
        except DeviceErrorReply as exc:
            if exc.code not in TRANSMISSION_ERRORS:  # an answer: retrying cannot help
                raise
            last = exc
        log.warning("%s: attempt %d of %d failed: %s", name, attempt + 1, retries + 1, last)
    assert last is not None
    raise last


def send(transport: SerialTransport, frame: bytes, retries: int) -> None:
    """Send a command that has no reply, once; read nothing.

    A pending resynchronisation (a reply lost earlier) is tried up to ``1 + retries``
    times first.

    Raises:
        LensTimeoutError, ProtocolError: the transport could not resynchronise.
        LensConnectionError: the port vanished.
    """
    for attempt in range(retries + 1):
        if not transport.unsynchronised:
            break
        try:
            transport.resynchronise()
        except (LensTimeoutError, ProtocolError) as exc:
            if attempt == retries:
                raise
            log.warning("resynchronising: attempt %d of %d failed: %s", attempt + 1, retries + 1, exc)
    transport.exchange(frame, None)
