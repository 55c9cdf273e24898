r"""Frame timing of the virtual camera: frame rate, exposure, read-out, hardware trigger or free-running."""

from __future__ import annotations

import math
from dataclasses import dataclass

from ...errors import InputError

__all__ = ["CameraTiming"]


@dataclass(frozen=True)
class CameraTiming:
    """Frame timing of the virtual camera.

    Attributes:
        frame_period_s: shortest time between exposure starts (1/60 s: 60 fps).
        exposure_s: exposure time (s).
        readout_s: from the end of the exposure until the frame is on the host (s).
        trigger: ``"hardware"`` (exposure starts when the controller asks, at most one
            per frame period) or ``"free"`` (exposures start only on the free-running
            frame boundaries ``phase_s + k * frame_period_s``).
        phase_s: phase of the free-running frame clock (s).
    """

    frame_period_s: float = 1.0 / 60.0
    exposure_s: float = 0.002
    readout_s: float = 0.003
    trigger: str = "hardware"
    phase_s: float = 0.0

    def __post_init__(self) -> None:
        if self.trigger not in ("hardware", "free"):
            raise InputError(f"trigger must be 'hardware' or 'free', got {self.trigger!r}")
        if not (self.frame_period_s > 0 and 0 < self.exposure_s <= self.frame_period_s and self.readout_s >= 0):
            raise InputError("need frame_period_s > 0, 0 < exposure_s <= frame_period_s, readout_s >= 0")

    def next_start(self, earliest_s: float, last_start_s: float | None) -> float:
        """The first allowed exposure start at or after ``earliest_s`` (s)."""
        t = earliest_s if last_start_s is None else max(earliest_s, last_start_s + self.frame_period_s)
        if self.trigger == "free":
            k = math.ceil((t - self.phase_s) / self.frame_period_s - 1e-9)
            t = self.phase_s + k * self.frame_period_s
        return t
