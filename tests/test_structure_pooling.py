"""Pooling the tile depths along the depth structure (issue 19): the robust local surface fit,
its place in the model, its JSON round trip, the ONNX export and the calibration of its scale."""

from __future__ import annotations

import json
import math

import pytest
import torch

from export import export_model, realistic_pairs, verify_onnx
from export.testing import make_test_model
from tdfd import Camera
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


@pytest.mark.parametrize("degree", [1, 2])
def test_gradcheck_float64(degree):
    g = torch.Generator().manual_seed(7)
    q = (1.5 + 0.05 * torch.rand(1, 1, 4, 5, generator=g, dtype=torch.float64)).requires_grad_()
    b = (0.01 + 0.02 * torch.rand(1, 1, 4, 5, generator=g, dtype=torch.float64)).requires_grad_()
    assert torch.autograd.gradcheck(lambda a, c: pool_inverse_depth(a, c, radius=1, degree=degree), (q, b))


@pytest.mark.parametrize("kw, match", [
    (dict(radius=0), "radius"), (dict(radius=1.5), "radius"), (dict(degree=3), "degree"),
    (dict(iterations=0), "iterations"), (dict(kernel_width=0.0), "kernel_width"),
    (dict(scale_floor=-1.0), "scale_floor"), (dict(ridge=-0.1), "ridge"), (dict(ridge=math.inf), "finite"),
    (dict(kernel_width=math.nan), "kernel_width")])
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
        model.set_structure_pooling({"radius": 2, "ridge": 0.05},
                                    {"log_b": [-6.0, -3.0], "log_b_calibrated": [-6.5, -3.2]})
        pooled = model.analyse(i1, i2)
    want_q = pool_inverse_depth(plain.inverse_depth, plain.log_scale.exp(), radius=2, ridge=0.05)
    q_lo, q_hi = model.analytic.inv_depth_limits
    assert torch.allclose(pooled.inverse_depth, want_q.clamp(q_lo, q_hi), rtol=1e-6)
    assert not torch.allclose(pooled.inverse_depth, plain.inverse_depth, rtol=1e-4)
    want_log = ScaleCalibration([-6.0, -3.0], [-6.5, -3.2])(plain.log_scale, pooled.inverse_depth)
    assert torch.allclose(pooled.log_scale, want_log, atol=1e-6)
    ratio = pooled.log_scale.exp() / model.confidence_scale
    assert torch.allclose(pooled.confidence, 1 / (1 + ratio * ratio), atol=1e-6)
    assert torch.equal(pooled.depth_analytic, plain.depth_analytic)
    # the training path never pools
    out = model.head_with_family(pooled.features, pooled.analytic.inverse_depth, pooled.analytic.rel_error)
    assert torch.allclose(out[0], plain.inverse_depth)
    # the JSON round trip
    model.save(tmp_path / "m")
    desc = DFDModel.read_description(tmp_path / "m")
    assert desc["structure_pooling"]["ridge"] == 0.05 and desc["pooled_scale_calibration"]["log_b"] == [-6.0, -3.0]
    with torch.no_grad():
        again = DFDModel.load(tmp_path / "m").eval().analyse(i1, i2)
    assert torch.allclose(again.depth, pooled.depth) and torch.allclose(again.confidence, pooled.confidence)
    # off again: the model as it was
    model.set_structure_pooling(None)
    with torch.no_grad():
        assert torch.equal(model.analyse(i1, i2).depth, plain.depth)


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


def test_onnx_export_carries_the_pooling(tmp_path):
    model = make_test_model(0)
    model.set_structure_pooling({"radius": 2}, {"log_b": [-6.0, -3.0], "log_b_calibrated": [-6.5, -3.2]})
    path = tmp_path / "pooled.onnx"
    export_model(model, path)
    # grids of 1x1, 4x5 and 6x8 tiles: the window larger than the grid, and interior tiles
    report = verify_onnx(path, model, sizes=[(64, 64), (160, 192), (224, 288)], batches=[1, 2])
    assert_parity(report, cases=6)


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
