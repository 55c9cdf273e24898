"""The emulated Lens Driver 4: the device model, fault injection, the pty server and the CLI."""

from __future__ import annotations

import math
import os
import signal
import struct
import subprocess
import sys
import time
from pathlib import Path

import pytest
import serial
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.driver_frames import cmd, i16, ref_crc, rep
from tdfd.driver import Calibration, Emulator, EmulatorSerial, EmulatorServer, Faults, Mode, OptotuneLens, StatusFlags
from tdfd.driver import protocol as p
from tdfd.errors import InputError, LensConnectionError, LensTimeoutError

REPO = Path(__file__).resolve().parents[1]




class FakeClock:
    def __init__(self, t: float = 100.0) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


@pytest.fixture
def clock() -> FakeClock:
    return FakeClock()


@pytest.fixture
def dev(clock: FakeClock) -> Emulator:
    return Emulator(clock=clock)


# --------------------------------------------------------------------------- byte-exact replies


def test_golden_exchanges(dev: Emulator) -> None:
    assert dev.handle(b"Start") == b"Ready\r\n"
    assert dev.handle(bytes.fromhex("41 77 04 B2 26 93")) == b""
    assert dev.handle(cmd(b"Ar\x00\x00")) == rep(b"A", bytes.fromhex("04 B2"))
    assert dev.handle(cmd(b"H")) == rep(b"H", b"A")
    assert dev.handle(cmd(b"V")) == rep(b"V", bytes([1, 8]) + struct.pack(">HH", 2021, 0))
    assert dev.handle(cmd(b"X")) == rep(b"X", b"EL103001")
    assert dev.handle(cmd(b"IR" + bytes(8))) == rep(b"IR", b"LD4EMU01")
    assert dev.handle(cmd(b"CrMA\x00\x00")) == rep(b"CMA", i16(29284))
    assert dev.handle(cmd(b"CrUA\x00\x00")) == rep(b"CUA", i16(4095))
    assert dev.handle(cmd(b"CrLA\x00\x00")) == rep(b"CLA", i16(-4095))
    assert dev.handle(cmd(b"MMA")) == rep(b"MMA", b"\x01")
    assert dev.handle(cmd(b"TCA")) == rep(b"TCA", i16(400))
    assert dev.handle(cmd(b"Sr")) == rep(b"S", bytes([4, 0, 0, 0]))  # no temperature limits yet
    assert dev.handle(cmd(b"MwDA")) == rep(b"MDA")


def test_focal_power_mode_exchanges(dev: Emulator) -> None:
    pt = dev.handle(cmd(b"PwTA" + i16(40 * 16) + i16(20 * 16)))
    frame = p.decode_frame(pt)
    assert frame.prefix == b"PT"
    status, max_raw, min_raw = struct.unpack(">Bhh", frame.data)
    assert status == 0 and min_raw == 0  # type A clips at -5 dpt
    expected_max = Calibration().power_dpt(292.84, 40.0)
    assert max_raw == math.floor((expected_max + 5) * 200)
    mca = dev.handle(cmd(b"MwCA"))
    assert mca == rep(b"MCA", frame.data)
    assert dev.mode is Mode.FOCAL_POWER
    assert dev.handle(bytes.fromhex("50 77 44 41 06 40 00 00 30 2C")) == b""  # 3 dpt: beyond the limit
    assert dev.focal_power_setpoint_dpt == pytest.approx(max_raw / 200 - 5)
    assert p.decode_frame(dev.handle(cmd(b"Sr"))).data[0] == StatusFlags.CANNOT_REACH_FOCAL_POWER
    assert dev.handle(cmd(b"PwDA" + i16(1300) + b"\0\0")) == b""  # 1.5 dpt
    assert dev.handle(cmd(b"PrDA" + bytes(4))) == rep(b"PD", i16(1300))
    assert dev.handle(cmd(b"Sr")) == rep(b"S", bytes(4))
    assert dev.handle(cmd(b"MMA")) == rep(b"MMA", b"\x05")


def test_errors(clock: FakeClock) -> None:
    dev = Emulator(clock=clock, unavailable={"V"})
    good = cmd(b"TCA")
    assert dev.handle(good[:-1] + bytes([good[-1] ^ 1])) == rep(b"E", b"\x01")
    assert dev.handle(b"Q") == rep(b"E", b"\x03")
    assert dev.handle(cmd(b"TCA") + b"x") == rep(b"E", b"\x03")
    assert dev.handle(cmd(b"V")) == rep(b"E", b"\x02")
    n_style = Emulator(clock=clock, error_style="N")
    assert n_style.handle(good[:-1] + b"\x00") == b"N\r\n"
    type_f = Emulator(clock=clock, firmware_type="F")
    for body in (b"MwCA", b"PwTA" + bytes(4), b"PwDA" + bytes(4), b"PrDA" + bytes(4)):
        assert type_f.handle(cmd(body)) == rep(b"E", b"\x02")


def test_reset_puts_it_in_firmware_update_mode(dev: Emulator) -> None:
    assert dev.feed(b"RESET") == []
    assert dev.reset_received
    assert dev.handle(b"Start") == b""
    assert dev.feed(cmd(b"H")) == []


def test_ignored_commands_in_the_wrong_mode(dev: Emulator) -> None:
    dev.handle(cmd(b"PwDA" + i16(1600) + b"\0\0"))  # current mode: ignored
    assert dev.focal_power_setpoint_dpt is None
    dev.handle(cmd(b"PwTA" + i16(640) + i16(320)))
    dev.handle(cmd(b"MwCA"))
    dev.handle(cmd(b"Aw" + i16(1000)))  # focal-power mode: ignored
    assert dev.handle(cmd(b"MMA")) == rep(b"MMA", b"\x05")
    assert dev.focal_power_setpoint_dpt == pytest.approx(-1.5)


def test_current_is_clamped_to_the_software_limits(clock: FakeClock) -> None:
    dev = Emulator(clock=clock, current_limits_ma=(-100.0, 150.0))
    dev.handle(cmd(b"Aw" + i16(4095)))
    assert dev.current_ma == pytest.approx(150.0, abs=0.1)
    assert dev.handle(cmd(b"CrLA\x00\x00")) == rep(b"CLA", i16(-1398))


def test_temperature(dev: Emulator, clock: FakeClock) -> None:
    dev.set_temperature(35.0, time_constant_s=10.0)
    assert dev.temperature_c == 25.0
    clock.t += 10.0
    assert dev.temperature_c == pytest.approx(35.0 - 10.0 / math.e)
    clock.t += 1000.0
    assert dev.handle(cmd(b"TCA")) == rep(b"TCA", i16(35 * 16))
    dev.handle(cmd(b"PwTA" + i16(30 * 16) + i16(20 * 16)))
    assert p.decode_frame(dev.handle(cmd(b"Sr"))).data[0] == StatusFlags.TEMPERATURE_OUTSIDE_USER_LIMITS
    dev.set_temperature(80.0)
    flags = StatusFlags(p.decode_frame(dev.handle(cmd(b"Sr"))).data[0])
    assert StatusFlags.TEMPERATURE_OUTSIDE_SPECIFICATION in flags
    no_sensor = Emulator(clock=clock, temperature_sensor=False, lens_eeprom=False)
    assert no_sensor.handle(cmd(b"TCA")) == rep(b"TCA", i16(4095))
    assert no_sensor.handle(cmd(b"X")) == rep(b"X", bytes(8))
    assert StatusFlags.NO_OR_FAULTY_EEPROM in StatusFlags(p.decode_frame(no_sensor.handle(cmd(b"Sr"))).data[0])


def test_wider_temperature_limits_narrow_the_focal_power_range(dev: Emulator) -> None:
    dev.handle(cmd(b"PwTA" + i16(30 * 16) + i16(20 * 16)))
    narrow = dev.focal_power_limits_dpt
    dev.handle(cmd(b"PwTA" + i16(60 * 16) + i16(0)))
    wide = dev.focal_power_limits_dpt
    assert wide[1] < narrow[1]


# --------------------------------------------------------------------------- settling and the clock


def test_first_order_settling(dev: Emulator, clock: FakeClock) -> None:
    t0 = clock.t
    dev.handle(cmd(b"Aw" + i16(2000)))
    start = -1.5
    target = Calibration().power_dpt(2000 * 292.84 / 4095)
    assert dev.target_focal_power_dpt == pytest.approx(target)
    assert dev.focal_power_at(t0) == pytest.approx(start)
    assert dev.focal_power_at(t0 - 1.0) == pytest.approx(start)
    assert dev.time_constant_s == pytest.approx(0.015 / math.log(100))
    residual = (target - dev.focal_power_at(t0 + 0.015)) / (target - start)
    assert residual == pytest.approx(0.01)
    tau = dev.time_constant_s
    assert dev.focal_power_at(t0 + tau) == pytest.approx(target + (start - target) / math.e)
    # a second step mid-way starts from where the lens actually is
    clock.t = t0 + tau
    dev.handle(cmd(b"Aw" + i16(0)))
    mid = dev.focal_power_at(t0 + tau)
    assert dev.focal_power_at(clock.t + 1.0) == pytest.approx(start)
    assert dev.focal_power_at(t0 + tau / 2) < mid  # history: still the first step
    clock.t += 1.0
    assert dev.focal_power_dpt == pytest.approx(start)


def test_settling_in_focal_power_mode_and_thermal_compensation(dev: Emulator, clock: FakeClock) -> None:
    dev.handle(cmd(b"PwTA" + i16(40 * 16) + i16(10 * 16)))
    dev.handle(cmd(b"MwCA"))
    t0 = clock.t
    dev.handle(cmd(b"PwDA" + i16(p.focal_power_dpt_to_raw(1.0, "A")) + b"\0\0"))
    assert dev.focal_power_at(t0 + 0.015) == pytest.approx(1.0 - 0.01 * 2.5)
    dev.set_temperature(35.0)
    assert dev.focal_power_at(t0 + 1.0) == pytest.approx(1.0)  # compensated
    assert dev.current_ma > (1.0 + 1.5) * 290 / 5  # by more current
    dev.handle(cmd(b"MwDA"))  # current mode keeps the compensated current …
    clock.t += 1.0
    assert dev.focal_power_dpt == pytest.approx(1.0, abs=0.002)  # 12-bit DAC step
    dev.set_temperature(45.0)  # … but no longer follows the temperature
    assert dev.focal_power_dpt == pytest.approx(1.0 - 0.67, abs=0.01)


def test_zero_settling_time(clock: FakeClock) -> None:
    dev = Emulator(clock=clock, settling_time_s=0.0)
    dev.handle(cmd(b"Aw" + i16(4095)))
    assert dev.focal_power_dpt == pytest.approx(Calibration().power_dpt(292.84))


def test_clock_going_backwards_restarts_history(dev: Emulator, clock: FakeClock) -> None:
    dev.handle(cmd(b"Aw" + i16(1000)))
    clock.t -= 50.0
    dev.handle(cmd(b"Aw" + i16(2000)))
    clock.t += 1.0
    assert dev.focal_power_dpt == pytest.approx(dev.target_focal_power_dpt)


# --------------------------------------------------------------------------- the byte stream


_COMMAND_STREAM = b"".join(
    [
        b"Start",
        cmd(b"H"),
        cmd(b"Aw" + i16(-1398)),
        cmd(b"Ar\x00\x00"),
        cmd(b"PwTA" + i16(640) + i16(320)),
        cmd(b"MwCA"),
        cmd(b"PwDA" + i16(1400) + b"\0\0"),
        cmd(b"PrDA" + bytes(4)),
        cmd(b"TCA"),
        cmd(b"Sr"),
    ]
)


@settings(max_examples=50, deadline=None)
@given(st.data())
def test_feed_any_chunking_gives_the_same_replies(data: st.DataObject) -> None:
    reference = Emulator(clock=FakeClock()).feed(_COMMAND_STREAM)
    assert len(reference) == 8  # Aw and PwDA answer nothing
    cuts = sorted(data.draw(st.lists(st.integers(0, len(_COMMAND_STREAM)), max_size=10)))
    dev = Emulator(clock=FakeClock())
    out, last = [], 0
    for cut in [*cuts, len(_COMMAND_STREAM)]:
        out += dev.feed(_COMMAND_STREAM[last:cut])
        last = cut
    assert out == reference
    assert dev.pending == b""


def test_feed_resynchronises_after_garbage(dev: Emulator) -> None:
    replies = dev.feed(b"\x00\x01zz" + cmd(b"TCA") + b"S" + cmd(b"Sr"))
    assert replies[0] == rep(b"E", b"\x03")
    assert rep(b"TCA", i16(400)) in replies
    assert replies[-1] == rep(b"S", bytes([4, 0, 0, 0]))


def test_feed_holds_partial_commands(dev: Emulator) -> None:
    assert dev.feed(b"CrM") == []
    assert dev.pending == b"CrM"
    assert dev.discard_partial() == b"CrM"
    assert dev.feed(cmd(b"CrMA\x00\x00")) == [rep(b"CMA", i16(29284))]


# --------------------------------------------------------------------------- faults


def test_faults_are_deterministic_with_a_seed() -> None:
    def run(seed: int) -> list:
        faults = Faults(bad_crc=0.3, drop=0.3, late=0.3, garbage=0.3, seed=seed)
        return [faults.apply(rep(b"A", i16(i))) for i in range(50)]

    assert run(5) == run(5)
    assert run(5) != run(6)


def test_fault_kinds() -> None:
    reply = rep(b"A", i16(1))
    assert Faults(drop=1.0).apply(reply) == (None, 0.0)
    bad, delay = Faults(bad_crc=1.0).apply(reply)
    assert delay == 0.0 and len(bad) == len(reply) and bad != reply
    with pytest.raises(p.ChecksumError):
        p.decode_frame(bad)
    assert Faults(late=1.0, late_s=0.2).apply(reply) == (reply, 0.2)
    junk, _ = Faults(garbage=1.0, garbage_max_bytes=3).apply(reply)
    assert junk.endswith(reply) and 1 <= len(junk) - len(reply) <= 3
    limited = Faults(drop=1.0, limit=1)
    assert limited.apply(reply)[0] is None and limited.apply(reply)[0] == reply
    assert limited.injected == 1


def test_fault_parse_errors() -> None:
    with pytest.raises(ValueError):
        Faults.parse(["nonsense=1"])
    with pytest.raises(ValueError):
        Faults.parse(["drop"])
    with pytest.raises(ValueError):
        Faults(drop=1.5)


# --------------------------------------------------------------------------- the pty server


def test_server_is_raw_and_binary_clean() -> None:
    with EmulatorServer() as srv:
        assert srv.port is not None and os.path.exists(srv.port)
        with serial.Serial(srv.port, 115200, timeout=0.5) as port:
            # a reply whose bytes include ^C, ^Q, ^S, CR and LF must pass unchanged
            srv.device.handle(b"Start")
            srv.device.handle(cmd(b"Aw" + bytes([0x0D, 0x0A])))
            port.write(cmd(b"Ar\x00\x00") + cmd(b"X"))
            expected = rep(b"A", bytes([0x0D, 0x0A])) + rep(b"X", b"EL103001")
            assert port.read(len(expected)) == expected
            srv.device.serial_number = bytes([3, 0x11, 0x13, 0x0D, 0x0A, 0x7F, 0x1A, 0x04])
            port.write(cmd(b"X"))
            expected = rep(b"X", srv.device.serial_number)
            assert port.read(len(expected)) == expected


def test_server_discards_stale_partial_commands() -> None:
    with EmulatorServer(partial_timeout_s=0.05) as srv, serial.Serial(srv.port, timeout=0.5) as port:
        port.write(b"CrM")
        time.sleep(0.2)
        assert srv.device.pending == b""
        port.write(cmd(b"TCA"))
        assert port.read(9) == rep(b"TCA", i16(400))


def test_server_stop_and_disconnect() -> None:
    srv = EmulatorServer().start()
    path = srv.port
    assert srv.running
    srv.disconnect()
    assert srv.disconnected and srv.wait(2.0) and not srv.running
    assert not os.path.exists(path)
    srv.stop()
    srv.stop()  # idempotent


def test_server_with_own_device_and_clock() -> None:
    clock = FakeClock(0.0)
    device = Emulator(clock=clock)
    with EmulatorServer(device) as srv, OptotuneLens.open(srv.port, timeout_s=0.2) as lens:
        assert srv.device is device
        lens.set_current_ma(100.0)
        lens.get_current_ma()  # the Aw has been processed when its successor is answered
        assert device.focal_power_at(0.0) == pytest.approx(-1.5)
        assert device.focal_power_at(1.0) == pytest.approx(device.target_focal_power_dpt)
    with pytest.raises(InputError, match="not both"):  # a typed error (issue 21), was a bare TypeError
        EmulatorServer(device, firmware_type="B")
    with pytest.raises(InputError, match="firmwaretype"):
        EmulatorServer(firmwaretype="B")


# --------------------------------------------------------------------------- the CLI


def _start_cli(*args: str) -> subprocess.Popen:
    env = dict(os.environ, PYTHONPATH=str(REPO))
    return subprocess.Popen(
        [sys.executable, "-m", "tdfd", "lens-emulator", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=REPO,
        env=env,
    )


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_cli_serves_until_interrupted(sig: signal.Signals) -> None:
    proc = _start_cli("--firmware-type", "B", "--fault", "garbage=0.5", "--seed", "3")
    try:
        path = proc.stdout.readline().strip()
        assert path.startswith("/dev/"), proc.stderr.read() if proc.poll() is not None else path
        with OptotuneLens.open(path, timeout_s=0.2) as lens:
            assert lens.firmware_type == "B"
            lens.set_current_ma(20.0)
            assert lens.get_current_ma() == pytest.approx(20.0, abs=0.1)
        proc.send_signal(sig)
        assert proc.wait(10) == 0
        assert proc.stdout.read() == ""  # the path is the only line of output
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_cli_rejects_bad_faults() -> None:
    proc = _start_cli("--fault", "bogus=1")
    out, err = proc.communicate(timeout=20)
    assert proc.returncode == 2 and out == "" and "bogus" in err


def test_cli_is_registered() -> None:
    from tdfd.cli import SUBCOMMAND_MODULES, build_parser

    assert "tdfd.driver.cli" in SUBCOMMAND_MODULES
    args = build_parser().parse_args(["lens-emulator", "--fault", "drop=0.1"])
    assert args.fault == ["drop=0.1"] and callable(args.func)


# --------------------------------------------------------------------------- the in-process port


def test_emulator_serial_runs_the_device_api() -> None:
    clock = FakeClock(0.0)
    port = EmulatorSerial(Emulator(clock=clock))
    lens = OptotuneLens(port, timeout_s=0.05).connect()
    lens.set_current_ma(-10.0)
    assert lens.get_current_ma() == pytest.approx(-10.0, abs=0.1)
    limits = lens.set_focal_power_mode()
    lens.set_focal_power_dpt(limits.max_dpt / 2)
    assert lens.get_focal_power_dpt() == pytest.approx(limits.max_dpt / 2, abs=0.005)
    assert port.device.focal_power_at(1.0) == pytest.approx(limits.max_dpt / 2, abs=0.005)
    assert lens.get_status().flags == StatusFlags(0)


def test_emulator_serial_faults() -> None:
    port = EmulatorSerial(timeout=0.05)
    lens = OptotuneLens(port, timeout_s=0.05).connect()
    port.faults = Faults(drop=1.0, limit=2)
    assert lens.get_temperature_c() == 25.0
    port.faults = Faults(bad_crc=1.0, garbage=1.0, limit=2)
    assert lens.get_temperature_c() == 25.0
    port.faults = Faults(late=1.0, late_s=0.02)
    assert lens.get_temperature_c() == 25.0
    port.faults = Faults(late=1.0, late_s=0.3)
    with pytest.raises(LensTimeoutError):
        lens.get_temperature_c()
    time.sleep(0.3)  # the late replies arrive, to be drained
    port.faults = Faults(drop=1.0)
    with pytest.raises(LensTimeoutError):
        lens.get_temperature_c()
    port.faults = Faults()
    assert lens.get_temperature_c() == 25.0  # resynchronised (a fence command first)
    port.faults = Faults(disconnect_after=1)
    assert lens.get_temperature_c() == 25.0
    with pytest.raises(LensConnectionError):
        lens.get_temperature_c()


# --------------------------------------------------------------------------- corrupted commands


@pytest.mark.parametrize("seed", range(6))
def test_corrupt_fault_on_a_query_is_retried(seed: int) -> None:
    port = EmulatorSerial(timeout=0.05)
    lens = OptotuneLens(port, timeout_s=0.05).connect()
    port.faults = Faults(corrupt=1.0, limit=1, seed=seed)
    assert lens.get_temperature_c() == 25.0
    assert port.faults.injected == 1


def test_corrupt_fault_on_a_set_command_over_the_pty() -> None:
    with EmulatorServer() as srv, OptotuneLens.open(srv.port, timeout_s=0.1, verify=True) as lens:
        srv.faults = Faults(corrupt=1.0, limit=1, seed=2)
        lens.set_current_ma(100.0)  # verified: the corrupted Aw is noticed and sent again
        assert srv.faults.injected == 1
        assert srv.device.current_ma == pytest.approx(100.0, abs=292.84 / 4095)


def test_emulator_serial_on_a_simulated_clock() -> None:
    clock = FakeClock(0.0)

    def sleep(dt: float) -> None:
        clock.t += dt

    port = EmulatorSerial(Emulator(clock=clock), timeout=0.5, clock=clock, sleep=sleep)
    lens = OptotuneLens(port, timeout_s=0.5).connect()
    port.faults = Faults(drop=1.0, limit=1)
    t0 = clock.t
    assert lens.get_temperature_c() == 25.0
    assert clock.t - t0 == pytest.approx(0.5)  # one read timeout, in simulated time only
