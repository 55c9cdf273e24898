"""The product's likelihood stage (tdfd.dfd.likelihood_stage and its parts): PSF hypotheses equal
to the renderer's kernels, the per-tile residual computed locally equal to the frame's, a seeded
fit that finds a rendered plane's depth and shared PSF with the noise not told, the fusion and
its scales file, and the stage's grid, ring and fault behaviour."""

from __future__ import annotations

import json
import math

import pytest
import torch

from data_synth.psf import PSFModel
from tdfd import Camera
from tdfd.dfd.cross_residual import tile_cross_residual_nll, valid_residual
from tdfd.dfd.inverse_variance import (LikelihoodScales, confidence_from_sigma, fuse, model_sigma, sigma_factor,
                                      tile_slope)
from tdfd.dfd.likelihood_stage import LikelihoodStage, fuse_with_fit, likelihood_stage, valid_tiles
from tdfd.dfd.psf_hypotheses import SHAPES, PsfHypothesis, diffraction_px, psf_hypotheses
from tdfd.dfd.seeded_fit import inverse_depth_grid, seed_mask, seeded_tile_fit
from tdfd.errors import InputError, ModelError, NonFiniteError, ShapeError
from tdfd.optics.thin_lens import camera_sigmas

CAM = Camera.preset("reference")


def render_plane(depth_m: float, hyp: PsfHypothesis, size: int = 192, noise: float = 1e-4, seed: int = 0,
                 gain2: float = 1.0) -> tuple[torch.Tensor, torch.Tensor]:
    """A fronto-parallel plane's two frames (B, 1, H, W): a random texture blurred by ``hyp`` at
    the camera's blurs for ``depth_m`` (valid convolution), white noise of std ``noise``."""
    g = torch.Generator().manual_seed(seed)
    n = 65
    sharp = 0.3 + 0.4 * torch.rand(size + n - 1, size + n - 1, generator=g, dtype=torch.float64)
    s1, s2 = (float(s) for s in camera_sigmas(CAM, depth_m))
    k = hyp.kernels(torch.tensor([s1, s2], dtype=torch.float64), n)
    frames = [torch.nn.functional.conv2d(sharp[None, None], k[i].flip(-1, -2)[None, None])[0, 0] for i in (0, 1)]
    frames = [f + noise * torch.randn(f.shape, generator=g, dtype=torch.float64) for f in frames]
    return frames[0][None, None].float(), (gain2 * frames[1])[None, None].float()


def test_hypothesis_kernels_are_the_renderers():
    sigma = torch.tensor([0.3, 2.5, -4.0], dtype=torch.float64)
    for shape in ("gaussian", "pillbox", 5.0):
        for d in (0.0, 0.62):
            ours = PsfHypothesis(shape, d).kernels(sigma, 31)
            theirs = PSFModel(shape, d).kernels(sigma, size=31)
            torch.testing.assert_close(ours, theirs, rtol=0, atol=1e-14)


def test_hypotheses_follow_the_family_and_the_airy_rms():
    d = 0.42 * 650e-9 * (CAM.focal_lengths_m[0] / CAM.aperture_m) / CAM.pixel_pitch_m
    assert diffraction_px(CAM) == pytest.approx(d, rel=1e-12)
    assert [h.shape for h in psf_hypotheses(CAM, "gaussian")] == ["gaussian", "gaussian"]
    assert [h.diffraction_px for h in psf_hypotheses(CAM, "gaussian")] == [0.0, pytest.approx(d)]
    assert len(psf_hypotheses(CAM)) == len(psf_hypotheses(CAM, "unknown")) == 2 * len(SHAPES)
    for bad in ("disk", ""):
        with pytest.raises(InputError, match="psf family"):
            psf_hypotheses(CAM, bad)
    with pytest.raises(InputError, match="wavelength"):
        diffraction_px(CAM, -1.0)
    for shape, dd in (("cone", 0.0), (0.5, 0.0), ("gaussian", -0.1), ("gaussian", math.nan)):
        with pytest.raises(InputError):
            PsfHypothesis(shape, dd)
    with pytest.raises(ShapeError):
        PsfHypothesis("gaussian", 0.62).kernels(torch.tensor([1.0]), 4)


def test_the_local_tile_residual_is_the_frames_cut_and_the_mask_skips_pairs():
    g = torch.Generator().manual_seed(1)
    y1, y2 = (torch.rand(120, 140, generator=g, dtype=torch.float64) for _ in range(2))
    sig = torch.tensor([1.0, 2.0, -1.5, 3.0], dtype=torch.float64)
    k = PsfHypothesis("pillbox").kernels(sig, 15).reshape(2, 2, 15, 15)
    origins = [(7, 7), (40, 60), (49, 69)]
    nu = torch.tensor([1.0, 2.0, 0.5], dtype=torch.float64)
    full = tile_cross_residual_nll(y1, y2, k[:, 0], k[:, 1], nu, nu, origins, 32)
    # the same tiles cut out of the whole frame's residual, as one tile covering each
    v = valid_residual(y1, y2, k[:, 0], k[:, 1])
    for t, (r, c) in enumerate(origins):
        r0, c0 = r - 7, c - 7
        region = (slice(r0, r0 + 32 + 14), slice(c0, c0 + 32 + 14))
        alone = tile_cross_residual_nll(y1[region], y2[region], k[:, 0], k[:, 1], nu[t:t + 1], nu[t:t + 1],
                                        [(7, 7)], 32)
        torch.testing.assert_close(alone[:, 0], full[:, t], rtol=1e-12, atol=0)
        # the region's own valid residual is the frame's, cut at the tile
        torch.testing.assert_close(valid_residual(y1[region], y2[region], k[:, 0], k[:, 1]),
                                   v[:, r0: r0 + 32, c0: c0 + 32], rtol=0, atol=1e-12)
    mask = torch.tensor([[True, False, True], [False, False, True]])
    part = tile_cross_residual_nll(y1, y2, k[:, 0], k[:, 1], nu, nu, origins, 32, mask=mask)
    torch.testing.assert_close(part[mask], full[mask], rtol=1e-12, atol=0)
    assert bool(torch.isinf(part[~mask]).all())
    with pytest.raises(InputError, match="mask"):
        tile_cross_residual_nll(y1, y2, k[:, 0], k[:, 1], nu, nu, origins, 32, mask=mask[:, :2])


def test_grid_and_seed_window():
    grid = inverse_depth_grid(CAM)
    near, far = CAM.depth_range_m
    assert float(grid[0]) == pytest.approx(0.8 / far) and float(grid[-1]) <= 1.1 / near + 1e-9
    m = seed_mask(grid, torch.tensor([2.005, 50.0], dtype=torch.float64))  # window +-0.10025: 1.91 .. 2.10
    assert grid[m[:, 0]].tolist() == pytest.approx([1.91 + 0.01 * i for i in range(20)])
    assert m[:, 1].nonzero().flatten().tolist() == [len(grid) - 1]  # off the grid: its nearest point
    for bad in (torch.tensor([0.0]), torch.tensor([math.nan])):
        with pytest.raises(InputError):
            seed_mask(grid, bad)
    with pytest.raises(InputError):
        inverse_depth_grid(CAM, window=0.0)


@pytest.mark.parametrize("true_hyp", [PsfHypothesis("pillbox"), PsfHypothesis("gaussian")])
def test_the_seeded_fit_finds_a_rendered_planes_depth_and_psf_without_the_noise(true_hyp):
    depth = 0.55
    i1, i2 = render_plane(depth, true_hyp, noise=2e-4)
    y1, y2 = i1[0, 0].double(), i2[0, 0].double()
    origins = [(64, 64), (64, 96), (96, 64), (96, 96)]
    seed = torch.full((4,), 1.0 / depth * 1.03, dtype=torch.float64)  # the model 3 % off
    fit = seeded_tile_fit(y1, y2, CAM, origins, 64, seed, psf_hypotheses(CAM))
    assert fit.hypothesis.shape == true_hyp.shape  # diffraction's 0.6 px is not told apart from a 4 px blur
    err = (fit.q * depth - 1.0).abs()
    assert float(err.max()) < 0.005
    assert bool(torch.isfinite(fit.sigma_q).all()) and float((fit.sigma_q * depth).max()) < 0.01
    # the NLL's minimum estimates the noise: white noise of variance v in both frames -> NLL about v
    assert 0.5 < float(fit.noise.median()) / 2e-4 ** 2 < 2.0
    # a seed whose window misses the truth: the minimum on the window's edge carries no weight
    far = seeded_tile_fit(y1, y2, CAM, origins, 64, seed * 1.2, [true_hyp])
    assert bool(torch.isinf(far.sigma_q).all())
    # walking the window downhill reaches the truth from 24 % off (the window is +-5 %), from either side
    for off in (1.2, 1.03 / 1.24 / 1.03):
        walked = seeded_tile_fit(y1, y2, CAM, origins, 64, seed * off, [true_hyp], walk=5)
        assert float((walked.q * depth - 1.0).abs().max()) < 0.005, off
        assert bool(torch.isfinite(walked.sigma_q).all())
        # the fit before the walk is kept for the stage's check against the neighbours
        assert bool(walked.walked.all()) and bool(torch.isinf(walked.unwalked.sigma_q).all())
        assert walked.unwalked.unwalked is None and not bool(walked.unwalked.walked.any())
    # too few moves: still on an edge, still no weight; a tile already inside is left alone
    short = seeded_tile_fit(y1, y2, CAM, origins, 64, seed * 1.2, [true_hyp], walk=1)
    assert bool(torch.isinf(short.sigma_q).all())
    assert far.unwalked is None and not bool(far.walked.any())
    near = seeded_tile_fit(y1, y2, CAM, origins, 64, seed, [true_hyp], walk=3)
    torch.testing.assert_close(near.q, seeded_tile_fit(y1, y2, CAM, origins, 64, seed, [true_hyp]).q)
    # a walked minimum that gains less than walk_gain over the first window's edge keeps no weight
    strict = seeded_tile_fit(y1, y2, CAM, origins, 64, seed * 1.2, [true_hyp], walk=5, walk_gain=1e9)
    torch.testing.assert_close(strict.q, far.q)
    assert not bool(strict.walked.any())  # a walk the gain refused does not count as walked
    assert bool(torch.isinf(strict.sigma_q).all())
    with pytest.raises(InputError, match="walk_gain"):
        seeded_tile_fit(y1, y2, CAM, origins, 64, seed, [true_hyp], walk=1, walk_gain=-1.0)
    # only the tiles let walk move
    let = torch.tensor([True, False, True, False])
    some = seeded_tile_fit(y1, y2, CAM, origins, 64, seed * 1.2, [true_hyp], walk=5, walk_tiles=let)
    assert torch.isfinite(some.sigma_q).tolist() == let.tolist()
    with pytest.raises(InputError, match="walk"):
        seeded_tile_fit(y1, y2, CAM, origins, 64, seed, [true_hyp], walk=-1)
    with pytest.raises(InputError, match="walk_tiles"):
        seeded_tile_fit(y1, y2, CAM, origins, 64, seed, [true_hyp], walk=1, walk_tiles=let[:2])


def test_model_sigma_and_confidence_invert_each_other():
    b0 = 0.01
    b = torch.tensor([0.005, 0.01, 0.04], dtype=torch.float64)
    conf = 1.0 / (1.0 + (b / b0) ** 2)
    torch.testing.assert_close(model_sigma(conf, b0), math.sqrt(2.0) * b)
    torch.testing.assert_close(confidence_from_sigma(model_sigma(conf, b0), b0), conf)
    assert math.isinf(float(model_sigma(torch.tensor([0.0]), b0)[0]))
    assert float(confidence_from_sigma(torch.tensor([math.inf]), b0)[0]) == 0.0
    for bad in (-0.1, 1.5, math.nan):
        with pytest.raises(InputError):
            model_sigma(torch.tensor([bad]), b0)
    with pytest.raises(InputError):
        model_sigma(conf, 0.0)


def test_sigma_factor_makes_the_median_ratio_a_normals():
    g = torch.Generator().manual_seed(0)
    e = torch.randn(20000, generator=g, dtype=torch.float64) * 0.02
    assert abs(sigma_factor(e, torch.full_like(e, 0.01)) - 2.0) < 0.05
    assert abs(sigma_factor(e, torch.full_like(e, 0.02)) - 1.0) < 0.03
    with pytest.raises(InputError):
        sigma_factor(e, torch.full_like(e, math.inf))


def test_fusion_weights_by_inverse_variance():
    q, s = fuse(torch.tensor([1.0, 1.0, 1.0, 1.0], dtype=torch.float64),
                torch.tensor([1.0, 2.0, math.inf, 0.0], dtype=torch.float64),
                torch.tensor([2.0, 2.0, 2.0, 2.0], dtype=torch.float64),
                torch.tensor([1.0, 1.0, 1.0, 1.0], dtype=torch.float64))
    torch.testing.assert_close(q, torch.tensor([1.5, 1.8, 2.0, 1.0], dtype=torch.float64))
    torch.testing.assert_close(s[:3], torch.tensor([0.5 ** 0.5, 0.8 ** 0.5, 1.0], dtype=torch.float64))
    assert bool(torch.isfinite(q).all())
    with pytest.raises(InputError, match="finite sigma"):
        fuse(torch.tensor([1.0]), torch.tensor([math.inf]), torch.tensor([2.0]), torch.tensor([math.inf]))
    with pytest.raises(InputError, match="shape"):
        fuse(torch.tensor([1.0]), torch.tensor([1.0, 1.0]), torch.tensor([2.0]), torch.tensor([1.0]))


def test_scales_round_trip_and_bad_files(tmp_path):
    s = LikelihoodScales(2.5, 0.8, provenance={"command": "x", "tiles": 10})
    s.save(tmp_path / "s.json")
    back = LikelihoodScales.load(tmp_path / "s.json")
    assert (back.fit, back.model, back.provenance) == ((2.5,), (0.8,), {"command": "x", "tiles": 10})
    (tmp_path / "bad.json").write_text("{")
    (tmp_path / "other.json").write_text(json.dumps({"format": "x", "fit": 1, "model": 1}))
    (tmp_path / "neg.json").write_text(json.dumps({"format": "tdfd.likelihood_scales/1", "fit": -1, "model": 1}))
    for name in ("bad.json", "other.json", "neg.json", "missing.json"):
        with pytest.raises(ModelError):
            LikelihoodScales.load(tmp_path / name)
    with pytest.raises(InputError):
        LikelihoodScales(math.inf, 1.0)
    for bad in (dict(fit=(1.0, 2.0), model=1.0, slope_edges=(0.02,)), dict(fit=(1.0, 2.0), model=(1.0, 1.0)),
                dict(fit=(1.0, 1.0, 1.0), model=(1.0, 1.0, 1.0), slope_edges=(0.03, 0.01))):
        with pytest.raises(InputError):
            LikelihoodScales(**bad)
    banded = LikelihoodScales((1.5, 3.0), (0.7, 0.6), (0.02,), {"command": "y"})
    banded.save(tmp_path / "b.json")
    assert LikelihoodScales.load(tmp_path / "b.json") == banded


def test_tile_slope_is_the_largest_relative_step_to_a_neighbour():
    q = torch.ones(4, 5, dtype=torch.float64)
    q[2, 3] = 1.2
    slope = tile_slope(q)
    assert float(slope[2, 3]) == pytest.approx(0.2 / 1.2)
    assert float(slope[1, 2]) == pytest.approx(0.2) and float(slope[0, 0]) == 0.0
    assert bool((slope[:, :2] == 0).all())


def test_the_stage_refines_the_interior_and_keeps_the_ring():
    depth = 0.55
    hyp = PsfHypothesis("pillbox")
    i1, i2 = render_plane(depth, hyp, size=192, noise=2e-4, gain2=1.3)  # a gain the mean match removes
    i1, i2 = i1 + 0.05, i2 + 0.05  # a black level, told
    model_d = torch.full((1, 1, 5, 5), depth * 1.03)
    model_c = torch.full((1, 1, 5, 5), 0.2)
    stage = LikelihoodStage(CAM, 64, 32, 0.01, family="pillbox", black_level=0.05)
    r = stage(i1, i2, model_d, model_c)
    inner = r.fitted[0, 0]
    assert inner.int().tolist() == valid_tiles(192, 192, 64, 32, 32).int().tolist()
    assert int(inner.sum()) == 9
    assert float((r.depth[0, 0][inner] / depth - 1).abs().max()) < 0.01  # from 3 % to under 1 %
    assert bool((r.confidence[0, 0][inner] > 0.2).all())
    assert bool((r.depth[0, 0][~inner] == model_d[0, 0][~inner]).all())
    assert bool((r.confidence[0, 0][~inner] == model_c[0, 0][~inner]).all())
    assert bool(torch.isnan(r.depth_fit[0, 0][~inner]).all()) and bool(torch.isinf(r.sigma_fit[0, 0][~inner]).all())
    assert r.hypotheses == [hyp]
    # the fit's own sigma, before the factor, is kept beside the factored one
    assert r.sigma_fit_raw.dtype == torch.float64 and bool(torch.isinf(r.sigma_fit_raw[0, 0][~inner]).all())
    scaled = LikelihoodStage(CAM, 64, 32, 0.01, family="pillbox", black_level=0.05,
                             scales=LikelihoodScales(2.5, 0.7))(i1, i2, model_d, model_c)
    torch.testing.assert_close(scaled.sigma_fit_raw, r.sigma_fit_raw, rtol=0, atol=0)
    torch.testing.assert_close(scaled.sigma_fit[0, 0][inner].double(), 2.5 * r.sigma_fit_raw[0, 0][inner],
                               rtol=1e-6, atol=0)
    # the black level given per call is the bound one
    per_call = LikelihoodStage(CAM, 64, 32, 0.01, family="pillbox")(i1, i2, model_d, model_c, black_level=0.05)
    assert torch.equal(per_call.depth, r.depth) and torch.equal(per_call.confidence, r.confidence)
    # a model at confidence 1 wins outright; at 0 the fit does
    sure = stage(i1, i2, model_d, torch.ones_like(model_c))
    assert bool((sure.depth[0, 0][inner] == model_d[0, 0][inner]).all())
    blind = stage(i1, i2, model_d, torch.zeros_like(model_c))
    torch.testing.assert_close(blind.depth[0, 0][inner], r.depth_fit[0, 0][inner])


def test_the_stage_rejects_bad_input_with_typed_errors():
    i1 = torch.rand(1, 1, 160, 160, generator=torch.Generator().manual_seed(0))
    d, c = torch.full((1, 1, 4, 4), 0.5), torch.full((1, 1, 4, 4), 0.5)
    kw = dict(tile=64, stride=32, confidence_scale=0.01)
    with pytest.raises(ShapeError, match="tile grid"):
        likelihood_stage(i1, i1, d[..., :3], c, CAM, **kw)
    with pytest.raises(ShapeError, match="frames"):
        likelihood_stage(i1, i1[..., :150], d, c, CAM, **kw)
    bad = i1.clone()
    bad[0, 0, 3, 3] = math.nan
    with pytest.raises(NonFiniteError):
        likelihood_stage(bad, i1, d, c, CAM, **kw)
    with pytest.raises(InputError, match="depths"):
        likelihood_stage(i1, i1, -d, c, CAM, **kw)
    with pytest.raises(InputError, match="confidences"):
        likelihood_stage(i1, i1, d, c + 1.0, CAM, **kw)
    with pytest.raises(InputError, match="no light"):
        likelihood_stage(i1, i1, d, c, CAM, black_level=2.0, **kw)
    with pytest.raises(InputError, match="band"):
        LikelihoodStage(CAM, band=0.9)
    with pytest.raises(InputError, match="walk"):
        LikelihoodStage(CAM, walk=-2)


def test_scales_keep_the_shared_bias_flag_and_read_version_1(tmp_path):
    s = LikelihoodScales((1.5, 3.0), (0.7, 0.6), (0.02,), shared_bias=True)
    s.save(tmp_path / "s.json")
    assert json.loads((tmp_path / "s.json").read_text())["format"] == "tdfd.likelihood_scales/5"
    assert LikelihoodScales.load(tmp_path / "s.json").shared_bias is True
    LikelihoodScales(2.0, 0.5, shared_bias=True, bias_radius=2).save(tmp_path / "r.json")
    assert LikelihoodScales.load(tmp_path / "r.json").bias_radius == 2
    for bad in (0, 1.5, "2"):
        with pytest.raises(InputError):
            LikelihoodScales(2.0, 0.5, shared_bias=True, bias_radius=bad)
    (tmp_path / "v1.json").write_text(json.dumps({"format": "tdfd.likelihood_scales/1", "fit": 2.0, "model": 0.5}))
    assert LikelihoodScales.load(tmp_path / "v1.json").shared_bias is False
    (tmp_path / "bad.json").write_text(json.dumps({"format": "tdfd.likelihood_scales/2", "fit": 2.0, "model": 0.5,
                                                   "shared_bias": "yes"}))
    with pytest.raises(ModelError):
        LikelihoodScales.load(tmp_path / "bad.json")


def test_scales_keep_the_registered_flag_and_read_version_4_as_unregistered(tmp_path):
    LikelihoodScales(2.0, 0.5, registered=True).save(tmp_path / "r.json")
    assert LikelihoodScales.load(tmp_path / "r.json").registered is True
    assert LikelihoodScales(2.0, 0.5).registered is False
    (tmp_path / "v4.json").write_text(json.dumps({"format": "tdfd.likelihood_scales/4", "fit": 2.0, "model": 0.5}))
    assert LikelihoodScales.load(tmp_path / "v4.json").registered is False
    with pytest.raises(InputError, match="registered"):
        LikelihoodScales(2.0, 0.5, registered=1)
    (tmp_path / "bad.json").write_text(json.dumps({"format": "tdfd.likelihood_scales/5", "fit": 2.0, "model": 0.5,
                                                   "registered": "yes"}))
    with pytest.raises(ModelError, match="registered"):
        LikelihoodScales.load(tmp_path / "bad.json")


def test_the_shared_bias_is_removed_from_the_model_before_the_fusion_and_from_the_ring():
    depth = 0.55
    hyp = PsfHypothesis("pillbox")
    i1, i2 = render_plane(depth, hyp, size=224, noise=5e-3)  # the fit's own sigma about 0.1 %
    model_d = torch.full((1, 1, 6, 6), depth * 1.03)  # a model 3 % off, sure of itself (0.045 %): a shared bias
    model_c = torch.full((1, 1, 6, 6), 0.999)
    plain = LikelihoodStage(CAM, 64, 32, 0.01, family="pillbox", scales=LikelihoodScales(1.0, 1.0))
    debias = LikelihoodStage(CAM, 64, 32, 0.01, family="pillbox", scales=LikelihoodScales(1.0, 1.0, shared_bias=True))
    a, b = plain(i1, i2, model_d, model_c), debias(i1, i2, model_d, model_c)
    inner = b.fitted[0, 0]
    assert int(inner.sum()) == 16
    assert a.bias.shape == (1, 1, 6, 6) and bool((a.bias == 0).all())
    torch.testing.assert_close(b.bias, torch.full_like(b.bias, float(b.bias[0, 0, 0, 0])))  # one for the image
    assert float(b.bias[0, 0, 0, 0]) == pytest.approx(-math.log(1.03), abs=0.005)
    torch.testing.assert_close(a.depth_fit, b.depth_fit, equal_nan=True)  # the fit does not see the bias
    err_a = (a.depth[0, 0][inner] / depth - 1).abs()
    err_b = (b.depth[0, 0][inner] / depth - 1).abs()
    assert float(err_a.median()) > 0.015 and float(err_b.max()) < 0.004
    ring = (b.depth[0, 0][~inner] / depth - 1).abs()
    assert float(ring.max()) < 0.005 and bool((b.confidence[0, 0][~inner] == model_c[0, 0][~inner]).all())


def test_shared_bias_weights_and_typed_errors():
    from tdfd.dfd.shared_bias import shared_bias, weighted_median

    assert weighted_median(torch.tensor([3.0, 1.0, 2.0]), torch.tensor([1.0, 1.0, 1.0])) == 2.0
    q = torch.linspace(1.0, 2.0, 10, dtype=torch.float64)
    q_model = q.clone()
    q_model[:4] *= 1.05  # four precise tiles say +5 %, six loose ones 0
    s_m = torch.full((10,), 0.01, dtype=torch.float64)
    s_f = torch.cat([torch.full((4,), 0.001), torch.full((6,), 0.05)]).to(torch.float64)
    assert shared_bias(q_model, s_m, q, s_f) == pytest.approx(math.log(1.05))
    s_f[:4] = math.inf  # no weight: now the loose ones decide, and too few are left
    assert shared_bias(q_model, s_m, q, s_f) == 0.0
    assert shared_bias(q_model, s_m, q, s_f, min_tiles=6) == pytest.approx(0.0, abs=1e-15)
    from tdfd.dfd.shared_bias import bias_map

    rows, cols = torch.arange(10) // 5, torch.arange(10) % 5
    with pytest.raises(InputError):
        bias_map(q_model, s_m, q, s_f, rows, cols, (2, 4))  # a column off the grid
    with pytest.raises(InputError):
        bias_map(q_model, s_m, q, s_f, rows, cols, (2, 5), radius=0)
    for bad in ((q_model, s_m, q[:5], s_f), (-q_model, s_m, q, s_f), (q_model, s_m * math.nan, q, s_f),
                (q_model, -s_m, q, s_f)):
        with pytest.raises(InputError):
            shared_bias(*bad)
    with pytest.raises(InputError):
        weighted_median(torch.tensor([1.0]), torch.tensor([0.0]))


def test_a_bias_radius_removes_each_regions_own_bias():
    """Two halves of one plane, the model 3 % far on the left and 3 % near on the right: one bias
    for the image removes one half's, one per neighbourhood both."""
    depth = 0.55
    hyp = PsfHypothesis("pillbox")
    i1, i2 = render_plane(depth, hyp, size=352, noise=5e-3)
    left = (torch.arange(10) < 5).to(torch.float32)
    model_d = (depth * (0.97 + 0.06 * left)).expand(1, 1, 10, 10).clone()
    model_c = torch.full((1, 1, 10, 10), 0.999)
    whole = LikelihoodStage(CAM, 64, 32, 0.01, family="pillbox",
                            scales=LikelihoodScales(1.0, 1.0, shared_bias=True))(i1, i2, model_d, model_c)
    local = LikelihoodStage(CAM, 64, 32, 0.01, family="pillbox",
                            scales=LikelihoodScales(1.0, 1.0, shared_bias=True, bias_radius=2))(i1, i2, model_d, model_c)
    inner = local.fitted[0, 0]
    assert int(inner.sum()) == 64
    away = inner & ((torch.arange(10) - 4.5).abs() > 2.0)[None, :]  # a radius from the halves' border
    err_whole = (whole.depth[0, 0][away] / depth - 1).abs()
    err_local = (local.depth[0, 0][away] / depth - 1).abs()
    assert float(err_whole.max()) > 0.03 and float(err_local.max()) < 0.005  # one bias fits one half only
    assert float(local.bias[0, 0, 5, 2]) == pytest.approx(-math.log(1.03), abs=0.005)
    assert float(local.bias[0, 0, 5, 7]) == pytest.approx(-math.log(0.97), abs=0.005)


def test_the_fused_scales_map_round_trips_and_version_2_loads_without_it(tmp_path):
    s = LikelihoodScales((1.5, 3.0), (0.7, 0.6), (0.02,), fused_log_b=(-6.0, -4.0, -2.0),
                         fused_log_b_calibrated=(-5.0, -3.5, -2.0))
    s.save(tmp_path / "s.json")
    back = LikelihoodScales.load(tmp_path / "s.json")
    assert back == s and back.fused_log_b == (-6.0, -4.0, -2.0)
    # between the knots log b + s(log b), s linear in the shifts (1, 0.5, 0); held beyond them
    b = torch.tensor([math.exp(-7.0), math.exp(-5.0), math.exp(-3.0), math.exp(-1.0), math.inf], dtype=torch.float64)
    torch.testing.assert_close(back.fused_scale(b)[:4].log(),
                               torch.tensor([-6.0, -4.25, -2.75, -1.0], dtype=torch.float64))
    assert back.fused_scale(b)[4] == math.inf
    plain = LikelihoodScales(2.0, 0.5)
    assert plain.fused_log_b is None and torch.equal(plain.fused_scale(b), b)
    (tmp_path / "v2.json").write_text(json.dumps({"format": "tdfd.likelihood_scales/2", "fit": 2.0, "model": 0.5,
                                                  "shared_bias": True, "bias_radius": 3}))
    v2 = LikelihoodScales.load(tmp_path / "v2.json")
    assert v2.fused_log_b is None and v2.fused_log_b_calibrated is None and v2.shared_bias


def test_the_fused_scales_slope_part_round_trips_and_needs_the_slope(tmp_path):
    s = LikelihoodScales(2.0, 0.5, fused_log_b=(-6.0, -2.0), fused_log_b_calibrated=(-6.0, -2.0),
                         fused_log_slope=(math.log(0.01), math.log(0.1)), fused_slope_log_shift=(-0.5, 0.25))
    s.save(tmp_path / "s.json")
    back = LikelihoodScales.load(tmp_path / "s.json")
    assert back == s and back.fused_slope_log_shift == (-0.5, 0.25)
    b = torch.full((5,), math.exp(-4.0), dtype=torch.float64)
    # slope 0 reads as 1e-4 (below the first knot: held), 0.01, sqrt(0.001) (halfway in log), 0.1, 1 (held)
    slope = torch.tensor([0.0, 0.01, math.sqrt(0.001), 0.1, 1.0], dtype=torch.float64)
    torch.testing.assert_close(back.fused_scale(b, slope).log(),
                               torch.tensor([-4.5, -4.5, -4.125, -3.75, -3.75], dtype=torch.float64))
    with pytest.raises(InputError, match="slope part"):
        back.fused_scale(b)
    with pytest.raises(InputError, match="slope part"):
        back.fused_scale(b, slope[:3])
    (tmp_path / "v3.json").write_text(json.dumps({"format": "tdfd.likelihood_scales/3", "fit": 2.0, "model": 0.5,
                                                  "fused_log_b": [-6.0, -2.0], "fused_log_b_calibrated": [-5.0, -2.0]}))
    v3 = LikelihoodScales.load(tmp_path / "v3.json")
    assert v3.fused_log_slope is None and float(v3.fused_scale(b[:1]).log()) == pytest.approx(-3.5)


@pytest.mark.parametrize("knots", [dict(fused_log_b=(-5.0, -3.0)),  # one of the pair
                                   dict(fused_log_b=(-5.0, -3.0), fused_log_b_calibrated=(-3.0, -4.0)),  # order lost
                                   dict(fused_log_b=(-3.0, -5.0), fused_log_b_calibrated=(-4.0, -3.0)),  # not increasing
                                   dict(fused_log_b=(-5.0,), fused_log_b_calibrated=(-4.0,)),  # one knot
                                   dict(fused_log_b=(-5.0, math.nan), fused_log_b_calibrated=(-4.0, -3.0)),
                                   # a slope part without a scale part
                                   dict(fused_log_slope=(-5.0, -3.0), fused_slope_log_shift=(0.0, 1.0)),
                                   dict(fused_log_b=(-5.0, -3.0), fused_log_b_calibrated=(-4.0, -3.0),
                                        fused_log_slope=(-5.0, -3.0)),  # one of the slope pair
                                   dict(fused_log_b=(-5.0, -3.0), fused_log_b_calibrated=(-4.0, -3.0),
                                        fused_log_slope=(-3.0, -5.0), fused_slope_log_shift=(0.0, 1.0))])
def test_bad_fused_scale_knots_are_typed_errors(tmp_path, knots):
    with pytest.raises(InputError):
        LikelihoodScales(2.0, 0.5, **knots)
    data = {"format": "tdfd.likelihood_scales/3", "fit": 2.0, "model": 0.5,
            **{k: [v if math.isfinite(v) else "nan" for v in vals] for k, vals in knots.items()}}
    (tmp_path / "bad.json").write_text(json.dumps(data))
    with pytest.raises(ModelError, match="bad likelihood scales"):
        LikelihoodScales.load(tmp_path / "bad.json")


def test_the_fused_confidence_goes_through_the_map_only_where_the_fit_adds_to_the_model():
    b0 = 0.01
    q_model = torch.tensor([2.0, 2.0, 2.0], dtype=torch.float64)
    q_fit = torch.tensor([2.02, 1.98, 2.0], dtype=torch.float64)
    s_model = torch.tensor([0.02, 0.02, 0.02], dtype=torch.float64)  # relative
    s_fit = torch.tensor([0.02, 0.04, math.inf], dtype=torch.float64)  # 1/m: 1 % and 2 %; none
    rows, cols = torch.tensor([0, 0, 1]), torch.tensor([0, 1, 0])
    plain = LikelihoodScales(1.0, 1.0)
    doubled = LikelihoodScales(1.0, 1.0, fused_log_b=(-20.0, 5.0), fused_log_b_calibrated=(-20.0 + math.log(2.0),
                                                                                         5.0 + math.log(2.0)))
    q0, c0, _, b0_raw = fuse_with_fit(q_model, s_model, q_fit, s_fit, torch.zeros(3), plain, b0, rows, cols, (2, 2))
    q1, c1, _, b1_raw = fuse_with_fit(q_model, s_model, q_fit, s_fit, torch.zeros(3), doubled, b0, rows, cols, (2, 2))
    torch.testing.assert_close(q0, q1)  # the map states the scale; the estimate is the same
    torch.testing.assert_close(b0_raw, b1_raw)
    # inverse variance of 1 % and 2 % relative: sigma 1/sqrt(1e4 + 2.5e3); the Laplace scale sigma / sqrt(2)
    expected = 1.0 / math.sqrt(1e4 + 2.5e3) / math.sqrt(2.0)
    assert float(b0_raw[0]) == pytest.approx(expected, rel=0.02)
    torch.testing.assert_close(c0[:2], 1.0 / (1.0 + (b0_raw[:2] / b0) ** 2))
    torch.testing.assert_close(c1[:2], 1.0 / (1.0 + (2.0 * b0_raw[:2] / b0) ** 2))
    # no fit: the model's own confidence, map or not (sigma 2 % is b = sqrt(2) %: conf 1/3)
    assert float(c0[2]) == pytest.approx(1.0 / 3.0) and float(c1[2]) == pytest.approx(1.0 / 3.0)


def test_scales_say_which_psf_they_were_fitted_for(tmp_path):
    """``psf``: profiled (the default, and what a file without the key was fitted for) or measured."""
    s = LikelihoodScales(2.0, 0.5, psf="measured")
    s.save(tmp_path / "m.json")
    assert LikelihoodScales.load(tmp_path / "m.json").psf == "measured"
    assert LikelihoodScales(2.0, 0.5).psf == "profiled"
    (tmp_path / "old.json").write_text(json.dumps({"format": "tdfd.likelihood_scales/3", "fit": 2.0, "model": 0.5}))
    assert LikelihoodScales.load(tmp_path / "old.json").psf == "profiled"
    with pytest.raises(InputError, match="psf must be one of"):
        LikelihoodScales(2.0, 0.5, psf="calibrated")
    (tmp_path / "bad.json").write_text(json.dumps({"format": "tdfd.likelihood_scales/3", "fit": 2.0, "model": 0.5,
                                                   "psf": "told"}))
    with pytest.raises(ModelError, match="bad likelihood scales"):
        LikelihoodScales.load(tmp_path / "bad.json")
