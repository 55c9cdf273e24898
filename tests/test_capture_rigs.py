"""`tdfd capture`: the hardware rig on the lens emulator (pty) with a fake OpenCV camera,
and the simulated rig through the CLI."""

from __future__ import annotations

import json

import numpy as np
import pytest

from tdfd import Camera
from tdfd.capture import capture_session, parse_pair, parse_sweep, read_folder
from tdfd.capture.hardware import CameraCaptureError, HardwareRig, to_raw_gray
from tdfd.capture.sim import SimulatedRig
from tdfd.camera_file import CameraFile
from tdfd.cli import main
from tdfd.driver import EmulatorServer, OptotuneLens
from tdfd.errors import InputError, LensRangeError


class FakeCapture:
    """A cv2.VideoCapture stand-in: BGR uint8 frames whose brightness follows a counter."""

    def __init__(self, fail_after: int | None = None) -> None:
        self.reads = self.grabs = 0
        self.released = False
        self.fail_after = fail_after

    def grab(self) -> bool:
        self.grabs += 1
        return True

    def read(self):  # noqa: ANN201
        self.reads += 1
        if self.fail_after is not None and self.reads > self.fail_after:
            return False, None
        g = np.random.default_rng(self.reads).integers(40, 200, (48, 64, 3)).astype(np.uint8)
        return True, g

    def release(self) -> None:
        self.released = True


def test_hardware_rig_on_the_emulator_reads_the_power_back(tmp_path) -> None:
    with EmulatorServer(settling_time_s=0.002) as srv:
        lens = OptotuneLens.open(srv.port, timeout_s=0.5)
        cam = FakeCapture()
        rig = HardwareRig(lens, cam, settle_s=0.02, flush=1, white_level=255)
        paths = capture_session(rig, tmp_path, sweep=[0.5, 1.0, 1.5], pairs=[(1.2, 2.2)], distance_m=0.42)
        with pytest.raises(LensRangeError):
            rig.capture(99.0)  # outside the driver's limits: typed, nothing sent
        assert srv.device.commands.count("PwDA") == 5
        rig.close()
    assert cam.released and cam.grabs == 5
    assert len(paths) == 5
    frames = read_folder(tmp_path)
    by_name = {f.name: f for f in frames}
    for name, p in (("sweep000", 0.5), ("sweep002", 1.5), ("pair00_1", 1.2), ("pair00_2", 2.2)):
        meta = by_name[name].metadata
        assert meta.lens_power_dpt == pytest.approx(p, abs=0.01)  # read back (PrDA) from the emulator
        assert meta.temperature_c == pytest.approx(25.0, abs=0.5)
        assert meta.distance_m == 0.42 and meta.white_level == 255
        assert meta.extra["commanded_power_dpt"] == p
    assert by_name["pair00_1"].metadata.pair == by_name["pair00_2"].metadata.pair == "pair00"
    assert by_name["sweep000"].shape == (48, 64)


def test_hardware_rig_reports_a_missing_frame() -> None:
    with EmulatorServer(settling_time_s=0.0) as srv:
        rig = HardwareRig(OptotuneLens.open(srv.port, timeout_s=0.5), FakeCapture(fail_after=0), settle_s=0.0)
        with pytest.raises(CameraCaptureError, match="no frame"):
            rig.capture(1.0)
        rig.close()


def test_to_raw_gray() -> None:
    assert to_raw_gray(np.zeros((4, 5, 3), np.uint8)).shape == (4, 5)
    assert to_raw_gray(np.zeros((4, 5), np.uint16)).dtype == np.uint16
    with pytest.raises(CameraCaptureError):
        to_raw_gray(np.zeros((4, 5), np.float32))


def test_parsers() -> None:
    assert parse_sweep("2:1:-0.5") == [2.0, 1.5, 1.0]
    assert parse_pair("1.5,2.5") == (1.5, 2.5)
    for bad in ("1:2", "1:2:0", "1:2:-1", "a:b:c"):
        with pytest.raises(InputError):
            parse_sweep(bad)
    for bad in ("1.5", "1,1", "x,2"):
        with pytest.raises(InputError):
            parse_pair(bad)


def _true_camera(tmp_path):  # noqa: ANN202
    cam = Camera.preset("reference")
    path = tmp_path / "true.json"
    path.write_text(json.dumps({**cam.to_dict(), "ecvfl_offset_dpt": 0.3, "magnification_per_dpt": 0.004}))
    return path


def test_sim_capture_cli_writes_the_contract_format(tmp_path, capsys) -> None:
    cam = _true_camera(tmp_path)
    out = tmp_path / "cap"
    assert main(["capture", str(out), "--sim", "--camera-file", str(cam), "--distance", "0.5",
                 "--sweep", "1:2:0.5", "--pair", "1.7,2.7", "--size", "64", "64"]) == 0
    frames = read_folder(out)
    assert [f.name for f in frames] == ["pair00_1", "pair00_2", "sweep000", "sweep001", "sweep002"]
    assert all(f.metadata.distance_m is None for f in frames)  # not recorded unless asked
    assert frames[0].metadata.white_level == 4095 and frames[0].path.read_bytes()[:4] == b"\x89PNG"
    assert main(["capture", str(tmp_path / "rec"), "--sim", "--camera-file", str(cam), "--distance", "0.5",
                 "--record-distance", "--size", "64", "64"]) == 0  # default: the camera's pair
    rec = read_folder(tmp_path / "rec")
    assert [f.power_dpt for f in rec] == [1.7, 2.7] and {f.metadata.distance_m for f in rec} == {0.5}
    assert main(["capture", str(out), "--sweep", "0:1:0.5"]) == 1  # neither --sim nor hardware named
    assert "needs --port and --camera" in capsys.readouterr().err


def test_simulated_rig_physics() -> None:
    """The rig's true camera: in focus at the commanded power P* = P_in_focus - offset, and
    its frames magnified by 1 + m P about the centre."""
    ref = Camera.preset("reference")
    rig = SimulatedRig(CameraFile(ref, 0.0, 0.3), distance_m=0.5, size=(64, 64), noise=False)
    assert rig.in_focus_command_dpt() == pytest.approx(2.0 - 0.3)
    assert rig.sigma_px(rig.in_focus_command_dpt()) == pytest.approx(0.0, abs=1e-9)
    assert rig.sigma_px(2.7) == pytest.approx(ref.mu_px_per_m * ref.blur_scale_m_dpt * 1.0)


def test_hardware_cli_opens_only_what_it_is_given_and_closes_on_failure(tmp_path, capsys) -> None:
    with EmulatorServer(settling_time_s=0.0) as srv:
        rc = main(["capture", str(tmp_path / "c"), "--port", srv.port, "--camera", str(tmp_path / "no-such.avi"),
                   "--sweep", "0:1:0.5"])
        assert rc == 1
        assert "cannot open camera" in capsys.readouterr().err
        assert srv.device.commands.count("Start") == 1  # the lens was opened (handshake) ...
        with OptotuneLens.open(srv.port, timeout_s=0.5) as again:  # ... and its port closed again
            assert again.firmware_type == "A"
    assert not (tmp_path / "c").exists()
