"""The relative blur's own uncertainty and the noise estimate the frames of one run share
(issue 20: the verification frames on periodic and band-limited textures).

A sharp periodic texture inflates a frame's own noise estimate (its pixel-scale edges leak
into the estimator's pass band), which biased the relative blur towards zero; and a
texture whose frequencies the blur has wiped out pins the relative blur down far less than
a broadband one. Both are measured here on typed-in Gaussian blurs of known variance.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from tdfd import Camera
from tdfd.autofocus.evidence import pair_focus_interval, shared_noise_variance, verify_focus
from tdfd.autofocus.relative_blur import RelativeBlur, relative_blur, relative_blur_px2
from tdfd.autofocus.sharpness import noise_variance
from tdfd.errors import InputError

NOISE = 0.01
YY, XX = np.mgrid[:128, :128]


def blurred(image: np.ndarray, sigma: float) -> np.ndarray:
    return image if sigma < 1e-3 else cv2.GaussianBlur(image, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)


def noisy(image: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    return (image + NOISE * rng.standard_normal(image.shape)).astype(np.float32)


def checkers(period_px: float) -> np.ndarray:
    s = np.sin(2 * np.pi * XX / period_px + 0.3) * np.sin(2 * np.pi * YY / period_px + 0.3)
    return (0.5 + 0.3 * np.sign(s)).astype(np.float32)


def broadband(seed: int = 5, sigma: float = 1.0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    t = cv2.GaussianBlur(rng.standard_normal((128, 128)).astype(np.float32), (0, 0), sigma)
    return (0.5 + 0.1 * t / t.std()).astype(np.float32)


def test_a_sharp_checkerboard_inflates_its_own_noise_estimate_but_not_the_shared_one():
    rng = np.random.default_rng(0)
    sharp, blurry = noisy(blurred(checkers(6), 0.5), rng), noisy(blurred(checkers(6), 2.0), rng)
    assert noise_variance(sharp) > 10 * NOISE**2  # the texture leaks in (28x here)
    assert shared_noise_variance([sharp, blurry]) == pytest.approx(NOISE**2, rel=0.25)
    assert shared_noise_variance([sharp, blurry]) == min(noise_variance(sharp), noise_variance(blurry))
    with pytest.raises(InputError, match="at least one frame"):
        shared_noise_variance([])


@pytest.mark.parametrize("sigma_b", [2.0, 3.0])
def test_the_inflated_noise_estimate_biases_the_relative_blur_and_the_shared_one_does_not(sigma_b):
    """A checkerboard (period 6 px) over a broadband texture: with each frame's own noise
    estimate the relative blur is low by more than 4 of its standard uncertainties; with the
    shared estimate it is within 2."""
    rng = np.random.default_rng(0)
    scene = checkers(6) + broadband() - 0.5
    a, b = noisy(blurred(scene, 0.5), rng), noisy(blurred(scene, sigma_b), rng)
    true = sigma_b**2 - 0.25
    own = relative_blur(a, b)
    shared = relative_blur(a, b, noise_var=shared_noise_variance([a, b]))
    assert true - own.px2 > 4 * own.sd_px2
    assert abs(shared.px2 - true) < 2 * shared.sd_px2


@pytest.mark.parametrize("sigmas", [(0.5, 2.0), (1.0, 3.0)])
def test_the_stated_uncertainty_matches_the_spread_over_noise_draws(sigmas):
    """Broadband texture, 40 independent noise draws: the median stated standard uncertainty
    is the observed standard deviation within 0.7-1.6x (the local Cramér-Rao bound of the
    fit), and the mean is within 1 % of the truth plus two of it (OpenCV's discrete kernel
    at sigma 0.5 px is about 1 % off a Gaussian's variance)."""
    rng = np.random.default_rng(1)
    scene = broadband(sigma=1.0)
    runs = [relative_blur(noisy(blurred(scene, sigmas[0]), rng), noisy(blurred(scene, sigmas[1]), rng),
                          noise_var=NOISE**2) for _ in range(40)]
    est = np.array([m.px2 for m in runs])
    stated = float(np.median([m.sd_px2 for m in runs]))
    assert 0.7 < stated / est.std() < 1.6
    true = sigmas[1] ** 2 - sigmas[0] ** 2
    assert abs(est.mean() - true) < 0.01 * true + 2 * stated


def test_a_texture_the_blur_wipes_out_is_measured_with_a_large_uncertainty():
    """Stripes of period 6 px blurred by sigma 4 px keep 2e-4 of their contrast: the relative
    blur against the sharp frame is barely pinned down (uncertainty > 20x a broadband
    texture's at the same blurs), and a checkerboard blurred to nothing says it may be
    anything from its true 8.75 px² to the search limit."""
    rng = np.random.default_rng(2)
    stripes = (0.5 + 0.3 * np.sin(2 * np.pi * XX / 6)).astype(np.float32)
    m_stripes = relative_blur(noisy(blurred(stripes, 0.5), rng), noisy(blurred(stripes, 4.0), rng), noise_var=NOISE**2)
    m_broad = relative_blur(noisy(blurred(broadband(), 0.5), rng), noisy(blurred(broadband(), 4.0), rng),
                            noise_var=NOISE**2)
    assert abs(m_broad.px2 - 15.75) < 3 * m_broad.sd_px2
    assert m_stripes.sd_px2 > 20 * m_broad.sd_px2
    gone = relative_blur(noisy(blurred(checkers(6), 0.5), rng), noisy(blurred(checkers(6), 3.0), rng),
                         noise_var=NOISE**2)
    assert gone.sd_px2 > 100 * m_broad.sd_px2 and abs(gone.px2 - 8.75) < 3 * gone.sd_px2


def test_relative_blur_px2_is_relative_blur_and_noise_var_is_checked():
    rng = np.random.default_rng(3)
    a, b = noisy(blurred(broadband(), 0.7), rng), noisy(blurred(broadband(), 2.0), rng)
    m = relative_blur(a, b, noise_var=NOISE**2)
    assert isinstance(m, RelativeBlur) and relative_blur_px2(a, b, noise_var=NOISE**2) == m.px2
    for bad in (-1e-4, math.nan, math.inf):
        with pytest.raises(InputError, match="noise_var"):
            relative_blur(a, b, noise_var=bad)


def test_a_flat_scene_measures_nothing_and_verification_says_why():
    """Noise-free flat frames: no relative blur is measurable (infinite uncertainty); the
    verification fails with that reason instead of an arbitrary focus error, and the pair's
    interval is unbounded (it allows every power: no second opinion)."""
    cam = Camera.preset("reference")
    flat = np.full((128, 160), 0.5, np.float32)
    assert relative_blur(flat, flat).sd_px2 == math.inf
    p1, p2 = cam.lens_powers_dpt
    check = verify_focus(flat, 2.2, [(flat, p1), (flat, p2)], cam)
    assert not check.passed and not check.consistent and math.isnan(check.error_dpt)
    assert "does not measure the relative blur" in check.reason
    assert pair_focus_interval(flat, p1, flat, p2, cam) == (-math.inf, math.inf)


def test_a_verification_frame_less_sharp_than_a_reference_never_passes():
    """The paper camera (4x binned), a frame at focus checked against the DFD pair and a
    first verification frame 0.3 dpt off: it passes, being the sharpest (ratio r > 1 to its
    sharpest reference); asked to be 2r as sharp it fails, its references counted as not
    agreeing (the rule that stops a periodic texture's misleading relative blurs from
    declaring a frame in focus that a reference out-sharpens); ``min_sharpness_ratio=0``
    disables the rule."""
    from tdfd.autofocus.evidence import sigma_px_per_dpt
    from tdfd.autofocus.sharpness import sharpness

    paper = Camera.preset("paper")
    PAPER4 = paper.replace(pixel_pitch_m=4 * paper.pixel_pitch_m, sensor_size_px=(300, 400),
                           mu_px_per_m=1 / (2 * 4 * paper.pixel_pitch_m), name="paper4")  # as paper_experiment bins it
    rng = np.random.default_rng(1)
    sharp = (0.2 + 0.6 * cv2.GaussianBlur(rng.random((256, 256)).astype(np.float32), (0, 0), 1.0)).astype(np.float32)

    def paper_frames(p_star: float, powers: list[float]) -> list[np.ndarray]:  # Gaussian blur M |P - P*| (eq. 7)
        return [blurred(sharp, sigma_px_per_dpt(PAPER4) * abs(p - p_star)) for p in powers]

    p1, p2 = PAPER4.lens_powers_dpt
    p_star = p2 + 0.8
    v_ok, v_first, f1, f2 = paper_frames(p_star, [p_star + 0.005, p_star + 0.3, p1, p2])
    refs = [(f1, p1), (f2, p2), (v_first, p_star + 0.3)]
    tol = 0.8 / 23.113
    r = sharpness(v_ok) / max(sharpness(im) for im, _ in refs)
    assert r > 1.0
    ok = verify_focus(v_ok, p_star + 0.005, refs, PAPER4, tolerance_dpt=tol)
    assert ok.passed and ok.consistent, ok.reason
    strict = verify_focus(v_ok, p_star + 0.005, refs, PAPER4, tolerance_dpt=tol, min_sharpness_ratio=2 * r)
    assert not strict.passed and not strict.consistent and "less sharp than a reference" in strict.reason
    assert strict.error_dpt == ok.error_dpt  # the relative blurs are the same; only the verdict changes
    off = verify_focus(v_ok, p_star + 0.005, refs, PAPER4, tolerance_dpt=tol, min_sharpness_ratio=0.0)
    assert off.passed
