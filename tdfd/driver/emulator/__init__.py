"""An emulated Optotune Lens Driver 4 with an EL-10-30 lens, served on a pseudo-terminal.

One idea per module, all re-exported here (imports point down this list):

* :mod:`.optics`: :class:`Calibration` (focal power versus current and temperature),
  :class:`LensOptics` (first-order settling, temperature, the set-point history) and the
  reachable focal-power range.
* :mod:`.stream`: how the device splits its input into commands (no terminators):
  :class:`~tdfd.driver.emulator.stream.CommandStream`.
* :mod:`.device`: :class:`Emulator`, the device model. :meth:`Emulator.handle` answers
  one complete command frame with the reply bytes (byte-exact, CRCs included);
  :meth:`Emulator.feed` takes a raw byte stream and returns the replies. It keeps the
  state a bench needs: mode, current, focal-power set-point, temperature, limits,
  firmware type, and the *optical* focal power over time (:meth:`Emulator.focal_power_at`).
* :mod:`.faults`: :class:`Faults`, seeded fault injection on replies (bad CRC, dropped,
  late, garbage before the reply) and a disconnect after a number of commands.
* :mod:`.pty_server`: :class:`EmulatorServer` serves an :class:`Emulator` on a pty from a
  background thread; ``.port`` is the slave device path, usable with
  ``serial.Serial(path)`` or :meth:`tdfd.driver.OptotuneLens.open`.
* :mod:`.serial_port`: :class:`EmulatorSerial`, an in-process pyserial-like port wired
  straight to an :class:`Emulator` (no pty, no thread): ``OptotuneLens(EmulatorSerial(device))``.

Times are read from the injectable ``clock`` (default :func:`time.monotonic`), so a
simulated bench can run the lens on simulated time. The optical and device behaviour
(documented assumptions, not manufacturer data) is described in :mod:`.optics` and
:mod:`.device`.

Example:
    >>> from tdfd.driver import protocol as p
    >>> t = [0.0]
    >>> lens = Emulator(clock=lambda: t[0])
    >>> lens.handle(p.encode_start())
    b'Ready\\r\\n'
    >>> lens.handle(p.encode_set_current(p.current_ma_to_raw(100.0, 292.84)))
    b''
    >>> lens.focal_power_at(0.0), round(lens.target_focal_power_dpt, 4)
    (-1.5, 0.2237)
    >>> step = lens.target_focal_power_dpt - lens.focal_power_at(0.0)
    >>> round((lens.target_focal_power_dpt - lens.focal_power_at(0.015)) / step, 6)  # 1 % left after 15 ms
    0.01
"""

from __future__ import annotations

from .device import Emulator
from .faults import Faults
from .optics import DEFAULT_SETTLING_TIME_S, Calibration, LensOptics
from .pty_server import EmulatorServer
from .serial_port import EmulatorSerial

__all__ = ["Calibration", "Emulator", "Faults", "EmulatorServer", "EmulatorSerial", "LensOptics", "DEFAULT_SETTLING_TIME_S"]
