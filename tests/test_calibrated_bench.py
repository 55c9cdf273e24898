"""The simulated autofocus bench with a true camera that differs from the controller's
(ECVFL power offset, focus breathing, another mu), and breathing registration in the loop."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from tdfd import Camera
from tdfd.autofocus.estimators import AnalyticEstimator
from tdfd.autofocus.registered import BreathingRegistered
from tdfd.autofocus.sim import Scene, SensorNoise, SimBench, VirtualCamera
from tdfd.breathing import magnify
from tdfd.camera_file import CameraFile
from tdfd.errors import InputError

PITCH = 3.45e-6
NOMINAL = Camera(aperture_m=1.6e-3, sensor_distance_m=16e-3, fixed_focal_length_m=16e-3, lens_powers_dpt=(1.5, 2.5),
                 pixel_pitch_m=PITCH, depth_range_m=(0.3, 1.0), mu_px_per_m=1 / (2 * PITCH), name="nominal")
TRUE = CameraFile(NOMINAL.replace(mu_px_per_m=1.15 / (2 * PITCH)), magnification_per_dpt=0.004, ecvfl_offset_dpt=0.3)
#: the true camera as a perfect calibration writes it (offset folded into the fixed lens)
ORACLE = CameraFile(TRUE.camera.replace(fixed_focal_length_m=1 / (TRUE.camera.fixed_power_dpt + 0.3)),
                    magnification_per_dpt=0.004)
HW = (128, 160)


def _camera(true: CameraFile, scene: Scene) -> VirtualCamera:
    return VirtualCamera(true.camera, scene, lambda t: 0.0, noise=SensorNoise(enabled=False),
                         power_offset_dpt=true.ecvfl_offset_dpt, magnification_per_dpt=true.magnification_per_dpt)


def test_virtual_camera_renders_at_the_real_power_and_breathes() -> None:
    scene = Scene.texture_plane(HW, 0.6, seed=2, families=("fractal",))
    plain = _camera(CameraFile(TRUE.camera), scene)
    offset = _camera(CameraFile(TRUE.camera, ecvfl_offset_dpt=0.3), scene)
    breathing = _camera(TRUE, scene)
    # an offset lens at command P renders what a perfect lens renders at P + offset
    np.testing.assert_allclose(offset.render([1.2]), plain.render([1.5]), atol=1e-6)
    assert np.abs(offset.render([1.2]) - plain.render([1.2])).max() > 0.01
    # breathing magnifies the frame by 1 + m (P + offset) about its centre
    expect = magnify(plain.render([1.5]), 1 + 0.004 * 1.5)
    np.testing.assert_allclose(breathing.render([1.2]), expect, atol=1e-6)
    assert np.abs(breathing.render([1.2]) - plain.render([1.5]))[:, :20].max() > 0.01


def test_bench_truth_is_the_true_camera_contrast_finds_the_offset_lens() -> None:
    """Contrast AF needs no camera model: on the offset lens it must land 0.3 dpt below the
    nominal in-focus power, and the record must call that in focus."""
    with SimBench(camera=NOMINAL, estimator=None, true_camera=TRUE, readout_hw=HW, compute_s=0.0, seed=5,
                  texture_families=("fractal",)) as bench:
        rec = bench.run_trial(0.5, method="contrast")
    nominal_focus = NOMINAL.in_focus_power_dpt(0.5)
    assert rec.ideal_power_dpt == pytest.approx(nominal_focus - 0.3)
    assert rec.in_focus, (rec.status, rec.reason, rec.final_power_dpt, rec.residual_blur_px)
    assert abs(rec.final_power_dpt - rec.ideal_power_dpt) < 0.1


def test_dfd_with_the_calibrated_camera_focuses_the_true_optics() -> None:
    est = BreathingRegistered(AnalyticEstimator(ORACLE.camera), ORACLE.magnification_per_dpt)
    with SimBench(camera=ORACLE.camera, estimator=est, true_camera=TRUE, readout_hw=(192, 256), compute_s=0.005,
                  seed=3, texture_families=("fractal",), evidence_s=0.002) as bench:
        recs = bench.run_trials([0.35, 0.6, 0.9])
    for r in recs:
        assert r.in_focus and r.frames <= 3, (r.target_depth_m, r.status, r.reason, r.residual_blur_px, r.frames)
        assert r.dfd_blur_px < 0.5


def test_breathing_registration_undoes_the_magnification() -> None:
    seen = {}

    class Stub:
        camera, tile, stride, min_confidence = NOMINAL, 32, 16, 0.2

        def __call__(self, a, b):  # noqa: ANN001, ANN204
            seen["a"], seen["b"] = a, b
            return np.zeros((1, 1)), np.zeros((1, 1))

    m = 0.05  # strong breathing (4.4 % between the frames), so whole-pixel moves matter in a small frame
    reg = BreathingRegistered(Stub(), m)
    assert reg.scales == pytest.approx((1 + 1.5 * m, 1 + 2.5 * m)) and reg.min_confidence == 0.2 and reg.tile == 32
    x = cv2.GaussianBlur(np.random.default_rng(0).random((160, 160)), (0, 0), 2.0)  # band-limited, as optics make it
    x = (x - x.mean()) / x.std()
    f1, f2 = magnify(x, reg.scales[0]), magnify(x, reg.scales[1])  # the frames at P1 and P2
    reg(f1, f2)
    inner = np.s_[24:-24, 24:-24]
    before = np.abs(f1 - f2)[inner].mean()
    after = np.abs(seen["a"] - seen["b"])[inner].mean()
    assert before > 0.3 and after < 0.4 * before, (before, after)
    for bad in (np.nan, 0.2):
        with pytest.raises(InputError):
            BreathingRegistered(Stub(), bad)
