"""Serving an emulated Lens Driver 4 on a pseudo-terminal (:class:`EmulatorServer`).

A background thread reads the pty master, feeds the :class:`~tdfd.driver.emulator.Emulator`
and writes its replies (after :class:`~tdfd.driver.emulator.Faults`); ``.port`` is the
slave device path, usable with ``serial.Serial(path)`` or
:meth:`tdfd.driver.OptotuneLens.open`.
"""

from __future__ import annotations

import inspect
import logging
import os
import select
import struct
import threading
import time
from collections import deque

from ...errors import DriverError, InputError
from .device import Emulator
from .faults import Faults

__all__ = ["EmulatorServer"]

log = logging.getLogger(__name__)


class EmulatorServer:
    """Serve an :class:`Emulator` on a pseudo-terminal from a background thread.

    Example::

        with EmulatorServer() as srv:
            lens = OptotuneLens.open(srv.port)
            lens.set_current_ma(100.0)
            srv.device.focal_power_at(srv.device.clock() + 0.02)

    Args:
        device: the model to serve (default: a new :class:`Emulator` from ``device_kwargs``).
        faults: fault injection (default: none). Replace at run time via :attr:`faults`.
        partial_timeout_s: an incomplete command older than this is discarded, seconds.
        **device_kwargs: passed to :class:`Emulator` when ``device`` is not given.

    Attributes:
        device: the :class:`Emulator`.
        port: the pty slave path (``/dev/pts/N``) once started, else ``None``.
    """

    def __init__(
        self,
        device: Emulator | None = None,
        *,
        faults: Faults | None = None,
        partial_timeout_s: float = 0.25,
        **device_kwargs: object,
    ) -> None:
        if device is not None and device_kwargs:
            raise InputError(
                f"EmulatorServer takes either device or Emulator keyword arguments, not both (got {sorted(device_kwargs)})"
            )
        unknown = sorted(set(device_kwargs) - set(inspect.signature(Emulator).parameters))
        if unknown:
            raise InputError(f"EmulatorServer: unknown Emulator keyword argument(s) {unknown}")
        self.device = device if device is not None else Emulator(**device_kwargs)  # type: ignore[arg-type]
        self._faults = faults if faults is not None else Faults()
        self.partial_timeout_s = float(partial_timeout_s)
        self.port: str | None = None
        self._lock = threading.Lock()
        self._master: int | None = None
        self._slave: int | None = None
        self._wake: tuple[int, int] | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._disconnect_requested = threading.Event()
        self._disconnected = threading.Event()
        self._commands_since_faults = 0

    # ------------------------------------------------------------------ control

    @property
    def faults(self) -> Faults:
        """The active :class:`Faults`; assigning restarts the ``disconnect_after`` count."""
        return self._faults

    @faults.setter
    def faults(self, faults: Faults) -> None:
        with self._lock:
            self._faults = faults
            self._commands_since_faults = 0
        self._poke()

    @property
    def disconnected(self) -> bool:
        """True once the pty was closed by a disconnect."""
        return self._disconnected.is_set()

    @property
    def running(self) -> bool:
        """True while the serving thread runs."""
        return self._thread is not None and self._thread.is_alive()

    def start(self) -> EmulatorServer:
        """Open the pty (raw mode on both ends) and start serving. Returns ``self``."""
        import tty

        if self._thread is not None:
            raise DriverError("EmulatorServer already started")
        master, slave = os.openpty()
        tty.setraw(master)
        tty.setraw(slave)
        os.set_blocking(master, False)
        self._master, self._slave = master, slave
        self.port = os.ttyname(slave)
        self._wake = os.pipe()
        self._thread = threading.Thread(target=self._serve, name=f"lens-emulator {self.port}", daemon=True)
        self._thread.start()
        log.info("lens emulator serving on %s", self.port)
        return self

    def _poke(self) -> None:
        if self._wake is not None:
            try:
                os.write(self._wake[1], b"x")
            except OSError:
                pass

    def disconnect(self) -> None:
        """Close the pty now: the client sees its port vanish."""
        self._disconnect_requested.set()
        self._poke()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._disconnected.wait(2.0)

    def stop(self) -> None:
        """Stop serving and close everything. Idempotent."""
        self._stop.set()
        self._poke()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(5.0)
        self._close_pty()
        if self._wake is not None:
            for fd in self._wake:
                try:
                    os.close(fd)
                except OSError:
                    pass
            self._wake = None

    def wait(self, timeout: float | None = None) -> bool:
        """Block until the serving thread ends (stop or disconnect); True if it did."""
        if self._thread is None:
            return True
        self._thread.join(timeout)
        return not self._thread.is_alive()

    def __enter__(self) -> EmulatorServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # ------------------------------------------------------------------ the thread

    def _close_pty(self) -> None:
        with self._lock:
            for attr in ("_master", "_slave"):
                fd = getattr(self, attr)
                if fd is not None:
                    try:
                        os.close(fd)
                    except OSError:
                        pass
                    setattr(self, attr, None)

    def _write(self, data: bytes) -> None:
        master = self._master
        if master is None:
            return
        view = memoryview(data)
        while view:
            try:
                n = os.write(master, view)
            except BlockingIOError:
                log.warning("lens emulator: pty full (client not reading), dropping %d byte(s)", len(view))
                return
            except OSError as exc:
                log.warning("lens emulator: write failed: %s", exc)
                return
            view = view[n:]

    def _wait_delivered(self, timeout_s: float = 0.5) -> None:
        """Give the client up to ``timeout_s`` to read what was written (the pty drops it on close)."""
        try:
            import fcntl
            import termios

            deadline = time.monotonic() + timeout_s
            quiet_since = None
            while self._slave is not None and time.monotonic() < deadline:
                waiting = struct.unpack("i", fcntl.ioctl(self._slave, termios.FIONREAD, b"\0\0\0\0"))[0]
                now = time.monotonic()
                if waiting:
                    quiet_since = None
                elif quiet_since is None:
                    quiet_since = now
                elif now - quiet_since >= 0.02:  # the pty moves bytes asynchronously: want a quiet spell
                    return
                time.sleep(0.002)
        except (ImportError, OSError):  # pragma: no cover - non-Linux ptys
            pass

    def _do_disconnect(self) -> None:
        log.warning("lens emulator: disconnecting %s", self.port)
        self._close_pty()
        self._disconnected.set()

    def _serve(self) -> None:
        out: deque[tuple[float, bytes]] = deque()
        last_rx = 0.0
        assert self._master is not None and self._wake is not None
        master, wake = self._master, self._wake[0]
        try:
            while not self._stop.is_set():
                if self._disconnect_requested.is_set() or (
                    self._faults.disconnect_after is not None
                    and self._commands_since_faults >= self._faults.disconnect_after
                ):
                    while out and out[0][0] <= time.monotonic():
                        self._write(out.popleft()[1])
                    self._wait_delivered()
                    self._do_disconnect()
                    return
                now = time.monotonic()
                while out and out[0][0] <= now:
                    self._write(out.popleft()[1])
                timeout = 0.05
                if out:
                    timeout = min(timeout, max(0.0, out[0][0] - now))
                if self.device.pending:
                    timeout = min(timeout, max(0.0, last_rx + self.partial_timeout_s - now))
                readable, _, _ = select.select([master, wake], [], [], timeout)
                if wake in readable:
                    os.read(wake, 512)
                if master in readable:
                    try:
                        data = os.read(master, 4096)
                    except BlockingIOError:
                        data = b""
                    except OSError as exc:
                        log.warning("lens emulator: read failed: %s", exc)
                        data = b""
                    if data:
                        last_rx = time.monotonic()
                        before = self.device.command_count
                        with self._lock:
                            data = self._faults.corrupt_command(data)
                        replies = self.device.feed(data)
                        now = time.monotonic()
                        with self._lock:
                            faults = self._faults
                            self._commands_since_faults += self.device.command_count - before
                            for reply in replies:
                                sent, delay = faults.apply(reply)
                                if sent is None:
                                    continue
                                due = now + delay
                                if out:
                                    due = max(due, out[-1][0])
                                out.append((due, sent))
                elif self.device.pending and time.monotonic() - last_rx >= self.partial_timeout_s:
                    self.device.discard_partial()
        except Exception:  # pragma: no cover - keep a bench informative if the model breaks
            log.exception("lens emulator thread failed")
            self._do_disconnect()
