"""The likelihood stage's pieces (benchmarks/bench_likelihood_stage.py): the seeded fit's minimum
and curvature sigma, the model's sigma from its confidence, the cross-fitted scale, the
inverse-variance fusion and the paired bootstrap."""

from __future__ import annotations

import math

import pytest
import torch

from benchmarks.bench_likelihood_stage import fuse, model_sigma, paired_bootstrap, seeded_fit, sigma_factor
from tdfd.errors import InputError

GRID = torch.arange(0.8, 3.6001, 0.01, dtype=torch.float64)


def test_the_seeded_fit_finds_a_quadratic_minimum_and_its_curvature_sigma():
    # L(q) = bins * nll = (q - q0)^2 / (2 s^2)  ->  sigma = s exactly
    q0, s, bins = torch.tensor([1.503, 2.2571]), torch.tensor([0.02, 0.05]), 1000.0
    nll = ((GRID[:, None] - q0[None]) ** 2 / (2 * s[None] ** 2) / bins + 1.0)[None].double()
    q, sigma, j = seeded_fit(nll, GRID, q0 * 1.01, bins)
    assert j == 0
    torch.testing.assert_close(q, q0.double(), rtol=0, atol=1e-9)
    torch.testing.assert_close(sigma, s.double(), rtol=1e-6, atol=0)


def test_the_seed_window_excludes_a_deeper_far_minimum_and_an_edge_minimum_has_no_sigma():
    near = 1.0 + 40.0 * (GRID - 1.8) ** 2
    far = 0.5 + 40.0 * (GRID - 3.0) ** 2
    nll = torch.minimum(near, far)[None, :, None].repeat(1, 1, 2)
    q, sigma, _ = seeded_fit(nll, GRID, torch.tensor([1.75, 2.21], dtype=torch.float64), 100.0)
    assert abs(float(q[0]) - 1.8) < 1e-9 and math.isfinite(float(sigma[0]))
    assert abs(float(q[1]) - 2.10) < 1e-9 and math.isinf(float(sigma[1]))  # the window's lower edge
    with pytest.raises(InputError):
        seeded_fit(nll, GRID, torch.tensor([1.75], dtype=torch.float64), 100.0)
    with pytest.raises(InputError):
        seeded_fit(nll, GRID, torch.tensor([1.75, 2.0], dtype=torch.float64), 0.0)


def test_the_shared_candidate_is_the_one_whose_tiles_fit_best():
    good = torch.stack([1.0 + (GRID - 2.0) ** 2, 1.0 + (GRID - 2.5) ** 2], 1)
    worse = good + torch.tensor([-0.1, 0.3], dtype=torch.float64)
    _, _, j = seeded_fit(torch.stack([worse, good]), GRID, torch.tensor([2.0, 2.5], dtype=torch.float64), 10.0)
    assert j == 1


def test_model_sigma_inverts_the_confidence():
    b0 = 0.01
    b = torch.tensor([0.005, 0.01, 0.04], dtype=torch.float64)
    conf = 1.0 / (1.0 + (b / b0) ** 2)
    torch.testing.assert_close(model_sigma(conf, b0), math.sqrt(2.0) * b)
    for bad in (0.0, 1.5, float("nan")):
        with pytest.raises(InputError):
            model_sigma(torch.tensor([bad]), b0)


def test_sigma_factor_makes_the_median_ratio_a_normals():
    g = torch.Generator().manual_seed(0)
    e = torch.randn(20000, generator=g, dtype=torch.float64) * 0.02
    assert abs(sigma_factor(e, torch.full_like(e, 0.01)) - 2.0) < 0.05
    assert abs(sigma_factor(e, torch.full_like(e, 0.02)) - 1.0) < 0.03
    with pytest.raises(InputError):
        sigma_factor(e, torch.full_like(e, math.inf))


def test_fusion_weights_by_inverse_variance():
    q = fuse(torch.tensor([1.0, 1.0, 1.0]), torch.tensor([1.0, 2.0, math.inf]),
             torch.tensor([2.0, 2.0, 2.0]), torch.tensor([1.0, 1.0, 1.0]))
    torch.testing.assert_close(q, torch.tensor([1.5, 1.8, 2.0]))
    with pytest.raises(InputError):
        fuse(torch.tensor([1.0]), torch.tensor([math.inf]), torch.tensor([2.0]), torch.tensor([math.inf]))


def test_paired_bootstrap_is_seeded_and_centred_on_the_difference():
    a = [[0.01, -0.02, 0.03]] * 20
    b = [[0.02, -0.04, 0.06]] * 20
    mean, lo, hi = paired_bootstrap(a, b, resamples=200, seed=3)
    assert abs(mean + 0.02) < 1e-12 and abs(lo + 0.02) < 1e-12 and abs(hi + 0.02) < 1e-12
    assert paired_bootstrap(a, b, 50, 1) == paired_bootstrap(a, b, 50, 1)
