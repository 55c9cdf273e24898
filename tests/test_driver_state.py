"""The driver's view of the lens is verified, not assumed (issue 22, "Driver state").

Each test reproduces one way the driver and the device used to part silently: a stale
reply taken as the answer to a later query, a mode change whose replies were lost, a set
command the device rejected, an ``E 3`` answer to a corrupted prefix, and a reply whose
payload holds a shorter complete frame. Reference frames are typed in from the protocol
facts (tests/driver_frames.py), never produced by the encoder under test.
"""

from __future__ import annotations

import time

import pytest

from tests.driver_frames import cmd, i16, rep
from tdfd.driver import Emulator, EmulatorSerial, Faults, Mode, OptotuneLens
from tdfd.errors import DeviceErrorReply, DriverError, LensModeError, LensTimeoutError

TIMEOUT_S = 0.02
MAX_MA = 292.84
ONE_RAW_MA = MAX_MA / 4095


class CorruptingPort(EmulatorSerial):
    """An in-process emulator port that corrupts chosen commands on their way to the device.

    ``corrupt[name] = [(index, xor), ...]`` corrupts the next commands starting with
    ``name``, one entry each, by XOR-ing the byte at ``index``.
    """

    def __init__(self, device: Emulator, **kwargs) -> None:  # noqa: ANN003
        super().__init__(device, **kwargs)
        self.corrupt: dict[bytes, list[tuple[int, int]]] = {}
        self.corrupted: list[bytes] = []

    def write(self, data: bytes) -> int:
        data = bytes(data)
        for name, plan in self.corrupt.items():
            if data.startswith(name) and plan:
                index, xor = plan.pop(0)
                bad = bytearray(data)
                bad[index] ^= xor
                data = bytes(bad)
                self.corrupted.append(data)
                break
        return super().write(data)


class DropRepliesStartingWith(Faults):
    """Drop every reply that starts with one of ``prefixes`` (the command still acts)."""

    def __init__(self, *prefixes: bytes) -> None:
        super().__init__()
        self.prefixes = prefixes

    def apply(self, reply: bytes) -> tuple[bytes | None, float]:
        if reply.startswith(self.prefixes):
            self.injected += 1
            return None, 0.0
        return super().apply(reply)


def connected(device: Emulator | None = None, *, retries: int = 2, port_cls=EmulatorSerial, **lens_kwargs):  # noqa: ANN001, ANN003, ANN201
    device = device if device is not None else Emulator()
    port = port_cls(device, timeout=TIMEOUT_S)
    lens = OptotuneLens(port, timeout_s=TIMEOUT_S, retries=retries, **lens_kwargs).connect()
    return lens, port, device


# --------------------------------------------------------------------------- stale replies


def settle_and_check(lens: OptotuneLens, dev: Emulator, expected_ma: float) -> None:
    """After the late replies are long due, the driver reads the device's current exactly."""
    time.sleep(6 * TIMEOUT_S)
    assert lens.get_current_ma() == pytest.approx(expected_ma, abs=ONE_RAW_MA)
    assert dev.current_ma == pytest.approx(expected_ma, abs=ONE_RAW_MA)


def test_a_reply_arriving_after_its_timeout_never_answers_a_later_query() -> None:
    lens, port, dev = connected(retries=0)
    port.faults = Faults(late=1.0, late_s=1.5 * TIMEOUT_S, limit=1)
    with pytest.raises(LensTimeoutError):
        lens.get_current_ma()  # its 'A' reply (0 mA) is still on its way
    port.faults = Faults()
    try:
        lens.set_current_ma(100.0)
        # the late 'A' reply arrives while this query waits: never take it as the answer
        assert lens.get_current_ma() == pytest.approx(100.0, abs=ONE_RAW_MA)
    except LensTimeoutError:
        pass  # reported: the driver could not resynchronise in time
    lens.set_current_ma(100.0)
    settle_and_check(lens, dev, 100.0)


def test_a_late_reply_to_a_retried_query_is_not_left_for_the_next_one() -> None:
    lens, port, dev = connected(retries=1)
    # both attempts' replies are late: the first attempt's answers the retry, and the
    # retry's own reply is still on its way when the next query with prefix 'A' is sent
    port.faults = Faults(late=1.0, late_s=1.5 * TIMEOUT_S, limit=2)
    try:
        assert lens.get_current_ma() == 0.0
    except LensTimeoutError:
        pass
    port.faults = Faults()
    try:
        lens.set_current_ma(-50.0)
        assert lens.get_current_ma() == pytest.approx(-50.0, abs=ONE_RAW_MA)
    except LensTimeoutError:
        pass
    lens.set_current_ma(-50.0)
    settle_and_check(lens, dev, -50.0)


def test_the_fence_discards_a_late_reply_with_the_same_prefix() -> None:
    from tests.test_driver_lens import FENCE, connect_script, scripted

    get = cmd(b"Ar\x00\x00")
    stale = rep(b"A", i16(0))  # the late answer to the timed-out query: 0 mA
    lens, port = scripted(
        connect_script()
        + [
            (get, b""),  # times out (retries=0)
            (FENCE[0], stale + FENCE[1]),  # the late reply arrives before the fence's own
            (cmd(b"Aw" + i16(1398)), b""),  # 100 mA of 292.84 mA
            (get, rep(b"A", i16(1398))),
        ],
        retries=0,
    )
    lens.connect()
    with pytest.raises(LensTimeoutError):
        lens.get_current_ma()
    lens.set_current_ma(100.0)
    assert lens.get_current_ma() == pytest.approx(1398 * MAX_MA / 4095)
    port.assert_done()
    assert lens.transport.fences == 1 and not lens.transport.unsynchronised


# --------------------------------------------------------------------------- mode desync


def test_lost_mode_change_replies_are_followed_by_reading_the_mode() -> None:
    lens, port, dev = connected()
    port.faults = DropRepliesStartingWith(b"MCA")  # MwCA acts, every reply is lost
    with pytest.raises(LensTimeoutError):
        lens.set_focal_power_mode()
    assert dev.mode is Mode.FOCAL_POWER
    assert lens.mode in (None, Mode.FOCAL_POWER)  # unknown, never the old mode
    port.faults = Faults()
    with pytest.raises(LensModeError):
        lens.set_current_ma(100.0)  # the device would ignore Aw in focal-power mode
    assert lens.mode is Mode.FOCAL_POWER


def test_lost_current_mode_replies_are_followed_by_reading_the_mode() -> None:
    lens, port, dev = connected()
    lens.set_focal_power_mode()
    port.faults = DropRepliesStartingWith(b"MDA")
    with pytest.raises(LensTimeoutError):
        lens.set_current_mode()
    assert dev.mode is Mode.CURRENT
    port.faults = Faults()
    with pytest.raises(LensModeError):
        lens.set_focal_power_dpt(1.0)  # PwDA would be ignored in current mode
    assert lens.mode is Mode.CURRENT
    lens.set_current_ma(20.0)
    assert dev.current_ma == pytest.approx(20.0, abs=ONE_RAW_MA)


def test_lost_handshake_reply_is_followed_by_reading_the_mode() -> None:
    lens, port, dev = connected()
    lens.set_focal_power_mode()
    port.faults = DropRepliesStartingWith(b"Ready")
    with pytest.raises(LensTimeoutError):
        lens.handshake()  # Start acted: current mode, 0 mA
    port.faults = Faults()
    with pytest.raises(LensModeError):
        lens.set_focal_power_dpt(1.0)
    assert lens.mode is Mode.CURRENT == dev.mode


# --------------------------------------------------------------------------- rejected set commands


@pytest.mark.parametrize("index", [2, 3, 4, 5])  # a value or CRC byte: the device answers E 1
def test_a_rejected_set_current_is_resent_when_verified(index: int) -> None:
    lens, port, dev = connected(port_cls=CorruptingPort)
    port.corrupt[b"Aw"] = [(index, 0x10)]
    lens.set_current_ma(100.0, verify=True)
    assert port.corrupted, "the fault was not injected"
    assert dev.current_ma == pytest.approx(100.0, abs=ONE_RAW_MA)
    assert lens.current_setpoint_ma == pytest.approx(dev.current_ma)


def test_a_rejected_set_current_is_an_error_when_it_stays_rejected() -> None:
    lens, port, dev = connected(port_cls=CorruptingPort, retries=1)
    port.corrupt[b"Aw"] = [(3, 0x01)] * 5
    with pytest.raises(DriverError):
        lens.set_current_ma(100.0, verify=True)
    assert dev.current_ma == 0.0
    assert lens.current_setpoint_ma is None  # unknown, not the value asked for


@pytest.mark.parametrize("index", [4, 5, 8, 9])
def test_a_rejected_set_focal_power_is_resent_when_verified(index: int) -> None:
    lens, port, dev = connected(port_cls=CorruptingPort, verify=True)  # the lens-wide default
    lens.set_focal_power_mode()
    port.corrupt[b"PwDA"] = [(index, 0x20)]
    lens.set_focal_power_dpt(1.25)
    assert port.corrupted
    assert dev.focal_power_setpoint_dpt == pytest.approx(1.25)
    assert lens.focal_power_setpoint_dpt == pytest.approx(1.25)


def test_verified_set_current_reads_back_with_the_golden_frames() -> None:
    from tests.test_driver_lens import connect_script, scripted

    lens, port = scripted(
        connect_script(max_raw=29200)
        + [
            (bytes.fromhex("41 77 05 7A 26 95"), b""),  # Aw 1402: 100 mA of 292 mA
            (cmd(b"Ar\x00\x00"), rep(b"A", i16(1402))),
        ]
    )
    lens.connect()
    lens.set_current_ma(100.0, verify=True)
    port.assert_done()


def test_verified_set_focal_power_reads_back_with_the_golden_frames() -> None:
    from tests.test_driver_lens import FP_MODE_SCRIPT, connect_script, scripted

    lens, port = scripted(
        connect_script()
        + FP_MODE_SCRIPT
        + [
            (bytes.fromhex("50 77 44 41 06 40 00 00 30 2C"), b""),  # PwDA 3 dpt, type A
            (cmd(b"PrDA" + bytes(4)), rep(b"PD", i16(1600))),
        ]
    )
    lens.connect()
    lens.set_focal_power_mode()
    lens.focal_power_limits = lens.focal_power_limits.__class__(lens.focal_power_limits.status, -5.0, 10.0)
    lens.set_focal_power_dpt(3.0, verify=True)
    port.assert_done()


# --------------------------------------------------------------------------- E 3: not recognised


def test_e3_answer_to_a_corrupted_prefix_is_retried() -> None:
    lens, port, dev = connected(port_cls=CorruptingPort)
    port.corrupt[b"Ar"] = [(0, 0x10)]  # 'A' -> 'Q': the device does not recognise the command
    assert lens.get_current_ma() == 0.0
    assert port.corrupted


def test_e3_is_reported_when_it_persists() -> None:
    lens, port, dev = connected(port_cls=CorruptingPort, retries=1)
    port.corrupt[b"TCA"] = [(0, 0x01)] * 2
    with pytest.raises(DeviceErrorReply) as info:
        lens.get_temperature_c()
    assert info.value.code == 3


# --------------------------------------------------------------------------- frames inside payloads


@pytest.mark.parametrize("serial_number", [b"AN\r\nBCDE", b"Ready\r\n\x00", b"N\r\nReady"])
def test_a_payload_holding_a_shorter_frame_is_decoded_by_its_length(serial_number: bytes) -> None:
    lens, port, dev = connected(Emulator(serial_number=serial_number, device_id=serial_number))
    assert lens.get_serial_number() == serial_number.rstrip(b"\x00").decode("ascii")
    assert lens.get_device_id() == serial_number.rstrip(b"\x00").decode("ascii")


def test_a_payload_holding_a_shorter_frame_in_a_scripted_exchange() -> None:
    from tests.test_driver_lens import scripted

    payload = b"N\r\nReady"
    lens, port = scripted([(cmd(b"X"), rep(b"X", payload)), (cmd(b"IR" + bytes(8)), b"\x13" + rep(b"IR", b"ERady\r\n\x00"))])
    assert lens.get_serial_number() == "N\r\nReady"
    assert lens.get_device_id() == "ERady\r\n"
    port.assert_done()


def test_verified_read_back_within_one_raw_step_is_taken_as_the_set_point() -> None:
    from tests.test_driver_lens import connect_script, scripted

    aw = cmd(b"Aw" + i16(1398))  # 100 mA of 292.84 mA
    ar = cmd(b"Ar\x00\x00")
    lens, port = scripted(
        connect_script()
        + [(aw, b""), (ar, rep(b"A", i16(1399)))]  # one step off: accepted, and what the device says is kept
        + [(aw, b""), (ar, rep(b"A", i16(1401))), (cmd(b"MMA"), rep(b"MMA", b"\x01")), (aw, b""), (ar, rep(b"A", i16(1398)))]
    )
    lens.connect()
    lens.set_current_ma(100.0, verify=True)
    assert lens.current_setpoint_ma == pytest.approx(1399 * MAX_MA / 4095)
    lens.set_current_ma(100.0, verify=True)  # three steps off: the mode is read, the command sent again
    assert lens.current_setpoint_ma == pytest.approx(1398 * MAX_MA / 4095)
    port.assert_done()
