"""The assist-light interface: what the autofocus loop may do with a light.

A light is **on with a pattern** or **off**. A simulated light knows several patterns
(``"coherent"``: the paper's sharpness-retaining laser pattern, ``"projector"``: an
incoherent projector focused at 56.8 cm); a real light (a laser-diode driver or relay on a
serial modem line, or a user's command) has one pattern, :data:`ON`, and accepts
``on()`` / ``on("on")`` only.

Nobody but :class:`tdfd.light.guard.LightGuard` should call :meth:`AssistLight.on`: the
guard is the one place where the on-time and duty-cycle caps and the off-on-every-exit
rule are enforced.
"""

from __future__ import annotations

import abc
import logging

from ..errors import InputError

__all__ = ["AssistLight", "ON"]

log = logging.getLogger(__name__)

#: the only pattern of a light that is simply on or off.
ON = "on"


class AssistLight(abc.ABC):
    """An assist illuminator: :meth:`on` with a pattern, :meth:`off`, :attr:`is_on`.

    Subclasses implement :meth:`_switch_on`, :meth:`_switch_off` and set
    :attr:`patterns`. :meth:`off` must be safe to call at any time, any number of
    times, also after a failed :meth:`on` and after :meth:`close`.

    Attributes:
        name: a label for logs and reports (e.g. ``"serial:/dev/ttyUSB0:rts"``).
        patterns: the patterns :meth:`on` accepts; the first is the default.
    """

    name: str = "light"
    patterns: tuple[str, ...] = (ON,)

    def __init__(self) -> None:
        self._on = False
        self._pattern: str | None = None

    # ------------------------------------------------------------------ protocol
    def resolve_pattern(self, pattern: str | None) -> str:
        """``pattern``, or the default one for ``None``.

        Raises:
            InputError: a pattern this light cannot show.
        """
        if pattern is None:
            return self.patterns[0]
        if pattern not in self.patterns:
            raise InputError(f"light {self.name} cannot show pattern {pattern!r} (it has {', '.join(self.patterns)})")
        return pattern

    def on(self, pattern: str | None = None) -> None:
        """Switch on with ``pattern`` (default: the light's first pattern).

        Raises:
            InputError: an unknown pattern.
            LightError: the switch failed; :meth:`off` has been attempted before it is raised.
        """
        p = self.resolve_pattern(pattern)
        self._pattern = p
        self._on = True  # "may be on" from the first attempt
        try:
            self._switch_on(p)
        except BaseException:
            # a half-done switch may have left it on: off is still attempted
            try:
                self.off()
            except Exception as exc:  # noqa: BLE001 - the first error is the one to report
                log.error("light %s: switching off after a failed switch-on failed too: %s", self.name, exc)
            raise
        log.debug("light %s on (%s)", self.name, p)

    def off(self) -> None:
        """Switch off (idempotent; always attempts the switch, even if believed off).

        Raises:
            LightError: the switch failed; :attr:`is_on` stays ``True`` (the light may be on).
        """
        self._switch_off()
        self._on = False
        self._pattern = None
        log.debug("light %s off", self.name)

    @property
    def is_on(self) -> bool:
        """``True`` if the light is, or may be, on (a failed switch-off leaves it ``True``)."""
        return self._on

    @property
    def pattern(self) -> str | None:
        """The pattern shown, ``None`` when off."""
        return self._pattern if self._on else None

    def close(self) -> None:
        """Switch off and release the device (idempotent)."""
        try:
            self.off()
        finally:
            self._release()

    def __enter__(self) -> "AssistLight":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.name!r}, {'on' if self._on else 'off'})"

    # ------------------------------------------------------------------ to implement
    @abc.abstractmethod
    def _switch_on(self, pattern: str) -> None:
        """Switch the hardware (or model) on with ``pattern``."""

    @abc.abstractmethod
    def _switch_off(self) -> None:
        """Switch the hardware (or model) off."""

    def _release(self) -> None:
        """Release the device (close a port). Default: nothing."""
