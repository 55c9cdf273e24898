"""Thin-lens geometry, PSFs and rendering: physics identities and gradients."""

import pytest
import torch

from tdfd import Camera
from tdfd.errors import InputError, NonFiniteError, ShapeError
from tdfd.optics import (blur_radius, camera_sigmas, defocus_layered, defocus_uniform, depth_from_sigma,
                         depth_from_square_difference, depth_from_square_difference_sensor_varying,
                         gaussian_otf, gaussian_psf, kernel_size_for, pillbox_otf, pillbox_psf,
                         gaussian_psf_1d, power_exponential_psf, psf_kernel, psf_second_moment, render_at_power,
                         render_pair, sampled_psf,
                         sensor_varying_sigmas, sigma_difference, sigma_from_depth, sigma_map)

REF = Camera.preset("reference")
PAPER = Camera.preset("paper")


# ----------------------------------------------------------------------------- thin lens
def test_zero_blur_at_focus():
    for p in (0.5, 1.7, 2.7, 3.2):
        d = REF.focus_distance_m(p)
        from tdfd.optics import blur_radius_from_power
        assert abs(float(blur_radius_from_power(REF, torch.tensor(d, dtype=torch.float64), p))) < 1e-15


def test_sign_convention_beyond_focus_is_positive():
    f = REF.focal_lengths_m[0]
    d_f = REF.focus_distance_m(REF.lens_powers_dpt[0])
    assert float(blur_radius(d_f * 1.5, f, REF.sensor_distance_m, REF.aperture_m)) > 0
    assert float(blur_radius(d_f / 1.5, f, REF.sensor_distance_m, REF.aperture_m)) < 0


def test_depth_sigma_depth_round_trip():
    d = torch.linspace(0.25, 1.5, 50, dtype=torch.float64)
    for f in REF.focal_lengths_m:
        s = sigma_from_depth(d, f, REF.sensor_distance_m, REF.aperture_m, REF.mu_px_per_m)
        back = depth_from_sigma(s, f, REF.sensor_distance_m, REF.aperture_m, REF.mu_px_per_m)
        assert torch.allclose(back, d, rtol=1e-12)


def test_sigma_difference_is_independent_of_depth_eq6():
    d = torch.linspace(0.3, 1.0, 20, dtype=torch.float64)
    s1, s2 = camera_sigmas(REF, d)
    expected = sigma_difference(*REF.focal_lengths_m, REF.sensor_distance_m, REF.aperture_m, REF.mu_px_per_m)
    assert torch.allclose(s1 - s2, expected.expand_as(d), rtol=1e-12)
    assert float(expected) == pytest.approx(REF.sigma_difference_px)


def test_square_difference_solve_round_trip():
    d = torch.linspace(0.3, 1.0, 30, dtype=torch.float64)
    s1, s2 = camera_sigmas(REF, d)
    q, r1, r2 = depth_from_square_difference(REF, s1 ** 2 - s2 ** 2)
    assert torch.allclose(1 / q, d, rtol=1e-12)
    assert torch.allclose(r1, s1) and torch.allclose(r2, s2)


def test_paper_worked_numbers_are_consistent():
    """Paper sec. 4 / Fig. 9: F1 = 9.30 cm, F2 = 8.63 cm, A = 1 cm, d_s = 9.8 cm, d_o = 75.4 cm."""
    F1, F2, A, ds, do, mu = 0.0930, 0.0863, 0.01, 0.098, 0.754, PAPER.mu_px_per_m
    s1 = sigma_from_depth(do, F1, ds, A, mu)
    s2 = sigma_from_depth(do, F2, ds, A, mu)
    # eq. 4 by hand
    assert float(s1) == pytest.approx(mu * A / 2 * ds * (1 / F1 - 1 / do - 1 / ds), rel=1e-6)
    # eq. 6: sigma1 - sigma2 fixed by the focal settings
    assert float(s1 - s2) == pytest.approx(mu * A * ds / 2 * (1 / F1 - 1 / F2), rel=1e-6)
    # eq. 5 from either sigma gives back 75.4 cm
    assert float(depth_from_sigma(s1, F1, ds, A, mu)) == pytest.approx(do, rel=1e-6)
    assert float(depth_from_sigma(s2, F2, ds, A, mu)) == pytest.approx(do, rel=1e-6)
    # eqs. 6 + 13 + 5 through the camera description
    q, _, _ = depth_from_square_difference(PAPER, torch.tensor(float(s1 ** 2 - s2 ** 2), dtype=torch.float64))
    assert 1 / float(q) == pytest.approx(do, rel=1e-9)
    # the focal length that focuses 75.4 cm lies between F1 and F2
    f_focus = 1 / (1 / do + 1 / ds)
    assert F2 < f_focus < F1


def test_sensor_varying_variant_round_trip():
    f, ds, a, mu = 0.025, (0.0262, 0.0258), 0.002, 9.4e4
    d = torch.tensor([0.4, 0.6, 0.9], dtype=torch.float64)
    s1, s2 = sensor_varying_sigmas(d, f, ds, a, mu)
    da, db = depth_from_square_difference_sensor_varying(s1 ** 2 - s2 ** 2, f, ds, a, mu)
    hit = torch.minimum((da - d).abs(), (db - d).abs())
    assert float(hit.max()) < 1e-9
    with pytest.raises(InputError):
        depth_from_square_difference_sensor_varying(1.0, f, (0.025, 0.025), a, mu)


# ----------------------------------------------------------------------------- PSFs
@pytest.mark.parametrize("shape", ["gaussian", "pillbox", 4.0, 10.0])
def test_psfs_sum_to_one_and_delta_at_zero(shape):
    s = torch.tensor([0.0, 0.3, 1.0, 2.5, 5.0], dtype=torch.float64)
    k = psf_kernel(s, shape, kernel_size_for(5.0, "gaussian"))
    assert torch.allclose(k.sum((-1, -2)), torch.ones(5, dtype=torch.float64), atol=1e-12)
    c = k.shape[-1] // 2
    assert float(k[0, c, c]) == pytest.approx(1.0, abs=1e-9)
    assert bool((k >= 0).all())


@pytest.mark.parametrize("shape", ["gaussian", "pillbox", 4.0])
def test_psf_rms_radius_matches_sigma(shape):
    s = torch.tensor([2.0, 4.0], dtype=torch.float64)
    k = psf_kernel(s, shape, kernel_size_for(4.0, "gaussian"))
    # pixel integration adds 1/12 px^2
    assert torch.allclose(psf_second_moment(k), s ** 2 + 1 / 12, rtol=0.03)


def test_one_gaussian_and_one_kernel_size_rule():
    s = torch.tensor([0.0, 0.7, 3.0], dtype=torch.float64)
    k1 = gaussian_psf_1d(s, 15)
    assert torch.equal(k1[..., :, None] * k1[..., None, :], gaussian_psf(s, 15))
    for sigma in (0.5, 2.0, 6.0):  # the rule keeps > 99.9 % of a Gaussian's energy per axis
        size = kernel_size_for(sigma)
        wide = gaussian_psf_1d(torch.tensor([sigma], dtype=torch.float64), 4 * size + 1)[0]
        c = wide.numel() // 2
        assert float(wide[c - size // 2: c + size // 2 + 1].sum()) > 0.999


@pytest.mark.parametrize("beta", [3.0, 8.0])
@pytest.mark.parametrize("supersample", [None, 1, 3, 5])
def test_sampled_power_exponential_keeps_its_rms_radius(beta, supersample):
    s = torch.tensor([0.4, 1.2, 2.0, 4.5], dtype=torch.float64)
    k = power_exponential_psf(s, beta, kernel_size_for(4.5), supersample=supersample)
    assert torch.allclose(k.sum((-1, -2)), torch.ones(4, dtype=torch.float64), atol=1e-12)
    # box integration (or its 1/12 px^2 stand-in at pixel centres) adds the pixel's variance;
    # a sub-pixel PSF is coarsely sampled (on the default 3x grid within 0.05 px^2; pixel
    # centres alone are for blurs above 1.5 px)
    assert torch.allclose(psf_second_moment(k)[1:], s[1:] ** 2 + 1 / 12, rtol=0.04)
    if supersample != 1:
        assert torch.allclose(psf_second_moment(k), s ** 2 + 1 / 12, atol=0.05)
    # a stretched metric passed to sampled_psf widens the kernel along x only
    wide = sampled_psf(s, beta, kernel_size_for(9.0), 3, radius2=lambda yy, xx: ((xx / 2) ** 2 + yy ** 2)[None].expand(4, -1, -1))
    assert torch.allclose(psf_second_moment(wide)[1:], 4 * s[1:] ** 2 + 1 / 12, rtol=0.06)
    assert torch.allclose(psf_second_moment(wide.transpose(-1, -2))[1:], s[1:] ** 2 + 1 / 12, rtol=0.06)


def test_psf_shape_errors():
    with pytest.raises(InputError):
        psf_kernel(torch.tensor([1.0]), "square", 9)
    with pytest.raises(ShapeError):
        gaussian_psf(torch.tensor([1.0]), 8)
    with pytest.raises(InputError):
        power_exponential_psf(torch.tensor([1.0]), 0.5, 9)


def test_otfs():
    w = torch.linspace(0, 2, 9, dtype=torch.float64)
    s = torch.tensor(1.5, dtype=torch.float64)
    assert torch.allclose(gaussian_otf(s, w), torch.exp(-0.5 * 2.25 * w ** 2))
    assert float(pillbox_otf(s, torch.tensor(0.0))) == pytest.approx(1.0)
    # first zero of the disk OTF at R omega = 3.8317
    assert float(pillbox_otf(s, torch.tensor(3.8317 / 3.0, dtype=torch.float64))) == pytest.approx(0.0, abs=1e-4)


def test_psf_kernels_gradcheck_float64():
    s = torch.tensor([0.8, 1.7], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda x: gaussian_psf(x, 9), (s,), fast_mode=True)
    assert torch.autograd.gradcheck(lambda x: pillbox_psf(x, 9), (s,), fast_mode=True)
    assert torch.autograd.gradcheck(lambda x: power_exponential_psf(x, 4.0, 9, supersample=2), (s,), fast_mode=True)


# ----------------------------------------------------------------------------- rendering
def _texture(n=64, b=2, seed=0, dtype=torch.float32):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(b, 1, n, n, generator=g, dtype=dtype)


def test_delta_psf_keeps_the_image():
    x = _texture()
    assert torch.allclose(defocus_uniform(x, torch.zeros(2)), x, atol=1e-6)
    assert torch.allclose(defocus_layered(x, torch.zeros_like(x)), x, atol=1e-6)


@pytest.mark.parametrize("shape", ["gaussian", "pillbox"])
def test_blur_preserves_energy_of_a_point_source(shape):
    x = torch.zeros(1, 1, 65, 65, dtype=torch.float64)
    x[..., 32, 32] = 1.0
    y = defocus_uniform(x, torch.tensor([3.0], dtype=torch.float64), shape)
    assert float(y.sum()) == pytest.approx(1.0, abs=1e-9)
    assert float(psf_second_moment(y[0, 0])) == pytest.approx(9.0 + 1 / 12, rel=0.02)


def test_layered_render_of_constant_sigma_equals_uniform():
    x = _texture(96)
    s = torch.full((2, 1, 96, 96), 1.3)
    assert torch.allclose(defocus_layered(x, s + 1e-4 * torch.rand(2, 1, 96, 96)), defocus_uniform(x, torch.full((2,), 1.3)), atol=2e-3)


def test_occlusion_near_layer_covers_far_layer():
    # sharp near half (sigma 0) beside a blurred far half: the near edge stays sharp
    x = torch.zeros(1, 1, 64, 64)
    x[..., 32:] = 1.0
    s = torch.zeros(1, 1, 64, 64)
    s[..., 32:] = 4.0  # far, bright, blurred
    y = defocus_layered(x, s)
    assert float(y[0, 0, 32, 20]) < 1e-3      # near dark region untouched by the far blur
    assert float(y[0, 0, 32, 34]) > 0.5       # far region keeps its brightness near the edge


def test_render_pair_uniform_path_matches_geometry():
    x = _texture(64, 1, dtype=torch.float64)
    d = torch.full((1, 1, 64, 64), 0.8, dtype=torch.float64)
    i1, _ = render_pair(REF, x, d)
    s1, _ = camera_sigmas(REF, 0.8)
    assert torch.allclose(i1, defocus_uniform(x, s1.reshape(1).double()))


def test_render_errors():
    x = _texture()
    with pytest.raises(ShapeError):
        defocus_uniform(x[0], torch.zeros(1))
    with pytest.raises(ShapeError):
        defocus_uniform(x, torch.zeros(3))
    with pytest.raises(NonFiniteError):
        defocus_uniform(x, torch.tensor([float("nan"), 1.0]))
    with pytest.raises(InputError):
        render_at_power(REF, x, -torch.ones_like(x), 1.7)
    with pytest.raises(ShapeError):
        render_at_power(REF, x, torch.ones(2, 1, 32, 32), 1.7)


def test_render_gradcheck_wrt_depth_and_camera_parameters():
    x = _texture(24, 1, dtype=torch.float64)
    # a two-plane scene (occlusion edge down the middle); gradients w.r.t. both depths
    mask = torch.zeros(1, 1, 24, 24, dtype=torch.float64)
    mask[..., 12:] = 1.0
    depths = torch.tensor([0.7, 0.45], dtype=torch.float64, requires_grad=True)
    # camera parameters in millimetres so that finite differences are well scaled
    f_mm = torch.tensor(REF.focal_lengths_m[0] * 1e3, dtype=torch.float64, requires_grad=True)
    aperture_mm = torch.tensor(REF.aperture_m * 1e3, dtype=torch.float64, requires_grad=True)

    def fn(dd, f_, a_):
        d = dd[0] * (1 - mask) + dd[1] * mask
        s = sigma_from_depth(d, f_ * 1e-3, REF.sensor_distance_m, a_ * 1e-3, REF.mu_px_per_m)
        return defocus_layered(x, s, "gaussian", layer_spacing=0.5)

    assert torch.autograd.gradcheck(fn, (depths, f_mm, aperture_mm), eps=1e-6, atol=1e-5, fast_mode=True)


def test_sigma_map_batch_powers():
    d = torch.full((2, 1, 4, 4), 0.5, dtype=torch.float64)
    s = sigma_map(REF, d, torch.tensor([1.7, 2.7], dtype=torch.float64))
    s1, s2 = camera_sigmas(REF, 0.5)
    assert float(s[0, 0, 0, 0]) == pytest.approx(float(s1)) and float(s[1, 0, 0, 0]) == pytest.approx(float(s2))
