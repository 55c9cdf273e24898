"""``tdfd autofocus`` light options: one clear line for bad input, the lens never touched."""

from __future__ import annotations

import os

import pytest

from tdfd.cli import main
from tdfd.driver import EmulatorServer


@pytest.fixture()
def lens_port():
    with EmulatorServer(temperature_c=22.0) as srv:
        yield srv


def _pty_name():
    master, slave = os.openpty()
    return master, slave, os.ttyname(slave)


@pytest.mark.parametrize("extra,message", [
    (["--assist-light", "laser:/dev/ttyUSB0"], "unknown form"),
    (["--assist-light", "serial:/dev/ttyUSB0:cts"], "serial:PORT:rts or serial:PORT:dtr"),
    (["--assist-light", "serial:/dev/tdfd-no-such-port:rts"], "cannot open the assist-light port '/dev/tdfd-no-such-port'"),
    (["--assist-light", "PTY"], "errno 25"),
    (["--illumination", "coherent"], "--illumination on hardware needs the light named with --assist-light"),
])
def test_bad_light_input_is_one_line_and_the_lens_is_untouched(lens_port, capsys, extra, message):
    fds = []
    if extra[-1] == "PTY":
        master, slave, name = _pty_name()
        fds = [master, slave]
        extra = [extra[0], f"serial:{name}:rts"]
    try:
        rc = main(["autofocus", "--port", lens_port.port, "--camera", "/nonexistent-camera", "--model", "analytic",
                   *extra])
    finally:
        for fd in fds:
            os.close(fd)
    err = capsys.readouterr().err.strip()
    assert rc == 1
    assert len(err.splitlines()) == 1 and message in err and err.startswith("tdfd autofocus: error:")
    assert lens_port.device.command_count == 0  # nothing reached the lens


def test_assist_light_on_the_bench_is_refused(capsys):
    rc = main(["autofocus", "--sim", "--assist-light", "serial:loop://:rts", "--trials", "1"])
    err = capsys.readouterr().err.strip()
    assert rc == 1 and "--illumination coherent|projector" in err and len(err.splitlines()) == 1


def test_sim_uniform_scene_with_the_coherent_light(capsys):
    rc = main(["autofocus", "--sim", "--scene", "uniform", "--illumination", "coherent", "--trials", "2",
               "--method", "dfd", "--model", "analytic", "--no-progress", "--compute", "1", "--readout", "192x224"])
    out = capsys.readouterr().out
    assert rc == 0
    assert "in focus (blur < 1 px): 2/2" in out and "assist light: lit 2 of 2 DFD trials" in out


def test_sigterm_runs_the_interrupt_exit_path(tmp_path):
    import subprocess
    import sys

    state = tmp_path / "laser"
    code = f"""
import os, pathlib, signal, sys
from tdfd.autofocus.light_cli import sigterm_as_interrupt
from tdfd.light import CommandLight, LightGuard
w = lambda t: [sys.executable, '-c', f"import pathlib; pathlib.Path({str(state)!r}).write_text({{t!r}})"]
guard = LightGuard(CommandLight(w('on'), w('off')))
try:
    with sigterm_as_interrupt(), guard.request():
        guard.switch_on()
        assert pathlib.Path({str(state)!r}).read_text() == 'on'
        os.kill(os.getpid(), signal.SIGTERM)
        signal.pause()
except KeyboardInterrupt:
    print('interrupted', pathlib.Path({str(state)!r}).read_text())
"""
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "interrupted off"


def test_subtract_ambient_without_a_light_is_refused(capsys):
    rc = main(["autofocus", "--sim", "--subtract-ambient", "--trials", "1"])
    err = capsys.readouterr().err.strip()
    assert rc == 1 and "--subtract-ambient needs a light" in err
