r"""The bench plant: executes controller commands on the emulated lens, the virtual camera and the estimator,
charging simulated time for each."""

from __future__ import annotations

import time
from typing import Callable

import numpy as np

from ...errors import InputError, TdfdError
from ...light.guard import LightGuard, exposure
from ..interfaces import Estimator, run_estimator
from ..messages import Capture, CaptureFault, Estimate, Estimation, EstimateFault, Frame, LensAck, LensFault, SetPower
from .camera import VirtualCamera
from .clock import SimClock
from .lens import EmulatedLens

__all__ = ["BenchPlant"]


class BenchPlant:
    """Executes controller commands on the bench (implements :class:`~tdfd.autofocus.interfaces.Plant`).

    Args:
        clock: simulated clock.
        lens: the emulated lens.
        camera: the virtual camera.
        estimator: the depth estimator.
        compute_s: ``"measured"`` (charge the estimator's wall time) or a fixed time per
            estimate in seconds.
        halt_at_s: simulated time at which :meth:`should_halt` turns true (continuous mode).
        on_time: called with the simulated time whenever it advances past a frame
            (continuous mode moves the target with it).
        light_guard: the guarded assist light; a lit ``Capture`` has it on from the
            exposure's start to its end only (``None``: no light, a lit capture fails).
    """

    def __init__(self, clock: SimClock, lens: EmulatedLens, camera: VirtualCamera, estimator: Estimator | None,
                 compute_s: float | str = "measured", halt_at_s: float | None = None,
                 on_time: Callable[[float], None] | None = None, light_guard: LightGuard | None = None) -> None:
        self.clock, self.lens, self.camera, self.estimator = clock, lens, camera, estimator
        self.light_guard = light_guard
        if compute_s != "measured" and not (isinstance(compute_s, (int, float)) and compute_s >= 0):
            raise InputError(f"compute_s must be 'measured' or a time >= 0 (s), got {compute_s!r}")
        self.compute_s = compute_s
        self.halt_at_s, self.on_time = halt_at_s, on_time
        self.lens_ready_s = clock.now()
        self.compute_times_s: list[float] = []
        self.frames: list[tuple[float, float, str]] = []  # (t_start, optical power, tag)

    def now(self) -> float:
        return self.clock.now()

    def should_halt(self) -> bool:
        return self.halt_at_s is not None and self.clock.now() >= self.halt_at_s

    def _command(self, power_dpt: float, settle_s: float) -> LensAck | LensFault:
        t_issue = self.clock.now()
        try:
            arrived = self.lens.command(power_dpt)
        except TdfdError as exc:
            return LensFault(power_dpt, f"{type(exc).__name__}: {exc}", self.clock.now())
        self.lens_ready_s = arrived + settle_s
        return LensAck(power_dpt, t_issue, self.lens_ready_s)

    def set_power(self, cmd: SetPower) -> LensAck | LensFault:
        return self._command(cmd.power_dpt, cmd.settle_s)

    def capture(self, cmd: Capture) -> Frame | CaptureFault:
        timing = self.camera.timing
        start = timing.next_start(max(self.clock.now(), self.lens_ready_s), self.camera.last_start_s)
        self.clock.advance_to(start)
        if self.on_time is not None:
            self.on_time(start)
        end = start + timing.exposure_s
        try:
            with exposure(self.light_guard, cmd.light, timing.exposure_s):
                image, optical = self.camera.expose(start)
                self.clock.advance_to(end)
        except TdfdError as exc:  # the light refused or failed: it is off, no frame
            return CaptureFault(cmd.tag, f"{type(exc).__name__}: {exc}", self.clock.now())
        self.frames.append((start, optical, cmd.tag))
        lens = None
        if cmd.then_power_dpt is not None:
            lens = self._command(cmd.then_power_dpt, cmd.settle_s)
        ready = end + timing.readout_s
        self.clock.advance_to(ready)
        return Frame(image, float(optical), start, end, max(ready, self.clock.now()), cmd.tag, lens=lens)

    def estimate(self, cmd: Estimate) -> Estimation | EstimateFault:
        if self.estimator is None:
            return EstimateFault("no depth estimator", self.clock.now())
        t0 = time.perf_counter()
        try:
            depth, conf = run_estimator(self.estimator, cmd)
        except TdfdError as exc:
            return EstimateFault(f"{type(exc).__name__}: {exc}", self.clock.now())
        wall = time.perf_counter() - t0
        charged = wall if self.compute_s == "measured" else float(self.compute_s)
        self.compute_times_s.append(wall)
        self.clock.advance(charged)
        return Estimation(np.asarray(depth), np.asarray(conf), self.estimator.tile, self.estimator.stride,
                          t_s=self.clock.now(), elapsed_s=charged)
