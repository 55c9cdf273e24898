r"""Commanding the lens with a read-back check: shared by the real-hardware loop and the simulated bench.

``PwDA`` (set the focal power) has no reply, so a command lost on the wire is only seen by
reading the set-point back (``PrDA``); :func:`command_lens` does both, with one re-send.
"""

from __future__ import annotations

import logging
import math
import time
from typing import Any, Callable, Protocol, runtime_checkable

from ..errors import DriverError

__all__ = ["LensLike", "command_lens"]

log = logging.getLogger(__name__)


@runtime_checkable
class LensLike(Protocol):
    """The part of :class:`tdfd.driver.OptotuneLens` the autofocus loop uses."""

    def set_focal_power_dpt(self, power_dpt: float) -> None: ...

    def get_focal_power_dpt(self) -> float: ...


def command_lens(lens: Any, power_dpt: float, verify: bool = True, clock: Callable[[], float] = time.monotonic,
                 tolerance_dpt: float = 0.006) -> float:
    """Set ``lens`` to ``power_dpt`` and (``verify``) read the set-point back, re-sending once on a mismatch.

    ``PwDA`` has no reply, so a command lost on the wire is only seen by reading the
    set-point back (``PrDA``).

    Args:
        lens: an :class:`~tdfd.driver.OptotuneLens` in focal-power mode.
        power_dpt: the set-point (dpt).
        verify: read the set-point back.
        clock: time source; its reading right after the command is returned.
        tolerance_dpt: accepted read-back difference (one raw step is 0.005 dpt).

    Returns:
        The time the command was written (after its bytes), by ``clock`` (s).

    Raises:
        DriverError: the driver failed (after its own retries), or the read-back disagrees twice.
    """
    got = math.nan
    for attempt in range(2):
        lens.set_focal_power_dpt(power_dpt)
        arrived = clock()
        if not verify:
            return arrived
        got = lens.get_focal_power_dpt()
        if abs(got - power_dpt) <= tolerance_dpt:
            return arrived
        log.warning("lens set-point read back %.3f dpt, expected %.3f dpt (attempt %d)", got, power_dpt, attempt + 1)
    raise DriverError(f"lens set-point reads back {got:.3f} dpt instead of {power_dpt:.3f} dpt")
