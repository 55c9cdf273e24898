"""Assist lights for active DFD autofocus (paper sec. 2.1: a pattern gives a texture-less
target the texture that depth-from-defocus needs).

What lives where:

* :mod:`tdfd.light.base`: :class:`AssistLight`, the interface (``on(pattern)``, ``off()``,
  ``is_on``).
* :mod:`tdfd.light.guard`: :class:`LightGuard`, the interlock every switch goes through
  (off unless exposing, on every exit path; on-time and duty caps, :class:`LightLimits`;
  never on without a named light).
* :mod:`tdfd.light.serial_line`: :class:`SerialLineLight`, a laser-diode driver or relay
  keyed from a USB-serial adapter's RTS or DTR line, read back after every switch.
* :mod:`tdfd.light.command`: :class:`CommandLight`, the user's own on/off commands.
* :mod:`tdfd.light.simulated`: :class:`SimulatedLight`, the bench's coherent module and
  projector (:mod:`tdfd.illumination`) with ambient light.
* :mod:`tdfd.light.spec`: ``--assist-light`` parsing (:func:`parse_light_spec`) and
  opening (:func:`open_light`), only for a light the user named.

:mod:`tdfd.light.simulated` (torch) is imported on first use of its names, so the
hardware loop runs without torch. This package sits below the autofocus loop (it imports nothing from
:mod:`tdfd.autofocus`). Errors: :class:`tdfd.errors.LightError` and its subclasses.
"""

from __future__ import annotations

from .base import ON, AssistLight
from .command import CommandLight
from .guard import DEFAULT_LIMITS, LightGuard, LightLimits, exposure
from .serial_line import SerialLineLight, open_serial_line
from .spec import LightSpec, open_light, parse_light_spec

__all__ = [
    "ON",
    "AssistLight",
    "CommandLight",
    "DEFAULT_LIMITS",
    "LightGuard",
    "LightLimits",
    "LightSpec",
    "SIMULATED_PATTERNS",
    "SerialLineLight",
    "SimulatedLight",
    "exposure",
    "open_light",
    "open_serial_line",
    "parse_light_spec",
]


def __getattr__(name: str):  # the simulated light needs torch: import it on first use
    if name in ("SimulatedLight", "SIMULATED_PATTERNS"):
        from . import simulated

        return getattr(simulated, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
