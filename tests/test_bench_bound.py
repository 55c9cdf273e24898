"""The information bound of benchmarks/bench_bound.py: OTFs and the Fisher information's scaling laws."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch

from benchmarks.bench_bound import (PSF_NUISANCES, _coords, depth_variances, median_at_bound, otf, otf_jacobian,
                                    plane_fisher, plane_information, psf_model, psf_prior_variance, ring_band)
from data_synth.params import SynthConfig
from data_synth.psf import PSFModel
from tdfd import Camera
from tdfd.errors import InputError
from tdfd.optics.thin_lens import camera_sigmas

REF = Camera.preset("reference")
PARAMS = {"psf_shape": "gaussian", "psf_beta": 2.0, "diffraction_sigma_px": 0.0, "astigmatism": 0.0,
          "astigmatism_angle": 0.0, "spherical": 0.0, "full_well_e": 10_000.0, "read_noise_e": 3.0, "bits": 12,
          "black_level_dn": 0.0, "gain": 1.0, "exposure": 1.0}


def _texture(amplitude: float, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return 0.3 + amplitude * (torch.rand(128, 128, generator=g, dtype=torch.float64) - 0.5)


def test_otf_of_a_point_is_one_and_of_a_blur_is_low_pass():
    flat = otf(PSFModel("gaussian"), 0.0)
    torch.testing.assert_close(flat, torch.ones_like(flat))
    for shape in ("gaussian", "pillbox"):
        h = otf(PSFModel(shape), 3.0)
        assert abs(float(h[0, 0].real) - 1.0) < 1e-9  # unit sum
        assert float(h.imag.abs().max()) < 1e-9  # symmetric PSF: real OTF
        assert float(h.abs().max()) <= 1.0 + 1e-9
    # the Gaussian's OTF follows exp(-sigma^2 omega^2 / 2) at low frequency (pixel integration aside)
    h = otf(PSFModel("gaussian"), 2.0)
    w = 2 * math.pi * 2 / 64
    assert abs(float(h[0, 2].real) - math.exp(-0.5 * 4.0 * w * w)) < 0.01


def test_psf_model_is_rebuilt_from_sample_parameters():
    m = psf_model({**PARAMS, "psf_shape": "beta", "psf_beta": 5.0, "astigmatism": 0.1, "spherical": -0.2})
    assert m.beta == 5.0 and m.astigmatism == 0.1 and m.spherical == -0.2


def test_information_scales_with_texture_power_and_vanishes_without_texture():
    flat = plane_information(REF, _texture(0.0), 0.5, PARAMS)
    j1 = plane_information(REF, _texture(0.1), 0.5, PARAMS)
    assert float(flat.abs().max()) < 1e-20 * float(j1.min())  # float rounding of a constant tile only
    j2 = plane_information(REF, _texture(0.2), 0.5, PARAMS)  # same mean level, same noise
    assert float(j1.min()) > 0
    # 4x the texture power: 4x the information (to the 1 % that the tile means, hence the shot
    # noise, move with the amplitude)
    torch.testing.assert_close(j2, 4.0 * j1, rtol=0.01, atol=0)


def test_less_noise_means_more_information():
    j = plane_information(REF, _texture(0.1), 0.5, PARAMS)
    quieter = plane_information(REF, _texture(0.1), 0.5, {**PARAMS, "full_well_e": 40_000.0})
    assert bool((quieter > 1.5 * j).all())


# ---------------------------------------------------------------- the PSF as a nuisance
def test_fisher_matrix_is_symmetric_positive_and_holds_the_depth_information():
    params = {**PARAMS, "psf_shape": "beta", "psf_beta": 5.0, "astigmatism": 0.1, "astigmatism_angle": 0.4,
              "spherical": -0.2, "diffraction_sigma_px": 0.5}
    f = plane_fisher(REF, _texture(0.1), 0.45, params)
    assert f.shape == (3, 3, 6, 6)
    torch.testing.assert_close(f, f.transpose(-1, -2))
    assert float(torch.linalg.eigvalsh(f).min()) > -1e-9 * float(f.abs().max())
    torch.testing.assert_close(f[..., 0, 0], plane_information(REF, _texture(0.1), 0.45, params))


def test_a_blur_common_to_both_frames_carries_no_information():
    # diffraction multiplies both OTFs by the same factor: it drops out of their ratio
    params = {**PARAMS, "psf_shape": "pillbox", "diffraction_sigma_px": 0.6}
    f = plane_fisher(REF, _texture(0.1), 0.45, params)
    diffraction = PSF_NUISANCES.index("diffraction") + 1
    assert float(f[..., diffraction, :].abs().max()) < 1e-9 * float(f[..., 0, 0].min())


def test_analytic_diffraction_derivative_matches_the_rendered_kernels():
    model = PSFModel("gaussian", diffraction_sigma_px=0.8)
    h1, _, d1, _ = otf_jacobian(REF, model, 1 / 0.45)
    t, dt = 0.64, 0.04
    s1, _ = camera_sigmas(REF, 0.45)
    up = otf(replace(model, diffraction_sigma_px=math.sqrt(t + dt)), float(s1))
    down = otf(replace(model, diffraction_sigma_px=math.sqrt(t - dt)), float(s1))
    numeric = (up - down) / (2 * dt)
    k = 1 + PSF_NUISANCES.index("diffraction")
    low = [(0, 3), (3, 0), (2, 2), (0, 6)]  # low frequencies, where the sampled Gaussian is exact
    for i, j in low:
        assert abs(float(d1[k, i, j].real - numeric[i, j].real)) < 0.05 * abs(float(numeric[i, j].real))
    assert float(d1[k, 0, 0].abs()) == 0.0 and float(h1[0, 0].real) == pytest.approx(1.0)


def test_shape_derivative_next_to_the_pillbox_points_towards_the_smooth_shapes():
    s1, _ = camera_sigmas(REF, 0.35)
    _, _, d1, _ = otf_jacobian(REF, PSFModel("pillbox"), 1 / 0.35)
    # kappa 0 -> 1/16, sampled as finely as the bound's PSFs (pixel-centre samples of the
    # hard-edged shapes would jitter as pixels cross the edge)
    towards = otf(PSFModel(16.0), float(s1), supersample=9) - otf(PSFModel("pillbox"), float(s1), supersample=9)
    a, b = d1[1].real.flatten(), towards.real.flatten()
    assert float((a * b).sum() / (a.norm() * b.norm())) > 0.9
    assert 0.5 < float(b.norm()) / (float(a.norm()) / 16) < 2.0  # and its size is the step's


def test_an_unknown_psf_only_costs_information():
    params = {**PARAMS, "psf_shape": "gaussian", "astigmatism": 0.05, "spherical": 0.1}
    prior = psf_prior_variance(SynthConfig(), REF)
    v = depth_variances(plane_fisher(REF, _texture(0.1, seed=3), 0.55, params), prior)
    assert bool((v["tile_known"] <= v["tile_shared"] * (1 + 1e-9)).all())
    assert bool((v["tile_shared"] <= v["tile_unknown"] * (1 + 1e-9)).all())
    assert float(v["plane_known"]) <= float(v["plane_unknown"]) < float(v["tile_known"].min())
    assert float(v["tile_unknown"].max()) > 1.01 * float(v["tile_known"].max())  # the shape matters here
    # a flat plane has no information: huge, finite variances, not a singular matrix's NaN
    flat = depth_variances(plane_fisher(REF, _texture(0.0), 0.55, params), prior)
    for k, x in flat.items():
        assert bool(torch.isfinite(x).all()) and float(x.min()) > 1e6, k


def test_prior_variances_match_data_synth_draws():
    from data_synth.params import draw_psf

    cfg, g = SynthConfig(), torch.Generator().manual_seed(7)
    coords = torch.tensor([_coords(draw_psf(g, cfg, REF)[0]) for _ in range(4000)], dtype=torch.float64)
    torch.testing.assert_close(psf_prior_variance(cfg, REF), coords.var(0), rtol=0.1, atol=0)


def test_median_at_the_bound_of_a_mixture_of_tiles():
    assert median_at_bound(torch.full((5,), 2.0)) == pytest.approx(2.0 * 0.67449, rel=1e-4)
    # one perfect tile, two of sigma 1: 1/3 + 2/3 P(|e| <= m) = 1/2, so P = 1/4, m = 0.3186
    m = median_at_bound(torch.tensor([1e-9, 1.0, 1.0]))  # 1/3 + 2/3 P(|e|<=m) = 1/2 -> P = 1/4
    assert m == pytest.approx(0.31864, rel=1e-3)
    assert median_at_bound(torch.tensor([0.5, 1.0])) < 0.67449 * 1.0


def test_information_within_a_band_is_additive_and_below_the_whole_spectrum():
    # Fisher information is a sum over bins: a band and its complement add up to the whole spectrum,
    # and a texture whose power lies above the band gives the band almost none of it
    params = {**PARAMS, "psf_shape": "pillbox"}
    band = ring_band(2, 13)
    whole = plane_fisher(REF, _texture(0.1), 0.45, params)
    inside = plane_fisher(REF, _texture(0.1), 0.45, params, band=band)
    outside = plane_fisher(REF, _texture(0.1), 0.45, params, band=1.0 - band)
    torch.testing.assert_close(inside + outside, whole)
    assert bool((inside[..., 0, 0] < whole[..., 0, 0]).all()) and bool((inside[..., 0, 0] > 0).all())
    y, x = torch.meshgrid(torch.arange(128.0), torch.arange(128.0), indexing="ij")
    fine = 0.3 + 0.1 * torch.cos(2 * math.pi * 20 / 64 * x).double()  # bin 20 (0.31 cycles/px), above the band
    j_fine_in = plane_fisher(REF, fine, 0.45, params, band=band, nuisances=False)[..., 0, 0]
    j_fine = plane_fisher(REF, fine, 0.45, params, nuisances=False)[..., 0, 0]
    assert bool((j_fine_in < 1e-3 * j_fine).all())
    # a stack of bands gives each band's information at once
    both = plane_fisher(REF, _texture(0.1), 0.45, params, band=torch.stack([band, 1.0 - band]))
    torch.testing.assert_close(both[0], inside)
    torch.testing.assert_close(both[1], outside)
    for bad in (band[:5], band[None, None]):
        with pytest.raises(InputError):
            plane_fisher(REF, _texture(0.1), 0.45, params, band=bad)
    # ring 0 is the DC bin alone; ring 1 the four axis neighbours and the four diagonal ones (|k| = 1.41)
    assert int(ring_band(0, 0).sum()) == 1 and int(ring_band(1, 1).sum()) == 8
    with pytest.raises(InputError):
        ring_band(5, 2)
