"""The device API: scripted exchanges (pymeasure style) and the emulator over a real pty."""

from __future__ import annotations

import logging
import math
import struct
import time

import pytest
import serial

from tests.driver_frames import cmd, i16, ref_crc, rep
from tdfd.driver import EmulatorServer, Faults, Mode, OptotuneLens, StatusFlags
from tdfd.driver import protocol as p
from tdfd.driver.transport import SerialTransport
from tdfd.errors import (
    ChecksumError,
    DeviceErrorReply,
    DriverError,
    ForbiddenCommandError,
    LensConnectionError,
    LensModeError,
    LensRangeError,
    LensTimeoutError,
    ProtocolError,
)




class ScriptedSerial:
    """A pyserial stand-in that plays a script of (expected write, reply) exchanges.

    A write that differs from the next expected one fails the test at once; so does
    a leftover exchange at the end (:meth:`assert_done`). Replies become readable after
    the matching write; a read returns what is there (a short read is a timeout).
    """

    def __init__(self, exchanges: list[tuple[bytes, bytes]], *, pending: bytes = b"") -> None:
        self.exchanges = list(exchanges)
        self.buffer = bytearray(pending)
        self.timeout = None
        self.is_open = True
        self.reads_after_last_write = 0
        self.writes: list[bytes] = []

    # pyserial surface
    @property
    def in_waiting(self) -> int:
        return len(self.buffer)

    def reset_input_buffer(self) -> None:
        self.buffer.clear()

    def read(self, n: int = 1) -> bytes:
        self.reads_after_last_write += 1
        out = bytes(self.buffer[:n])
        del self.buffer[:n]
        return out

    def write(self, data: bytes) -> int:
        data = bytes(data)
        assert self.exchanges, f"unexpected write {data.hex(' ')}: script exhausted"
        expected, reply = self.exchanges.pop(0)
        assert data == expected, f"wrote {data.hex(' ')}, script expects {expected.hex(' ')}"
        self.writes.append(data)
        self.buffer += reply
        self.reads_after_last_write = 0
        return len(data)

    def flush(self) -> None:
        pass

    def close(self) -> None:
        self.is_open = False

    def assert_done(self) -> None:
        assert not self.exchanges, f"{len(self.exchanges)} scripted exchange(s) unused: {self.exchanges[0][0]!r}…"


def connect_script(*, firmware: bytes = b"A", max_raw: int = 29284, limits: tuple[int, int] = (-4095, 4095), mode: int = 1) -> list:
    return [
        (b"Start", b"Ready\r\n"),
        (cmd(b"H"), rep(b"H", firmware)),
        (cmd(b"CrMA\x00\x00"), rep(b"CMA", i16(max_raw))),
        (cmd(b"CrLA\x00\x00"), rep(b"CLA", i16(limits[0]))),
        (cmd(b"CrUA\x00\x00"), rep(b"CUA", i16(limits[1]))),
        (cmd(b"MMA"), rep(b"MMA", bytes([mode]))),
    ]


def scripted(script: list, **kwargs) -> tuple[OptotuneLens, ScriptedSerial]:  # noqa: ANN003
    port = ScriptedSerial(script)
    lens = OptotuneLens(port, timeout_s=0.01, **kwargs)
    return lens, port


#: after a query ends without its reply, the next exchange starts with a fence (H: firmware type)
FENCE = (cmd(b"H"), rep(b"H", b"A"))

FP_MODE_SCRIPT = [
    (cmd(b"PwTA" + i16(640) + i16(320)), rep(b"PT", bytes([0]) + i16(1500) + i16(0))),
    (cmd(b"MwCA"), rep(b"MCA", bytes([0]) + i16(1500) + i16(0))),  # type A: -5 … +2.5 dpt
]


# --------------------------------------------------------------------------- scripted


def test_connect_reads_identity_and_limits() -> None:
    lens, port = scripted(connect_script(max_raw=29200, limits=(-2000, 3000)))
    lens.connect()
    port.assert_done()
    assert lens.firmware_type == "A"
    assert lens.max_current_ma == pytest.approx(292.0)
    assert lens.current_limits_ma == pytest.approx((-2000 * 292 / 4095, 3000 * 292 / 4095))
    assert lens.mode is Mode.CURRENT


def test_set_current_sends_the_golden_frame_and_reads_nothing() -> None:
    lens, port = scripted(connect_script(max_raw=29200) + [(bytes.fromhex("41 77 05 7A 26 95"), b"")])
    lens.connect()
    lens.set_current_ma(100.0)
    port.assert_done()
    assert port.reads_after_last_write == 0


def test_negative_current() -> None:
    lens, port = scripted(
        connect_script()
        + [(cmd(b"Aw" + i16(-1398)), b""), (cmd(b"Ar\x00\x00"), rep(b"A", i16(-1398)))]
    )
    lens.connect()
    lens.set_current_ma(-100.0)
    assert lens.get_current_ma() == pytest.approx(-99.973, abs=1e-3)
    port.assert_done()


def test_focal_power_mode_sends_temperature_limits_first_then_golden_set_point() -> None:
    lens, port = scripted(
        connect_script()
        + FP_MODE_SCRIPT
        + [(bytes.fromhex("50 77 44 41 06 40 00 00 30 2C"), b"")]  # 3 dpt, type A: the golden frame
    )
    lens.connect()
    limits = lens.set_focal_power_mode((20.0, 40.0))
    assert (limits.min_dpt, limits.max_dpt) == (-5.0, 2.5)
    assert lens.mode is Mode.FOCAL_POWER
    with pytest.raises(LensRangeError):
        lens.set_focal_power_dpt(3.0)  # beyond the reported +2.5 dpt: nothing sent
    lens.focal_power_limits = p.FocalPowerLimits(limits.status, -5.0, 10.0)  # pretend a wider lens
    lens.set_focal_power_dpt(3.0)
    port.assert_done()
    assert port.reads_after_last_write == 0


@pytest.mark.parametrize("firmware", [b"B", b"C", b"E"])
def test_focal_power_without_offset_for_other_firmware(firmware: bytes) -> None:
    lens, port = scripted(
        connect_script(firmware=firmware)
        + [
            (cmd(b"PwTA" + i16(640) + i16(320)), rep(b"PT", bytes([0]) + i16(700) + i16(-300))),
            (cmd(b"MwCA"), rep(b"MCA", bytes([0]) + i16(700) + i16(-300))),
            (cmd(b"PwDA" + i16(600) + b"\0\0"), b""),
            (cmd(b"PrDA" + bytes(4)), rep(b"PD", i16(-250))),
        ]
    )
    lens.connect()
    assert lens.set_focal_power_mode() == p.FocalPowerLimits(StatusFlags(0), -1.5, 3.5)
    lens.set_focal_power_dpt(3.0)
    assert lens.get_focal_power_dpt() == -1.25
    port.assert_done()


def test_every_query_decodes() -> None:
    lens, port = scripted(
        connect_script()
        + [
            (cmd(b"V"), rep(b"V", bytes([1, 8]) + struct.pack(">HH", 2021, 3))),
            (cmd(b"X"), rep(b"X", b"AB123456")),
            (cmd(b"IR" + bytes(8)), rep(b"IR", b"LD4\0\0\0\0\0")),
            (cmd(b"TCA"), rep(b"TCA", i16(412))),
            (cmd(b"TCA"), rep(b"TCA", i16(4095))),
            (cmd(b"Sr"), rep(b"S", bytes([0x84, 1, 2, 3]))),
            (cmd(b"MMA"), rep(b"MMA", bytes([5]))),
            (cmd(b"MwDA"), rep(b"MDA")),
            (cmd(b"X"), rep(b"X", bytes(8))),
        ]
    )
    lens.connect()
    assert str(lens.get_firmware_version()) == "1.8.2021.3"
    assert lens.get_serial_number() == "AB123456"
    assert lens.get_device_id() == "LD4"
    assert lens.get_temperature_c() == 25.75
    assert lens.get_temperature_c() is None
    status = lens.get_status()
    assert status.raw == bytes([0x84, 1, 2, 3])
    assert StatusFlags.TEMPERATURE_OUTSIDE_USER_LIMITS in status.flags
    assert lens.get_mode() is Mode.FOCAL_POWER and lens.mode is Mode.FOCAL_POWER
    lens.set_current_mode()
    assert lens.mode is Mode.CURRENT
    assert lens.get_serial_number() == ""
    port.assert_done()


def test_range_checks_send_nothing() -> None:
    lens, port = scripted(connect_script(limits=(-2000, 2000)))
    lens.connect()
    for bad in (200.0, -200.0, 293.0, math.nan, math.inf):
        with pytest.raises(LensRangeError):
            lens.set_current_ma(bad)
    with pytest.raises(LensRangeError):
        lens.set_temperature_limits_c(40.0, 20.0)
    port.assert_done()  # and nothing was written: the script would have failed


def test_mode_checks() -> None:
    lens, port = scripted(connect_script() + FP_MODE_SCRIPT)
    lens.connect()
    with pytest.raises(LensModeError):
        lens.set_focal_power_dpt(1.0)  # current mode
    lens.set_focal_power_mode()
    with pytest.raises(LensModeError):
        lens.set_current_ma(10.0)
    port.assert_done()


def test_device_error_reply_not_retried() -> None:
    lens, port = scripted(connect_script(firmware=b"F") + [(cmd(b"PwTA" + i16(640) + i16(320)), rep(b"E", b"\x02"))])
    lens.connect()
    with pytest.raises(DeviceErrorReply) as info:
        lens.set_focal_power_mode()
    assert info.value.code == 2
    port.assert_done()


@pytest.mark.parametrize("error_reply", [rep(b"E", b"\x01"), b"N\r\n"])
def test_crc_error_reply_is_retried(error_reply: bytes) -> None:
    get = cmd(b"Ar\x00\x00")
    lens, port = scripted(connect_script() + [(get, error_reply), FENCE, (get, rep(b"A", i16(7)))])
    lens.connect()
    assert lens.get_current_ma() == pytest.approx(7 * 292.84 / 4095)
    port.assert_done()


def test_persistent_crc_error_reply_raises_after_retries() -> None:
    get = cmd(b"TCA")
    lens, port = scripted(connect_script() + [(get, b"N\r\n"), FENCE, (get, b"N\r\n"), FENCE, (get, b"N\r\n")])
    lens.connect()
    with pytest.raises(DeviceErrorReply) as info:
        lens.get_temperature_c()
    assert info.value.code == 1
    port.assert_done()


def test_timeout_retries_are_bounded() -> None:
    get = cmd(b"TCA")
    lens, port = scripted(connect_script() + [(get, b""), FENCE, (get, b""), FENCE, (get, b"")], retries=2)
    lens.connect()
    with pytest.raises(LensTimeoutError):
        lens.get_temperature_c()
    port.assert_done()  # exactly 1 + 2 attempts, each after a fence


def test_timeout_then_success() -> None:
    get = cmd(b"TCA")
    lens, port = scripted(connect_script() + [(get, b"TC"), FENCE, (get, rep(b"TCA", i16(400)))])
    lens.connect()
    assert lens.get_temperature_c() == 25.0
    port.assert_done()


def test_bad_reply_crc_raises_checksum_error_after_retries() -> None:
    get = cmd(b"CrMA\x00\x00")
    bad = rep(b"CMA", i16(29284))[:-3] + b"\x00\r\n"
    lens, port = scripted([(get, bad)] * 2, retries=1)
    with pytest.raises(ChecksumError):
        lens.get_max_current_ma()
    port.assert_done()


def test_garbage_and_late_frames_before_the_reply_are_skipped() -> None:
    get = cmd(b"Ar\x00\x00")
    lens, port = scripted(connect_script() + [(get, b"\x00\xff" + rep(b"TCA", i16(1)) + rep(b"A", i16(-5)))])
    lens.connect()
    assert lens.get_current_ma() == pytest.approx(-5 * 292.84 / 4095)
    port.assert_done()


def test_stray_input_is_drained_and_logged(caplog: pytest.LogCaptureFixture) -> None:
    port = ScriptedSerial([(cmd(b"TCA"), rep(b"TCA", i16(400)))], pending=rep(b"E", b"\x01") + b"\x13junk")
    lens = OptotuneLens(port, timeout_s=0.01)
    lens.firmware_type = "A"
    with caplog.at_level(logging.WARNING, logger="tdfd.driver"):
        assert lens.get_temperature_c() == 25.0
    assert "stray error reply" in caplog.text and "drained" in caplog.text
    assert lens.transport.stray_frames == [p.ErrorFrame(1)]
    port.assert_done()


class VanishingSerial(ScriptedSerial):
    def write(self, data: bytes) -> int:
        raise serial.SerialException("write failed: [Errno 5] Input/output error")


def test_vanished_port_is_a_connection_error() -> None:
    lens = OptotuneLens(VanishingSerial([]), timeout_s=0.01)
    with pytest.raises(LensConnectionError):
        lens.handshake()
    lens.close()


def test_transport_refuses_reset() -> None:
    port = ScriptedSerial([])
    transport = SerialTransport(port, timeout_s=0.01)
    for frame in (b"RESET", b"RESET\x00\x00", b"reset"):
        with pytest.raises(ForbiddenCommandError):
            transport.write(frame)
    assert port.writes == []


def test_constructor_does_no_io_and_sets_timeout() -> None:
    port = ScriptedSerial([])
    OptotuneLens(port, timeout_s=0.25)
    assert port.timeout == 0.25 and port.writes == []


def test_open_on_loop_url_times_out_cleanly() -> None:
    # loop:// echoes our own command back: never a valid reply, so a bounded timeout
    with pytest.raises(LensTimeoutError):
        OptotuneLens.open("loop://", timeout_s=0.02, retries=1)


def test_open_missing_port_is_a_connection_error() -> None:
    with pytest.raises(LensConnectionError):
        OptotuneLens.open("/dev/does-not-exist-tdfd", timeout_s=0.05)


# --------------------------------------------------------------------------- against the emulator over a pty

TIMEOUT_S = 0.1


@pytest.fixture
def server():  # noqa: ANN201
    with EmulatorServer() as srv:
        yield srv
        assert not srv.device.reset_received
        assert "RESET" not in srv.device.commands


@pytest.fixture
def lens(server: EmulatorServer):  # noqa: ANN201
    with OptotuneLens.open(server.port, timeout_s=TIMEOUT_S, retries=2) as lens:
        yield lens


def test_pty_identity(lens: OptotuneLens, server: EmulatorServer) -> None:
    dev = server.device
    assert lens.firmware_type == "A"
    assert lens.max_current_ma == pytest.approx(292.84)
    assert lens.current_limits_ma == pytest.approx((-292.84, 292.84))
    assert lens.mode is Mode.CURRENT
    assert str(lens.get_firmware_version()) == "1.8.2021.0"
    assert lens.get_serial_number() == "EL103001"
    assert lens.get_device_id() == "LD4EMU01"
    assert lens.get_temperature_c() == 25.0
    assert lens.get_status().flags == StatusFlags.NO_TEMPERATURE_LIMITS
    lens.handshake()
    assert dev.commands[:2] == ["Start", "H"] and dev.commands[-1] == "Start"


def test_pty_current(lens: OptotuneLens, server: EmulatorServer) -> None:
    dev = server.device
    for ma in (100.0, -100.0, 292.84, 0.0, -57.3):
        t0 = time.monotonic()
        lens.set_current_ma(ma)
        assert time.monotonic() - t0 < TIMEOUT_S  # no reply awaited
        assert lens.get_current_ma() == pytest.approx(ma, abs=292.84 / 4095)
        assert dev.current_ma == pytest.approx(ma, abs=292.84 / 4095)
    lens.set_current_ma(100.0)
    lens.get_current_ma()
    assert dev.target_focal_power_dpt == pytest.approx(-1.5 + 100.0 * 5 / 290, abs=1e-3)
    assert lens.get_focal_power_dpt() == pytest.approx(dev.target_focal_power_dpt, abs=0.005)
    with pytest.raises(LensRangeError):
        lens.set_current_ma(300.0)
    lens.handshake()  # zeroes the current
    assert lens.get_current_ma() == 0.0


def test_pty_focal_power(lens: OptotuneLens, server: EmulatorServer) -> None:
    dev = server.device
    limits = lens.set_focal_power_mode((20.0, 40.0))
    assert dev.commands[-2:] == ["PwTA", "MwCA"]
    assert dev.mode is Mode.FOCAL_POWER and lens.get_mode() is Mode.FOCAL_POWER
    assert dev.temperature_limits_c == (20.0, 40.0)
    assert (limits.min_dpt, limits.max_dpt) == pytest.approx(dev.focal_power_limits_dpt)
    assert limits.min_dpt == -5.0 and 2.0 < limits.max_dpt < 3.0
    for dpt in (1.0, -2.5, limits.max_dpt, limits.min_dpt):
        lens.set_focal_power_dpt(dpt)
        assert lens.get_focal_power_dpt() == pytest.approx(dpt)
        assert dev.focal_power_setpoint_dpt == pytest.approx(dpt)
    lens.set_focal_power_dpt(1.0)
    lens.get_focal_power_dpt()
    t = dev.clock()
    assert dev.focal_power_at(t + 0.015) == pytest.approx(1.0, abs=0.06)  # settled to ~1 %
    assert dev.focal_power_at(t + 0.1) == pytest.approx(1.0, abs=1e-6)
    assert lens.get_current_ma() == pytest.approx((1.0 + 1.5) * 290 / 5, abs=0.1)
    with pytest.raises(LensRangeError):
        lens.set_focal_power_dpt(limits.max_dpt + 0.01)
    with pytest.raises(LensModeError):
        lens.set_current_ma(10.0)
    assert lens.get_status().flags == StatusFlags(0)
    lens.set_current_mode()
    assert dev.mode is Mode.CURRENT and lens.get_mode() is Mode.CURRENT
    assert lens.get_current_ma() == pytest.approx(145.0, abs=0.1)  # the current stays


def test_pty_firmware_type_b() -> None:
    with EmulatorServer(firmware_type="B") as srv, OptotuneLens.open(srv.port, timeout_s=TIMEOUT_S) as lens:
        limits = lens.set_focal_power_mode()
        assert limits.min_dpt < -5.0  # no type-A clipping
        lens.set_focal_power_dpt(3.0 if limits.max_dpt >= 3.0 else 2.0)
        assert lens.get_focal_power_dpt() == pytest.approx(srv.device.focal_power_setpoint_dpt)


def test_pty_firmware_type_without_focal_power() -> None:
    with EmulatorServer(firmware_type="F") as srv, OptotuneLens.open(srv.port, timeout_s=TIMEOUT_S) as lens:
        with pytest.raises(DeviceErrorReply) as info:
            lens.set_focal_power_mode()
        assert info.value.code == 2
        lens.set_current_ma(10.0)  # current mode still works


def test_pty_mode_command_unavailable() -> None:
    with EmulatorServer(unavailable={"MMA"}) as srv, OptotuneLens.open(srv.port, timeout_s=TIMEOUT_S) as lens:
        assert lens.mode is None  # E 2 on MMA: mode unknown, not fatal
        lens.set_current_ma(10.0)


def test_pty_no_temperature_sensor() -> None:
    with EmulatorServer(temperature_sensor=False) as srv, OptotuneLens.open(srv.port, timeout_s=TIMEOUT_S) as lens:
        assert lens.get_temperature_c() is None


# --------------------------------------------------------------------------- injected faults over the pty


def test_fault_dropped_reply_is_retried(lens: OptotuneLens, server: EmulatorServer) -> None:
    server.faults = Faults(drop=1.0, limit=2)
    assert lens.get_temperature_c() == 25.0
    assert server.faults.injected == 2


def test_fault_dropped_replies_time_out(lens: OptotuneLens, server: EmulatorServer) -> None:
    server.faults = Faults(drop=1.0)
    t0 = time.monotonic()
    with pytest.raises(LensTimeoutError):
        lens.get_temperature_c()
    assert time.monotonic() - t0 < 6 * TIMEOUT_S
    assert server.faults.injected == 3  # 1 + 2 retries
    server.faults = Faults()
    assert lens.get_temperature_c() == 25.0


def test_fault_bad_crc_is_retried(lens: OptotuneLens, server: EmulatorServer) -> None:
    server.faults = Faults(bad_crc=1.0, limit=1)
    assert lens.get_max_current_ma() == pytest.approx(292.84)
    server.faults = Faults(bad_crc=1.0)
    with pytest.raises(ChecksumError):
        lens.get_current_ma()
    server.faults = Faults(bad_crc=1.0, limit=1)
    lens.handshake()  # a corrupted 'Ready' (no CRC) is retried too


def test_fault_late_reply(lens: OptotuneLens, server: EmulatorServer) -> None:
    server.faults = Faults(late=1.0, late_s=TIMEOUT_S / 4)
    assert lens.get_temperature_c() == 25.0  # late but within the timeout
    server.faults = Faults(late=1.0, late_s=TIMEOUT_S * 1.5, limit=1)
    assert lens.get_temperature_c() == 25.0  # first attempt times out, the late reply or the retry answers
    server.faults = Faults(late=1.0, late_s=TIMEOUT_S * 5)
    with pytest.raises(LensTimeoutError):
        lens.get_current_ma()
    server.faults = Faults()
    time.sleep(TIMEOUT_S * 5)
    assert lens.get_temperature_c() == 25.0  # stale late replies drained
    assert lens.transport.drained


def test_fault_garbage_before_replies(lens: OptotuneLens, server: EmulatorServer) -> None:
    server.faults = Faults(garbage=1.0, garbage_max_bytes=12, seed=7)
    for _ in range(20):
        assert lens.get_temperature_c() == 25.0
    lens.set_current_ma(50.0)
    assert lens.get_current_ma() == pytest.approx(50.0, abs=0.1)


def test_fault_mixed_random(lens: OptotuneLens, server: EmulatorServer) -> None:
    server.faults = Faults(bad_crc=0.1, drop=0.1, garbage=0.2, late=0.1, late_s=0.02, seed=1)
    failures = 0
    for i in range(30):
        try:
            lens.set_current_ma(float(i))
            assert lens.get_current_ma() == pytest.approx(float(i), abs=0.1)
        except (LensTimeoutError, ChecksumError):
            failures += 1
    assert failures <= 3  # typed, rare, and the loop carries on


def test_fault_disconnect(lens: OptotuneLens, server: EmulatorServer) -> None:
    server.faults = Faults(disconnect_after=1)
    assert lens.get_temperature_c() == 25.0  # answered, then the port vanishes
    assert server.wait(2.0) and server.disconnected
    with pytest.raises(LensConnectionError):
        lens.get_temperature_c()
    with pytest.raises(LensConnectionError):
        lens.set_current_ma(1.0)


def test_disconnect_now(lens: OptotuneLens, server: EmulatorServer) -> None:
    server.disconnect()
    with pytest.raises(LensConnectionError):
        lens.get_current_ma()
    with pytest.raises(DriverError):  # and the port cannot be reopened
        OptotuneLens.open(server.port, timeout_s=TIMEOUT_S)


def test_corrupted_command_gets_an_unsolicited_error_that_is_drained(lens: OptotuneLens, server: EmulatorServer) -> None:
    frame = bytearray(p.encode_set_current(100))
    frame[-1] ^= 0xFF  # a command corrupted on the wire
    lens.transport.port.write(bytes(frame))
    time.sleep(0.02)
    assert lens.get_temperature_c() == 25.0
    assert p.ErrorFrame(1) in lens.transport.stray_frames


def test_bare_n_error_style() -> None:
    with EmulatorServer(error_style="N") as srv, OptotuneLens.open(srv.port, timeout_s=TIMEOUT_S) as lens:
        lens.transport.port.write(b"Aw\x00\x01\x00\x00")  # bad CRC
        time.sleep(0.02)
        assert lens.get_temperature_c() == 25.0
        assert p.ErrorFrame(1, bare=True) in lens.transport.stray_frames


def test_babbling_port_is_cut_off() -> None:
    get = cmd(b"TCA")
    lens, port = scripted([(get, bytes(300)), FENCE, (get, bytes(300))], retries=1)
    lens.firmware_type = "A"
    with pytest.raises(ProtocolError):
        lens.get_temperature_c()
    port.assert_done()
