"""The model trained for the calibrated bench camera (models/bench_calibrated, issue 18): it
serves both calibrations of that camera, the self-calibrated one as is and the
known-distance one (whose fixed lens it measured 0.30 dpt stronger) with its inverse depth
shifted; the shipped reference model serves neither."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tdfd.errors import ModelError
from tdfd.runtime import DepthRuntime

ROOT = Path(__file__).resolve().parents[1]
HERE = ROOT / "models" / "bench_calibrated"
MODEL = HERE / "model.onnx"


def f0(name: str) -> float:
    return json.loads((HERE / name).read_text())["fixed_focal_length_m"]


def test_the_model_serves_the_self_calibrated_camera_at_its_own_depth():
    rt = DepthRuntime(MODEL, threads=1, camera=HERE / "CAM-self.json")
    assert rt.inverse_depth_offset_dpt == 0.0
    assert rt.model_camera.depth_range_m == (0.3, 1.5)  # trained on the widened range (CAM-self-wide.json)
    assert rt.magnification_per_dpt == pytest.approx(json.loads((HERE / "CAM-self.json").read_text())["magnification_per_dpt"])


def test_the_model_serves_the_known_distance_calibration_with_a_shift():
    rt = DepthRuntime(MODEL, threads=1, camera=HERE / "CAM-known-distance.json")
    # q_model - q_camera = the model camera's fixed-lens power minus this camera's (same ECVFL powers)
    expected = 1 / f0("CAM-self-wide.json") - 1 / f0("CAM-known-distance.json")
    assert expected == pytest.approx(-0.300, abs=0.002)
    assert rt.inverse_depth_offset_dpt == pytest.approx(expected, abs=2e-3)


@pytest.mark.parametrize("cam", ["CAM-self.json", "CAM-known-distance.json"])
def test_the_shipped_model_refuses_the_calibrated_camera(cam, shipped_onnx):
    with pytest.raises(ModelError, match="does not cover camera"):
        DepthRuntime(shipped_onnx, threads=1, camera=HERE / cam)
