"""The controller's model-free evidence (tdfd.autofocus.evidence): the relative-blur measure
and its search range scaled to the camera's blur (issue 17: the paper camera's blur of tens
of pixels)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from tdfd import Camera
from tdfd.autofocus.evidence import pair_focus_interval, sigma_px_per_dpt, verify_focus
from tdfd.autofocus.relative_blur import MIN_SEARCH_PX2, relative_blur_px2, relative_blur_search_px2, search_margin_px

REF = Camera.preset("reference")
PAPER = Camera.preset("paper")
#: the paper camera binned 4x, as benchmarks/paper_experiment.py simulates it: 21.2 um pixels
PAPER4 = PAPER.replace(pixel_pitch_m=4 * PAPER.pixel_pitch_m, sensor_size_px=(300, 400),
                       mu_px_per_m=1 / (2 * 4 * PAPER.pixel_pitch_m), name="paper4")


def eq4_sigma_px(cam: Camera, depth: float, frame: int) -> float:
    """Paper eq. 4 typed in: sigma = mu (A/2) d_s (1/F - 1/d_o - 1/d_s)."""
    f, ds, a = cam.focal_lengths_m[frame], cam.frame_sensor_distances_m[frame], cam.frame_apertures_m[frame]
    return cam.mu_px_per_m * a / 2 * ds * (1 / f - 1 / depth - 1 / ds)


def scene(size: int = 256, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return (0.2 + 0.6 * cv2.GaussianBlur(rng.random((size, size)).astype(np.float32), (0, 0), 1.0)).astype(np.float32)


def blurred(image: np.ndarray, sigma: float) -> np.ndarray:
    return image if sigma < 1e-3 else cv2.GaussianBlur(image, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)


def test_search_range_keeps_64_px2_for_the_reference_camera():
    assert relative_blur_search_px2(REF) == MIN_SEARCH_PX2 == 64.0
    assert search_margin_px(64.0) == 12


def test_search_range_follows_the_cameras_largest_blur():
    sigma_max = max(abs(eq4_sigma_px(PAPER4, d, i)) for d in PAPER4.depth_range_m for i in (0, 1))
    assert sigma_max > 30  # the binned paper camera blurs by up to ~32 px (RMS) at 0.3 m
    assert relative_blur_search_px2(PAPER4) == pytest.approx((1.5 * sigma_max) ** 2, rel=1e-9)
    assert search_margin_px(relative_blur_search_px2(PAPER4)) == int(np.ceil(1.5 * 1.5 * sigma_max))


def test_relative_blur_is_measured_beyond_64_px2_only_with_the_wider_search():
    sharp = scene()
    a, b = blurred(sharp, 2.0), blurred(sharp, 18.0)  # D = 324 - 4 = 320 px^2
    wide = relative_blur_search_px2(PAPER4)
    d = relative_blur_px2(a, b, max_px2=wide, margin_px=search_margin_px(wide))
    assert d == pytest.approx(320.0, rel=0.05)
    assert relative_blur_px2(b, a, max_px2=wide, margin_px=search_margin_px(wide)) == pytest.approx(-320.0, rel=0.05)
    assert relative_blur_px2(a, b) <= 64.0 + 1e-6  # the former fixed range cannot see it


def paper_frames(p_star: float, powers: list[float], seed: int = 1) -> list[np.ndarray]:
    """Frames of one scene at ECVFL ``powers`` with Gaussian blur M |P - P*| (eq. 7), noise-free."""
    m = sigma_px_per_dpt(PAPER4)
    sharp = scene(seed=seed)
    return [blurred(sharp, m * abs(p - p_star)) for p in powers]


def test_verification_frame_is_judged_on_a_camera_with_large_blur():
    """The paper camera's DFD pair far from focus (sigma 9 and 19 px). The far pair alone
    measures a frame's focus error but, at 6 % of D = 270 px^2, too loosely to confirm 0.8 px
    of blur; with the first verification frame 0.3 dpt away as a near reference (the
    controller's correction step) the frame at focus is confirmed and one 0.15 dpt off is not."""
    p1, p2 = PAPER4.lens_powers_dpt
    p_star = p2 + 0.8
    v_ok, v_off, v_first, f1, f2 = paper_frames(p_star, [p_star + 0.005, p_star + 0.15, p_star + 0.3, p1, p2])
    tol = 0.8 / 23.113  # the controller's 0.8 px of blur radius; (A/2) d_s / pitch = 23.1 px/dpt binned
    far = verify_focus(v_ok, p_star + 0.005, [(f1, p1), (f2, p2)], PAPER4, tolerance_dpt=tol)
    assert far.consistent and far.error_dpt == pytest.approx(0.005, abs=0.02) and not far.passed
    refs = [(f1, p1), (f2, p2), (v_first, p_star + 0.3)]
    ok = verify_focus(v_ok, p_star + 0.005, refs, PAPER4, tolerance_dpt=tol)
    assert ok.passed, ok.reason
    off = verify_focus(v_off, p_star + 0.15, refs, PAPER4, tolerance_dpt=tol)
    assert not off.passed and off.error_dpt == pytest.approx(0.15, abs=0.03)
    # the former fixed 64 px^2 search saturates on the far pair: its focus error is far off
    capped = verify_focus(v_ok, p_star + 0.005, [(f1, p1), (f2, p2)], PAPER4, tolerance_dpt=tol, max_px2=64.0)
    assert not capped.passed and abs(capped.error_dpt - 0.005) > 0.2


def test_pair_interval_on_a_camera_with_large_blur():
    p1, p2 = PAPER4.lens_powers_dpt
    p_star = p2 + 0.8
    f1, f2 = paper_frames(p_star, [p1, p2])
    lo, hi = pair_focus_interval(f1, p1, f2, p2, PAPER4, shape_range=(1.0, 1.0))
    assert lo <= p_star <= hi and hi - lo < 0.35  # 2 x 6 % of D = 270 px^2 on each side
