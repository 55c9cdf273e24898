r"""The bench's simulated clock: only the bench advances it."""

from __future__ import annotations

from ...errors import InputError

__all__ = ["SimClock"]


class SimClock:
    """Simulated time in seconds; only the bench advances it.

    Example:
        >>> c = SimClock(); _ = c.advance(0.5); _ = c.advance_to(0.25); c()
        0.5
    """

    def __init__(self, t0: float = 0.0) -> None:
        self._t = float(t0)

    def __call__(self) -> float:
        return self._t

    def now(self) -> float:
        """The present simulated time (s)."""
        return self._t

    def advance(self, dt: float) -> float:
        """Move ``dt >= 0`` seconds forward; return the new time."""
        if dt < 0:
            raise InputError(f"simulated time cannot go backwards ({dt} s)")
        self._t += float(dt)
        return self._t

    def advance_to(self, t: float) -> float:
        """Move forward to ``t`` if it is later; return the new time."""
        self._t = max(self._t, float(t))
        return self._t
