"""Which cameras a model covers: the ``tdfd.coverage`` metadata, the load-time check in
``DepthRuntime(..., camera=...)`` and the shipped model's coverage (issue 18)."""

from __future__ import annotations

import json
from pathlib import Path

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
    assert check_coverage(REF, camera_coverage(REF), cam) == 0.0


@pytest.mark.parametrize("f0,ecvfl_shift", [(0.0249, 0.0), (0.0252, 0.0), (0.025, 0.3), (0.0249, -0.2)])
def test_a_camera_with_another_fixed_lens_power_is_served_with_an_inverse_depth_offset(f0, ecvfl_shift):
    """Eq. 4 depends on 1/F - 1/d_o only: a fixed lens (or both ECVFL powers) stronger by
    delta blurs at q as the model's camera at q - delta, for both frames alike."""
    p1, p2 = REF.lens_powers_dpt
    cam = REF.replace(fixed_focal_length_m=f0, lens_powers_dpt=(p1 + ecvfl_shift, p2 + ecvfl_shift),
                      depth_range_m=(0.34, 0.7))
    delta_typed = (1 / REF.fixed_focal_length_m - 1 / f0) - ecvfl_shift  # model's total power minus the camera's
    offset = check_coverage(REF, camera_coverage(REF), cam)
    assert offset == pytest.approx(delta_typed, abs=1e-9)
    for d in (0.34, 0.5, 0.7):  # the camera at d blurs as the model's camera at 1/(1/d + offset)
        d_model = 1 / (1 / d + offset)
        for frame in (0, 1):
            assert eq4_px(cam, d, frame) == pytest.approx(eq4_px(REF, d_model, frame), abs=1e-9)


def test_an_offset_camera_whose_shifted_blur_leaves_the_covered_range_is_refused():
    cam = REF.replace(fixed_focal_length_m=0.0249)  # 0.16 dpt stronger: its 1 m blurs as the model's 1.19 m
    with pytest.raises(ModelError, match=r"frame 1 blurs .* the model covers"):
        check_coverage(REF, camera_coverage(REF), cam)


@pytest.mark.parametrize("cam,match", [
    (REF.replace(depth_range_m=(0.25, 1.0)), r"frame 1 blurs .* the model covers"),
    (REF.replace(depth_range_m=(0.3, 1.5)), r"frame 1 blurs .* the model covers"),
    (REF.replace(mu_px_per_m=REF.mu_px_per_m * 1.01), "would be wrong"),
    (REF.replace(lens_powers_dpt=(1.7, 2.8)), "would be wrong"),
    (REF.replace(lens_powers_dpt=(1.8, 2.7)), "at best under a shift of inverse depth"),
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


def test_runtime_returns_the_offset_cameras_depth(exported_onnx, tmp_path):
    """A camera whose fixed lens is 0.16 dpt stronger: the same frames give its depth,
    1/(1/d_model - offset), and its in-focus power equals the model camera's for the frames."""
    path, _ = exported_onnx
    cam = REF.replace(fixed_focal_length_m=0.0249, depth_range_m=(0.34, 0.7), name="stronger-f0")
    plain = DepthRuntime(path, threads=1)
    shifted = DepthRuntime(path, threads=1, camera=CameraFile(cam).write(tmp_path / "f0.json"))
    offset = shifted.inverse_depth_offset_dpt
    assert plain.inverse_depth_offset_dpt == 0.0 and offset == pytest.approx(1 / 0.025 - 1 / 0.0249, abs=1e-9)
    rng = np.random.default_rng(3)
    f1, f2 = (rng.random((96, 96)).astype(np.float32) for _ in range(2))
    a, b = plain(f1, f2), shifted(f1, f2)
    q_model, q_cam = 1 / a.depth.astype(np.float64), 1 / b.depth.astype(np.float64)
    inside = (q_model - offset > 1 / 1.4) & (q_model - offset < 2 / 0.34)  # the camera's extended range
    assert inside.any()
    np.testing.assert_allclose(q_cam[inside], q_model[inside] - offset, rtol=1e-5)
    np.testing.assert_array_equal(b.confidence[inside], a.confidence[inside])
    assert np.all(b.confidence[~inside] == 0)
    np.testing.assert_allclose(1 / b.depth_analytic.astype(np.float64)[inside],
                               1 / a.depth_analytic.astype(np.float64)[inside] - offset, rtol=1e-5)
    # the focusing power is a property of the blur, not of the depth convention
    np.testing.assert_allclose(shifted.in_focus_power_dpt(b.depth[inside]), plain.in_focus_power_dpt(a.depth[inside]),
                               atol=1e-4)


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


def test_the_pooled_map_takes_the_offset_cameras_depth_too(tmp_path):
    """The shipped file's structure-pooled map follows the camera's depth convention as the tiles do."""
    path = Path(__file__).resolve().parents[1] / "models" / "reference.onnx"
    cam = REF.replace(fixed_focal_length_m=0.0249, depth_range_m=(0.34, 0.7), name="stronger-f0")
    plain = DepthRuntime(path, threads=1)
    shifted = DepthRuntime(path, threads=1, camera=CameraFile(cam).write(tmp_path / "f0.json"))
    assert plain.has_pooled and shifted.has_pooled
    offset = shifted.inverse_depth_offset_dpt
    rng = np.random.default_rng(4)
    f1, f2 = (rng.random((192, 256)).astype(np.float32) for _ in range(2))
    a, b = plain(f1, f2), shifted(f1, f2)
    q_model, q_cam = 1 / a.depth_pooled.astype(np.float64), 1 / b.depth_pooled.astype(np.float64)
    inside = (q_model - offset > 1 / 1.4) & (q_model - offset < 2 / 0.34)
    assert inside.any()
    np.testing.assert_allclose(q_cam[inside], q_model[inside] - offset, rtol=1e-5)
    np.testing.assert_array_equal(b.confidence_pooled[inside], a.confidence_pooled[inside])
    assert np.all(b.confidence_pooled[~inside] == 0)
