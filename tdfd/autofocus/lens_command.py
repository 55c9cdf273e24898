r"""Commanding the lens with a read-back check: shared by the real-hardware loop and the simulated bench.

``PwDA`` (set the focal power) has no reply, so a command lost on the wire is only seen by
reading the set-point back (``PrDA``); :func:`command_lens` does both, with one re-send.
"""

from __future__ import annotations

import time
from typing import Callable, Protocol, runtime_checkable

__all__ = ["LensLike", "command_lens"]



@runtime_checkable
class LensLike(Protocol):
    """The part of :class:`tdfd.driver.OptotuneLens` the autofocus loop uses."""

    def set_focal_power_dpt(self, power_dpt: float, *, verify: bool | None = None) -> None: ...

    def get_focal_power_dpt(self) -> float: ...


def command_lens(lens: LensLike, power_dpt: float, verify: bool = True,
                 clock: Callable[[], float] = time.monotonic) -> float:
    """Set ``lens`` to ``power_dpt``; with ``verify`` the driver checks that the device took it.

    ``PwDA`` has no reply, so a command lost or corrupted on the wire is only seen by
    reading the set-point back (``PrDA``). The driver's verified set
    (:meth:`tdfd.driver.OptotuneLens.set_focal_power_dpt` with ``verify=True``) reads it
    back, re-sends a command the device rejected or never got, re-reads the mode after a
    lost reply, and raises when the set-point does not take: the loop never works on a
    lens state it only assumes (issue 22).

    Args:
        lens: an :class:`~tdfd.driver.OptotuneLens` in focal-power mode.
        power_dpt: the set-point (dpt).
        verify: have the driver read the set-point back (the autofocus loop always does).
        clock: time source; its reading once the set-point is in place is returned.

    Returns:
        The time the set-point was in place (after the read-back when verified), by ``clock`` (s).

    Raises:
        DriverError: the driver failed after its own retries (``LensStateError`` when the
            set-point does not take, ``LensModeError``, ``LensTimeoutError``, ...).
    """
    lens.set_focal_power_dpt(power_dpt, verify=bool(verify))
    return clock()
