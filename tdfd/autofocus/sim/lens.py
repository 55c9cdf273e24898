r"""The bench's lens: the Lens Driver 4 emulator on a real pty, driven through the real driver on simulated time."""

from __future__ import annotations

import logging
from typing import Any

from ..lens_command import command_lens
from .clock import SimClock
from .port import BAUD, TimedPort

__all__ = ["EmulatedLens", "BENCH_TEMPERATURE_LIMITS_C"]

log = logging.getLogger(__name__)

#: temperature limits (°C) sent before focal-power mode on the bench: the emulated
#: EL-10-30-C reaches +3.55 dpt at 25 °C, enough for 0.3 m (3.33 dpt).
BENCH_TEMPERATURE_LIMITS_C = (15.0, 25.0)


class EmulatedLens:
    """The lens emulator on a pty, opened through the real :class:`~tdfd.driver.OptotuneLens`.

    Args:
        clock: the bench clock (the emulator's clock too).
        settling_time_s: the emulator's 1 % settling time (s).
        timeout_s: the driver's reply timeout (s).
        retries: the driver's retries per query.
        temperature_limits_c: sent before switching to focal-power mode.
        temperature_c: the emulated lens temperature (°C).

    Attributes:
        server: the :class:`~tdfd.driver.EmulatorServer` (``.device`` is the model).
        lens: the connected driver, in focal-power mode.
        power_limits_dpt: ``(min, max)`` focal power the driver reported.
    """

    def __init__(self, clock: SimClock, settling_time_s: float = 0.015, timeout_s: float = 0.1, retries: int = 2,
                 temperature_limits_c: tuple[float, float] = BENCH_TEMPERATURE_LIMITS_C,
                 temperature_c: float = 22.0) -> None:
        import serial

        from ...driver import EmulatorServer, OptotuneLens

        self.clock = clock
        self.server = EmulatorServer(clock=clock, settling_time_s=settling_time_s, temperature_c=temperature_c).start()
        try:
            raw = serial.serial_for_url(self.server.port, baudrate=BAUD, timeout=timeout_s, write_timeout=1.0)
            self.port = TimedPort(raw, clock, self.server.device)
            self.lens = OptotuneLens(self.port, timeout_s=timeout_s, retries=retries, owns_port=True)
            self.lens.connect(handshake=True)
            limits = self.lens.set_focal_power_mode(temperature_limits_c)
        except BaseException:
            self.close()
            raise
        self.power_limits_dpt = (float(limits.min_dpt), float(limits.max_dpt))
        log.info("bench lens on %s: focal-power range %.3f to %.3f dpt", self.server.port, *self.power_limits_dpt)

    def set_faults(self, faults: Any | None) -> None:
        """Turn the emulator's fault injection on (a :class:`~tdfd.driver.Faults`) or off (``None``)."""
        from ...driver import Faults

        self.server.faults = faults if faults is not None else Faults()

    def optical_power_at(self, t_s: float) -> float:
        """The lens's optical focal power at simulated time ``t_s`` (dpt)."""
        return float(self.server.device.focal_power_at(t_s))

    def command(self, power_dpt: float, verify: bool = True) -> float:
        """Set the focal power and read the set-point back; return the arrival time of the command (s).

        Raises:
            DriverError: the driver failed (after its retries), or the read-back disagrees twice.
        """
        return command_lens(self.lens, power_dpt, verify=verify, clock=self.clock.now)

    def close(self) -> None:
        """Close the driver and stop the emulator. Idempotent."""
        lens = getattr(self, "lens", None)
        if lens is not None:
            lens.close()
        else:
            port = getattr(self, "port", None)
            if port is not None:
                port.close()
        self.server.stop()
