"""The information bound of benchmarks/bench_bound.py: OTFs and the Fisher information's scaling laws."""

from __future__ import annotations

import math

import torch

from benchmarks.bench_bound import otf, plane_information, psf_model
from data_synth.psf import PSFModel
from tdfd import Camera

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
