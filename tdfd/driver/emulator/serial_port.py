"""An in-process, pyserial-like port wired to an emulated Lens Driver 4 (:class:`EmulatorSerial`)."""

from __future__ import annotations

import logging
import time
from collections import deque

from .device import Emulator
from .faults import Faults

__all__ = ["EmulatorSerial"]

log = logging.getLogger(__name__)


class EmulatorSerial:
    """An in-process, pyserial-like port wired to an :class:`Emulator` (no pty, no thread).

    Replies become readable as soon as the command is written (late ones after
    ``late_s`` of wall-clock time); :class:`Faults` apply as on the pty. After an injected
    disconnect every call raises ``serial.SerialException`` like a vanished port.

    Args:
        device: the model (default: a new :class:`Emulator`).
        faults: fault injection (default: none).
        timeout: read timeout, seconds (as pyserial's ``timeout``).

    Example:
        >>> from tdfd.driver import OptotuneLens
        >>> lens = OptotuneLens(EmulatorSerial()).connect()
        >>> lens.set_current_ma(50.0); round(lens.get_current_ma(), 1)
        50.0
    """

    def __init__(self, device: Emulator | None = None, *, faults: Faults | None = None, timeout: float | None = 0.5) -> None:
        self.device = device if device is not None else Emulator()
        self.timeout = timeout
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
        now = time.monotonic()
        while self._out and self._out[0][0] <= now:
            self._rx += self._out.popleft()[1]

    @property
    def in_waiting(self) -> int:
        """Bytes readable now."""
        self._check()
        self._collect()
        return len(self._rx)

    def write(self, data: bytes) -> int:
        """Feed bytes to the device; queue its (faulted) replies."""
        self._check()
        before = self.device.command_count
        replies = self.device.feed(bytes(data))
        self._commands += self.device.command_count - before
        now = time.monotonic()
        for reply in replies:
            sent, delay = self._faults.apply(reply)
            if sent is not None:
                due = max(now + delay, self._out[-1][0] if self._out else 0.0)
                self._out.append((due, sent))
        return len(data)

    def read(self, size: int = 1) -> bytes:
        """Up to ``size`` bytes, waiting at most :attr:`timeout` for late ones."""
        self._check()
        deadline = time.monotonic() + (self.timeout if self.timeout is not None else 3600.0)
        self._collect()
        while len(self._rx) < size and self._out:
            wait = min(self._out[0][0], deadline) - time.monotonic()
            if wait <= 0 and time.monotonic() >= deadline:
                break
            time.sleep(max(wait, 0.0))
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
