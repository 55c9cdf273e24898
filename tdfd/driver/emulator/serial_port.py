"""An in-process, pyserial-like port wired to an emulated Lens Driver 4 (:class:`EmulatorSerial`)."""

from __future__ import annotations

import logging
import time
from collections import deque
from typing import Callable

from .device import Emulator
from .faults import Faults

__all__ = ["EmulatorSerial"]

log = logging.getLogger(__name__)


class EmulatorSerial:
    """An in-process, pyserial-like port wired to an :class:`Emulator` (no pty, no thread).

    Replies become readable as soon as the command is written (late ones after
    ``late_s``); :class:`Faults` apply as on the pty. A read that cannot be completed
    waits out its timeout, as pyserial's does. After an injected disconnect every call
    raises ``serial.SerialException`` like a vanished port.

    Time is read from ``clock`` and waited with ``sleep``: pass a simulated clock's pair
    (and the same clock to the :class:`Emulator`) to run timeouts and late replies in
    simulated time, e.g. for long fault-injection runs.

    Args:
        device: the model (default: a new :class:`Emulator`).
        faults: fault injection (default: none).
        timeout: read timeout, seconds (as pyserial's ``timeout``).
        clock: time source, seconds (default :func:`time.monotonic`).
        sleep: waits a number of seconds on ``clock`` (default :func:`time.sleep`).
        partial_timeout_s: an incomplete command older than this is discarded when the
            next bytes are written (as the pty server does after an idle gap), seconds.

    Example:
        >>> from tdfd.driver import OptotuneLens
        >>> lens = OptotuneLens(EmulatorSerial()).connect()
        >>> lens.set_current_ma(50.0); round(lens.get_current_ma(), 1)
        50.0
    """

    def __init__(
        self,
        device: Emulator | None = None,
        *,
        faults: Faults | None = None,
        timeout: float | None = 0.5,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
        partial_timeout_s: float = 0.25,
    ) -> None:
        self.device = device if device is not None else Emulator(clock=clock)
        self.timeout = timeout
        self.clock = clock
        self.sleep = sleep
        self.partial_timeout_s = float(partial_timeout_s)
        self._last_write = clock()
        self.port = "emulator://"
        self.is_open = True
        self._out: deque[tuple[float, bytes]] = deque()
        self._rx = bytearray()
        self._vanished = False
        self.faults = faults if faults is not None else Faults()

    @property
    def faults(self) -> Faults:
        """The active :class:`Faults`; assigning restarts the ``disconnect_after`` count."""
        return self._faults

    @faults.setter
    def faults(self, faults: Faults) -> None:
        self._faults = faults
        self._commands = 0

    def _due_to_vanish(self) -> bool:
        after = self._faults.disconnect_after
        return after is not None and self._commands >= after and not self._rx and not self._out

    def _check(self) -> None:
        import serial

        if not self._vanished and self._due_to_vanish():
            self._vanished = True
            log.warning("emulator port: disconnecting (injected fault)")
        if self._vanished:
            raise serial.SerialException("device disconnected (injected fault)")
        if not self.is_open:
            raise serial.PortNotOpenError()

    def _collect(self) -> None:
        now = self.clock()
        while self._out and self._out[0][0] <= now:
            self._rx += self._out.popleft()[1]

    @property
    def in_waiting(self) -> int:
        """Bytes readable now."""
        self._check()
        self._collect()
        return len(self._rx)

    def write(self, data: bytes) -> int:
        """Feed bytes (maybe corrupted by :attr:`faults`) to the device; queue its (faulted) replies."""
        self._check()
        now = self.clock()
        if self.device.pending and now - self._last_write >= self.partial_timeout_s:
            self.device.discard_partial()
        self._last_write = now
        before = self.device.command_count
        replies = self.device.feed(self._faults.corrupt_command(bytes(data)))
        self._commands += self.device.command_count - before
        for reply in replies:
            sent, delay = self._faults.apply(reply)
            if sent is not None:
                due = max(now + delay, self._out[-1][0] if self._out else 0.0)
                self._out.append((due, sent))
        return len(data)

    def read(self, size: int = 1) -> bytes:
        """Up to ``size`` bytes, waiting at most :attr:`timeout` (the whole timeout if fewer come)."""
        self._check()
        deadline = self.clock() + (self.timeout if self.timeout is not None else 3600.0)
        self._collect()
        while len(self._rx) < size:
            now = self.clock()
            if now >= deadline:
                break
            self.sleep(max(0.0, (min(self._out[0][0], deadline) if self._out else deadline) - now))
            self._collect()
        out = bytes(self._rx[:size])
        del self._rx[:size]
        return out

    def reset_input_buffer(self) -> None:
        """Discard readable bytes."""
        self._check()
        self._collect()
        self._rx.clear()

    def flush(self) -> None:
        """Nothing to flush."""
        self._check()

    def close(self) -> None:
        """Close (idempotent)."""
        self.is_open = False
