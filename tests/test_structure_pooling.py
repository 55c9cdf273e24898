"""Pooling the tile depths along the depth structure (issue 19): the robust local surface fit,
its place in the model, its JSON round trip, the ONNX export and the calibration of its scale."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from export import export_model, realistic_pairs, verify_onnx
from export.testing import make_test_model
from tdfd import Camera
from tdfd.contract import OUTPUT_NAMES, POOLED_OUTPUT_NAMES
from tdfd.errors import InputError, ModelError, NonFiniteError, RangeError, ShapeError
from tdfd.model import DFDModel
from tdfd.model.scale_calibration import ScaleCalibration
from tdfd.model.structure_pooling import StructurePooling, pool_inverse_depth
from tests.onnx_parity import assert_parity
from training import calibrate_scale


def _grid(h: int, w: int) -> tuple[torch.Tensor, torch.Tensor]:
    yy, xx = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
    return yy.reshape(1, 1, h, w), xx.reshape(1, 1, h, w)


@pytest.mark.parametrize("degree", [0, 1, 2])
def test_a_surface_of_the_fits_degree_is_kept(degree):
    y, x = _grid(7, 9)
    surface = {0: 2.0 + 0 * x, 1: 2.0 + 0.04 * y - 0.03 * x, 2: 2.0 + 0.04 * y - 0.03 * x + 0.003 * y * x - 0.002 * x * x}
    q = surface[degree]
    b = 0.002 + 0.03 * torch.rand(q.shape, generator=torch.Generator().manual_seed(degree), dtype=torch.float64)
    out = pool_inverse_depth(q, b, degree=degree, ridge=0.0)
    assert torch.allclose(out, q, rtol=1e-9, atol=1e-9)


def test_a_constant_fit_is_biased_on_a_curved_surface_and_the_quadratic_is_not():
    y, x = _grid(8, 8)
    q = 1.5 + 0.01 * (x - 3.5) ** 2
    b = torch.full_like(q, 0.01)
    assert float((pool_inverse_depth(q, b, degree=0) - q).abs().max()) > 0.01
    assert float((pool_inverse_depth(q, b, degree=2, ridge=0.0) - q).abs().max()) < 1e-9


def test_noise_on_a_plane_is_averaged_down():
    g = torch.Generator().manual_seed(0)
    y, x = _grid(24, 32)
    truth = 1.8 + 0.01 * y - 0.005 * x
    rel = 0.02
    q = truth * (1 + rel * torch.randn(truth.shape, generator=g, dtype=torch.float64))
    out = pool_inverse_depth(q, torch.full_like(q, rel))
    inner = (slice(None), slice(None), slice(2, -2), slice(2, -2))
    before = ((q - truth) / truth)[inner].pow(2).mean().sqrt()
    after = ((out - truth) / truth)[inner].pow(2).mean().sqrt()
    # 25 tiles and 6 parameters: the centre value's variance shrinks several-fold
    assert float(after) < 0.5 * float(before)


def test_the_curvature_test_keeps_planes_flat_and_curves_curved():
    """On noisy planes the plane fit (``curvature_test``) errs less than the quadratic; on a
    clearly curved surface the test keeps the quadratic, where a plane would be biased."""
    g = torch.Generator().manual_seed(11)
    y, x = _grid(24, 32)
    rel = 0.02
    inner = (slice(None), slice(None), slice(2, -2), slice(2, -2))

    def rms(out, truth):
        return float(((out - truth) / truth)[inner].pow(2).mean().sqrt())

    plane = 1.8 + 0.01 * y - 0.005 * x
    noisy = plane * (1 + rel * torch.randn(plane.shape, generator=g, dtype=torch.float64))
    # the stated scale twice the noise: as the model's tiles, whose errors a local fit mostly
    # shares with their neighbours (the test's threshold was chosen on such tiles)
    b = torch.full_like(noisy, 2 * rel)
    quadratic = pool_inverse_depth(noisy, b)
    tested = pool_inverse_depth(noisy, b, curvature_test=1.0)
    assert rms(tested, plane) < 0.85 * rms(quadratic, plane)
    assert rms(pool_inverse_depth(noisy, b, degree=1), plane) <= rms(tested, plane) + 1e-12  # the plane is the limit
    # a bowl whose curvature the window sees far above the noise: the quadratic stays
    bowl = 1.5 + 0.004 * (x - 15.5) ** 2 + 0.003 * (y - 11.5) ** 2
    noisy_bowl = bowl * (1 + 0.002 * torch.randn(bowl.shape, generator=g, dtype=torch.float64))
    b2 = torch.full_like(bowl, 0.002)
    kept, curved = pool_inverse_depth(noisy_bowl, b2, curvature_test=1.0), pool_inverse_depth(noisy_bowl, b2)
    assert float((kept == curved).double().mean()) > 0.9 and rms(kept, bowl) < 1.1 * rms(curved, bowl)
    assert rms(pool_inverse_depth(noisy_bowl, b2, degree=1), bowl) > 3 * rms(kept, bowl)
    # off (0) is the quadratic everywhere; a lower degree ignores the test
    assert torch.equal(pool_inverse_depth(noisy, b, curvature_test=0.0), quadratic)
    assert torch.equal(pool_inverse_depth(noisy, b, degree=1, curvature_test=5.0), pool_inverse_depth(noisy, b, degree=1))


def test_an_occlusion_edge_is_kept():
    """Two surfaces 30 % apart in inverse depth: no tile is pulled towards the other one."""
    g = torch.Generator().manual_seed(1)
    y, x = _grid(12, 16)
    truth = torch.where(x < 7, 1.4 + 0 * x, 1.82 + 0.01 * y)
    q = truth * (1 + 0.005 * torch.randn(truth.shape, generator=g, dtype=torch.float64))
    out = pool_inverse_depth(q, torch.full_like(q, 0.005))
    assert float(((out - truth) / truth).abs().max()) < 0.01  # a mixed fit would err by up to 15 %
    mean = pool_inverse_depth(q, torch.full_like(q, 0.005), kernel_width=1e3)  # no robust kernel
    assert float(((mean - truth) / truth).abs().max()) > 0.05  # the kernel is what keeps the edge


def test_the_confident_tiles_decide():
    y, x = _grid(9, 9)
    truth = 2.0 + 0.02 * x
    q, b = truth.clone(), torch.full_like(truth, 0.005)
    q[..., 4, 4] *= 1.04  # an unconfident outlier is replaced by its neighbours' surface
    b[..., 4, 4] = 0.5
    out = pool_inverse_depth(q, b)
    assert abs(float(out[..., 4, 4] / truth[..., 4, 4]) - 1) < 1e-3
    q2, b2 = truth * (1 + 0.04 * torch.randn(truth.shape, generator=torch.Generator().manual_seed(2),
                                             dtype=torch.float64)), torch.full_like(truth, 0.5)
    q2[..., 4, 4], b2[..., 4, 4] = truth[..., 4, 4], 0.001  # a confident tile among noisy unconfident ones
    out2 = pool_inverse_depth(q2, b2)
    assert abs(float(out2[..., 4, 4] / truth[..., 4, 4]) - 1) < 2e-3


@pytest.mark.parametrize("shape", [(1, 1), (1, 6), (2, 5), (5, 1), (3, 3)])
def test_small_grids_are_finite_and_keep_a_constant(shape):
    q = torch.full((2, 1) + shape, 1.7, dtype=torch.float64)
    b = torch.rand(q.shape, generator=torch.Generator().manual_seed(3), dtype=torch.float64) * 0.1
    out = pool_inverse_depth(q, b)
    assert torch.allclose(out, q, rtol=1e-9)
    noisy = q + 0.01 * torch.randn(q.shape, generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    assert torch.isfinite(pool_inverse_depth(noisy, b)).all()
    if shape == (1, 1):
        assert torch.allclose(pool_inverse_depth(noisy, b), noisy, rtol=1e-7)


def test_images_of_a_batch_are_pooled_apart():
    g = torch.Generator().manual_seed(5)
    q = 1.5 + 0.05 * torch.rand(3, 1, 6, 7, generator=g, dtype=torch.float64)
    b = 0.005 + 0.02 * torch.rand(3, 1, 6, 7, generator=g, dtype=torch.float64)
    out = pool_inverse_depth(q, b)
    for k in range(3):
        assert torch.allclose(out[k:k + 1], pool_inverse_depth(q[k:k + 1], b[k:k + 1]), rtol=1e-12)


def test_float32_agrees_with_float64():
    g = torch.Generator().manual_seed(6)
    q = 1.2 + 0.6 * torch.rand(2, 1, 11, 15, generator=g, dtype=torch.float64)
    b = 0.003 + 0.2 * torch.rand(2, 1, 11, 15, generator=g, dtype=torch.float64)
    a = pool_inverse_depth(q, b)
    c = pool_inverse_depth(q.float(), b.float()).double()
    assert torch.allclose(c, a, rtol=1e-5)


@pytest.mark.parametrize("degree, curvature_test", [(1, 0.0), (2, 0.0), (2, 1.0)])
def test_gradcheck_float64(degree, curvature_test):
    g = torch.Generator().manual_seed(7)
    q = (1.5 + 0.05 * torch.rand(1, 1, 4, 5, generator=g, dtype=torch.float64)).requires_grad_()
    b = (0.01 + 0.02 * torch.rand(1, 1, 4, 5, generator=g, dtype=torch.float64)).requires_grad_()
    if curvature_test:  # both branches taken on this grid: the test's choice is piecewise constant
        with torch.no_grad():
            tested = pool_inverse_depth(q, b, radius=1, curvature_test=curvature_test)
            assert not torch.equal(tested, pool_inverse_depth(q, b, radius=1))
            assert not torch.equal(tested, pool_inverse_depth(q, b, radius=1, degree=1))
    assert torch.autograd.gradcheck(
        lambda a, c: pool_inverse_depth(a, c, radius=1, degree=degree, curvature_test=curvature_test), (q, b))


@pytest.mark.parametrize("kw, match", [
    (dict(radius=0), "radius"), (dict(radius=1.5), "radius"), (dict(degree=3), "degree"),
    (dict(iterations=0), "iterations"), (dict(kernel_width=0.0), "kernel_width"),
    (dict(scale_floor=-1.0), "scale_floor"), (dict(ridge=-0.1), "ridge"), (dict(ridge=math.inf), "finite"),
    (dict(kernel_width=math.nan), "kernel_width"), (dict(curvature_test=-1.0), "curvature_test"),
    (dict(curvature_test=math.inf), "finite")])
def test_bad_options_are_named(kw, match):
    q = torch.ones(1, 1, 3, 3)
    with pytest.raises(InputError, match=match):
        pool_inverse_depth(q, q, **kw)
    with pytest.raises(InputError, match=match):
        StructurePooling(**kw)


@pytest.mark.parametrize("q_value, b_value, error, match", [
    (math.nan, 0.01, NonFiniteError, "finite"), (1.5, math.inf, NonFiniteError, "finite"),
    (0.0, 0.01, RangeError, "> 0"), (-1.0, 0.01, RangeError, "> 0"), (1.5, -0.01, RangeError, "scale >= 0")])
def test_bad_values_are_named(q_value, b_value, error, match):
    q, b = torch.full((1, 1, 4, 4), 1.5), torch.full((1, 1, 4, 4), 0.01)
    q[..., 2, 1], b[..., 1, 2] = q_value, b_value
    with pytest.raises(error, match=match):
        pool_inverse_depth(q, b)


def test_bad_shapes_are_named():
    with pytest.raises(ShapeError, match="equal"):
        pool_inverse_depth(torch.ones(1, 1, 3, 3), torch.ones(1, 1, 3, 4))
    with pytest.raises(ShapeError, match="B, 1, h, w"):
        pool_inverse_depth(torch.ones(1, 2, 3, 3), torch.ones(1, 2, 3, 3))
    with pytest.raises(InputError, match="unknown structure pooling option"):
        StructurePooling.from_config({"radius": 2, "sigma": 1.0})


def test_model_pools_its_own_depth_and_calibrates_the_pooled_scale(tmp_path):
    model = make_test_model(0).eval()
    i1, i2 = realistic_pairs(model.camera, 2, 224, 288, seed=0)  # a 6x8 tile grid
    with torch.no_grad():
        plain = model.analyse(i1, i2)
        assert plain.depth_pooled is None and len(model(i1, i2)) == 3
        model.set_structure_pooling({"radius": 2, "ridge": 0.05},
                                    {"log_b": [-6.0, -3.0], "log_b_calibrated": [-6.5, -3.2]})
        pooled = model.analyse(i1, i2)
        outputs = model(i1, i2)
    # the tiles stay each tile's own estimate, bit for bit; the pooled map comes beside them
    for name in ("depth", "confidence", "depth_analytic", "inverse_depth", "log_scale"):
        assert torch.equal(getattr(pooled, name), getattr(plain, name)), name
    want_q = pool_inverse_depth(plain.inverse_depth, plain.log_scale.exp(), radius=2, ridge=0.05)
    q_lo, q_hi = model.analytic.inv_depth_limits
    assert torch.allclose(pooled.inverse_depth_pooled, want_q.clamp(q_lo, q_hi), rtol=1e-6)
    assert torch.allclose(pooled.depth_pooled, 1 / pooled.inverse_depth_pooled)
    assert not torch.allclose(pooled.inverse_depth_pooled, plain.inverse_depth, rtol=1e-4)
    want_log = ScaleCalibration([-6.0, -3.0], [-6.5, -3.2])(plain.log_scale, pooled.inverse_depth_pooled)
    assert torch.allclose(pooled.log_scale_pooled, want_log, atol=1e-6)
    ratio = pooled.log_scale_pooled.exp() / model.confidence_scale
    assert torch.allclose(pooled.confidence_pooled, 1 / (1 + ratio * ratio), atol=1e-6)
    assert pooled.depth_map[0] is pooled.depth_pooled and plain.depth_map[0] is plain.depth
    # forward: the contract's three outputs, then the pooled two
    assert len(outputs) == 5
    for got, want in zip(outputs, (plain.depth, plain.confidence, plain.depth_analytic, pooled.depth_pooled,
                                   pooled.confidence_pooled)):
        assert torch.equal(got, want)
    # the training path never pools
    out = model.head_with_family(pooled.features, pooled.analytic.inverse_depth, pooled.analytic.rel_error)
    assert torch.allclose(out[0], plain.inverse_depth)
    # what training scores with optim.pooled_weight: the pooled map's depth, bitwise
    with torch.no_grad():
        assert torch.equal(model.pooled_inverse_depth(pooled.inverse_depth, pooled.log_scale),
                           pooled.inverse_depth_pooled)
    # the JSON round trip
    model.save(tmp_path / "m")
    desc = DFDModel.read_description(tmp_path / "m")
    assert desc["structure_pooling"]["ridge"] == 0.05 and desc["pooled_scale_calibration"]["log_b"] == [-6.0, -3.0]
    with torch.no_grad():
        again = DFDModel.load(tmp_path / "m").eval().analyse(i1, i2)
    assert torch.allclose(again.depth_pooled, pooled.depth_pooled)
    assert torch.allclose(again.confidence_pooled, pooled.confidence_pooled)
    # off again: the model as it was
    model.set_structure_pooling(None)
    with torch.no_grad():
        assert torch.equal(model.analyse(i1, i2).depth, plain.depth)
    with pytest.raises(InputError, match="no structure pooling"):
        model.pool(plain.inverse_depth, plain.log_scale)
    with pytest.raises(InputError, match="no structure pooling"):
        model.pooled_inverse_depth(plain.inverse_depth, plain.log_scale)


def test_a_pooled_calibration_without_pooling_is_refused(tmp_path):
    model = make_test_model(0)
    with pytest.raises(InputError, match="needs structure_pooling"):
        model.set_structure_pooling(None, {"log_b": [-6.0, -3.0], "log_b_calibrated": [-6.0, -3.0]})
    _, meta = model.save(tmp_path / "m")
    cfg = json.loads(meta.read_text())
    cfg["structure_pooling"] = {"radius": 0}
    meta.write_text(json.dumps(cfg))
    with pytest.raises(ModelError, match="radius"):
        DFDModel.load(tmp_path / "m")


def test_an_older_description_loads_without_pooling(tmp_path):
    model = make_test_model(0)
    _, meta = model.save(tmp_path / "m")
    cfg = json.loads(meta.read_text())
    del cfg["structure_pooling"], cfg["pooled_scale_calibration"]
    meta.write_text(json.dumps(cfg))
    loaded = DFDModel.load(tmp_path / "m")
    assert loaded.structure_pooling is None and loaded.pooled_scale_calibration.to_config() is None
    # a description from before the curvature test: the quadratic everywhere, as it was
    cfg["structure_pooling"] = {"radius": 2, "degree": 2, "kernel_width": 2.5, "iterations": 2, "scale_floor": 0.005,
                                "ridge": 0.001}
    meta.write_text(json.dumps(cfg))
    assert DFDModel.load(tmp_path / "m").structure_pooling.curvature_test == 0.0


def test_onnx_export_carries_the_pooling(tmp_path):
    model = make_test_model(0)
    # the shipped options: the curvature test's choice (a Where) in the graph too
    model.set_structure_pooling({"radius": 2, "curvature_test": 1.0},
                                {"log_b": [-6.0, -3.0], "log_b_calibrated": [-6.5, -3.2]})
    path = tmp_path / "pooled.onnx"
    export_model(model, path)
    # grids of 1x1, 4x5 and 6x8 tiles: the window larger than the grid, and interior tiles
    report = verify_onnx(path, model, sizes=[(64, 64), (160, 192), (224, 288)], batches=[1, 2])
    assert_parity(report, cases=6)
    # the contract's three outputs, then the pooled map: checked against torch like the others
    from tdfd.runtime import DepthRuntime
    rt = DepthRuntime(path, threads=1)
    assert [o.name for o in rt.session.get_outputs()] == list(OUTPUT_NAMES + POOLED_OUTPUT_NAMES) and rt.has_pooled
    i1, i2 = realistic_pairs(model.camera, 1, 224, 288, seed=5)
    a, b = i1[0, 0].numpy(), i2[0, 0].numpy()
    res, tiles_only = rt(a, b), rt(a, b, pooled=False)
    assert tiles_only.depth_pooled is None and np.array_equal(res.depth, tiles_only.depth)
    with torch.no_grad():
        want = model.analyse(i1, i2)
    np.testing.assert_allclose(res.depth_pooled, want.depth_pooled[0, 0].numpy(), rtol=1e-4)
    np.testing.assert_allclose(res.confidence_pooled, want.confidence_pooled[0, 0].numpy(), atol=1e-3)
    assert res.depth_map[0] is res.depth_pooled
    full = res.at_full_resolution()
    assert full.depth_pooled.shape == (224, 288) and full.confidence_pooled.shape == (224, 288)
    # a pair that is no DFD pair (the lens did not move): no confidence in either map
    same = rt(a, a)
    assert same.problem and not same.confidence.any() and not same.confidence_pooled.any()
    # a pooled output that disagrees with torch is caught, the tiles' being right
    model.set_structure_pooling({"radius": 1}, {"log_b": [-6.0, -3.0], "log_b_calibrated": [-6.5, -3.2]})
    with pytest.raises(ModelError, match="_pooled"):
        verify_onnx(path, model, sizes=[(224, 288)], batches=[1])


def test_a_file_without_the_pooling_has_the_contracts_three_outputs(tmp_path):
    from tdfd.runtime import DepthRuntime
    model = make_test_model(0)
    path = export_model(model, tmp_path / "plain.onnx")
    rt = DepthRuntime(path, threads=1)
    assert [o.name for o in rt.session.get_outputs()] == list(OUTPUT_NAMES) and not rt.has_pooled
    i1, i2 = realistic_pairs(model.camera, 1, 128, 128, seed=1)
    assert rt(i1[0, 0].numpy(), i2[0, 0].numpy()).depth_pooled is None
    assert len(rt.run_all(i1.numpy(), i2.numpy())) == 3
    with pytest.raises(ModelError, match="no .*depth_pooled"):
        rt.run_pooled(i1.numpy(), i2.numpy())


def test_calibration_stage_fits_the_pooled_scale(tmp_path):
    model = DFDModel(Camera.preset("reference"), tile=64, stride=32, hidden=8, blocks=1)
    model.save(tmp_path / "m")
    with pytest.raises(InputError, match="no structure pooling"):
        calibrate_scale.collect_scale_errors(model, planes=2, scenes=1, pooled=True)
    args = ["--planes", "8", "--scenes", "1", "--bins", "4", "--smooth", "1", "--threads", "1", "--depth-bins", "3",
            "--border-levels", "2"]
    assert calibrate_scale.main(["--model", str(tmp_path / "m"), "--out", str(tmp_path / "p"), *args,
                                 "--structure-pooling", '{"radius": 1}', "--plot", str(tmp_path / "cal.png")]) == 0
    desc = DFDModel.read_description(tmp_path / "p")
    assert desc["structure_pooling"]["radius"] == 1
    assert set(desc["pooled_scale_calibration"]) == {"log_b", "log_b_calibrated", "inverse_depth_per_m",
                                                     "depth_log_shift", "border_log_shift"}
    fit = desc["extra"]["scale_calibration_fit"]
    assert fit["pooled"]["structure_pooling"]["radius"] == 1 and fit["pooled"]["tiles"] == fit["tiles"]
    assert (tmp_path / "cal_pooled.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # the first map is the same fit with or without the pooling after it
    assert calibrate_scale.main(["--model", str(tmp_path / "m"), "--out", str(tmp_path / "n"), *args]) == 0
    assert DFDModel.read_description(tmp_path / "n")["scale_calibration"] == desc["scale_calibration"]
    assert DFDModel.read_description(tmp_path / "n")["structure_pooling"] is None
    # --pooled-only keeps the tiles' map (what the autofocus reads) and fits the pooled one on top
    tiles_map = DFDModel.read_description(tmp_path / "p")["scale_calibration"]
    assert calibrate_scale.main(["--model", str(tmp_path / "n"), "--out", str(tmp_path / "q"), *args,
                                 "--structure-pooling", '{"radius": 1}', "--pooled-only"]) == 0
    only = DFDModel.read_description(tmp_path / "q")
    assert only["scale_calibration"] == tiles_map and only["pooled_scale_calibration"] == desc["pooled_scale_calibration"]
    assert only["extra"]["scale_calibration_fit"]["knot_factors"] == fit["knot_factors"]
    with pytest.raises(SystemExit):
        calibrate_scale.main(["--model", str(tmp_path / "n"), "--pooled-only", *args])
    # the pooled map on its own, larger set (the first scenes of the same seeds), the tiles' map kept
    assert calibrate_scale.main(["--model", str(tmp_path / "q"), "--out", str(tmp_path / "r"), *args, "--pooled-only",
                                 "--pooled-planes", "12", "--pooled-scenes", "2"]) == 0
    more = DFDModel.read_description(tmp_path / "r")
    pooled_fit = more["extra"]["scale_calibration_fit"]["pooled"]
    assert (pooled_fit["planes"], pooled_fit["scenes_per_layout"]) == (12, 2) and pooled_fit["tiles"] > fit["tiles"]
    assert more["scale_calibration"] == tiles_map and more["pooled_scale_calibration"] != only["pooled_scale_calibration"]
    with pytest.raises(InputError, match="pooled_only"):
        calibrate_scale.calibrate_model(DFDModel.load(tmp_path / "n"), planes=2, scenes=1, pooled_only=True)
    # 'none' takes a pooled model's stage away
    assert calibrate_scale.main(["--model", str(tmp_path / "p"), "--out", str(tmp_path / "o"), *args,
                                 "--structure-pooling", "none"]) == 0
    assert DFDModel.read_description(tmp_path / "o")["pooled_scale_calibration"] is None


def test_calibration_stage_refuses_bad_pooling_options(tmp_path, capsys):
    DFDModel(Camera.preset("reference"), tile=64, stride=32, hidden=8, blocks=1).save(tmp_path / "m")
    for bad in ("{not json", '{"radius": 0}', '{"sigma": 1}'):
        with pytest.raises(SystemExit):
            calibrate_scale.main(["--model", str(tmp_path / "m"), "--structure-pooling", bad])
        assert "--structure-pooling" in capsys.readouterr().err


def test_the_tuning_tool_scores_options_on_the_calibration_scenes(tmp_path, capsys):
    from benchmarks import tune_pooling

    model = DFDModel(Camera.preset("reference"), tile=64, stride=32, hidden=8, blocks=1)
    model.save(tmp_path / "m")
    tiles = tune_pooling.collect_tiles(model, planes=2, scenes=1)
    assert list(tiles) == ["planes", "slanted", "layout", "smooth"]
    assert tiles["layout"]["q"].shape == (1, 1, 14, 19) and tiles["layout"]["edge"].dtype == torch.bool
    limits, rng = model.analytic.inv_depth_limits, model.camera.depth_range_m
    none = tune_pooling.score_pooling(tiles, None, limits, rng)
    assert set(none) == {"planes", "slanted", "layout", "smooth", "structure"}
    assert none["structure"] == pytest.approx((none["slanted"] + none["layout"] + none["smooth"]) / 3)
    pooled = tune_pooling.score_pooling(tiles, {"curvature_test": 1.0}, limits, rng)
    assert pooled != none and all(math.isfinite(v) for v in pooled.values())
    with pytest.raises(InputError, match="unknown structure pooling option"):
        tune_pooling.score_pooling(tiles, {"sigma": 1.0}, limits, rng)
    assert tune_pooling.main(["--model", str(tmp_path / "m"), "--planes", "2", "--scenes", "1", "--threads", "1",
                              "--options", '[{}, {"degree": 1}]']) == 0
    out = capsys.readouterr().out
    assert "| no pooling |" in out and '| `{"degree": 1}` |' in out
    for bad in ("{not json", '{"radius": 2}', '[{"radius": 0}]'):
        with pytest.raises(SystemExit):
            tune_pooling.main(["--model", str(tmp_path / "m"), "--options", bad])


def test_the_pooled_loss_reaches_the_scales_only_through_the_pooling():
    """``training.losses.pooled_loss``: the pooled error in units of the tiles' scales; the
    scales get a gradient through the pooling's weights (a tile that pulls its neighbours' fits
    off the truth is pushed towards a larger scale, they towards smaller ones) and none through
    the units."""
    from training.losses import pooled_loss

    truth = torch.full((1, 1, 5, 5), 0.5, dtype=torch.float64)
    q = 1 / truth.clone()
    q[0, 0, 2, 3] *= 1.03  # an outlier within the kernel's reach of its neighbours' fits
    log_b = torch.full_like(q, math.log(0.01)).requires_grad_(True)
    pooled = pool_inverse_depth(q, torch.exp(log_b), radius=1, degree=0)
    loss = pooled_loss(pooled, log_b, truth)
    expected = ((pooled - 1 / truth).abs() * truth / torch.exp(log_b)).mean()
    assert torch.allclose(loss.detach(), expected.detach(), rtol=1e-12) and float(loss.detach()) > 0
    loss.backward()
    grad = log_b.grad[0, 0]
    assert float(grad[2, 3]) < 0 and float(grad[2, 3]) == float(grad.min())  # the outlier's scale is pushed up
    assert bool((grad[1:4, 2:5] > 0).sum() == 8)  # its neighbours' down: they are right
    direct = log_b.detach().clone().requires_grad_(True)  # a pooled map that does not depend on the scales
    assert not pooled_loss(pooled.detach(), direct, truth).requires_grad
