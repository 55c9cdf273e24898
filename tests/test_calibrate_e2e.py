"""End to end on the simulated bench: capture -> calibrate (both routes) -> in-focus power
from a pair, with a camera that is no preset (16 mm lens, 3.45 um pixels, 1.6 mm aperture,
mu 15 % off the datasheet, an ECVFL offset of 0.3 dpt and 0.4 %/dpt breathing that the
nominal file does not know)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from tdfd import Camera
from tdfd.camera_file import CameraFile, load_camera_file
from tdfd.calibration import calibrate_known_distance, calibrate_self, in_focus_power_from_pair
from tdfd.capture import capture_session, read_folder
from tdfd.capture.sim import SimulatedRig
from tdfd.cli import main

PITCH = 3.45e-6
NOMINAL = Camera(aperture_m=1.6e-3, sensor_distance_m=16e-3, fixed_focal_length_m=16e-3, lens_powers_dpt=(1.5, 2.5),
                 pixel_pitch_m=PITCH, depth_range_m=(0.3, 1.0), mu_px_per_m=1 / (2 * PITCH), name="nominal")
TRUE = CameraFile(NOMINAL.replace(mu_px_per_m=1.15 / (2 * PITCH)), magnification_per_dpt=0.004, ecvfl_offset_dpt=0.3)
SIZE = (256, 256)
K_TRUE = TRUE.camera.mu_px_per_m * TRUE.camera.blur_scale_m_dpt


@pytest.fixture(scope="module")
def folders(tmp_path_factory):  # noqa: ANN201
    root = tmp_path_factory.mktemp("e2e")
    sweep = list(np.arange(0.0, 3.51, 0.25))
    capture_session(SimulatedRig(TRUE, 0.5, size=SIZE, seed=1), root / "self", sweep=sweep, pairs=[(1.5, 2.5)])
    for i, d in enumerate((0.4, 0.7)):  # two more scenes, one folder each, no distance recorded
        capture_session(SimulatedRig(TRUE, d, size=SIZE, seed=20 + i), root / f"self{i + 2}", sweep=sweep,
                        pairs=[(1.5, 2.5)])
    for i, d in enumerate((0.35, 0.5, 0.8)):
        capture_session(SimulatedRig(TRUE, d, size=SIZE, seed=10 + i), root / "known", pairs=[(1.5, 2.5)],
                        distance_m=d, prefix=f"d{i}_")
    (root / "nominal.json").write_text(json.dumps(NOMINAL.to_dict()))
    return root


# Issue 18's targets are 0.03 dpt for the in-focus power from one pair across the range and
# 10 % for the breathing. Predictions use 128-px regions (PREDICTION_REGION_PX); at 256x256
# that is 4 regions, and one calibration scene leaves a 1-2 % K error whose effect grows
# towards the range ends (0.35 and 0.95 m, 1.1-1.3 dpt from the pair's midpoint). The
# assertions hold the middle of the range to the target and the ends to twice it;
# docs/BENCHMARKS.md (section calibration) has the figures at 384x384.
MIDDLE, ENDS = 0.03, 0.06


def _check(errs: list[float]) -> None:
    assert max(abs(e) for e in errs[1:3]) <= MIDDLE, errs  # 0.45 and 0.6 m
    assert max(abs(e) for e in errs) <= ENDS, errs


def _errors(cal: CameraFile) -> list[float]:
    out = []
    for i, d in enumerate((0.35, 0.45, 0.6, 0.8, 0.95)):
        rig = SimulatedRig(TRUE, d, size=SIZE, seed=100 + i)
        (f1, _), (f2, _) = rig.capture(1.5), rig.capture(2.5)
        p = in_focus_power_from_pair(cal.camera, f1 / 4095, f2 / 4095, 1.5, 2.5,
                                     magnification_per_dpt=cal.magnification_per_dpt)
        out.append(p - rig.in_focus_command_dpt())
    return out


def test_self_calibration(folders) -> None:
    r = calibrate_self(read_folder(folders / "self"), CameraFile(NOMINAL))
    assert r.k_px_per_dpt == pytest.approx(K_TRUE, rel=0.02)
    assert "datasheet" in r.offset_source  # no known distance: said so
    _check(_errors(r.camera_file))
    # target 10 %: met at 384x384 (benchmark); at 256x256 this scene measures 20 % low
    assert r.magnification_per_dpt == pytest.approx(0.004, rel=0.25)


def test_known_distance_calibration(folders) -> None:
    r = calibrate_known_distance(read_folder(folders / "known"), CameraFile(NOMINAL))
    assert r.k_px_per_dpt == pytest.approx(K_TRUE, rel=0.02)
    # the ECVFL offset (0.3 dpt) folded into the fixed lens: in-focus power of a distance
    assert r.camera_file.camera.in_focus_power_dpt(0.5) == pytest.approx(TRUE.camera.in_focus_power_dpt(0.5) - 0.3, abs=0.03)
    assert "known distances" in r.offset_source
    _check(_errors(r.camera_file))
    assert r.magnification_per_dpt == pytest.approx(0.004, rel=0.1)


def test_calibrate_cli_writes_camera_json_and_plot(folders, tmp_path, capsys) -> None:
    out = tmp_path / "cam.json"
    assert main(["calibrate", str(folders / "known"), "--camera", str(folders / "nominal.json"), "-o", str(out)]) == 0
    text = capsys.readouterr().out
    assert "known-distance route" in text and "residuals pairs: RMS" in text
    cf = load_camera_file(out)  # a valid tdfd.camera object + documented extras
    data = json.loads(out.read_text())
    assert data["calibration"]["route"] == "known-distance" and "residual_rms_dpt" in data["calibration"]
    assert cf.magnification_per_dpt == data["magnification_per_dpt"] != 0
    assert Camera.from_dict(data).mu_px_per_m == cf.camera.mu_px_per_m
    assert out.with_suffix(".png").read_bytes()[:4] == b"\x89PNG"


def test_range_ends_need_large_regions() -> None:
    """The true camera predicts the in-focus power within 0.03 dpt at both range ends, where
    one frame of the pair is blurred by 3.3-3.8 px, with the default 128-px regions; 64-px
    regions under-measure that blur (the measured cause of the range-end misses)."""
    oracle = TRUE.camera.replace(fixed_focal_length_m=1 / (TRUE.camera.fixed_power_dpt + TRUE.ecvfl_offset_dpt))
    for d in (0.3, 1.0):
        rig = SimulatedRig(TRUE, d, size=(384, 384), seed=7, noise=False)
        (f1, _), (f2, _) = rig.capture(1.5), rig.capture(2.5)
        err = {r: in_focus_power_from_pair(oracle, f1 / 4095, f2 / 4095, 1.5, 2.5, magnification_per_dpt=0.004,
                                           **({} if r == "default" else {"region": r})) - rig.in_focus_command_dpt()
               for r in ("default", 64)}
        assert abs(err["default"]) < 0.03, (d, err)
        assert abs(err[64]) > 0.04, (d, err)  # what the default region size fixes


def test_calibrate_cli_self_route_over_three_scene_folders(folders, tmp_path, capsys) -> None:
    out = tmp_path / "cam3.json"
    dirs = [str(folders / name) for name in ("self", "self2", "self3")]
    assert main(["calibrate", *dirs, "--camera", str(folders / "nominal.json"), "-o", str(out), "--no-plot"]) == 0
    assert "self route" in capsys.readouterr().out
    data = json.loads(out.read_text())
    assert data["calibration"]["folder"] == dirs and len(data["calibration"]["scenes"]) == 3
    three = load_camera_file(out)
    k3 = three.camera.mu_px_per_m * three.camera.blur_scale_m_dpt
    assert abs(k3 / K_TRUE - 1) <= 0.01, k3 / K_TRUE - 1  # three scenes average the one scene's K error down
    _check(_errors(three))
