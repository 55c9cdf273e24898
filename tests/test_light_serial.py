"""SerialLineLight against pyserial's loop:// (RTS -> CTS, DTR -> DSR), a pty and a missing port."""

from __future__ import annotations

import os

import pytest
import serial

from tdfd.errors import LightConnectionError, LightSpecError, LightVerifyError, ModemLineError
from tdfd.light import SerialLineLight, open_light, open_serial_line


@pytest.mark.parametrize("line,partner,other", [("rts", "cts", "dsr"), ("dtr", "dsr", "cts")])
def test_loop_line_follows_every_switch(line, partner, other):
    plain = serial.serial_for_url("loop://")
    assert getattr(plain, partner) is True  # pyserial asserts both lines when it opens a port...
    plain.close()
    port = open_serial_line("loop://", line)
    assert getattr(port, partner) is False  # ...open_serial_line opens with the keyed line off
    light = SerialLineLight(port, line, owns_port=True)
    assert light.readback == "loopback"
    other_before = getattr(port, other)
    for step in ("on", "off", "on", "on", "off", "off"):
        getattr(light, step)()
        want = step == "on"
        assert getattr(port, partner) is want, step
        assert light.is_on is want
        assert light.read_line() is want
        assert getattr(port, other) is other_before  # the other line is never touched
    light.on()
    light.close()  # close switches off first
    assert light.is_on is False
    assert not port.is_open


def test_open_light_loop_starts_off():
    light = open_light("serial:loop://:dtr")
    try:
        assert light.is_on is False and light.port.dsr is False
        light.on()
        assert light.port.dsr is True
    finally:
        light.close()


class _StuckPort:
    """A port whose loop-back line is stuck low (a broken wire, a dead driver)."""

    port = "loop://stuck"

    def __init__(self):
        self.rts = False
        self.writes = []

    def __setattr__(self, key, value):
        if key == "rts":
            self.__dict__.setdefault("writes", []).append(value)
        object.__setattr__(self, key, value)

    @property
    def cts(self):
        return False


def test_readback_mismatch_is_typed_and_switches_off():
    port = _StuckPort()
    light = SerialLineLight(port, "rts", readback="loopback")
    with pytest.raises(LightVerifyError, match="RTS reads back off after switching it on"):
        light.on()
    assert port.rts is False  # off was attempted after the failed switch-on
    assert port.writes[-2:] == [True, False]


def test_pty_refuses_modem_lines_errno_25():
    master, slave = os.openpty()
    try:
        name = os.ttyname(slave)
        with pytest.raises(ModemLineError, match="errno 25") as info:
            open_light(f"serial:{name}:rts")
        assert isinstance(info.value, LightConnectionError)
        assert name in str(info.value)
        assert isinstance(info.value.__cause__, OSError) and info.value.__cause__.errno == 25
    finally:
        os.close(master)
        os.close(slave)


def test_missing_port_is_one_typed_error():
    with pytest.raises(LightConnectionError, match="/dev/tdfd-no-such-port") as info:
        open_light("serial:/dev/tdfd-no-such-port:dtr")
    assert not isinstance(info.value, ModemLineError)


def test_bad_url_and_line():
    with pytest.raises(LightConnectionError):
        open_serial_line("bogus://nowhere", "rts")
    with pytest.raises(LightSpecError):
        open_light("serial:loop://:cts")
