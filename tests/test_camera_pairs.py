"""Any varying camera parameter (issue 18): two ECVFL powers, two sensor distances (paper,
remark after eq. 13) or two apertures (Pentland) - camera JSON, eq. 4 per frame, the depth
solve, the renderer, registration and the analytic estimator's accuracy."""

import json

import pytest
import torch

from tdfd import Camera
from tdfd.breathing import magnify
from tdfd.camera_file import CameraFile, load_camera_file
from tdfd.dfd import FourierRatioDFD, register_sensor_pair
from tdfd.dfd.calibrate import calibrate_mu
from tdfd.errors import CameraError, ShapeError
from tdfd.forward import defocus_pair
from tdfd.optics import (camera_sigmas, defocus_uniform, depth_from_square_difference,
                         depth_from_square_difference_sensor_varying, render_pair, square_difference_slope)
from tdfd.optics.render import frame_sigma_map
from tdfd.textures import fractal

REF = Camera.preset("reference")
#: Pentland's aperture pair: 1 mm and 0.5 mm, both frames focused at infinity.
APERTURE = REF.replace(aperture_m=1e-3, apertures_m=(1e-3, 0.5e-3), lens_powers_dpt=(0.0, 0.0), name="aperture-pair")
#: The sensor moves from 25.0 mm to 25.5 mm between the frames, ECVFL fixed at 2.2 dpt.
SENSOR = REF.replace(lens_powers_dpt=(2.2, 2.2), sensor_distances_m=(0.025, 0.0255), name="sensor-pair")
#: Everything varies at once.
MIXED = REF.replace(apertures_m=(2e-3, 1.5e-3), sensor_distances_m=(0.025, 0.0252), name="mixed")
#: Moderate blur (|sigma| <= 2 px in both frames) for each camera.
MODERATE = {"aperture-pair": [0.6, 0.65, 0.7, 0.8, 0.9, 1.0], "sensor-pair": [0.34, 0.36, 0.38, 0.40, 0.42, 0.44]}


def pink_texture(n: int, batch: int, seed: int) -> torch.Tensor:
    return (0.2 + 0.6 * fractal(n, torch.Generator().manual_seed(seed), batch, beta=2.0)).float()


def eq4(depth, f, ds, a, mu):
    """Paper eq. 4 typed in: sigma = mu (A/2) d_s (1/F - 1/d_o - 1/d_s)."""
    return mu * (a / 2) * ds * (1 / f - 1 / depth - 1 / ds)


# ------------------------------------------------------------------------- camera JSON
@pytest.mark.parametrize("cam", [APERTURE, SENSOR, MIXED], ids=lambda c: c.name)
def test_per_frame_keys_round_trip(cam, tmp_path):
    d = cam.to_dict()
    assert ("apertures_m" in d) == (cam.apertures_m is not None)
    assert ("sensor_distances_m" in d) == (cam.sensor_distances_m is not None)
    assert Camera.from_dict(d) == cam
    assert Camera.from_json(cam.to_json()) == cam
    path = CameraFile(cam, magnification_per_dpt=0.002).write(tmp_path / "cam.json")
    back = load_camera_file(path)
    assert back.camera == cam and back.extra == {}
    assert json.loads(path.read_text())["focal_lengths_m"] == pytest.approx(list(cam.focal_lengths_m))


def test_default_camera_json_is_unchanged():
    assert REF.sensor_distances_m is None and REF.apertures_m is None and REF.varying == ("lens_power",)
    assert set(REF.to_dict()) == {"aperture_m", "sensor_distance_m", "focal_lengths_m", "pixel_pitch_m",
                                  "depth_range_m", "mu_px_per_m", "fixed_focal_length_m", "lens_powers_dpt"}
    # two equal per-frame values are no variation: the same camera, the contract's keys only
    same = REF.replace(sensor_distances_m=(0.025, 0.025), apertures_m=(2e-3, 2e-3))
    assert same == REF and same.to_dict() == REF.to_dict()


def test_shipped_model_metadata_camera_is_the_reference(shipped_onnx):
    import onnx

    meta = {p.key: p.value for p in onnx.load(str(shipped_onnx), load_external_data=False).metadata_props}
    cam = json.loads(meta["tdfd.camera"])
    assert "sensor_distances_m" not in cam and "apertures_m" not in cam
    assert Camera.from_dict(cam) == REF


def test_per_frame_value_may_stand_in_for_the_scalar():
    d = SENSOR.to_dict()
    del d["sensor_distance_m"]
    assert Camera.from_dict(d) == SENSOR
    assert SENSOR.varying == ("sensor_distance",) and APERTURE.varying == ("aperture",)
    assert MIXED.varying == ("lens_power", "sensor_distance", "aperture")
    assert SENSOR.image_scale_ratio == pytest.approx(1.02) and APERTURE.image_scale_ratio == 1.0


@pytest.mark.parametrize("change,match", [
    (dict(apertures_m=(2e-3,)), "pair"),
    (dict(apertures_m=(2e-3, -1e-3)), r"apertures_m\[1\]"),
    (dict(apertures_m=(2e-3, float("nan"))), r"apertures_m\[1\]"),
    (dict(sensor_distances_m=(0.025, "x")), r"sensor_distances_m\[1\]"),
    (dict(sensor_distances_m=(0.026, 0.027)), "frame 1"),
    (dict(apertures_m=(1e-3, 2e-3)), "frame 1"),
    (dict(lens_powers_dpt=(2.0, 2.0)), "must differ"),
    (dict(lens_powers_dpt=(2.0, 2.0), apertures_m=(2e-3, 2e-3)), "must differ"),
    # aperture pair focused inside the working range: depths either side of focus blur alike
    (dict(lens_powers_dpt=(2.0, 2.0), apertures_m=(2e-3, 1e-3)), "straddles"),
])
def test_bad_per_frame_values_raise_camera_error(change, match):
    with pytest.raises(CameraError, match=match):
        REF.replace(**change)


def test_bad_per_frame_value_in_a_file_names_the_file(tmp_path):
    p = tmp_path / "bad.json"
    p.write_text(json.dumps({**REF.to_dict(), "apertures_m": [2e-3, 0]}))
    with pytest.raises(CameraError, match="bad.json.*apertures_m"):
        load_camera_file(p)


def test_sigma_difference_is_refused_where_it_depends_on_depth():
    assert REF.sigma_difference_px == pytest.approx(float(camera_sigmas(REF, 0.5)[0] - camera_sigmas(REF, 0.5)[1]))
    for cam in (APERTURE, SENSOR):
        with pytest.raises(CameraError, match="depends on depth"):
            cam.sigma_difference_px


# ------------------------------------------------------------------------- physics
@pytest.mark.parametrize("cam", [REF, APERTURE, SENSOR, MIXED], ids=lambda c: c.name)
def test_frame_sigmas_are_eq4_with_the_varying_subscript(cam):
    d = torch.tensor([0.3, 0.45, 0.7, 1.0], dtype=torch.float64)
    s = camera_sigmas(cam, d)
    for i in (0, 1):
        want = eq4(d, cam.focal_lengths_m[i], cam.frame_sensor_distances_m[i], cam.frame_apertures_m[i], cam.mu_px_per_m)
        assert torch.allclose(s[i], want, rtol=1e-12)
        assert torch.allclose(frame_sigma_map(cam, d.reshape(1, 1, 2, 2), i).flatten(), want, rtol=1e-12)


def test_aperture_pair_sigmas_scale_with_aperture_and_sign_convention_holds():
    # one sensor distance and focal length: sigma_i proportional to A_i; focused at infinity,
    # every finite object is nearer than focus, so sigma < 0 (thin_lens.py's convention)
    s1, s2 = camera_sigmas(APERTURE, torch.tensor([0.3, 0.6, 1.0], dtype=torch.float64))
    assert torch.allclose(s2, 0.5 * s1) and bool((s1 < 0).all())


@pytest.mark.parametrize("cam", [REF, APERTURE, SENSOR, MIXED], ids=lambda c: c.name)
def test_depth_solve_inverts_eq4_over_the_range(cam):
    d = torch.linspace(0.3, 1.0, 15, dtype=torch.float64)
    s1, s2 = camera_sigmas(cam, d)
    q, r1, r2 = depth_from_square_difference(cam, s1 * s1 - s2 * s2)
    assert torch.allclose(q, 1.0 / d, rtol=1e-9)
    assert torch.allclose(r1, s1, atol=1e-9) and torch.allclose(r2, s2, atol=1e-9)  # signs come out of the solve


@pytest.mark.parametrize("cam", [APERTURE, SENSOR], ids=lambda c: c.name)
def test_the_mirrored_root_gives_the_same_blur_pair_and_is_rejected(cam):
    """D(q) is symmetric about the turning point: the other root is a real ambiguity, and the
    solve takes the working range's side."""
    q = torch.tensor([1.2, 2.5], dtype=torch.float64)
    mirror = 2 * cam.turning_inverse_depth - q
    s = [camera_sigmas(cam, 1.0 / x) for x in (q, mirror)]
    dsq = [a * a - b * b for a, b in s]
    assert torch.allclose(dsq[0], dsq[1], rtol=1e-9)
    assert torch.allclose(depth_from_square_difference(cam, dsq[1])[0], q, rtol=1e-9)


def test_sensor_pair_solve_agrees_with_the_papers_variant():
    d = 0.4
    s1, s2 = camera_sigmas(SENSOR, d)
    roots = depth_from_square_difference_sensor_varying(s1 * s1 - s2 * s2, SENSOR.focal_lengths_m[0],
                                                        SENSOR.sensor_distances_m, SENSOR.aperture_m, SENSOR.mu_px_per_m)
    q = float(depth_from_square_difference(SENSOR, s1 * s1 - s2 * s2)[0])
    assert min(abs(1.0 / float(r) - q) for r in roots) < 1e-9


@pytest.mark.parametrize("cam", [APERTURE, SENSOR, MIXED], ids=lambda c: c.name)
def test_depth_solve_gradcheck_and_slope(cam):
    s1, s2 = camera_sigmas(cam, torch.tensor([0.35, 0.6, 0.95], dtype=torch.float64))
    dsq = (s1 * s1 - s2 * s2).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x: depth_from_square_difference(cam, x)[0], (dsq,))
    (g,) = torch.autograd.grad(depth_from_square_difference(cam, dsq)[0].sum(), dsq)
    q = depth_from_square_difference(cam, dsq)[0].detach()
    assert torch.allclose(1.0 / g.abs(), square_difference_slope(cam, q), rtol=1e-7)


def test_slope_of_the_ecvfl_pair_is_eq6():
    assert float(square_difference_slope(REF, 2.0)) == pytest.approx(
        2 * REF.mu_px_per_m * REF.blur_scale_m_dpt * abs(REF.sigma_difference_px))


# ------------------------------------------------------------------------- renderer
@pytest.mark.parametrize("cam", [APERTURE, SENSOR], ids=lambda c: c.name)
def test_renderer_blurs_each_frame_by_its_own_sigma(cam):
    x = pink_texture(64, 1, seed=3).double()
    d = 0.5
    i1, i2 = render_pair(cam, x, torch.full_like(x, d))
    s1, s2 = camera_sigmas(cam, d)
    assert torch.allclose(i1, defocus_uniform(x, s1.reshape(1)), atol=1e-12)
    assert torch.allclose(i2, defocus_uniform(x, s2.reshape(1)), atol=1e-12)
    pair = defocus_pair(cam, x, torch.full_like(x, d))
    assert torch.allclose(pair[:, 0:1], i1, atol=1e-9) and torch.allclose(pair[:, 1:2], i2, atol=1e-9)


def test_renderer_two_planes_per_frame():
    """A step depth map: each side of the step away from the edge is the uniform render."""
    x = pink_texture(96, 1, seed=4).double()
    depth = torch.full_like(x, 0.4)
    depth[..., 48:] = 0.8
    pair = defocus_pair(SENSOR, x, depth)
    for i in (0, 1):
        for d, cols in ((0.4, slice(8, 30)), (0.8, slice(66, 88))):
            s = camera_sigmas(SENSOR, d)[i]
            want = defocus_uniform(x, s.reshape(1))
            assert torch.allclose(pair[:, i:i + 1, 16:80, cols], want[..., 16:80, cols], atol=2e-3)


# ------------------------------------------------------------------------- registration
def test_registration_undoes_the_sensor_pairs_magnification():
    x = defocus_uniform(pink_texture(96, 2, seed=5).double(), torch.tensor(1.0))  # a defocused frame
    assert register_sensor_pair(x, APERTURE) is x
    mag = torch.from_numpy(magnify(x.numpy(), SENSOR.image_scale_ratio))
    back = register_sensor_pair(mag, SENSOR)
    assert back.shape == x.shape and back.dtype == x.dtype
    inner = (slice(None), slice(None), slice(12, -12), slice(12, -12))
    err_back, err_mag = (float((y - x)[inner].abs().mean()) for y in (back, mag))
    assert err_back < 0.1 * err_mag
    with pytest.raises(ShapeError):
        register_sensor_pair(x[:, 0], SENSOR)


# ------------------------------------------------------------------------- estimator
@pytest.mark.parametrize("cam", [APERTURE, SENSOR], ids=lambda c: c.name)
def test_analytic_moderate_blur_accuracy_within_one_percent(cam):
    """As test_dfd's ECVFL test: noise-free Gaussian renders, |sigma| <= 2 px, 64-px tiles."""
    m = FourierRatioDFD(cam, tile=64, stride=64)
    errors = []
    for i, d in enumerate(MODERATE[cam.name]):
        s1, s2 = camera_sigmas(cam, d)
        assert max(abs(float(s1)), abs(float(s2))) <= 2.0
        x = pink_texture(192, 2, seed=i)
        i1, i2 = render_pair(cam, x, torch.full_like(x, d))
        depth, conf = m(i1, i2)
        errors.append(((depth - d).abs() / d).flatten())
        assert bool((conf > 0.5).all())
    assert float(torch.cat(errors).median()) <= 0.01


def test_sensor_pair_with_magnified_frame_registered_within_one_percent():
    """Frame 2 as a real sensor-distance pair takes it (d_s2/d_s1 = 1.02 larger), registered."""
    m = FourierRatioDFD(SENSOR, tile=64, stride=64)
    errors = []
    for i, d in enumerate(MODERATE["sensor-pair"]):
        x = pink_texture(192, 2, seed=20 + i)
        i1, i2 = render_pair(SENSOR, x, torch.full_like(x, d))
        i2 = torch.from_numpy(magnify(i2.double().numpy(), SENSOR.image_scale_ratio)).float().clamp(0, 1)
        depth, _ = m(i1, register_sensor_pair(i2, SENSOR).clamp(0, 1))
        errors.append(((depth - d).abs() / d).flatten())
    assert float(torch.cat(errors).median()) <= 0.01


def test_mu_calibrates_on_an_aperture_pair():
    x = pink_texture(128, 1, seed=9)
    d = 0.7
    i1, i2 = render_pair(APERTURE, x, torch.full_like(x, d))
    assert calibrate_mu(APERTURE, [(i1, i2, d)], tile=128) == pytest.approx(APERTURE.mu_px_per_m, rel=0.01)
