"""CommandLight with real subprocesses (no shell): state files, failures, timeouts."""

from __future__ import annotations

import shlex
import sys
from pathlib import Path

import pytest

from tdfd.errors import InputError, LightCommandError, LightSpecError
from tdfd.light import CommandLight, open_light, parse_light_spec


def _writer(path: Path, text: str, status: int = 0) -> list[str]:
    code = f"import pathlib, sys; pathlib.Path({str(path)!r}).write_text({text!r}); sys.exit({status})"
    return [sys.executable, "-c", code]


def test_on_off_run_the_commands(tmp_path):
    state = tmp_path / "laser"
    light = CommandLight(_writer(state, "on"), _writer(state, "off"))
    assert not state.exists()  # constructing runs nothing
    light.on()
    assert state.read_text() == "on" and light.is_on
    light.off()
    assert state.read_text() == "off" and not light.is_on


def test_spec_string_is_split_without_a_shell(tmp_path):
    state = tmp_path / "relay state"  # a space: must survive shlex quoting, and no shell is involved
    on, off = (shlex.join(_writer(state, t)) for t in ("on", "off"))
    light = open_light(f"cmd:{on},{off}")
    assert state.read_text() == "off"  # opening runs off once: a known state
    light.on()
    assert state.read_text() == "on"
    light.close()
    assert state.read_text() == "off"


def test_failing_on_still_runs_off(tmp_path):
    state, off_ran = tmp_path / "laser", tmp_path / "off"
    bad_on = [sys.executable, "-c", "import sys; sys.stderr.write('relay jammed\\n'); sys.exit(3)"]
    light = CommandLight(bad_on, _writer(off_ran, "yes"))
    with pytest.raises(LightCommandError, match=r"exited with status 3: relay jammed"):
        light.on()
    assert off_ran.read_text() == "yes"
    assert not light.is_on
    assert not state.exists()


def test_failing_off_leaves_is_on(tmp_path):
    state = tmp_path / "laser"
    light = CommandLight(_writer(state, "on"), _writer(state, "off-failed", status=1))
    light.on()
    with pytest.raises(LightCommandError, match="status 1"):
        light.off()
    assert light.is_on  # it may still be on: the guard keeps trying and reports it


def test_timeout_and_missing_program(tmp_path):
    slow = CommandLight([sys.executable, "-c", "import time; time.sleep(10)"], _writer(tmp_path / "x", "off"),
                        timeout_s=0.3)
    with pytest.raises(LightCommandError, match="did not finish within 0.3 s"):
        slow.on()
    assert (tmp_path / "x").read_text() == "off"
    missing = CommandLight(["/nonexistent/tdfd-laser-on"], _writer(tmp_path / "y", "off"))
    with pytest.raises(LightCommandError, match="cannot run the light on command"):
        missing.on()


def test_bad_commands_are_input_errors():
    with pytest.raises(InputError):
        CommandLight("", "off")
    with pytest.raises(InputError):
        CommandLight("laser 'on", "off")
    with pytest.raises(InputError):
        CommandLight("on", "off", timeout_s=0)
    with pytest.raises(LightSpecError):
        parse_light_spec("cmd:only-one-command")


def test_quoted_comma_in_a_command():
    spec = parse_light_spec("cmd:gpio set 'a,b',gpio clear x")
    assert spec.on_cmd == "gpio set 'a,b'" and spec.off_cmd == "gpio clear x"
