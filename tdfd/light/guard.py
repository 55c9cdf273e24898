"""The light interlock: the one place where an assist light is switched and its limits are kept.

Every switch of an assist light goes through a :class:`LightGuard`. It keeps three rules:

1. **Off unless exposing.** :meth:`LightGuard.exposing` switches the light on for the
   block (a frame's exposure) and off when the block ends, whatever ends it (normal
   return, an exception, ``KeyboardInterrupt``, a lens/camera/estimator fault).
   :meth:`LightGuard.request` brackets one focus request and switches the light off at
   its end too; an ``atexit`` hook switches every guarded light off when the interpreter
   exits; :meth:`LightGuard.close` does it explicitly.
2. **Caps** (:class:`LightLimits`): a maximum on-time per focus request and a maximum
   duty cycle over a sliding window. A switch-on whose expected on-time does not fit in
   what is left of either is refused; a light that stays on past what is left is forced
   off, by a watchdog timer on real time (even while the loop is blocked in a camera
   read) or at the next :meth:`LightGuard.check` / switch-off on a simulated clock.
   Both raise :class:`~tdfd.errors.LightSafetyError` and log an error.
3. **Never on without a named light.** A guard built with ``light=None`` refuses every
   switch-on.

Default limits (:class:`LightLimits`): 0.5 s on per focus request, 10 % duty over any
10 s window. A lit DFD pair keeps the light on for two exposures (about 2 x 2 ms on the
bench's camera, plus the light's switching time), so a focus request uses a few per cent
of its budget and a continuous run re-focusing twice a second stays near 1 % duty. These
limits bound what the *autofocus loop* does with the light; they are not an eye-safety
classification: the laser's class and its maximum permissible exposure set the real
limits of a given rig, and the limits can only be made stricter or looser by the user
who knows them.

The clock is injectable: the bench passes its simulated clock (no watchdog thread; the
bench calls :meth:`LightGuard.check` as time advances), hardware uses
:func:`time.monotonic` (watchdog on).

Example:
    >>> from tdfd.light.simulated import SimulatedLight
    >>> from tdfd import Camera
    >>> t = [0.0]
    >>> guard = LightGuard(SimulatedLight(Camera.preset("reference")), clock=lambda: t[0])
    >>> with guard.request():
    ...     with guard.exposing("coherent", expected_s=0.002):
    ...         t[0] += 0.002
    ...         guard.light.is_on
    True
    >>> guard.light.is_on, round(guard.request_on_s, 6)
    (False, 0.002)
"""

from __future__ import annotations

import atexit
import contextlib
import logging
import threading
import time
import weakref
from collections import deque
from dataclasses import dataclass
from typing import Callable, Iterator

from ..errors import InputError, LightSafetyError
from .base import AssistLight

__all__ = ["LightLimits", "LightGuard", "DEFAULT_LIMITS", "exposure"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class LightLimits:
    """What the autofocus loop may do with an assist light.

    Attributes:
        max_on_s: longest total on-time in one focus request (s).
        max_duty: largest fraction of ``duty_window_s`` the light may be on, in (0, 1].
        duty_window_s: the sliding window of the duty cycle (s).
    """

    max_on_s: float = 0.5
    max_duty: float = 0.1
    duty_window_s: float = 10.0

    def __post_init__(self) -> None:
        if not (self.max_on_s > 0 and 0 < self.max_duty <= 1 and self.duty_window_s > 0):
            raise InputError(f"light limits need max_on_s > 0, 0 < max_duty <= 1 and duty_window_s > 0, got {self}")


#: the default limits (module documentation).
DEFAULT_LIMITS = LightLimits()

_GUARDS: "weakref.WeakSet[LightGuard]" = weakref.WeakSet()
_ATEXIT_LOCK = threading.Lock()
_atexit_registered = False


def _all_off_at_exit() -> None:
    for guard in list(_GUARDS):
        guard.force_off("interpreter exit")


def _register(guard: "LightGuard") -> None:
    global _atexit_registered
    with _ATEXIT_LOCK:
        _GUARDS.add(guard)
        if not _atexit_registered:
            atexit.register(_all_off_at_exit)
            _atexit_registered = True


class LightGuard:
    """The interlock every assist-light switch goes through (module documentation).

    Args:
        light: the light, or ``None`` when the user named none (every switch-on refused).
        limits: on-time and duty caps.
        clock: time source in seconds (``time.monotonic`` on hardware, the bench's
            simulated clock there).
        watchdog: force the light off on a timer thread when its time is up (default: on
            for :func:`time.monotonic` / :func:`time.perf_counter`, off for any other clock,
            whose time a timer cannot follow).

    Attributes:
        request_on_s: on-time used in the current focus request (s).
        total_on_s: on-time since the guard was made (s).
        switch_ons: switch-ons so far.
        refusals: switch-ons refused by a cap.
        trips: times the light was forced off because its time ran out.
    """

    def __init__(self, light: AssistLight | None, limits: LightLimits = DEFAULT_LIMITS,
                 clock: Callable[[], float] = time.monotonic, watchdog: bool | None = None) -> None:
        self.light, self.limits, self.clock = light, limits, clock
        self.watchdog = (clock in (time.monotonic, time.perf_counter)) if watchdog is None else bool(watchdog)
        self._lock = threading.RLock()
        self._intervals: deque[tuple[float, float]] = deque()  # closed on-periods in the duty window
        self._on_since: float | None = None
        self._deadline: float | None = None
        self._timer: threading.Timer | None = None
        self._tripped: str | None = None
        self.request_on_s = 0.0
        self.total_on_s = 0.0
        self.switch_ons = self.refusals = self.trips = 0
        if light is not None:
            _register(self)

    # ------------------------------------------------------------------ state
    @property
    def named(self) -> bool:
        """``True`` if a light was named (switch-ons can be allowed)."""
        return self.light is not None

    @property
    def is_on(self) -> bool:
        """``True`` if the guarded light is (or may be) on."""
        return self.light is not None and self.light.is_on

    def window_on_s(self, now: float | None = None) -> float:
        """On-time inside the duty window ending at ``now`` (s), the present on-period included."""
        now = self.clock() if now is None else now
        start = now - self.limits.duty_window_s
        with self._lock:
            used = sum(max(0.0, min(b, now) - max(a, start)) for a, b in self._intervals)
            if self._on_since is not None:
                used += max(0.0, now - max(self._on_since, start))
        return used

    def duty(self, now: float | None = None) -> float:
        """Duty cycle over the window ending at ``now`` (fraction)."""
        return self.window_on_s(now) / self.limits.duty_window_s

    def budget_s(self, now: float | None = None) -> float:
        """How long the light may still be on from ``now`` (s): the smaller of what is left
        of this request's on-time and of the duty window (the window is taken as not
        sliding while the light is on, a conservative bound)."""
        now = self.clock() if now is None else now
        with self._lock:
            req = self.limits.max_on_s - self.request_on_s
            if self._on_since is not None:
                req -= now - self._on_since
            duty = self.limits.max_duty * self.limits.duty_window_s - self.window_on_s(now)
        return min(req, duty)

    # ------------------------------------------------------------------ switching
    def switch_on(self, pattern: str | None = None, expected_s: float = 0.0) -> None:
        """Switch the light on for about ``expected_s`` seconds.

        Raises:
            LightSafetyError: no light was named, or ``expected_s`` does not fit in the
                on-time or duty budget (the light stays off).
            InputError: an unknown pattern.
            LightError: the light failed to switch (it has been switched off).
        """
        if self.light is None:
            self.refusals += 1
            raise LightSafetyError("no assist light was named: the light is never switched on")
        with self._lock:
            self._raise_if_tripped()
            now = self.clock()
            self._prune(now)
            budget = self.budget_s(now)
            if budget <= 0 or budget < expected_s:
                self.refusals += 1
                msg = (f"light {self.light.name} refused: {expected_s * 1e3:.1f} ms wanted, {max(budget, 0) * 1e3:.1f} ms "
                       f"left (request on-time {self.request_on_s * 1e3:.1f} of {self.limits.max_on_s * 1e3:.0f} ms, "
                       f"duty {self.duty(now) * 100:.2f} % of {self.limits.max_duty * 100:g} % over "
                       f"{self.limits.duty_window_s:g} s)")
                log.error(msg)
                raise LightSafetyError(msg)
            if self._on_since is None:
                self._on_since = now
                self.switch_ons += 1
            self._deadline = now + budget
            try:
                self.light.on(pattern)
            except BaseException:
                self._close_period(self.clock())
                raise
            self._arm(budget)

    def switch_off(self) -> None:
        """Switch the light off and account its on-time.

        Raises:
            LightSafetyError: the light had stayed on past its budget (it is off now), or
                the watchdog forced it off meanwhile.
            LightError: the switch failed (the light may be on: :attr:`is_on` says so).
        """
        if self.light is None:
            return
        with self._lock:
            self._disarm()
            now = self.clock()
            overran = self._deadline is not None and self._on_since is not None and now > self._deadline + 1e-12
            try:
                self.light.off()
            finally:
                self._close_period(now)
            if overran:
                self.trips += 1
                msg = f"light {self.light.name} was on past its budget: switched off (on-time cap or duty cap)"
                log.error(msg)
                raise LightSafetyError(msg)
            self._raise_if_tripped()

    def check(self) -> None:
        """Enforce the caps now: force the light off if its time is up.

        Raises:
            LightSafetyError: the light was forced off (now or by the watchdog).
        """
        with self._lock:
            if self._on_since is not None and self._deadline is not None and self.clock() > self._deadline + 1e-12:
                self._trip("on-time or duty budget used up")
            self._raise_if_tripped()

    def force_off(self, why: str = "") -> bool:
        """Switch the light off, never raising (exit paths). Returns ``True`` if it is off."""
        if self.light is None:
            return True
        with self._lock:
            self._disarm()
            try:
                if self.light.is_on or self._on_since is not None:
                    self.light.off()
                    if why:
                        log.info("light %s off (%s)", self.light.name, why)
            except Exception as exc:  # noqa: BLE001 - an exit path: report, keep going
                log.error("light %s: switching off (%s) failed: %s", self.light.name, why or "exit", exc)
            finally:
                self._close_period(self.clock())
            return not self.light.is_on

    # ------------------------------------------------------------------ contexts
    @contextlib.contextmanager
    def exposing(self, pattern: str | None = None, expected_s: float = 0.0) -> Iterator["LightGuard"]:
        """The light on for the block (one exposure), off when it ends, on every path.

        Raises:
            LightSafetyError: refused, or the block overran the budget (the light is off).
        """
        self.switch_on(pattern, expected_s)
        try:
            yield self
        except BaseException:
            self.force_off("exposure aborted")
            raise
        self.switch_off()

    @contextlib.contextmanager
    def request(self) -> Iterator["LightGuard"]:
        """One focus request: a fresh on-time budget; the light is off when it ends."""
        with self._lock:
            self.request_on_s = 0.0
            self._tripped = None
        try:
            yield self
        finally:
            self.force_off("end of the focus request")

    def close(self) -> None:
        """Switch the light off and release it (idempotent)."""
        self.force_off("guard closed")
        if self.light is not None:
            try:
                self.light.close()
            except Exception as exc:  # noqa: BLE001 - closing: report, keep going
                log.error("closing light %s: %s", self.light.name, exc)
        _GUARDS.discard(self)

    def __enter__(self) -> "LightGuard":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ internals
    def _prune(self, now: float) -> None:
        start = now - self.limits.duty_window_s
        while self._intervals and self._intervals[0][1] <= start:
            self._intervals.popleft()

    def _close_period(self, now: float) -> None:
        if self._on_since is not None:
            dt = max(0.0, now - self._on_since)
            self._intervals.append((self._on_since, now))
            self.request_on_s += dt
            self.total_on_s += dt
        self._on_since = self._deadline = None

    def _trip(self, why: str) -> None:
        assert self.light is not None
        self.trips += 1
        self._tripped = f"light {self.light.name} forced off: {why}"
        log.error(self._tripped)
        try:
            self.light.off()
        except Exception as exc:  # noqa: BLE001 - report both
            log.error("light %s: forced switch-off failed: %s", self.light.name, exc)
        finally:
            self._close_period(self.clock())

    def _raise_if_tripped(self) -> None:
        if self._tripped is not None:
            msg, self._tripped = self._tripped, None
            raise LightSafetyError(msg)

    def _arm(self, budget_s: float) -> None:
        if not self.watchdog:
            return
        self._disarm()
        token = object()
        timer = threading.Timer(max(budget_s, 0.0), self._fire, args=(token,))
        timer.daemon = True
        self._token = token
        self._timer = timer
        timer.start()

    def _disarm(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None

    def _fire(self, token: object) -> None:
        with self._lock:
            if self._on_since is not None and getattr(self, "_token", None) is token:
                self._timer = None
                self._trip("watchdog: on-time or duty budget used up")


def exposure(guard: LightGuard | None, pattern: str | None, expected_s: float = 0.0
             ) -> contextlib.AbstractContextManager:
    """What a plant wraps one exposure in: the light on with ``pattern`` for the block
    (through ``guard``), or nothing for an unlit frame (``pattern=None``).

    Raises:
        LightSafetyError: a lit frame without a guarded light (none was named), or a cap
            refused it.
    """
    if pattern is None:
        return contextlib.nullcontext()
    if guard is None:
        raise LightSafetyError(f"a frame lit with {pattern!r} was asked for, but no assist light was named")
    return guard.exposing(pattern, expected_s)
