r"""The state machine every autofocus controller is built on, and the loop that drives one against a plant.

:class:`StateMachine` is generator-backed: a subclass (a policy: :class:`tdfd.autofocus.dfd.DFDController`,
:class:`tdfd.autofocus.contrast.ContrastController`) writes its run as a generator that
yields :mod:`~tdfd.autofocus.messages` commands and receives the observations answering
them; the base class checks that each observation answers the pending command, counts
frames, lens commands and time, and retries lens and capture faults a bounded number of
times. :func:`drive` runs a controller against a :class:`~tdfd.autofocus.interfaces.Plant`.
"""

from __future__ import annotations

import logging
from typing import Any, Generator

from ..errors import InputError
from .interfaces import Plant
from .messages import (
    AFResult,
    Capture,
    CaptureFault,
    Command,
    ControllerError,
    Done,
    Estimate,
    Estimation,
    EstimateFault,
    Frame,
    Halt,
    LensAck,
    LensFault,
    Observation,
    SetPower,
    State,
)

__all__ = ["Abort", "Gen", "StateMachine", "drive"]

log = logging.getLogger(__name__)


class Abort(Exception):
    """Raised inside a controller's generator to end the run: ``status`` ``"failed"`` (``reason`` becomes
    :attr:`AFResult.error`), ``"dry-run"`` or ``"halted"``."""

    def __init__(self, reason: str, status: str = "failed") -> None:
        super().__init__(reason)
        self.reason, self.status = reason, status


#: a controller's run: yields commands, receives observations.
Gen = Generator[Command, Observation, Any]


class StateMachine:
    """Generator-backed state machine: :meth:`start` gives the first command, :meth:`step` the next.

    Subclasses implement :meth:`_run`, a generator that yields commands and receives the
    observations answering them. It shares the counting (frames, lens commands, time) and
    the fault handling (bounded retries of lens commands) in helper generators.

    Args:
        settle_s: lens settling time waited after each power command (s).
        lens_retries: further attempts after a lens fault before the run fails.
        capture_retries: further attempts after a failed capture before the run fails.
        power_limits_dpt: the lens's ``(min, max)`` focal power (dpt), ``None`` if unknown.
    """

    def __init__(self, settle_s: float = 0.015, lens_retries: int = 2, capture_retries: int = 1,
                 power_limits_dpt: tuple[float, float] | None = None) -> None:
        if settle_s < 0 or lens_retries < 0 or capture_retries < 0:
            raise InputError("settle_s, lens_retries and capture_retries must be >= 0")
        self.settle_s = float(settle_s)
        self.lens_retries, self.capture_retries = int(lens_retries), int(capture_retries)
        self.power_limits_dpt = None if power_limits_dpt is None else (float(power_limits_dpt[0]), float(power_limits_dpt[1]))
        self.state = State.IDLE
        self.result = AFResult()
        self._gen: Gen | None = None
        self._pending: Command | None = None
        self._last_t = 0.0
        self._lens_power: float | None = None

    # -------------------------------------------------------------- public protocol
    def start(self, t_s: float | None = None) -> Command:
        """Begin a run and return the first command.

        Args:
            t_s: time of the focus request (s); default: the time of the first observation.
        """
        self.state = State.IDLE
        self.result = AFResult(method=self._initial_method(), t_start_s=t_s)
        self._gen = self._wrapped()
        return self._advance(None, first=True)

    def step(self, observation: Observation) -> Command:
        """Feed the observation that answers the last command; return the next command.

        Raises:
            ControllerError: the run has not started or has ended, or the observation does
                not answer the pending command.
        """
        if self._gen is None or isinstance(self._pending, Done):
            raise ControllerError("the controller is not running: call start()")
        if not isinstance(observation, Halt):
            self._check_answer(observation)
        return self._advance(observation)

    @property
    def done(self) -> bool:
        """``True`` once :class:`Done` has been returned."""
        return isinstance(self._pending, Done)

    # -------------------------------------------------------------- internals
    def _initial_method(self) -> str:
        return "dfd"

    def _check_answer(self, obs: Observation) -> None:
        cmd = self._pending
        ok = {
            SetPower: (LensAck, LensFault),
            Capture: (Frame, CaptureFault),
            Estimate: (Estimation, EstimateFault),
        }
        expected = ok.get(type(cmd), ())
        if not isinstance(obs, expected):
            raise ControllerError(f"{type(obs).__name__} does not answer {type(cmd).__name__} (state {self.state.value})")

    def _advance(self, obs: Observation | None, first: bool = False) -> Command:
        assert self._gen is not None
        cmd = next(self._gen) if first else self._gen.send(obs)  # type: ignore[arg-type]
        self._pending = cmd
        if isinstance(cmd, Done):
            self.state = State.DONE
        return cmd

    def _wrapped(self) -> Gen:
        try:
            yield from self._run()
        except Abort as exc:
            self.result.status = exc.status
            if exc.status == "failed":
                self.result.error = exc.reason
                log.error("autofocus failed: %s", exc.reason)
        yield Done(self.result)

    def _run(self) -> Gen:  # pragma: no cover - abstract
        raise NotImplementedError
        yield  # noqa: unreachable

    def _note_time(self, t: float) -> None:
        self._last_t = t
        if self.result.t_start_s is None:
            self.result.t_start_s = t

    def _halt(self, obs: Observation) -> None:
        if isinstance(obs, Halt):
            self._note_time(obs.t_s)
            raise Abort("halted", status="halted")

    def check_power(self, power_dpt: float) -> float:
        """Clamp ``power_dpt`` into the lens range, recording an explicit error if it was outside."""
        if self.power_limits_dpt is None:
            return power_dpt
        lo, hi = self.power_limits_dpt
        if lo <= power_dpt <= hi:
            return power_dpt
        clamped = min(max(power_dpt, lo), hi)
        self.result.clamped = True
        msg = f"in-focus power {power_dpt:.3f} dpt outside the lens range [{lo:.3f}, {hi:.3f}] dpt: clamped to {clamped:.3f} dpt"
        self.result.error = msg
        log.error(msg)
        return clamped

    # helper generators ---------------------------------------------------------
    def _set_power(self, power_dpt: float) -> Generator[Command, Observation, LensAck]:
        """``SetPower`` with bounded retries; aborts the run if the lens keeps failing."""
        last = ""
        for attempt in range(self.lens_retries + 1):
            self.result.lens_commands += 1
            obs = yield SetPower(power_dpt, self.settle_s)
            self._halt(obs)
            if isinstance(obs, LensAck):
                self._note_time(obs.t_s)
                self._lens_power = obs.power_dpt
                return obs
            assert isinstance(obs, LensFault)
            self._note_time(obs.t_s)
            last = obs.error
            log.warning("lens command %.3f dpt failed (attempt %d of %d): %s", power_dpt, attempt + 1,
                        self.lens_retries + 1, last)
        raise Abort(f"lens did not accept {power_dpt:.3f} dpt after {self.lens_retries + 1} attempts: {last}")

    def _capture(self, tag: str, then_power_dpt: float | None = None, light: str | None = None
                 ) -> Generator[Command, Observation, tuple[Frame, LensAck | None]]:
        """``Capture`` with bounded retries; a failed ``then`` move is retried with ``SetPower``."""
        last = ""
        for attempt in range(self.capture_retries + 1):
            if then_power_dpt is not None:
                self.result.lens_commands += 1
            obs = yield Capture(tag, then_power_dpt, self.settle_s, light)
            self._halt(obs)
            self.result.frames += 1 if isinstance(obs, Frame) else 0
            lens = obs.lens
            if isinstance(obs, CaptureFault):
                self._note_time(obs.t_s)
                last = obs.error
                log.warning("capture %r failed (attempt %d of %d): %s", tag, attempt + 1, self.capture_retries + 1, last)
                if isinstance(lens, LensAck):  # the lens moved anyway: do not move it again
                    self._lens_power = lens.power_dpt
                    then_power_dpt = None
                continue
            assert isinstance(obs, Frame)
            self._note_time(obs.t_ready_s)
            ack: LensAck | None = None
            if then_power_dpt is not None:
                if isinstance(lens, LensAck):
                    ack = lens
                    self._lens_power = lens.power_dpt
                else:  # the exposure-end command failed: retry it as a plain SetPower
                    reason = lens.error if isinstance(lens, LensFault) else "no answer"
                    log.warning("lens command %.3f dpt after %r failed: %s", then_power_dpt, tag, reason)
                    ack = yield from self._set_power(then_power_dpt)
            return obs, ack
        raise Abort(f"no frame for {tag!r} after {self.capture_retries + 1} attempts: {last}")


def drive(controller: StateMachine, plant: Plant, max_steps: int = 100_000) -> AFResult:
    """Run ``controller`` against ``plant`` until it is done and return its result.

    Hardware faults arrive as :class:`LensFault` / :class:`CaptureFault` /
    :class:`EstimateFault` observations (the plant converts exceptions); the controller
    decides to retry or fail. ``plant.should_halt()`` ends a continuous run.

    Raises:
        ControllerError: more than ``max_steps`` commands (a controller bug).
    """
    cmd = controller.start(plant.now())
    for _ in range(max_steps):
        if isinstance(cmd, Done):
            return cmd.result
        if plant.should_halt():
            cmd = controller.step(Halt(plant.now()))
            continue
        if isinstance(cmd, SetPower):
            obs: Observation = plant.set_power(cmd)
        elif isinstance(cmd, Capture):
            obs = plant.capture(cmd)
        elif isinstance(cmd, Estimate):
            obs = plant.estimate(cmd)
        else:  # pragma: no cover
            raise ControllerError(f"unknown command {cmd!r}")
        cmd = controller.step(obs)
    raise ControllerError(f"controller did not finish within {max_steps} commands")
