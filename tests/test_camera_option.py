"""A camera file as well as a preset name: ``python -m training --set model.camera=PATH.json``
and ``python -m export --camera PATH.json`` (issue 18)."""

from __future__ import annotations

import json
from pathlib import Path

import onnx
import pytest

from tdfd import Camera
from tdfd.camera_file import CameraFile, resolve_camera
from tdfd.errors import CameraError
from tests.tiny_training import TINY
from training.config import ConfigError, load_config
from training.data import build_model

HERE = Path(__file__).resolve().parent
REF = Camera.preset("reference")
#: a camera that is no preset: an aperture pair focused at infinity, other focal length and pixels
APERTURE = Camera(aperture_m=1.2e-3, apertures_m=(1.2e-3, 0.6e-3), sensor_distance_m=0.016, fixed_focal_length_m=0.016,
                  lens_powers_dpt=(0.0, 0.0), pixel_pitch_m=3.45e-6, depth_range_m=(0.3, 1.0),
                  mu_px_per_m=1 / (2 * 3.45e-6))



@pytest.fixture
def cam_file(tmp_path) -> Path:
    return CameraFile(APERTURE).write(tmp_path / "mycam.json")


# ------------------------------------------------------------------------- resolve_camera
def test_resolve_camera_takes_presets_and_files(cam_file):
    assert resolve_camera("reference") == REF and resolve_camera("paper") == Camera.preset("paper")
    assert resolve_camera(cam_file) == APERTURE and resolve_camera(str(cam_file)) == APERTURE


def test_resolve_camera_errors_name_the_file(tmp_path):
    with pytest.raises(CameraError, match="missing.json"):
        resolve_camera(tmp_path / "missing.json")
    bad = tmp_path / "broken.json"
    bad.write_text("{not json")
    with pytest.raises(CameraError, match="broken.json.*invalid JSON"):
        resolve_camera(bad)
    incomplete = tmp_path / "incomplete.json"
    incomplete.write_text(json.dumps({"aperture_m": 0.002}))
    with pytest.raises(CameraError, match="incomplete.json.*lacks"):
        resolve_camera(incomplete)
    with pytest.raises(CameraError, match="neither a preset"):
        resolve_camera("refrence")


# ------------------------------------------------------------------------- training
def test_training_config_takes_a_camera_file(cam_file):
    cfg = load_config(None, [f"model.camera={cam_file}", "model.tile=32", "model.stride=16", "model.hidden=4"])
    assert cfg.model.camera == str(cam_file)
    assert build_model(cfg.model).camera == APERTURE


def test_training_config_refuses_a_bad_camera_naming_it(tmp_path, capsys):
    with pytest.raises(ConfigError, match=r"model\.camera: .*nope\.json"):
        load_config(None, [f"model.camera={tmp_path / 'nope.json'}"])
    from training.__main__ import main

    with pytest.raises(SystemExit):
        main(["--print-config", "--set", f"model.camera={tmp_path / 'nope.json'}"])
    assert "nope.json" in capsys.readouterr().err


def test_train_and_export_for_a_camera_file(tmp_path, cam_file, monkeypatch, capsys):
    """A tiny training run on the camera file, then export checked against the same file."""
    monkeypatch.syspath_prepend(str(HERE))
    from export.__main__ import main as export_main
    from training.loop import train

    cfg = load_config(None, TINY + [f"out_dir={tmp_path / 'run'}", f"model.camera={cam_file}"])
    train(cfg)
    from tdfd.model import DFDModel

    stem = tmp_path / "run" / "model"
    assert DFDModel.load(stem).camera == APERTURE
    out = tmp_path / "mycam.onnx"
    args = ["--weights", str(stem.with_suffix(".safetensors")), "--out", str(out), "--sizes", "64x64", "--batches", "1"]
    assert export_main(args + ["--camera", str(cam_file)]) == 0
    meta = {p.key: json.loads(p.value) for p in onnx.load(str(out)).metadata_props}
    assert Camera.from_dict(meta["tdfd.camera"]) == APERTURE
    capsys.readouterr()
    # the same weights are refused for another camera, naming it
    assert export_main(args + ["--camera", "reference"]) == 1
    assert "not for reference" in capsys.readouterr().err
    assert export_main(args + ["--camera", str(tmp_path / "gone.json")]) == 1
    assert "gone.json" in capsys.readouterr().err


def test_export_analytic_layer_for_a_camera_file(tmp_path, cam_file):
    from export.__main__ import main as export_main

    out = tmp_path / "analytic.onnx"
    assert export_main(["--analytic", "--camera", str(cam_file), "--out", str(out), "--sizes", "64x64",
                        "--batches", "1"]) == 0
    meta = {p.key: json.loads(p.value) for p in onnx.load(str(out)).metadata_props}
    assert meta["tdfd.camera"]["apertures_m"] == [1.2e-3, 0.6e-3]
    assert Camera.from_dict(meta["tdfd.camera"]) == APERTURE
