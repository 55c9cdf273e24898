"""Focal-power mode of the Optotune Lens Driver 4 (:class:`FocalPowerMode`, mixed into
:class:`~tdfd.driver.lens.OptotuneLens`): temperature limits (``PwTA``), the switch to
focal-power mode (``MwCA``), and the focal-power set-point (``PwDA``, read back with
``PrDA``), range-checked against the limits of the ``MCA`` reply.

The mixin uses the device class's exchanges (``_lock``, ``_query``, ``_set``,
``_known_mode``, ``get_firmware_type``) and its state (``mode``,
``verify``, ``firmware_type``, the set-points and limits); see
:class:`~tdfd.driver.lens.OptotuneLens` for their meaning.
"""

from __future__ import annotations

import logging
import math

from ..errors import LensModeError, LensRangeError, ProtocolError
from . import protocol as p
from .protocol import FocalPowerLimits, Mode, StatusFlags

__all__ = ["FocalPowerMode", "DEFAULT_TEMPERATURE_LIMITS_C"]

log = logging.getLogger(__name__)

#: (lower, upper) temperature limits in °C sent before switching to focal-power mode.
DEFAULT_TEMPERATURE_LIMITS_C = (20.0, 40.0)


class FocalPowerMode:
    """The focal-power commands of :class:`~tdfd.driver.lens.OptotuneLens`."""

    def set_temperature_limits_c(self, lower_c: float, upper_c: float) -> FocalPowerLimits:
        """Send the temperature limits for focal-power mode (``PwTA``).

        Args:
            lower_c: lower temperature limit, °C.
            upper_c: upper temperature limit, °C.

        Returns:
            The focal-power range the driver guarantees within these limits (``PT`` reply).

        Raises:
            LensRangeError: non-finite limits or ``lower_c >= upper_c``.
        """
        if not (math.isfinite(lower_c) and math.isfinite(upper_c)) or lower_c >= upper_c:
            raise LensRangeError(f"temperature limits must be finite with lower < upper, got [{lower_c}, {upper_c}] °C")
        with self._lock:
            frame = p.encode_set_temperature_limits(p.temperature_c_to_raw(upper_c), p.temperature_c_to_raw(lower_c))
            reply = self._query(frame)
            limits = p.parse_focal_power_limits(reply, self._firmware())
            self.temperature_limits_c = (float(lower_c), float(upper_c))
            if limits.status:
                log.warning("temperature limits reply status: %s", limits.status)
            return limits

    def set_focal_power_mode(
        self, temperature_limits_c: tuple[float, float] = DEFAULT_TEMPERATURE_LIMITS_C
    ) -> FocalPowerLimits:
        """Switch to focal-power mode: temperature limits (``PwTA``) first, then ``MwCA``.

        Args:
            temperature_limits_c: (lower, upper) temperature limits, °C.

        Returns:
            The focal-power limits of the ``MCA`` reply; later set-points are checked
            against them (also in :attr:`focal_power_limits`).
        """
        with self._lock:
            self.set_temperature_limits_c(*temperature_limits_c)
            reply = self._query(p.encode_focal_power_mode())
            limits = p.parse_focal_power_limits(reply, self._firmware())
            if limits.min_dpt > limits.max_dpt:
                raise ProtocolError(f"focal-power limits reversed: {limits}")
            self.focal_power_limits = limits
            self.mode = Mode.FOCAL_POWER
            self.current_setpoint_ma = None
            self.focal_power_setpoint_dpt = None  # the driver keeps a set-point of its own choosing
            if limits.status & StatusFlags.NO_TEMPERATURE_LIMITS:
                log.warning("the driver reports no temperature limits after PwTA")
            log.info("focal-power mode: %.3f to %.3f dpt", limits.min_dpt, limits.max_dpt)
            return limits


    def _firmware(self) -> str:
        return self.firmware_type if self.firmware_type is not None else self.get_firmware_type()

    def set_focal_power_dpt(self, power_dpt: float, *, verify: bool | None = None) -> None:
        """Set the focal power (``PwDA``; the driver sends no reply).

        Args:
            power_dpt: focal power, dioptres, within :attr:`focal_power_limits`.
            verify: read the focal power back (``PrDA``) and re-send a command the device
                did not take; ``None``: :attr:`verify`.

        Raises:
            LensModeError: not in focal-power mode (call :meth:`set_focal_power_mode`),
                also when the mode read again after a lost reply is another one.
            LensRangeError: not finite or outside the limits of the ``MCA`` reply.
            UnsupportedFirmwareError: a firmware type without documented encoding.
            LensStateError: verified, and the set-point still reads back otherwise after
                ``1 + retries`` sends.
        """
        verify = self.verify if verify is None else bool(verify)
        with self._lock:
            mode = self._known_mode()
            limits = self.focal_power_limits
            if mode != Mode.FOCAL_POWER or limits is None:
                raise LensModeError(
                    "set_focal_power_dpt needs focal-power mode with known limits "
                    f"(mode {mode.name if mode else 'unknown'}): call set_focal_power_mode() first"
                )
            firmware = self._firmware()
            raw = p.focal_power_dpt_to_raw(power_dpt, firmware)
            lo = p.focal_power_dpt_to_raw(limits.min_dpt, firmware)
            hi = p.focal_power_dpt_to_raw(limits.max_dpt, firmware)
            if not lo <= raw <= hi:
                raise LensRangeError(
                    f"focal power {power_dpt} dpt outside the driver's limits [{limits.min_dpt:.3f}, {limits.max_dpt:.3f}] dpt"
                )
            self.focal_power_setpoint_dpt = None  # unknown until sent (and, if asked, read back)
            raw = self._set(p.encode_set_focal_power(raw), p.encode_get_focal_power(), raw, Mode.FOCAL_POWER,
                            "focal-power", verify)
            self.focal_power_setpoint_dpt = p.focal_power_raw_to_dpt(raw, firmware)

    def get_focal_power_dpt(self) -> float:
        """The focal power (``PrDA``), dioptres."""
        raw = p.unpack_i16(self._query(p.encode_get_focal_power()).data)
        return p.focal_power_raw_to_dpt(raw, self._firmware())
