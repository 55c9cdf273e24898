"""The likelihood-stage benchmark's own pieces (benchmarks/bench_likelihood_stage.py): the oracle's
seeded fit's minimum and curvature sigma, the paired bootstrap, the structure table, the re-fusion
with other scales and the confidence's deciles (the product stage's pieces: tests/test_likelihood_stage.py)."""

from __future__ import annotations

import math

import pytest
import torch

from benchmarks.bench_likelihood_stage import paired_bootstrap, seeded_fit
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


def test_paired_bootstrap_is_seeded_and_centred_on_the_difference():
    a = [[0.01, -0.02, 0.03]] * 20
    b = [[0.02, -0.04, 0.06]] * 20
    mean, lo, hi = paired_bootstrap(a, b, resamples=200, seed=3)
    assert abs(mean + 0.02) < 1e-12 and abs(lo + 0.02) < 1e-12 and abs(hi + 0.02) < 1e-12
    assert paired_bootstrap(a, b, 50, 1) == paired_bootstrap(a, b, 50, 1)


def test_product_scores_are_relative_depth_errors_per_plane():
    from benchmarks.bench_likelihood_stage import score_product

    rows = [{"true_q": [2.0, 2.0], "model_q": [2.0, 1.6], "product_fit_q": [2.5, 2.0], "product_q": [2.0, 2.0]}]
    sc = score_product(rows)
    assert sc["model"] == [[0.0, pytest.approx(0.25)]]
    assert sc["seeded"] == [[pytest.approx(-0.2), 0.0]] and sc["fused"] == [[0.0, 0.0]]


def test_the_structure_table_scores_edges_apart_and_bootstraps_scenes():
    from benchmarks.stage_rows import structure_table

    n = 40
    true = torch.full((n,), 0.5, dtype=torch.float64)
    model = true * 1.02
    fused = true * torch.where(torch.arange(n) % 2 == 0, 1.01, 1.03).to(torch.float64)
    rows = {"slanted": {"true": true, "model": model, "model_conf": torch.full((n,), 0.3, dtype=torch.float64),
                        "fused": fused, "fused_conf": torch.full((n,), 0.6, dtype=torch.float64),
                        "fit": fused.clone(), "fitted": torch.arange(n) >= 10, "edge": torch.arange(n) < 10,
                        "scene": torch.arange(n) // 10}}
    table = structure_table(rows, reps=50)
    away, every = table
    assert away[:3] == ["slanted", "away from edges", 30] and every[2] == 40
    assert away[3] == "2.00 %" and away[4] in ("1.00 %", "2.00 %", "3.00 %")
    assert away[7] == "0 % / 100 %" and away[8] == "- / " + away[4]


def test_refusing_the_stages_fits_with_its_own_scales_gives_its_map_and_other_scales_another():
    from benchmarks.stage_rows import refused
    from tdfd import Camera
    from tdfd.dfd.inverse_variance import LikelihoodScales
    from tdfd.dfd.likelihood_stage import LikelihoodStage

    from tdfd.dfd.psf_hypotheses import PsfHypothesis
    from tests.test_likelihood_stage import render_plane

    i1, i2 = render_plane(0.5, PsfHypothesis("gaussian"), size=224, noise=2e-3)
    g = torch.Generator().manual_seed(4)
    depth = 0.5 * (1.03 + 0.005 * torch.rand(1, 1, 6, 6, generator=g))  # a model 3 % off
    conf = torch.full((1, 1, 6, 6), 0.7)
    scales = LikelihoodScales(2.0, 0.7, shared_bias=True, bias_radius=2)
    stage = LikelihoodStage(Camera.preset("reference"), 64, 32, 0.01, family="gaussian", scales=scales)
    r = stage(i1, i2, depth, conf)
    assert int(r.fitted.sum()) == 16
    d, c = refused(stage, r, depth, conf, scales)
    torch.testing.assert_close(d, r.depth, rtol=1e-5, atol=0)
    torch.testing.assert_close(c, r.confidence, rtol=1e-4, atol=1e-6)
    d0, _ = refused(stage, r, depth, conf, LikelihoodScales(2.0, 0.7))  # the model's map as it is
    assert torch.equal(d0[~r.fitted], depth[~r.fitted])
    assert float(r.bias.abs().min()) > 1e-4 and not torch.allclose(d0, r.depth)
    # a map of the fused scale with a slope part: the same confidence as the stage's, through the tiles' slopes
    sloped = LikelihoodScales(2.0, 0.7, shared_bias=True, bias_radius=2, fused_log_b=(-9.0, -2.0),
                              fused_log_b_calibrated=(-8.5, -2.0), fused_log_slope=(math.log(1e-3), math.log(0.1)),
                              fused_slope_log_shift=(-0.7, 0.7))
    stage_s = LikelihoodStage(Camera.preset("reference"), 64, 32, 0.01, family="gaussian", scales=sloped)
    r_s = stage_s(i1, i2, depth, conf)
    _, c_s = refused(stage_s, r_s, depth, conf, sloped)
    torch.testing.assert_close(c_s, r_s.confidence, rtol=1e-4, atol=1e-6)
    assert not torch.allclose(r_s.confidence[r_s.fitted], r.confidence[r.fitted])


def _laplace_tiles(n: int, factor: float, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Confidences (b0 = 0.01) and signed errors ``factor`` times the Laplace errors they state."""
    g = torch.Generator().manual_seed(seed)
    b = 0.002 + 0.05 * torch.rand(n, generator=g, dtype=torch.float64)
    u = torch.rand(n, generator=g, dtype=torch.float64) - 0.5
    return 1.0 / (1.0 + (b / 0.01) ** 2), -factor * b * torch.sign(u) * torch.log1p(-2.0 * u.abs())


def test_the_decile_summary_passes_a_stated_uncertainty_and_fails_one_half_too_small():
    from benchmarks.stage_uncertainty import decile_summary

    conf, err = _laplace_tiles(6000, 1.0, 0)
    scene = torch.arange(6000) // 30
    good = decile_summary(conf, err, scene, 0.01, reps=20)
    assert good[0] == "10 of 10" and good[1] == 0
    conf, err = _laplace_tiles(6000, 1.5, 1)  # errors 1.5 times what the confidence states
    bad = decile_summary(conf, err, scene, 0.01, reps=20)
    assert bad[0] == "0 of 10" and bad[1] >= 8  # most outside the band by more than two standard errors
    lo, hi = (float(x) for x in bad[2].split("-"))
    assert 1.25 < lo <= hi < 1.8 and bad[3].endswith(")")


def test_the_relative_inverse_depth_error_and_its_typed_errors():
    from benchmarks.stage_uncertainty import relative_inverse_depth_error

    e = relative_inverse_depth_error(torch.tensor([0.5, 0.4]), torch.tensor([0.55, 0.4]))
    torch.testing.assert_close(e, torch.tensor([0.1, 0.0], dtype=torch.float64))  # q / q_true - 1
    with pytest.raises(InputError, match="shape"):
        relative_inverse_depth_error(torch.ones(2), torch.ones(3))
    with pytest.raises(InputError, match="depth must be finite and > 0"):
        relative_inverse_depth_error(torch.tensor([0.5, 0.0]), torch.ones(2))


def test_confidence_rows_score_each_estimator_on_planes_and_structure_scenes():
    from benchmarks.bench_likelihood_stage import confidence_rows

    conf, err = _laplace_tiles(2500, 1.0, 2)
    q_true = torch.full((2500,), 2.0, dtype=torch.float64)
    q = q_true * (1.0 + err)
    planes = {"clean": [{"index": i, "true_q": q_true[25 * i:25 * i + 25].tolist(),
                         "model_q": q[25 * i:25 * i + 25].tolist(), "model_conf": conf[25 * i:25 * i + 25].tolist(),
                         "product_q": q[25 * i:25 * i + 25].tolist(),
                         "product_conf": (conf[25 * i:25 * i + 25] ** 4).tolist()}  # far less confident
                        for i in range(100)]}
    structure = {lay: {"true": 1.0 / q_true[:1000], "model": 1.0 / q[:1000], "model_conf": conf[:1000],
                       "fused": 1.0 / q[:1000], "fused_conf": conf[:1000], "edge": torch.arange(1000) % 4 == 0,
                       "scene": torch.arange(1000) // 50} for lay in ("slanted", "layout")}
    labels = {"model": "the model", "product": "stage", "baseline": "base"}
    rows = confidence_rows(planes, structure, 0.01, labels, reps=10)
    assert [r[:3] for r in rows] == [["planes, clean", "the model", 2500], ["planes, clean", "stage", 2500],
                                     ["structure scenes, all tiles", "the model", 2000],
                                     ["structure scenes, all tiles", "stage", 2000],
                                     ["structure scenes, away from edges", "the model", 1500],
                                     ["structure scenes, away from edges", "stage", 1500]]
    assert rows[0][3] == "10 of 10" and rows[1][3] != "10 of 10"  # the understated confidence is caught
    # a short run: one plane and one scene leave no set to score, and no error
    one = {lay: {k: v[:40] for k, v in t.items()} for lay, t in list(structure.items())[:1]}
    one[next(iter(one))]["scene"] = torch.zeros(40, dtype=torch.long)
    assert confidence_rows({"clean": planes["clean"][:1]}, one, 0.01, labels, reps=10) == []
