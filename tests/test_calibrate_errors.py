"""`tdfd calibrate` refuses captures that cannot make a camera, naming the file or region;
and the focus, registration and fitting pieces on known answers."""

from __future__ import annotations

import json

import numpy as np
import pytest

from tdfd import Camera
from tdfd.breathing import magnify
from tdfd.calibration import CalibrationError, calibrate_known_distance, calibrate_self
from tdfd.calibration.fit import group_scenes
from tdfd.calibration.focus import symmetric_peak
from tdfd.calibration.registration import fit_magnification_per_dpt, relative_magnification
from tdfd.camera_file import CameraFile, load_camera_file
from tdfd.capture import capture_session, read_folder, write_frame
from tdfd.capture.folder import CaptureFolderError
from tdfd.capture.sim import SimulatedRig
from tdfd.cli import main
from tdfd.errors import CameraError, InputError

REF = Camera.preset("reference")
TRUE = CameraFile(REF, magnification_per_dpt=0.0, ecvfl_offset_dpt=0.3)


def _sweep(tmp_path, powers, distance=0.5, size=(128, 128), pairs=()):  # noqa: ANN001, ANN202
    capture_session(SimulatedRig(TRUE, distance, size=size, seed=4), tmp_path, sweep=list(powers), pairs=list(pairs))
    return read_folder(tmp_path)


def test_sweep_that_never_reaches_focus_names_the_region_and_frame(tmp_path) -> None:
    frames = _sweep(tmp_path, np.arange(0.0, 1.21, 0.2), pairs=[(0.2, 1.2)])  # in focus at 1.7 dpt: beyond the sweep
    with pytest.raises(CalibrationError, match=r"never reaches focus in region \(row \d, col \d\).*sweep006\.png"):
        calibrate_self(frames, CameraFile(REF))


def test_too_few_sweep_frames(tmp_path) -> None:
    frames = _sweep(tmp_path, [1.5, 1.7, 1.9])
    with pytest.raises(CalibrationError, match="has 3 frames.*at least 5"):
        calibrate_self(frames, CameraFile(REF))


def test_known_distance_route_needs_pairs_with_distances(tmp_path) -> None:
    frames = _sweep(tmp_path, [1.5, 1.7, 1.9], pairs=[(1.7, 2.7)])  # distance not recorded
    with pytest.raises(CalibrationError, match="needs at least one DFD pair.*distance_m") as err:
        calibrate_known_distance(frames, CameraFile(REF))
    assert str(err.value).startswith(f"{tmp_path}: ")  # names the capture folder


def test_self_calibration_without_a_sweep(tmp_path) -> None:
    capture_session(SimulatedRig(TRUE, 0.5, size=(128, 128)), tmp_path, pairs=[(1.7, 2.7)], distance_m=0.5)
    with pytest.raises(CalibrationError, match="needs a focus sweep") as err:
        calibrate_self(read_folder(tmp_path), CameraFile(REF))
    assert str(err.value).startswith(f"{tmp_path}: ")


def test_scenes_are_grouped_per_folder_and_distance(tmp_path) -> None:
    for folder in ("a", "b"):  # two sweeps at the same powers, no distance: one scene per folder
        for k, p in enumerate((1.0, 1.5)):
            write_frame(tmp_path / folder, f"s{k}", np.full((8, 8), 2000, np.uint16), lens_power_dpt=p, white_level=4095)
    frames = read_folder(tmp_path / "a") + read_folder(tmp_path / "b")
    scenes = group_scenes(frames)
    assert [len(s.sweep) for s in scenes] == [2, 2]
    assert [s.folder for s in scenes] == [tmp_path / "a", tmp_path / "b"]
    assert scenes[1].label == f"unknown distance in {tmp_path / 'b'}"
    assert group_scenes(read_folder(tmp_path / "a"))[0].label == "unknown distance"  # one folder: as before
    write_frame(tmp_path / "a", "s9", np.full((8, 8), 2000, np.uint16), lens_power_dpt=1.5, white_level=4095)
    with pytest.raises(CaptureFolderError, match="two sweep frames of one scene"):
        group_scenes(read_folder(tmp_path / "a") + read_folder(tmp_path / "b"))


def test_untextured_scene(tmp_path) -> None:
    for k, p in enumerate(np.arange(1.0, 2.41, 0.2)):
        write_frame(tmp_path, f"s{k}", np.full((64, 64), 2000, np.uint16), lens_power_dpt=float(p), white_level=4095)
    with pytest.raises(CalibrationError, match="no region of the sweep .* has texture"):
        calibrate_self(read_folder(tmp_path), CameraFile(REF))


def test_cli_errors_are_one_line(tmp_path, capsys) -> None:
    (tmp_path / "nominal.json").write_text("{bad")
    assert main(["calibrate", str(tmp_path), "--camera", str(tmp_path / "nominal.json"), "-o", str(tmp_path / "o.json")]) == 1
    assert "nominal.json: invalid JSON" in capsys.readouterr().err
    (tmp_path / "nominal.json").write_text(json.dumps(REF.to_dict()))
    assert main(["calibrate", str(tmp_path / "none"), "--camera", str(tmp_path / "nominal.json"), "-o", str(tmp_path / "o.json")]) == 1
    assert "not a folder" in capsys.readouterr().err


def test_camera_file_round_trip_and_errors(tmp_path) -> None:
    cf = CameraFile(REF, magnification_per_dpt=0.004, calibration={"route": "self"}, extra={"note": "x"})
    back = load_camera_file(cf.write(tmp_path / "c.json"))
    assert back.camera == REF and back.magnification_per_dpt == 0.004 and back.calibration == {"route": "self"}
    assert back.extra == {"note": "x"}
    with pytest.raises(CameraError, match="cannot read"):
        load_camera_file(tmp_path / "missing.json")
    (tmp_path / "m.json").write_text(json.dumps({**REF.to_dict(), "magnification_per_dpt": "big"}))
    with pytest.raises(CameraError, match="m.json: 'magnification_per_dpt' must be a finite number"):
        load_camera_file(tmp_path / "m.json")


def test_symmetric_peak_is_unbiased_off_grid() -> None:
    p = np.arange(0.0, 3.01, 0.25)
    for true in (1.0, 1.07, 1.13, 1.2):
        curve = -np.log1p(((p - true) / 0.3) ** 2)  # not a parabola, not a Gaussian: even in p - true
        assert symmetric_peak(p, curve, half_width=0.7) == pytest.approx(true, abs=0.01)
    with pytest.raises(InputError):
        symmetric_peak(np.array([1.0, 0.5, 2.0]), np.zeros(3), 1.0)


def test_registration_recovers_magnification_and_breathing() -> None:
    x = np.random.default_rng(1).random((256, 256))
    for s in (0.995, 1.004, 1.01):
        rho, n = relative_magnification(x, magnify(x, s))
        assert rho == pytest.approx(s, abs=2e-4) and n >= 9
    pa, pb = np.zeros(4), np.array([0.5, 1.0, 2.0, 3.0])
    m, res = fit_magnification_per_dpt(pa, pb, (1 + 0.004 * pb) / (1 + 0.004 * pa))
    assert m == pytest.approx(0.004, rel=1e-9) and np.abs(res).max() < 1e-12
    with pytest.raises(InputError):
        fit_magnification_per_dpt([1.0], [1.0], [1.0])
