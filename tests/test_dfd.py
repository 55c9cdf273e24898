"""Analytic Fourier-ratio DFD: spectra, estimators, solve, confidence, calibration, errors."""

import math

import pytest
import torch

from tdfd import Camera
from tdfd.dfd import FourierRatioDFD, TileSpectra, fft_tile_power, fourier_ratio_dfd, whole_image_dfd
from tdfd.dfd.calibrate import calibrate_mu, mu_from_square_difference, radius_square_difference
from tdfd.errors import DTypeError, InputError, NonFiniteError, RangeError, ShapeError
from tdfd.optics import camera_sigmas, render_pair
from tdfd.textures import fractal

REF = Camera.preset("reference")


def pink_texture(n: int, batch: int, seed: int, dtype=torch.float32) -> torch.Tensor:
    """1/f ("natural image") noise texture in [0.2, 0.8], shape (batch, 1, n, n)."""
    return (0.2 + 0.6 * fractal(n, torch.Generator().manual_seed(seed), batch, beta=2.0)).to(dtype)


# ---------------------------------------------------------------------------- spectra
@pytest.mark.parametrize("tile,stride,prewhiten", [(16, 8, True), (32, 16, False), (24, 24, True), (20, 8, True), (21, 7, False)])
def test_conv_dft_equals_fft(tile, stride, prewhiten):
    x = torch.rand(2, 1, 3 * tile + 5, 2 * tile + 3, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    spec = TileSpectra(tile, stride, max_bin=tile // 2 - 1, prewhiten=prewhiten).double()
    p = spec(x)
    ref = fft_tile_power(x, tile, stride, prewhiten)[..., spec.ky % tile, spec.kx].permute(0, 3, 1, 2)
    assert p.shape == ref.shape
    assert torch.allclose(p, ref, rtol=1e-9, atol=1e-9 * float(ref.abs().max()))


def test_noise_gain_matches_white_noise_power():
    spec = TileSpectra(32, 32, max_bin=10)
    x = torch.randn(8, 1, 320, 320, generator=torch.Generator().manual_seed(0)) * 0.1
    p = spec(x).mean((0, 2, 3)).double()  # 800 tiles
    expected = 0.01 * spec.noise_gain()
    nonzero = expected > 1e-3 * expected.max()
    ratio = p[nonzero] / expected[nonzero]
    assert float(ratio.mean()) == pytest.approx(1.0, abs=0.03)


def test_laplacian_forms_agree_and_match_the_stencil(monkeypatch):
    """Torch eager uses shifted subtractions, export a 3x3 Conv: the same arithmetic."""
    from tdfd.dfd import spectra

    x = torch.rand(2, 1, 20, 31, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    sliced = spectra.laplacian_valid(x)
    monkeypatch.setattr(spectra, "is_exporting", lambda: True)
    conv = spectra.laplacian_valid(x)
    assert sliced.shape == conv.shape == (2, 1, 18, 29)
    torch.testing.assert_close(sliced, conv, rtol=0, atol=1e-12)
    i, j = 6, 8  # output (i - 1, j - 1) is pixel (i, j)
    stencil = 4 * x[1, 0, i, j] - x[1, 0, i - 1, j] - x[1, 0, i + 1, j] - x[1, 0, i, j - 1] - x[1, 0, i, j + 1]
    assert float(sliced[1, 0, i - 1, j - 1]) == pytest.approx(float(stencil), abs=1e-12)
    full = spectra.laplacian_prewhiten(x)
    assert full.shape == x.shape and float(full[..., 0, :].abs().max()) == 0.0 and float(full[..., :, -1].abs().max()) == 0.0


@pytest.mark.parametrize("tile,stride", [(64, 32), (33, 11)])
def test_noise_variance_estimate_on_white_noise(tile, stride):
    """Half-resolution (even grid) and full-resolution (odd grid) estimates of white-noise variance."""
    from tdfd.dfd.fourier_ratio import noise_variance_per_tile
    from tdfd.grid import grid_shape

    g = torch.Generator().manual_seed(5)
    s = 0.02
    x1 = 0.5 + s * torch.randn(2, 1, 200, 230, generator=g, dtype=torch.float64)
    x2 = 0.5 + s * torch.randn(2, 1, 200, 230, generator=g, dtype=torch.float64)
    v = noise_variance_per_tile(x1, x2, tile, stride)
    assert v.shape == (2, 1, *grid_shape(200, 230, tile, stride))
    assert float(v.median()) / s**2 == pytest.approx(1.0, abs=0.08)
    # a smooth ramp adds (almost) nothing: the diagonal difference cancels linear trends
    ramp = torch.linspace(0, 0.3, 230, dtype=torch.float64)[None, None, None, :] + torch.linspace(0, 0.2, 200, dtype=torch.float64)[:, None]
    assert float(noise_variance_per_tile(x1 + ramp, x2 + ramp, tile, stride).median()) / s**2 == pytest.approx(1.0, abs=0.08)


def test_half_resolution_window_mean_is_exact_on_block_constant_images():
    from tdfd.dfd.fourier_ratio import _tile_stats
    from tdfd.dfd.spectra import periodic_hann
    from tdfd.grid import tile_mean

    blocks = torch.rand(2, 1, 50, 61, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    x = blocks.repeat_interleave(2, 2).repeat_interleave(2, 3)  # (2, 1, 100, 122), constant in 2x2 blocks
    w = periodic_hann(32, torch.float64)
    m, _ = _tile_stats(x, 32, 16, w, 1)
    torch.testing.assert_close(m, tile_mean(x, 32, 16, weight=w[:, None] * w[None, :]), rtol=1e-12, atol=1e-12)


def test_grid_shape_follows_the_contract():
    m = FourierRatioDFD(REF, tile=64, stride=32)
    x = torch.full((1, 1, 130, 200), 0.5)
    d, c = m(x, x)
    assert d.shape == (1, 1, (130 - 64) // 32 + 1, (200 - 64) // 32 + 1) == c.shape
    assert m.grid_shape(480, 640) == (14, 19)


# ---------------------------------------------------------------------------- accuracy
@pytest.mark.parametrize("estimator", ["wls", "eq13"])
def test_moderate_blur_accuracy_within_one_percent(estimator):
    """Noise-free Gaussian renders of textured planes with |sigma| <= 2 px (0.39-0.54 m)."""
    m = FourierRatioDFD(REF, tile=64, stride=64, estimator=estimator)
    errors = []
    for i, d in enumerate([0.39, 0.42, 0.45, 0.48, 0.51, 0.54]):
        s1, s2 = camera_sigmas(REF, d)
        assert max(abs(float(s1)), abs(float(s2))) <= 2.05
        x = pink_texture(192, 2, seed=i)
        i1, i2 = render_pair(REF, x, torch.full_like(x, d))
        depth, conf = m(i1, i2)
        errors.append(((depth - d).abs() / d).flatten())
        assert bool((conf > 0.5).all())
    assert float(torch.cat(errors).median()) <= 0.01


def test_whole_range_error_is_bounded_and_signed_solution_is_unique():
    m = FourierRatioDFD(REF, tile=128, stride=128)
    for i, d in enumerate([0.3, 0.7, 1.0]):
        x = pink_texture(256, 1, seed=10 + i)
        i1, i2 = render_pair(REF, x, torch.full_like(x, d))
        r = m.analyse(i1, i2)
        s1, s2 = camera_sigmas(REF, d)
        assert float(((r.depth - d).abs() / d).median()) < 0.05
        # sigma signs come out of the solve (eqs. 6 + 13)
        assert float(r.sigma1.median()) * float(s1) > 0 and float(r.sigma2.median()) * float(s2) > 0


def test_gain_difference_between_frames_does_not_bias_depth():
    m = FourierRatioDFD(REF, tile=64, stride=64)
    x = pink_texture(128, 1, seed=5)
    i1, i2 = render_pair(REF, x, torch.full_like(x, 0.5))
    d0, _ = m(i1, i2)
    d1, _ = m(i1, 0.8 * i2)
    assert torch.allclose(d0, d1, rtol=2e-3)


def test_noise_aware_fit_beats_eq13_with_noise():
    g = torch.Generator().manual_seed(0)
    x = pink_texture(256, 2, seed=7)
    d = 0.8
    i1, i2 = render_pair(REF, x, torch.full_like(x, d))
    i1 = i1 + 0.01 * torch.randn(i1.shape, generator=g)
    i2 = i2 + 0.01 * torch.randn(i2.shape, generator=g)
    err = {}
    for est in ("wls", "eq13"):
        depth, _ = FourierRatioDFD(REF, tile=64, stride=64, estimator=est)(i1, i2)
        err[est] = float(((depth - d).abs() / d).median())
    assert err["wls"] < 0.08, err
    assert err["wls"] < 0.5 * err["eq13"], err


def test_uniform_image_gives_low_confidence_and_finite_depth():
    m = FourierRatioDFD(REF, tile=64, stride=32)
    x = torch.full((2, 1, 128, 128), 0.4)
    g = torch.Generator().manual_seed(1)
    noisy = x + 0.004 * torch.randn(x.shape, generator=g)
    for a, b in ((x, x), (noisy, noisy + 0.004 * torch.randn(x.shape, generator=g))):
        depth, conf = m(a, b)
        assert bool(torch.isfinite(depth).all()) and bool(torch.isfinite(conf).all())
        assert float(conf.max()) < 0.1
        lo, hi = m.inv_depth_limits
        assert bool(((1 / depth >= lo - 1e-6) & (1 / depth <= hi + 1e-6)).all())


def test_whole_image_region_as_in_the_paper():
    x = pink_texture(160, 1, seed=2)
    i1, i2 = render_pair(REF, x, torch.full_like(x, 0.47))
    depth, conf = whole_image_dfd(i1[..., :150], i2[..., :150], REF)
    assert depth.shape == (1, 1, 1, 1)
    assert float(depth) == pytest.approx(0.47, rel=0.01)


# ---------------------------------------------------------------------------- gradients
def test_estimation_gradcheck_float64_wrt_depth_and_images():
    x = pink_texture(32, 1, seed=4, dtype=torch.float64)
    m = FourierRatioDFD(REF, tile=16, stride=16, max_bin=6).double()

    def depth_of_plane(d):
        i1, i2 = render_pair(REF, x, d.expand(1, 1, 32, 32))
        r = m.analyse(i1, i2)
        return r.inverse_depth, r.confidence

    d = torch.tensor(0.5, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(depth_of_plane, (d,), eps=1e-6, atol=1e-5)
    i1, i2 = render_pair(REF, x, torch.full_like(x, 0.6))
    i1.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda a: m.analyse(a, i2).inverse_depth, (i1,), eps=1e-6, atol=1e-5, fast_mode=True)


def test_depth_is_differentiable_wrt_mu_through_the_solve():
    from tdfd.optics import depth_from_square_difference
    mu = torch.tensor(REF.mu_px_per_m / 1e5, dtype=torch.float64, requires_grad=True)
    dsq = torch.tensor([3.0, -5.0], dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda m_: depth_from_square_difference(REF, dsq, m_ * 1e5)[0], (mu,))


# ---------------------------------------------------------------------------- errors
def test_typed_errors_name_the_problem():
    m = FourierRatioDFD(REF, tile=64, stride=32)
    ok = torch.full((1, 1, 96, 96), 0.5)
    with pytest.raises(ShapeError, match="differ"):
        m(ok, ok[..., :90])
    with pytest.raises(ShapeError, match="B, 1, H, W"):
        m(ok[0], ok[0])
    with pytest.raises(ShapeError, match="smaller than one"):
        m(ok[..., :40, :40], ok[..., :40, :40])
    with pytest.raises(DTypeError):
        m(ok.to(torch.uint8), ok.to(torch.uint8))
    with pytest.raises(DTypeError):
        m(ok.numpy(), ok.numpy())
    bad = ok.clone()
    bad[0, 0, 3, 3] = float("nan")
    with pytest.raises(NonFiniteError, match="image_f2"):
        m(ok, bad)
    with pytest.raises(RangeError, match="linear intensity"):
        m(ok * 255, ok * 255)
    with pytest.raises(InputError):
        FourierRatioDFD(REF, tile=64, stride=80)
    with pytest.raises(InputError):
        FourierRatioDFD(REF, estimator="median")


# ---------------------------------------------------------------------------- calibration
def test_mu_calibration_single_pair_at_46_cm_and_least_squares():
    true_mu = REF.mu_px_per_m
    pairs = []
    for i, d in enumerate([0.33, 0.46, 0.6]):
        x = pink_texture(128, 1, seed=20 + i)
        i1, i2 = render_pair(REF, x, torch.full_like(x, d))
        pairs.append((i1, i2, d))
    # the paper calibrates from one pair at 46 cm; near |sigma1| = |sigma2| the signal is
    # weak (r1^2 - r2^2 -> 0 at 0.455 m for this camera), so the pair at 0.33 m is the better single shot
    assert calibrate_mu(REF, [pairs[0]], tile=128) == pytest.approx(true_mu, rel=0.01)
    assert calibrate_mu(REF, pairs, tile=128) == pytest.approx(true_mu, rel=0.01)
    # a camera calibrated with the wrong mu now estimates depth correctly again
    wrong = REF.replace(mu_px_per_m=2 * true_mu)
    mu = calibrate_mu(wrong, pairs, tile=128)
    depth, _ = FourierRatioDFD(wrong.replace(mu_px_per_m=mu), tile=128, stride=128)(pairs[2][0], pairs[2][1])
    assert float(depth.median()) == pytest.approx(0.6, rel=0.01)


def test_mu_least_squares_errors():
    with pytest.raises(InputError):
        mu_from_square_difference(REF, [0.5], [1.0, 2.0])
    d0 = 1 / (0.5 * sum(REF.lens_powers_dpt))  # |r1| = |r2| here
    assert abs(radius_square_difference(REF, d0)) < 1e-20
    with pytest.raises(InputError):
        mu_from_square_difference(REF, [d0], [1.0])
    with pytest.raises(InputError, match="disagree"):
        mu_from_square_difference(REF, [0.33], [-5.0])
