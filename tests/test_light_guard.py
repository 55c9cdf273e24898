"""The light interlock: caps on a fake clock, off on every exit path, the watchdog, atexit."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import pytest

from tdfd.errors import LightError, LightSafetyError
from tdfd.light import LightGuard, LightLimits, SerialLineLight, open_serial_line
from tdfd.light.base import AssistLight


class FakeClock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


class RecordingLight(AssistLight):
    """A light that records every switch (and can be told to fail)."""

    def __init__(self, fail_on: bool = False) -> None:
        super().__init__()
        self.events: list[str] = []
        self.fail_on = fail_on

    def _switch_on(self, pattern):
        self.events.append("on")
        if self.fail_on:
            raise LightError("switch-on failed")

    def _switch_off(self):
        self.events.append("off")


def loop_light():
    return SerialLineLight(open_serial_line("loop://", "rts"), "rts", owns_port=True)


def test_on_time_cap_per_request_refuses_then_resets():
    clock, light = FakeClock(), loop_light()
    guard = LightGuard(light, LightLimits(max_on_s=0.1, max_duty=1.0, duty_window_s=1.0), clock=clock)
    with guard.request():
        for _ in range(2):
            with guard.exposing(expected_s=0.04):
                assert light.port.cts is True
                clock.t += 0.04
            assert light.port.cts is False
        with pytest.raises(LightSafetyError, match="refused"):
            with guard.exposing(expected_s=0.04):
                pytest.fail("the block must not run when the cap refuses")
        assert light.port.cts is False and guard.refusals == 1
        assert guard.request_on_s == pytest.approx(0.08)
    clock.t += 5.0
    with guard.request():  # a new focus request has a fresh on-time budget
        with guard.exposing(expected_s=0.04):
            clock.t += 0.04
    assert light.port.cts is False
    light.close()


def test_overrun_is_forced_off_with_a_typed_error():
    clock, light = FakeClock(), loop_light()
    guard = LightGuard(light, LightLimits(max_on_s=0.1, max_duty=1.0, duty_window_s=1.0), clock=clock)
    with guard.request():
        with pytest.raises(LightSafetyError, match="past its budget"):
            with guard.exposing(expected_s=0.01):
                clock.t += 0.25  # a camera read that hangs with the light on
        assert light.port.cts is False and guard.trips == 1
    # check() trips a light left on as soon as the clock passes its budget
    with guard.request():
        guard.switch_on(expected_s=0.01)
        clock.t += 0.05
        guard.check()  # within budget: nothing happens
        assert light.port.cts is True
        clock.t += 0.06
        with pytest.raises(LightSafetyError, match="forced off"):
            guard.check()
        assert light.port.cts is False and not light.is_on
    light.close()


def test_duty_cap_over_the_sliding_window():
    clock, light = FakeClock(), RecordingLight()
    guard = LightGuard(light, LightLimits(max_on_s=10.0, max_duty=0.1, duty_window_s=1.0), clock=clock)
    on_times = []
    for k in range(6):  # 50 ms on every 100 ms: 50 % wanted, 10 % of 1 s allowed
        with guard.request():
            try:
                with guard.exposing(expected_s=0.05):
                    clock.t += 0.05
                on_times.append(k)
            except LightSafetyError:
                pass
        clock.t += 0.05
    assert on_times == [0, 1]
    assert guard.duty() == pytest.approx(0.1) and guard.refusals == 4
    assert not light.is_on
    clock.t += 1.0  # the window slides past the old on-periods
    with guard.exposing(expected_s=0.05):
        clock.t += 0.05
    assert light.events[-2:] == ["on", "off"]


def test_no_light_named_is_never_on():
    guard = LightGuard(None)
    with pytest.raises(LightSafetyError, match="no assist light was named"):
        with guard.exposing("coherent"):
            pytest.fail("unreachable")
    assert guard.force_off() is True and not guard.is_on


@pytest.mark.parametrize("exc", [ValueError("estimator blew up"), KeyboardInterrupt(), OSError("camera gone")])
def test_off_after_exception_inside_exposure(exc):
    clock, light = FakeClock(), loop_light()
    guard = LightGuard(light, clock=clock)
    with pytest.raises(type(exc)):
        with guard.request():
            with guard.exposing(expected_s=0.002):
                assert light.port.cts is True
                raise exc
    assert light.port.cts is False and not light.is_on
    light.close()


def test_off_after_keyboard_interrupt_in_a_request():
    clock, light = FakeClock(), loop_light()
    guard = LightGuard(light, clock=clock)
    with pytest.raises(KeyboardInterrupt):
        with guard.request():
            guard.switch_on(expected_s=0.002)  # switched on outside an exposure block
            raise KeyboardInterrupt
    assert light.port.cts is False
    light.close()


def test_failed_switch_on_is_accounted_and_off():
    clock, light = FakeClock(), RecordingLight(fail_on=True)
    guard = LightGuard(light, clock=clock)
    with pytest.raises(LightError, match="switch-on failed"):
        guard.switch_on()
    assert light.events == ["on", "off"] and not light.is_on and not guard.is_on


def test_watchdog_switches_off_during_a_blocked_exposure():
    light = loop_light()
    guard = LightGuard(light, LightLimits(max_on_s=0.05, max_duty=1.0, duty_window_s=10.0))  # time.monotonic
    assert guard.watchdog
    with pytest.raises(LightSafetyError, match="watchdog"):
        with guard.request():
            with guard.exposing(expected_s=0.01):
                deadline = time.monotonic() + 2.0
                while light.port.cts and time.monotonic() < deadline:  # a camera read that hangs
                    time.sleep(0.005)
                assert light.port.cts is False  # off while the loop is still blocked
    assert guard.trips == 1
    guard.close()


def test_atexit_switches_off(tmp_path: Path):
    state = tmp_path / "laser"
    code = f"""
import pathlib, sys
from tdfd.light import CommandLight, LightGuard
w = lambda t: [sys.executable, '-c', f"import pathlib; pathlib.Path({str(state)!r}).write_text({{t!r}})"]
guard = LightGuard(CommandLight(w('on'), w('off')))
guard.switch_on(expected_s=0.0)
assert pathlib.Path({str(state)!r}).read_text() == 'on'
raise KeyboardInterrupt  # an unhandled Ctrl-C: no finally of ours runs, atexit does
"""
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert done.returncode != 0 and "KeyboardInterrupt" in done.stderr
    assert state.read_text() == "off"
