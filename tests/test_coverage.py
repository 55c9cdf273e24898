"""Which cameras a model covers: the ``tdfd.coverage`` metadata, the load-time check in
``DepthRuntime(..., camera=...)`` and the shipped model's coverage (issue 18)."""

from __future__ import annotations

import json

import numpy as np
import onnx
import pytest

from export.verify import check_contract
from tdfd import Camera
from tdfd.camera_file import CameraFile
from tdfd.contract import COVERAGE_KEY, METADATA_KEYS
from tdfd.coverage import COVERAGE_TOLERANCE_PX, camera_coverage, check_coverage
from tdfd.errors import CameraError, ModelError
from tdfd.runtime import DepthRuntime

REF = Camera.preset("reference")
#: twice the aperture on twice the pixel pitch: the same blur in pixels at every depth
TWIN = REF.replace(aperture_m=4e-3, pixel_pitch_m=10.6e-6, mu_px_per_m=1 / (2 * 10.6e-6), name="twin")
APERTURE = REF.replace(aperture_m=1e-3, apertures_m=(1e-3, 0.5e-3), lens_powers_dpt=(0.0, 0.0), name="aperture-pair")


def eq4_px(cam: Camera, depth: float, frame: int) -> float:
    """Paper eq. 4 typed in: mu (A/2) d_s (1/F - 1/d_o - 1/d_s)."""
    f, ds, a = cam.focal_lengths_m[frame], cam.frame_sensor_distances_m[frame], cam.frame_apertures_m[frame]
    return cam.mu_px_per_m * a / 2 * ds * (1 / f - 1 / depth - 1 / ds)


def test_coverage_is_both_frames_blur_over_the_working_range():
    cov = camera_coverage(REF)
    assert set(cov) == {"sigma1_px", "sigma2_px", "depth_range_m", "tolerance_px"}
    # blur is linear in inverse depth: the extremes are at the range ends
    for i, key in enumerate(("sigma1_px", "sigma2_px")):
        ends = sorted(eq4_px(REF, d, i) for d in REF.depth_range_m)
        assert cov[key] == pytest.approx(ends, abs=1e-9)
    assert cov["depth_range_m"] == [0.3, 1.0] and cov["tolerance_px"] == COVERAGE_TOLERANCE_PX
    assert json.loads(json.dumps(cov)) == cov


@pytest.mark.parametrize("cam", [REF, TWIN, REF.replace(depth_range_m=(0.35, 0.9)), REF.replace(fixed_focal_length_m=0.025)],
                         ids=["itself", "pixel-twin", "narrower", "same"])
def test_covered_cameras(cam):
    check_coverage(REF, camera_coverage(REF), cam)


@pytest.mark.parametrize("cam,match", [
    (REF.replace(depth_range_m=(0.25, 1.0)), r"frame 1 blurs .* the model covers"),
    (REF.replace(depth_range_m=(0.3, 1.5)), r"frame 1 blurs .* the model covers"),
    (REF.replace(mu_px_per_m=REF.mu_px_per_m * 1.01), "would be wrong"),
    (REF.replace(lens_powers_dpt=(1.7, 2.8)), "would be wrong"),
    (REF.replace(fixed_focal_length_m=0.0249), "would be wrong"),
    (APERTURE, "would be wrong"),
])
def test_uncovered_cameras_are_refused(cam, match):
    with pytest.raises(ModelError, match=match) as info:
        check_coverage(REF, camera_coverage(REF), cam, "m.onnx", "cam.json")
    assert "m.onnx" in str(info.value) and "model.camera=cam.json" in str(info.value)


@pytest.mark.parametrize("bad", [None, {}, {"sigma1_px": [1, 0], "sigma2_px": [0, 1], "tolerance_px": 0.01},
                                 {"sigma1_px": [0, 1], "sigma2_px": [0, float("nan")], "tolerance_px": 0.01},
                                 {"sigma1_px": [0, 1], "sigma2_px": [0, 1], "tolerance_px": -1}])
def test_malformed_coverage_is_a_model_error(bad):
    with pytest.raises(ModelError, match="tdfd.coverage"):
        check_coverage(REF, bad, REF)


def test_coverage_is_an_extra_key_not_a_contract_key():
    assert COVERAGE_KEY == "tdfd.coverage" and COVERAGE_KEY not in METADATA_KEYS
    assert METADATA_KEYS == ("tdfd.camera", "tdfd.grid", "tdfd.version")  # CONTRACT.md section 2


# ------------------------------------------------------------------------- runtime
def test_runtime_checks_the_users_camera_at_load_time(exported_onnx, tmp_path):
    path, model = exported_onnx
    meta = {p.key: json.loads(p.value) for p in onnx.load(str(path)).metadata_props}
    assert meta[COVERAGE_KEY] == camera_coverage(model.camera)
    rt = DepthRuntime(path, threads=1)
    assert rt.camera == rt.model_camera == REF
    rt = DepthRuntime(path, threads=1, camera=TWIN)
    assert rt.camera == TWIN and rt.model_camera == REF
    assert rt.in_focus_power_dpt(0.5) == pytest.approx(TWIN.in_focus_power_dpt(0.5))
    assert DepthRuntime(path, threads=1, camera="reference").camera == REF
    good = CameraFile(REF.replace(depth_range_m=(0.4, 0.8))).write(tmp_path / "narrow.json")
    assert DepthRuntime(path, threads=1, camera=good).camera.depth_range_m == (0.4, 0.8)
    bad = CameraFile(APERTURE).write(tmp_path / "aperture.json")
    with pytest.raises(ModelError, match=r"does not cover camera .*aperture\.json"):
        DepthRuntime(path, threads=1, camera=bad)
    with pytest.raises(CameraError, match="missing.json"):
        DepthRuntime(path, threads=1, camera=tmp_path / "missing.json")


def test_runtime_refuses_a_check_against_a_model_without_coverage(exported_onnx, tmp_path):
    proto = onnx.load(str(exported_onnx[0]))
    keep = [(p.key, p.value) for p in proto.metadata_props if p.key != COVERAGE_KEY]
    del proto.metadata_props[:]
    for k, v in keep:
        proto.metadata_props.add(key=k, value=v)
    old = tmp_path / "old.onnx"
    onnx.save(proto, str(old))
    assert DepthRuntime(old, threads=1).camera == REF  # still loads without a camera to check
    with pytest.raises(ModelError, match="states no 'tdfd.coverage'"):
        DepthRuntime(old, threads=1, camera=REF)


def test_contract_check_validates_coverage(exported_onnx):
    path, model = exported_onnx
    proto = onnx.load(str(path))
    assert check_contract(proto, model)[COVERAGE_KEY] == camera_coverage(REF)
    for value in ("{bad", json.dumps({"sigma1_px": [0, 1]}), json.dumps({**camera_coverage(REF), "sigma1_px": [0.0, 1.0]})):
        bad = onnx.ModelProto()
        bad.CopyFrom(proto)
        for p in bad.metadata_props:
            if p.key == COVERAGE_KEY:
                p.value = value
        with pytest.raises(ModelError, match="coverage"):
            check_contract(bad, model)


def test_shipped_model_states_its_coverage(shipped_onnx):
    meta = {p.key: p.value for p in onnx.load(str(shipped_onnx), load_external_data=False).metadata_props}
    cov = json.loads(meta[COVERAGE_KEY])
    assert cov == camera_coverage(REF)
    assert np.allclose(cov["sigma1_px"], [-3.85, 1.65], atol=0.01)
    rt = DepthRuntime(shipped_onnx, threads=1, camera=REF.replace(depth_range_m=(0.35, 0.9)))
    assert rt.camera.depth_range_m == (0.35, 0.9)
