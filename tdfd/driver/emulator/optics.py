"""The emulated lens's optics: calibration, first-order settling and temperature.

Documented assumptions, not manufacturer data:

* Calibration (:class:`Calibration`): at the reference temperature (25 °C) the focal
  power is ``-1.5 dpt + current_mA × 5/290 dpt/mA`` (−1.5 dpt at 0 mA, +3.5 dpt at
  290 mA, as an EL-10-30-C); without compensation it drops 0.067 dpt/°C above 25 °C.
* Settling: first order with time constant ``settling_time_s / ln(100)``: a step is
  within 1 % of its size ``settling_time_s`` (default 15 ms) after the command arrives.
* A target is either *compensated* (focal-power mode: the driver corrects the thermal
  drift) or not (current mode: the unfiltered drift adds to the filtered power).

:class:`LensOptics` keeps the set-point history, so the optical power at any past time is
exact for the model. It holds no clock: every method takes the time.
"""

from __future__ import annotations

import bisect
import logging
import math
from dataclasses import dataclass

from .. import protocol as p

__all__ = ["Calibration", "LensOptics", "reachable_focal_power_raw", "DEFAULT_SETTLING_TIME_S"]

log = logging.getLogger(__name__)

#: time for a focal-power step to settle within 1 %, seconds (EL-10-30: about 15 ms).
DEFAULT_SETTLING_TIME_S = 0.015
_HISTORY_MAX = 20000
_TYPE_A_RANGE_RAW = (0, 4095)  # −5 … +15.475 dpt


@dataclass(frozen=True)
class Calibration:
    """Linear focal power of the emulated lens versus current and temperature.

    ``power = offset_dpt + slope_dpt_per_ma × current_mA
    + temperature_coefficient_dpt_per_c × (temperature_C − reference_temperature_c)``.

    Examples:
        >>> c = Calibration()
        >>> c.power_dpt(0.0), round(c.power_dpt(290.0), 6)
        (-1.5, 3.5)
        >>> round(c.current_ma(c.power_dpt(123.0, 35.0), 35.0), 9)
        123.0
    """

    offset_dpt: float = -1.5
    slope_dpt_per_ma: float = 5.0 / 290.0
    temperature_coefficient_dpt_per_c: float = -0.067
    reference_temperature_c: float = 25.0

    def drift_dpt(self, temperature_c: float) -> float:
        """Power change from the reference temperature at fixed current, dpt."""
        return self.temperature_coefficient_dpt_per_c * (temperature_c - self.reference_temperature_c)

    def power_dpt(self, current_ma: float, temperature_c: float | None = None) -> float:
        """Focal power at ``current_ma`` and ``temperature_c`` (default: reference), dpt."""
        t = self.reference_temperature_c if temperature_c is None else temperature_c
        return self.offset_dpt + self.slope_dpt_per_ma * current_ma + self.drift_dpt(t)

    def current_ma(self, power_dpt: float, temperature_c: float | None = None) -> float:
        """Current giving ``power_dpt`` at ``temperature_c`` (default: reference), mA."""
        t = self.reference_temperature_c if temperature_c is None else temperature_c
        return (power_dpt - self.offset_dpt - self.drift_dpt(t)) / self.slope_dpt_per_ma




def reachable_focal_power_raw(
    calibration: Calibration,
    current_limits_ma: tuple[float, float],
    temperature_limits_c: tuple[float, float],
    encoding: str,
) -> tuple[int, int]:
    """The focal-power range (raw, ``encoding``'s units) reachable at every temperature between the limits.

    With currents inside the software limits: the lower end at the lower current and lower
    temperature, the upper end at the upper current and upper temperature (the drift is
    negative); type A clips to its encodable −5…+15.475 dpt.

    Examples:
        >>> reachable_focal_power_raw(Calibration(), (-292.84, 292.84), (25.0, 25.0), "A")
        (0, 1709)
    """
    offset = p.FOCAL_POWER_FIRMWARE_TYPES[encoding]
    lo = math.ceil((calibration.power_dpt(current_limits_ma[0], temperature_limits_c[0]) + offset) * 200.0 - 1e-9)
    hi = math.floor((calibration.power_dpt(current_limits_ma[1], temperature_limits_c[1]) + offset) * 200.0 + 1e-9)
    if encoding == "A":
        lo, hi = max(lo, _TYPE_A_RANGE_RAW[0]), min(hi, _TYPE_A_RANGE_RAW[1])
    lo, hi = max(lo, -0x8000), min(hi, 0x7FFF)
    return (lo, max(lo, hi))


class LensOptics:
    """Optical focal power and temperature of the emulated lens over time.

    Not thread-safe on its own: :class:`~tdfd.driver.emulator.Emulator` holds its lock
    around every call.

    Args:
        calibration: focal power versus current and temperature.
        settling_time_s: time for a step to settle within 1 %, seconds.
        t0: the time of the initial state, seconds.
        temperature_c: the initial lens temperature, °C.
    """

    def __init__(self, calibration: Calibration, settling_time_s: float, t0: float, temperature_c: float) -> None:
        self.calibration = calibration
        self.settling_time_s = float(settling_time_s)
        self._temperature = (t0, float(temperature_c), float(temperature_c), 0.0)  # t0, T0, target, tau
        target = calibration.power_dpt(0.0)
        self._seg_t: list[float] = [t0]
        self._seg: list[tuple[float, float, float, bool]] = [(t0, target, target, False)]  # t0, p0, target, compensated

    @property
    def time_constant_s(self) -> float:
        """First-order time constant of the focal power, seconds (settling_time_s / ln 100)."""
        return self.settling_time_s / math.log(100.0)

    def target_at(self, t: float) -> float:
        """The power the lens settles to from the last command on, drift at time ``t`` included, dpt."""
        _, _, target, compensated = self._seg[-1]
        return target + (0.0 if compensated else self.calibration.drift_dpt(self.temperature_at(t)))

    def focal_power_at(self, t: float) -> float:
        """The optical focal power at time ``t``, dpt.

        Exact for the first-order model: past times use the recorded set-point history
        (the last 20000 changes), times after the last command extrapolate the settling.
        Before the first record it is the initial power.
        """
        k = bisect.bisect_right(self._seg_t, t) - 1
        if k < 0:
            t0, p0, _, compensated = self._seg[0]
            filtered = p0
        else:
            t0, p0, target, compensated = self._seg[k]
            filtered = self._settle(p0, target, t - t0)
        return filtered + (0.0 if compensated else self.calibration.drift_dpt(self.temperature_at(t)))

    def _settle(self, p0: float, target: float, dt: float) -> float:
        tau = self.time_constant_s
        if tau <= 0.0:
            return target
        return target + (p0 - target) * math.exp(-max(dt, 0.0) / tau)

    def retarget(self, t: float, target: float, compensated: bool) -> None:
        """From time ``t`` on, settle towards ``target`` (dpt; ``compensated``: no thermal drift)."""
        last_t = self._seg_t[-1]
        if t < last_t:
            log.warning("emulator clock went backwards (%.6f < %.6f): restarting the focal-power history", t, last_t)
            t0, p0, old_target, _ = self._seg[-1]
            now_p = self._settle(p0, old_target, 0.0)
            self._seg_t, self._seg = [t], [(t, now_p, now_p, compensated)]
            last_t = t
        k = len(self._seg) - 1
        t0, p0, old_target, _ = self._seg[k]
        p_now = self._settle(p0, old_target, t - t0)
        self._seg_t.append(t)
        self._seg.append((t, p_now, target, compensated))
        if len(self._seg) > _HISTORY_MAX:
            del self._seg_t[: _HISTORY_MAX // 2]
            del self._seg[: _HISTORY_MAX // 2]

    def temperature_at(self, t: float) -> float:
        """Lens temperature at time ``t``, °C (first-order approach to the last target)."""
        t0, temp0, target, tau = self._temperature
        if t < t0:
            return temp0
        if tau <= 0.0:
            return target
        return target + (temp0 - target) * math.exp(-(t - t0) / tau)

    def set_temperature(self, t: float, temperature_c: float, time_constant_s: float = 0.0) -> None:
        """From time ``t`` on, move the temperature towards ``temperature_c`` (°C) with ``time_constant_s``."""
        self._temperature = (t, self.temperature_at(t), float(temperature_c), float(time_constant_s))
