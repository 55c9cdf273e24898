"""Driver for the Optotune Lens Driver 4 (electrically tunable lens), and its emulator.

Layers, from the wire up (imports point down this list):

* :mod:`tdfd.driver.protocol` (a package): sans-I/O protocol, one idea per module:
  ``framing`` (CRC-16/ARC, command table, reply lengths), ``units`` (16-bit fields, mA,
  dpt, °C), ``commands`` (one encoder per command), ``replies`` (reply types and parsers),
  ``decoder`` (one frame; the resynchronising feed decoder).
* :mod:`tdfd.driver.transport`: fixed-length, timed reads and writes over any
  pyserial-like object; drains stray input before each command.
* :mod:`tdfd.driver.link`: bounded retries (which failures are worth another attempt).
* :mod:`tdfd.driver.lens`: :class:`OptotuneLens`, the device API (mA, dpt, °C), with
  range checks, typed errors, and a view of the device it verifies (mode re-read after a
  lost reply, set-points read back on request); its focal-power mode (temperature limits,
  ``MwCA``, the focal-power set-point) is the mixin of :mod:`tdfd.driver.focal_power`.
* :mod:`tdfd.driver.emulator` (a package): a byte-exact device model (:class:`Emulator`,
  ``device``) with first-order focal-power settling (``optics``) and an injectable
  clock, served on a pseudo-terminal by :class:`EmulatorServer` (``pty_server``) or wired
  in-process by :class:`EmulatorSerial` (``serial_port``), with fault injection
  (:class:`Faults`, ``faults``).
* :mod:`tdfd.driver.cli`: ``tdfd lens-emulator``.

This package imports nothing from the depth-from-defocus side of tdfd.
"""

from __future__ import annotations

from .emulator import Calibration, Emulator, EmulatorSerial, EmulatorServer, Faults
from .lens import OptotuneLens
from .protocol import FirmwareVersion, FocalPowerLimits, Mode, Status, StatusFlags
from .transport import SerialTransport, open_port

__all__ = [
    "OptotuneLens",
    "Emulator",
    "EmulatorServer",
    "EmulatorSerial",
    "Faults",
    "Calibration",
    "SerialTransport",
    "open_port",
    "Mode",
    "Status",
    "StatusFlags",
    "FirmwareVersion",
    "FocalPowerLimits",
]
