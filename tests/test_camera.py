"""Camera description: presets, conversions, contract JSON."""

import json
import math

import pytest

from tdfd import Camera
from tdfd.errors import CameraError


def test_reference_preset_matches_contract():
    cam = Camera.preset("reference")
    assert cam.fixed_focal_length_m == 0.025
    assert cam.sensor_distance_m == 0.025
    assert cam.aperture_m == 0.002
    assert cam.pixel_pitch_m == 5.3e-6
    assert cam.lens_powers_dpt == (1.7, 2.7)
    assert cam.depth_range_m == (0.3, 1.0)
    # ECVFL at 0 dpt focuses at infinity
    assert math.isinf(cam.focus_distance_m(0.0))
    # |r_b| about 8 px at the ends of the range (CONTRACT.md section 1)
    from tdfd.optics import camera_blur_radii_px
    worst = max(abs(float(camera_blur_radii_px(cam, d, p))) for d in (0.3, 1.0) for p in cam.lens_powers_dpt)
    assert 7.0 < worst < 8.5


def test_to_dict_is_exactly_the_contract_keys():
    d = Camera.preset("reference").to_dict()
    assert set(d) == {"aperture_m", "sensor_distance_m", "focal_lengths_m", "pixel_pitch_m", "depth_range_m",
                      "mu_px_per_m", "fixed_focal_length_m", "lens_powers_dpt"}
    assert d["focal_lengths_m"] == pytest.approx([1 / (40 + 1.7), 1 / (40 + 2.7)])
    json.dumps(d)


@pytest.mark.parametrize("name", ["reference", "paper"])
def test_json_round_trip(name):
    cam = Camera.preset(name)
    assert Camera.from_json(cam.to_json()) == cam


def test_paper_preset_focal_lengths():
    cam = Camera.preset("paper")
    assert cam.focal_lengths_m == pytest.approx((0.0930, 0.0863), rel=1e-12)
    assert cam.aperture_m == 0.01 and cam.sensor_distance_m == 0.098 and cam.mu_px_per_m == 2.74e5


def test_in_focus_power_inverts_focus_distance():
    cam = Camera.preset("reference")
    for d in (0.3, 0.45, 0.7, 1.0):
        assert cam.focus_distance_m(cam.in_focus_power_dpt(d)) == pytest.approx(d)
    assert cam.ecvfl_power_dpt(cam.focal_length_m(2.2)) == pytest.approx(2.2)


@pytest.mark.parametrize("change", [dict(aperture_m=0), dict(aperture_m=float("nan")), dict(pixel_pitch_m=-1),
                                    dict(lens_powers_dpt=(2.0, 2.0)), dict(depth_range_m=(1.0, 0.3)),
                                    dict(mu_px_per_m="x")])
def test_invalid_cameras_raise_camera_error(change):
    with pytest.raises(CameraError):
        Camera.preset("reference").replace(**change)


def test_unknown_preset_and_inconsistent_json():
    with pytest.raises(CameraError, match="unknown camera preset"):
        Camera.preset("nope")
    d = Camera.preset("reference").to_dict()
    d["focal_lengths_m"] = [0.02, 0.03]
    with pytest.raises(CameraError, match="disagree"):
        Camera.from_dict(d)
    with pytest.raises(CameraError):
        Camera.from_json("{not json")
