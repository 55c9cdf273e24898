"""Tests against a real Optotune Lens Driver 4: run with ``pytest --ecvfl-port PORT``.

Skipped otherwise (see ``tests/conftest.py``). They move the lens only a little (±20 mA,
small focal-power steps inside the reported range) and leave it in current mode at 0 mA.
They never write EEPROM (no ``Cw..`` commands) and never send ``RESET``.
"""

from __future__ import annotations

import math
import time

import pytest

from tdfd.driver import Mode, OptotuneLens, StatusFlags
from tdfd.errors import LensModeError, LensRangeError

pytestmark = pytest.mark.hardware


@pytest.fixture(scope="module")
def lens(request: pytest.FixtureRequest):  # noqa: ANN201
    port = request.config.getoption("--ecvfl-port")
    with OptotuneLens.open(port, timeout_s=0.5, retries=2) as lens:
        try:
            yield lens
        finally:
            try:
                lens.set_current_mode()
                lens.set_current_ma(0.0)
            except Exception:  # noqa: BLE001 - best effort on the way out
                pass


def test_identity(lens: OptotuneLens) -> None:
    assert lens.firmware_type in {"A", "B", "C", "E", "F"}
    version = lens.get_firmware_version()
    assert version.major >= 1
    assert 0 < lens.max_current_ma <= 400
    lower, upper = lens.current_limits_ma
    assert -lens.max_current_ma - 0.1 <= lower < upper <= lens.max_current_ma + 0.1
    serial_number = lens.get_serial_number()
    device_id = lens.get_device_id()
    assert isinstance(serial_number, str) and isinstance(device_id, str)
    print(f"firmware {lens.firmware_type} {version}, lens {serial_number!r}, device {device_id!r}")


def test_monitoring(lens: OptotuneLens) -> None:
    temperature = lens.get_temperature_c()
    assert temperature is None or -20.0 < temperature < 80.0
    status = lens.get_status()
    assert len(status.raw) == 4
    assert StatusFlags.NOT_ALL_HARDWARE_AVAILABLE not in status.flags
    assert isinstance(lens.get_mode(), Mode)


def test_current_round_trip(lens: OptotuneLens) -> None:
    lens.set_current_mode()
    lsb = lens.max_current_ma / 4095
    for current_ma in (20.0, -20.0, 0.0):
        lens.set_current_ma(current_ma)
        assert lens.get_current_ma() == pytest.approx(current_ma, abs=lsb)
    with pytest.raises(LensRangeError):
        lens.set_current_ma(lens.max_current_ma * 1.5)


def test_focal_power_mode(lens: OptotuneLens) -> None:
    if lens.firmware_type not in {"A", "B", "C", "E"}:
        pytest.skip(f"no documented focal-power encoding for firmware type {lens.firmware_type}")
    limits = lens.set_focal_power_mode((20.0, 40.0))
    assert limits.min_dpt < limits.max_dpt
    assert lens.get_mode() is Mode.FOCAL_POWER
    middle = round((limits.min_dpt + limits.max_dpt) / 2, 2)
    for power_dpt in (middle, middle + 0.25 if middle + 0.25 <= limits.max_dpt else middle - 0.25):
        lens.set_focal_power_dpt(power_dpt)
        time.sleep(0.05)  # > 15 ms settling
        assert lens.get_focal_power_dpt() == pytest.approx(power_dpt, abs=0.01)
    with pytest.raises(LensRangeError):
        lens.set_focal_power_dpt(limits.max_dpt + 1.0)
    with pytest.raises(LensModeError):
        lens.set_current_ma(0.0)
    lens.set_current_mode()
    assert lens.get_mode() is Mode.CURRENT
    lens.set_current_ma(0.0)


def test_verified_set_points_read_back(lens: OptotuneLens) -> None:
    """Verified sets read back within one raw step (how exact Ar/PrDA are is not documented)."""
    lens.set_current_mode()
    for current_ma in (15.0, -15.0, 0.0):
        lens.set_current_ma(current_ma, verify=True)
        assert lens.current_setpoint_ma == pytest.approx(current_ma, abs=lens.max_current_ma / 4095)
    if lens.firmware_type in {"A", "B", "C", "E"}:
        limits = lens.set_focal_power_mode((20.0, 40.0))
        middle = round((limits.min_dpt + limits.max_dpt) / 2, 2)
        lens.set_focal_power_dpt(middle, verify=True)
        assert lens.focal_power_setpoint_dpt == pytest.approx(middle, abs=0.0051)
        lens.set_current_mode()
    lens.set_current_ma(0.0, verify=True)


def test_handshake_zeroes_the_current(lens: OptotuneLens) -> None:
    lens.set_current_mode()
    lens.set_current_ma(10.0)
    lens.handshake()
    assert math.isclose(lens.get_current_ma(), 0.0, abs_tol=lens.max_current_ma / 4095)


def test_query_rate(lens: OptotuneLens) -> None:
    n = 50
    t0 = time.monotonic()
    for _ in range(n):
        lens.get_current_ma()
    per_query_s = (time.monotonic() - t0) / n
    print(f"{per_query_s * 1e3:.2f} ms per query")
    assert per_query_s < 0.05
