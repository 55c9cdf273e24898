r"""A serial port proxy that charges the bench's simulated clock for the bytes on the wire."""

from __future__ import annotations

import time
from typing import Any

from .clock import SimClock

__all__ = ["TimedPort", "BAUD", "BITS_PER_BYTE"]

#: the Lens Driver 4's baud rate.
BAUD = 115200
#: bits on the wire per byte (start, 8 data, stop).
BITS_PER_BYTE = 10


class TimedPort:
    """A pyserial-like proxy that charges simulated time for the serial traffic.

    Writes advance the clock by the bytes' wire time *before* they reach the emulator (so
    the emulator stamps a command with its arrival time) and then wait until the emulator
    has processed the command, which keeps the bench deterministic. Reads advance the
    clock by the wire time of what arrives; a short read (a timeout) costs the timeout.
    """

    def __init__(self, port: Any, clock: SimClock, device: Any, baud: int = BAUD) -> None:
        self._port, self._clock, self._device, self._baud = port, clock, device, baud

    def _wire(self, n: int) -> float:
        return n * BITS_PER_BYTE / self._baud

    @property
    def timeout(self) -> float:
        return self._port.timeout

    @timeout.setter
    def timeout(self, value: float) -> None:
        self._port.timeout = value

    @property
    def in_waiting(self) -> int:
        return self._port.in_waiting

    @property
    def port(self) -> str:
        return getattr(self._port, "port", "emulator")

    def write(self, data: bytes) -> int:
        before = self._device.command_count
        self._clock.advance(self._wire(len(data)))
        n = self._port.write(data)
        try:
            self._port.flush()
        except Exception:  # noqa: BLE001 - the real write reports a vanished port
            pass
        deadline = time.monotonic() + 1.0
        while self._device.command_count == before and time.monotonic() < deadline:
            time.sleep(0.0002)
        return n

    def flush(self) -> None:
        pass

    def read(self, n: int = 1) -> bytes:
        t0 = time.monotonic()
        data = self._port.read(n)
        waited = time.monotonic() - t0
        self._clock.advance(self._wire(len(data)))
        if len(data) < n:
            self._clock.advance(float(self._port.timeout or 0.0))
        elif waited > 0.05:  # a late reply: charge the wait
            self._clock.advance(waited)
        return data

    def reset_input_buffer(self) -> None:
        self._port.reset_input_buffer()

    def close(self) -> None:
        self._port.close()
