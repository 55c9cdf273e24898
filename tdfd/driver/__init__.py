"""Driver for the Optotune Lens Driver 4 (electrically tunable lens), and its emulator.

Layers, from the wire up:

* :mod:`tdfd.driver.protocol`: sans-I/O encoding, CRC-16/ARC and a resynchronising
  frame decoder.
* :mod:`tdfd.driver.transport`: fixed-length, timed reads and writes over any
  pyserial-like object; drains stray input before each command.
* :mod:`tdfd.driver.lens`: :class:`OptotuneLens`, the device API (mA, dpt, °C), with
  range checks, typed errors and bounded retries.
* :mod:`tdfd.driver.emulator`: a byte-exact device model (:class:`Emulator`) with
  first-order focal-power settling and an injectable clock, served on a pseudo-terminal
  by :class:`EmulatorServer` (or wired in-process by :class:`EmulatorSerial`), with
  fault injection (:class:`Faults`).

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
