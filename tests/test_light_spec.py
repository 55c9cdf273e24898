"""--assist-light parsing: every form, and one typed error for the rest; parsing opens nothing."""

from __future__ import annotations

import pytest

from tdfd.errors import InputError, LightSpecError
from tdfd.light import LightSpec, parse_light_spec


@pytest.mark.parametrize("text,want", [
    ("serial:/dev/ttyUSB0:rts", LightSpec("serial", port="/dev/ttyUSB0", line="rts")),
    ("serial:COM3:DTR", LightSpec("serial", port="COM3", line="dtr")),
    ("serial:loop://:rts", LightSpec("serial", port="loop://", line="rts")),
    ("serial:socket://lab-pi:7000:dtr", LightSpec("serial", port="socket://lab-pi:7000", line="dtr")),
    ("cmd:laser on,laser off", LightSpec("cmd", on_cmd="laser on", off_cmd="laser off")),
    ("CMD: a , b ", LightSpec("cmd", on_cmd="a", off_cmd="b")),
])
def test_forms(text, want):
    assert parse_light_spec(text) == want


@pytest.mark.parametrize("text", ["", "laser", "usb:/dev/ttyUSB0:rts", "serial:/dev/ttyUSB0", "serial:rts",
                                  "serial:/dev/ttyUSB0:cts", "serial::rts", "cmd:", "cmd:on,", "cmd:,off",
                                  "/dev/ttyUSB0:rts"])
def test_unknown_forms_are_one_typed_error(text):
    with pytest.raises(LightSpecError) as info:
        parse_light_spec(text)
    assert isinstance(info.value, InputError)
    assert "\n" not in str(info.value) and "--assist-light" in str(info.value)


def test_parsing_opens_nothing():
    spec = parse_light_spec("serial:/dev/tdfd-no-such-port:rts")  # no error: nothing is opened
    assert str(spec) == "serial:/dev/tdfd-no-such-port:rts"
