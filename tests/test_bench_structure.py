"""Helpers of the issue-19 benchmarks: occlusion-edge tiles, the confidence-to-scale inversion,
the decile calibration table, the per-tile information bound and the latency ratio."""

from __future__ import annotations

import math

import pytest
import torch

from benchmarks.bench_bound import median_at_bound, plane_fisher, tile_fisher
from benchmarks.bench_onnx import latency_ratio
from benchmarks.bench_structure import largest_share
from benchmarks.depth_edges import depth_discontinuities, edge_tiles, tile_depth_spread
from benchmarks.depth_models import predicted_scale
from benchmarks.uncertainty import decile_table, laplace_mixture_median, scene_bootstrap
from tdfd import Camera
from tdfd.errors import InputError
from tdfd.model import DFDModel

REF = Camera.preset("reference")


# ---------------------------------------------------------------- occlusion edges
def _ramp(h: int, w: int, q0: float, slope_per_px: float) -> torch.Tensor:
    """Depth (m) of a plane whose inverse depth rises by ``slope_per_px`` (relative to q0) per column."""
    x = torch.arange(w, dtype=torch.float64)[None, :].expand(h, w)
    return 1.0 / (q0 * (1.0 + slope_per_px * x))


def test_a_step_flags_exactly_the_tiles_around_it():
    d = torch.full((128, 320), 0.8, dtype=torch.float64)
    d[:, 160:] = 0.5  # a near object from column 160 on: pixels 159 | 160
    # 64-px tiles at stride 32: columns 32j .. 32j + 63; tiles 3 to 5 hold column 159 or 160
    own = edge_tiles(d, 64, 32, reach=0)
    assert own.shape == (3, 9)
    assert own[0].tolist() == [False, False, False, True, True, True, False, False, False]
    near = edge_tiles(d, 64, 32)  # one tile further on each side
    assert near[0].tolist() == [False, False, True, True, True, True, True, False, False]
    assert bool((near == near[0]).all())  # the same in every row of tiles


def test_steep_smooth_slopes_are_no_edges_but_a_small_step_on_them_is():
    # 3 % per pixel: steeper than any data_synth relief, yet smooth
    d = _ramp(96, 200, 1.2, 0.03)
    assert not bool(depth_discontinuities(d).any())
    assert not bool(edge_tiles(d, 64, 32).any())
    # a curved surface (quadratic in x) is no edge either
    x = torch.linspace(-1, 1, 200, dtype=torch.float64)
    curved = (1.0 / (2.0 + 1.5 * x**2))[None].expand(96, 200).clone()
    assert not bool(depth_discontinuities(curved).any())
    # a 2 % step on the gentle ramp is one
    stepped = _ramp(96, 200, 1.2, 0.001)
    stepped[:, 100:] /= 1.02
    disc = depth_discontinuities(stepped)
    assert disc[:, 99:101].all() and int(disc.sum()) == 2 * 96
    # below the jump threshold it is not
    small = _ramp(96, 200, 1.2, 0.001)
    small[:, 100:] /= 1.005
    assert not bool(depth_discontinuities(small).any())


def test_edge_rows_work_along_columns_too_and_bad_maps_are_refused():
    d = torch.full((200, 64), 0.4, dtype=torch.float64)
    d[70:, :] = 0.9
    assert edge_tiles(d, 64, 32, reach=0)[:, 0].tolist() == [False, True, True, False, False]  # rows 69 | 70
    with pytest.raises(InputError):
        depth_discontinuities(torch.zeros(8, 8))
    with pytest.raises(InputError):
        edge_tiles(torch.ones(32, 32), 64, 32)  # smaller than a tile


# ---------------------------------------------------------------- confidence -> scale
def test_scale_inversion_recovers_the_models_own_log_scale():
    model = DFDModel(REF, tile=32, stride=32, hidden=8, blocks=1, confidence_scale=0.02)
    g = torch.Generator().manual_seed(3)
    with torch.no_grad():
        for p in model.refine.parameters():  # a head that predicts varied scales
            p.copy_(0.3 * torch.randn(p.shape, generator=g))
        feats = torch.randn(2, _in_channels(model), 4, 5, generator=g)
        q_a = torch.full((2, 1, 4, 5), 2.0)
        rel = torch.exp(torch.empty(2, 1, 4, 5).uniform_(-6.0, 0.0, generator=g))
        _, log_scale, conf, _ = model.head(feats, q_a, rel)
    b = predicted_scale(conf, model.confidence_scale)
    keep = conf < 0.999  # float32 confidence resolves b only where it is not saturated at 1
    assert int(keep.sum()) > 10
    torch.testing.assert_close(b[keep], torch.exp(log_scale.double())[keep], rtol=2e-3, atol=0)


def _in_channels(model: DFDModel) -> int:
    from tdfd.model import num_features

    return num_features(model.analytic.num_rings, model.contexts)


def test_scale_inversion_edges_and_errors():
    b = predicted_scale(torch.tensor([1.0, 0.5, 0.2], dtype=torch.float64), 0.01)
    assert float(b[0]) == 0.0 and abs(float(b[1]) - 0.01) < 1e-15 and abs(float(b[2]) - 0.02) < 1e-12
    with pytest.raises(InputError):
        predicted_scale(torch.tensor([1.2]), 0.01)
    with pytest.raises(InputError):
        predicted_scale(torch.tensor([float("nan")]), 0.01)


# ---------------------------------------------------------------- decile table
def test_laplace_mixture_median():
    assert abs(laplace_mixture_median(torch.tensor([0.02])) - 0.02 * math.log(2)) < 1e-9
    # an equal mix of b = 1 and b = 3: P(|e| <= m) = 1 - (exp(-m) + exp(-m/3)) / 2 = 1/2
    m = laplace_mixture_median(torch.tensor([1.0, 3.0]))
    assert abs(0.5 * (math.exp(-m) + math.exp(-m / 3)) - 0.5) < 1e-9
    assert laplace_mixture_median(torch.tensor([0.0, 0.0, 1.0])) < 1e-50  # two thirds exact
    with pytest.raises(InputError):
        laplace_mixture_median(torch.tensor([]))


def _laplace(scale: torch.Tensor, g: torch.Generator) -> torch.Tensor:
    u = torch.rand(scale.shape, generator=g, dtype=torch.float64) - 0.5
    return -scale * torch.sign(u) * torch.log1p(-2 * u.abs())


def test_decile_table_passes_calibrated_errors_and_catches_overconfidence():
    g = torch.Generator().manual_seed(0)
    n = 20_000
    scale = torch.exp(torch.empty(n, dtype=torch.float64).uniform_(-7, -2, generator=g))
    conf = 1.0 / (1.0 + (scale / 0.01) ** 2)
    rows = decile_table(conf, scale, _laplace(scale, g))
    assert len(rows) == 10 and sum(r["tiles"] for r in rows) == n
    assert all(r["ok"] for r in rows), [round(r["ratio"], 3) for r in rows]
    assert all(abs(r["within"] - 0.5) < 0.05 for r in rows)
    assert rows[0]["conf_hi"] <= rows[-1]["conf_lo"]  # from least to most confident
    # errors 1.5x what the model states: every decile fails, ratio ~1.5
    bad = decile_table(conf, scale, 1.5 * _laplace(scale, g))
    assert not any(r["ok"] for r in bad)
    assert all(1.3 < r["ratio"] < 1.7 for r in bad)
    with pytest.raises(InputError):
        decile_table(conf[:5], scale[:5], scale[:5])  # fewer tiles than bins
    with pytest.raises(InputError):
        decile_table(conf, scale[:-1], scale)


# ---------------------------------------------------------------- per-tile bound
PARAMS = {"psf_shape": "gaussian", "psf_beta": 2.0, "diffraction_sigma_px": 0.3, "astigmatism": 0.05,
          "astigmatism_angle": 0.2, "spherical": 0.1, "full_well_e": 10_000.0, "read_noise_e": 3.0, "bits": 12,
          "black_level_dn": 0.0, "gain": 1.0, "exposure": 1.0}


def _texture(seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return 0.3 + 0.1 * (torch.rand(128, 160, generator=g, dtype=torch.float64) - 0.5)


def test_tile_fisher_of_a_constant_depth_is_the_plane_fisher():
    sharp = _texture()
    f = tile_fisher(REF, sharp, torch.full((3, 4), 0.45, dtype=torch.float64), PARAMS)
    torch.testing.assert_close(f, plane_fisher(REF, sharp, 0.45, PARAMS))


def test_tile_fisher_interpolates_between_depths():
    sharp = _texture(1)
    # a slanted plane over 1.6-2.4 1/m (0.42-0.63 m), the depth information only
    depth = 1.0 / torch.linspace(1.6, 2.4, 12, dtype=torch.float64).reshape(3, 4)
    coarse = tile_fisher(REF, sharp, depth, PARAMS, nuisances=False)  # the default node spacing
    # each tile as if the whole image were at its depth
    for i, j in ((0, 0), (0, 1), (1, 2), (2, 3)):
        exact = plane_fisher(REF, sharp, float(depth[i, j]), PARAMS, nuisances=False)[i, j]
        torch.testing.assert_close(coarse[i, j], exact, rtol=0.02, atol=0)
    # the nodes hit the ends of the range exactly
    torch.testing.assert_close(coarse[0, 0], plane_fisher(REF, sharp, float(depth[0, 0]), PARAMS, nuisances=False)[0, 0],
                               rtol=1e-12, atol=0)
    with pytest.raises(InputError):
        tile_fisher(REF, sharp, depth[:2], PARAMS)


# ---------------------------------------------------------------- latency ratio
def test_latency_ratio_pairs_rounds():
    # the new model is 1.1x the baseline in every round, while the load doubles half-way
    base = [1.0] * 10 + [2.0] * 10
    new = [1.1] * 10 + [2.2] * 10
    r = latency_ratio(new, base)
    assert abs(r["paired"] - 1.1) < 1e-12 and abs(r["median"] - 1.65 / 1.5) < 1e-12
    with pytest.raises(ValueError):
        latency_ratio([], base)


# ---------------------------------------------------------------- the two model runners
def test_onnx_and_torch_runners_give_the_same_depth_and_scale():
    from benchmarks.depth_models import load_depth_model
    from benchmarks.report import ROOT
    from tdfd.optics import render_pair

    torch_model = load_depth_model(ROOT / "models" / "reference")
    onnx_model = load_depth_model(ROOT / "models" / "reference.onnx")
    assert (onnx_model.tile, onnx_model.stride) == (torch_model.tile, torch_model.stride)
    assert onnx_model.confidence_scale == torch_model.confidence_scale
    g = torch.Generator().manual_seed(5)
    sharp = (0.4 + 0.2 * torch.rand(1, 1, 128, 192, generator=g, dtype=torch.float64)).clamp(0, 1)
    i1, i2 = render_pair(REF, sharp, torch.full((1, 1, 128, 192), 0.5, dtype=torch.float64))
    d_t, c_t, _ = torch_model.run(i1.float(), i2.float())
    d_o, c_o, _ = onnx_model.run(i1.float(), i2.float())
    torch.testing.assert_close(d_o, d_t, rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(c_o, c_t, rtol=1e-3, atol=1e-4)
    # the shipped model pools: 'map' scores the pooled map, 'tiles' each tile's own estimate, in both runners
    assert torch_model.pooled and onnx_model.pooled
    tiles_t = load_depth_model(ROOT / "models" / "reference", output="tiles")
    tiles_o = load_depth_model(ROOT / "models" / "reference.onnx", output="tiles")
    assert not tiles_t.pooled and not tiles_o.pooled
    dt_t, ct_t, _ = tiles_t.run(i1.float(), i2.float())
    dt_o, _, _ = tiles_o.run(i1.float(), i2.float())
    torch.testing.assert_close(dt_o, dt_t, rtol=1e-4, atol=1e-5)
    with torch.no_grad():
        r = DFDModel.load(ROOT / "models" / "reference").eval().analyse(i1.float(), i2.float())
    assert torch.equal(dt_t, r.depth) and torch.equal(ct_t, r.confidence) and torch.equal(d_t, r.depth_pooled)
    assert not torch.allclose(d_t, dt_t, rtol=1e-4)
    with pytest.raises(InputError, match="output"):
        load_depth_model(ROOT / "models" / "reference", output="pooled")


def test_the_told_runner_tells_each_scene_its_family_and_the_summary_compares():
    from benchmarks.bench_structure import summarise_structure
    from benchmarks.depth_models import load_depth_model
    from benchmarks.report import ROOT
    from tdfd.model import family_code
    from tdfd.optics import render_pair

    model = load_depth_model(ROOT / "models" / "reference")
    assert model.run_told is not None and load_depth_model(ROOT / "models" / "reference.onnx").run_told is None
    net = DFDModel.load(ROOT / "models" / "reference").eval()
    g = torch.Generator().manual_seed(6)
    sharp = (0.4 + 0.2 * torch.rand(2, 1, 128, 128, generator=g, dtype=torch.float64)).clamp(0, 1)
    i1, i2 = render_pair(REF, sharp, torch.full((2, 1, 128, 128), 0.6, dtype=torch.float64))
    params = [{"psf_shape": "pillbox", "sample_seed": 1}, {"psf_shape": "beta", "sample_seed": 2}]
    d, c, _ = model.run_told(i1.float(), i2.float(), params)
    with torch.no_grad():
        codes = torch.stack([family_code("pillbox"), family_code(None)])
        want = net.analyse(i1.float(), i2.float(), codes)
    torch.testing.assert_close(d, want.depth_map[0])  # the shipped model's pooled map
    assert not torch.allclose(d[0], model.run(i1.float(), i2.float())[0][0])  # the pillbox scene was told
    # the summary's told block: the Gaussian and pillbox scenes' tiles away from edges only
    t = torch.full((6,), 0.5)
    tiles = {"true": t, "refined": t * 1.04, "analytic": t, "confidence": torch.full((6,), 0.2),
             "edge": torch.tensor([False] * 5 + [True]), "psf": torch.tensor([0, 1, 2, 0, 1, 0]),
             "refined_told": t * torch.tensor([1.01, 1.01, 1.5, 1.01, 1.01, 1.5]),
             "confidence_told": torch.tensor([0.6, 0.6, 0.9, 0.2, 0.2, 0.9])}
    told = summarise_structure(tiles, (0.3, 1.0))["told"]
    assert told["tiles"] == 4 and told["told"] == pytest.approx(0.01, rel=1e-4)
    assert told["untold"] == pytest.approx(0.04, rel=1e-4) and told["share_told"] == 0.5


def test_summary_splits_the_bound_tiles_by_their_information():
    from benchmarks.bench_structure import INFORMATION_BANDS, summarise_structure

    # six tiles away from edges: two well measured (bound 0.2 %), two middling (3 %), two without
    # information (50 %); one more near an edge, which the split leaves out
    t = torch.full((7,), 0.5)
    bound = torch.tensor([0.002, 0.002, 0.03, 0.03, 0.5, 0.5, math.nan])
    tiles = {"true": t, "refined": t * torch.tensor([1.01, 1.03, 1.05, 1.05, 1.3, 1.1, 2.0]),
             "analytic": t * 1.2, "confidence": torch.tensor([0.9, 0.7, 0.3, 0.3, 0.0, 0.0, 1.0]),
             "edge": torch.tensor([False] * 6 + [True]),
             "bound_shared": bound, "bound_known": bound}
    bands = summarise_structure(tiles, (0.3, 1.0))["bound"]["by_information"]
    assert [b["lo"] for b in bands] == [INFORMATION_BANDS[0][0], 0.02, 0.05]  # empty bands are left out
    assert [b["tiles"] for b in bands] == [2, 2, 2] and sum(b["share"] for b in bands) == pytest.approx(1.0)
    assert bands[0]["refined"] == pytest.approx(0.01, rel=1e-4)  # torch's median: the lower of two
    assert bands[0]["at_bound"] == pytest.approx(0.6745 * 0.002, rel=1e-3)
    assert bands[2]["analytic"] == pytest.approx(0.2, rel=1e-4) and bands[0]["confidence"] == pytest.approx(0.7)


def test_scene_bootstrap_counts_scenes_not_tiles():
    """Tiles whose errors share their scene's scale: resampling scenes gives a larger standard
    error than treating every tile as its own scene (the tiles are not independent)."""
    g = torch.Generator().manual_seed(11)
    scenes, per = 12, 150
    scene_factor = torch.exp(0.8 * torch.randn(scenes, generator=g, dtype=torch.float64)).repeat_interleave(per)
    b = torch.exp(torch.empty(scenes * per, dtype=torch.float64).uniform_(-6.0, -2.0, generator=g))
    u = torch.rand(scenes * per, generator=g, dtype=torch.float64) - 0.5
    e = scene_factor * b * -u.sign() * torch.log1p(-2 * u.abs())
    conf = 1 / (1 + (b / 0.01) ** 2)
    by_scene = scene_bootstrap(conf, b, e, torch.arange(scenes).repeat_interleave(per), bins=5, reps=60)
    by_tile = scene_bootstrap(conf, b, e, torch.arange(scenes * per), bins=5, reps=60)
    assert by_scene.shape == (5,) and bool((by_scene > 0).all())
    assert float(by_scene.mean()) > 2 * float(by_tile.mean())
    with pytest.raises(InputError, match="two scenes"):
        scene_bootstrap(conf, b, e, torch.zeros(scenes * per), bins=5)
    with pytest.raises(InputError, match="one value per tile"):
        scene_bootstrap(conf, b, e, torch.zeros(3), bins=5)


def test_tile_depth_spread_zero_on_a_plane_and_exact_on_a_ramp():
    plane = torch.full((96, 160), 0.5, dtype=torch.float64)
    assert torch.equal(tile_depth_spread(plane, 64, 32), torch.zeros(2, 4, dtype=torch.float64))
    q = torch.linspace(1.0, 4.0, 160, dtype=torch.float64).expand(96, 160)  # inverse depth rises along the rows
    sp = tile_depth_spread(1.0 / q, 64, 32)
    step = 3.0 / 159
    first = 63 * step / (1.0 + 31.5 * step)  # range / mean of the first tile's columns
    assert sp.shape == (2, 4) and float(sp[0, 0]) == pytest.approx(first, rel=1e-12)
    assert bool((sp[:, 1:] < sp[:, :-1]).all())  # the same range over larger means
    with pytest.raises(InputError, match="positive"):
        tile_depth_spread(torch.zeros(96, 160), 64, 32)
    with pytest.raises(InputError, match="smaller"):
        tile_depth_spread(plane[:32], 64, 32)


def test_largest_share_of_the_best_tiles_within_a_median():
    sigma = torch.tensor([0.005] * 40 + [0.2] * 60, dtype=torch.float64)  # sorted, the best first
    share = largest_share(lambda k: median_at_bound(sigma[:k]), 100, 0.01)
    # 40 tiles at 0.5 % have a median of 0.34 %; each tile at 20 % added pushes it up, past 1 % at the 80th
    assert share == pytest.approx(0.79)
    assert median_at_bound(sigma[:round(100 * share)]) <= 0.01 < median_at_bound(sigma[:round(100 * share) + 1])
    assert largest_share(lambda k: median_at_bound(sigma[:k]), 100, 0.001) == 0.0  # not even the best tile
    assert largest_share(lambda k: median_at_bound(sigma[:k]), 100, 1.0) == 1.0
    assert largest_share(lambda k: 0.0, 0, 0.01) == 0.0


def test_scene_intervals_widen_when_few_scenes_carry_the_tiles():
    """1000 tiles whose errors follow their scene's level: held by 5 scenes, the median's
    interval over the scenes is much wider than held by 50, and much wider than a bootstrap
    that takes every tile for its own scene; the concentration names the largest scenes' share."""
    from benchmarks.bench_structure import TOP_SCENES, scene_intervals

    g = torch.Generator().manual_seed(4)

    def tiles(scenes: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        level = torch.exp(torch.empty(scenes, dtype=torch.float64).uniform_(-5.0, -2.0, generator=g))
        scene = torch.arange(scenes).repeat_interleave(1000 // scenes)
        err = level[scene] * (1.0 + 0.1 * torch.rand(1000, generator=g, dtype=torch.float64))
        return err, torch.where(err < 0.02, 0.8, 0.1), scene

    def width(r: dict) -> float:
        return r["refined_hi"] - r["refined_lo"]

    err5, conf5, scene5 = tiles(5)
    r5 = scene_intervals(err5, conf5, scene5, reps=300)
    r50 = scene_intervals(*tiles(50), reps=300)
    per_tile = scene_intervals(err5, conf5, torch.arange(1000), reps=300)
    assert r5["scenes"] == 5 and r50["scenes"] == 50 and per_tile["scenes"] == 1000
    assert width(r5) > 2.0 * width(r50) and width(r5) > 3.0 * width(per_tile)
    assert r5["refined_lo"] <= float(err5.median()) <= r5["refined_hi"]
    assert 0.0 <= r5["share_lo"] < r5["share_hi"] <= 1.0
    assert r50["top_scenes_share"] == pytest.approx(TOP_SCENES / 50)
    uneven = torch.cat([torch.zeros(620, dtype=torch.long), torch.arange(1, 20).repeat_interleave(20)])
    r = scene_intervals(err5, conf5, uneven, reps=10)
    assert r["top_scenes_share"] == pytest.approx((620 + 20 * (TOP_SCENES - 1)) / 1000)
    with pytest.raises(ValueError, match="equal non-empty"):
        scene_intervals(err5, conf5[:-1], scene5)


def test_merged_layouts_keep_their_scenes_apart():
    """Scene 0 of one layout and scene 0 of another are two scenes in the summary of all layouts."""
    from benchmarks.bench_structure import merge_layouts, summarise_structure

    t = torch.full((4,), 0.5)
    one = {"true": t, "refined": t * 1.02, "analytic": t, "confidence": torch.zeros(4),
           "edge": torch.zeros(4, dtype=torch.bool), "scene": torch.tensor([0, 0, 1, 1])}
    merged = merge_layouts({"slanted": one, "layout": dict(one, refined=t * 1.04)})
    assert merged["refined"].shape == (8,) and merged["scene"].unique().numel() == 4
    assert summarise_structure(merged, (0.3, 1.0), reps=20)["interior"]["scenes"] == 4
    assert "refined_lo" not in summarise_structure(one, (0.3, 1.0), reps=0)["interior"]


def test_worker_processes_collect_the_same_tiles_in_the_same_order():
    """``--jobs``: the scenes split over spawned processes give the tiles one process gives."""
    from benchmarks.bench_structure import collect_layouts
    from benchmarks.depth_models import load_depth_model
    from benchmarks.report import ROOT

    path = str(ROOT / "models" / "reference")
    model = load_depth_model(path, threads=1)
    one = collect_layouts(model, path, 3, (192, 256), bound=False, told=False, jobs=1)
    split = collect_layouts(model, path, 3, (192, 256), bound=False, told=False, jobs=2)
    assert list(split) == list(one)
    for lay in one:
        assert one[lay]["scene"].unique().tolist() == [0, 1, 2]
        for k in one[lay]:
            torch.testing.assert_close(split[lay][k], one[lay][k], msg=f"{lay} {k}")


def test_a_target_is_met_only_when_the_scenes_interval_meets_it():
    from benchmarks.bench_structure import judge_over_scenes

    assert judge_over_scenes(0.019, 0.015, 0.0199, 0.02, at_most=True) == "yes"
    assert judge_over_scenes(0.019, 0.015, 0.026, 0.02, at_most=True).startswith("**undecided**")
    assert judge_over_scenes(0.021, 0.019, 0.026, 0.02, at_most=True) == "**no**"
    assert judge_over_scenes(0.55, 0.51, 0.60, 0.5, at_most=False) == "yes"
    assert judge_over_scenes(0.55, 0.45, 0.60, 0.5, at_most=False).startswith("**undecided**")
    assert judge_over_scenes(0.13, 0.10, 0.55, 0.5, at_most=False) == "**no**"
