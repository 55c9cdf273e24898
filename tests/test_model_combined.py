"""DFDModel: shapes, zero-init equivalence with the analytic layer, gradients, persistence."""

from __future__ import annotations

import json

import pytest
import torch

from tdfd import Camera
from tdfd.dfd import FourierRatioDFD
from tdfd.errors import InputError, ModelError, RangeError, ShapeError
from tdfd.model import DFDModel, RefineNet, num_features
from tdfd.optics import render_pair

REF = Camera.preset("reference")


def _pair(b=2, h=128, w=160, depth=0.45, seed=0):
    g = torch.Generator().manual_seed(seed)
    x = 0.4 + 0.1 * torch.randn(b, 1, h, w, generator=g)
    return render_pair(REF, x.clamp(0, 1), torch.full((b, 1, h, w), depth))


@pytest.fixture(scope="module")
def small_model():
    torch.manual_seed(0)
    return DFDModel(REF, tile=32, stride=16, hidden=8, blocks=1)


@pytest.mark.parametrize("b,h,w", [(1, 32, 32), (2, 48, 80), (3, 64, 33), (1, 100, 47)])
def test_shapes_any_size(small_model, b, h, w):
    i1, i2 = _pair(b, h, w)
    depth, conf, depth_a = small_model(i1, i2)
    hh, ww = (h - 32) // 16 + 1, (w - 32) // 16 + 1
    for t in (depth, conf, depth_a):
        assert t.shape == (b, 1, hh, ww) and t.dtype == torch.float32
    assert bool((conf >= 0).all() and (conf <= 1).all())
    assert bool(torch.isfinite(depth).all() and (depth > 0).all())


@pytest.mark.parametrize("dilation_base", [1, 2])
def test_refinenet_fully_convolutional(dilation_base):
    net = RefineNet(5, hidden=4, blocks=3, dilation_base=dilation_base)
    for h, w in [(1, 1), (1, 7), (6, 2)]:
        assert net(torch.randn(2, 5, h, w)).shape == (2, 2, h, w)
    assert net.config()["dilation_base"] == dilation_base
    with pytest.raises(InputError):
        RefineNet(5, kernel_size=2)
    with pytest.raises(InputError):
        RefineNet(5, dilation_base=0)


def test_zero_init_reproduces_analytic():
    model = DFDModel(REF)  # default grid 64 / 32
    i1, i2 = _pair(2, 128, 160, depth=0.6)
    depth, conf, depth_a = model(i1, i2)
    ana, _ = FourierRatioDFD(REF, tile=64, stride=32)(i1, i2)
    assert torch.equal(depth, depth_a)
    torch.testing.assert_close(depth_a, ana, rtol=0, atol=0)
    assert model.analyse(i1, i2).features.shape[1] == num_features(FourierRatioDFD(REF).num_rings)


def test_pooled_context_features_and_persistence(tmp_path):
    """context > 1 adds the fit of neighbourhood-averaged measurements (Welch pooling)."""
    from tdfd.model import pool_measurements

    torch.manual_seed(2)
    model = DFDModel(REF, tile=32, stride=16, hidden=8, blocks=1, context=3)
    i1, i2 = _pair(2, 96, 112)
    feats = model.analyse(i1, i2).features
    rings = model.analytic.num_rings
    assert feats.shape[1] == num_features(rings, 3) == num_features(rings) + 2 * rings + 3
    assert bool(torch.isfinite(feats).all())
    # pooling: interior tiles average their 3x3 neighbourhood, corners the 2x2 that exist
    meas = model.analytic.measure(i1, i2)
    pooled = pool_measurements(meas, 3)
    torch.testing.assert_close(pooled[0][:, :, 1, 1], meas[0][:, :, 0:3, 0:3].mean((2, 3)))
    torch.testing.assert_close(pooled[0][:, :, 0, 0], meas[0][:, :, 0:2, 0:2].mean((2, 3)))
    # the stacked single fit equals two separate fits (per tile, and pooled with span^2 samples)
    from tdfd.model import tile_features

    span2 = ((32 + 2 * 16) / 32) ** 2
    separate = tile_features(model.analytic.fit(*meas), model.analytic, model.analytic.fit(*pooled, count_scale=span2))
    torch.testing.assert_close(feats, separate, rtol=1e-5, atol=1e-5)
    # on a uniform-depth pair the pooled fit agrees with the per-tile one on average
    d_scale = feats.shape[1] - 3  # pooled sigma^2 difference is the third-last channel
    assert abs(float(feats[:, d_scale].mean() - feats[:, 5 * rings + 1].mean())) < 0.05
    model.save(tmp_path / "m")
    loaded = DFDModel.load(tmp_path / "m")
    assert loaded.context == 3 and loaded.analytic_matches is True
    torch.testing.assert_close(loaded(i1, i2)[0], model(i1, i2)[0])
    for bad in (0, 2, 2.5, [3, 4], [3, 3], True, ["3"]):
        with pytest.raises(InputError):
            DFDModel(REF, tile=32, stride=16, context=bad)


def test_two_context_sides_add_two_pooled_fits(tmp_path):
    """context=[3, 5]: one pooled fit per side, in the order of the sides, and each equal to
    its own separate fit (the stacked single fit is only an optimisation)."""
    from tdfd.model import pool_measurements, tile_features

    torch.manual_seed(3)
    model = DFDModel(REF, tile=32, stride=16, hidden=8, blocks=1, context=[5, 3])
    assert model.contexts == (3, 5) and model.context == [3, 5]
    i1, i2 = _pair(2, 112, 128)
    feats = model.analyse(i1, i2).features
    rings = model.analytic.num_rings
    assert feats.shape[1] == num_features(rings, [3, 5]) == num_features(rings) + 2 * (2 * rings + 3)
    meas = model.analytic.measure(i1, i2)
    fits = [model.analytic.fit(*pool_measurements(meas, c), count_scale=((32 + (c - 1) * 16) / 32) ** 2) for c in (3, 5)]
    separate = tile_features(model.analytic.fit(*meas), model.analytic, fits)
    torch.testing.assert_close(feats, separate, rtol=1e-5, atol=1e-5)
    # the wider neighbourhood averages more tiles: its predicted error is not larger
    rel3 = feats[:, num_features(rings) + 2 * rings + 1]
    rel5 = feats[:, num_features(rings) + 2 * (2 * rings + 3) - 2]
    assert float(rel5.mean()) <= float(rel3.mean()) + 1e-6
    model.save(tmp_path / "m2")
    loaded = DFDModel.load(tmp_path / "m2")
    assert loaded.contexts == (3, 5) and loaded.analytic_matches is True
    torch.testing.assert_close(loaded(i1, i2)[1], model(i1, i2)[1])


def test_a_description_with_the_removed_coarse_option_is_refused(tmp_path):
    model = DFDModel(REF, tile=32, stride=16, hidden=8, blocks=1)
    model.save(tmp_path / "m")
    meta = tmp_path / "m.json"
    meta.write_text(json.dumps({**json.loads(meta.read_text()), "coarse": [1, 3]}))
    with pytest.raises(ModelError, match="coarse fits"):
        DFDModel.load(tmp_path / "m")
    with pytest.raises(InputError, match="coarse"):
        DFDModel(REF, tile=32, stride=16, coarse=[1])


def test_gradients_flow_through_every_parameter():
    torch.manual_seed(1)
    model = DFDModel(REF, tile=32, stride=16, hidden=8, blocks=2)
    torch.nn.init.normal_(model.refine.head.weight, std=0.1)
    i1, i2 = _pair(2, 64, 64)
    r = model.analyse(i1, i2)
    (r.depth.mean() + r.confidence.mean() + r.log_scale.mean()).backward()
    for name, p in model.refine.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name
        assert float(p.grad.abs().max()) > 0, name


def test_confidence_is_monotone_in_predicted_scale(small_model):
    i1, i2 = _pair(1, 64, 64)
    feats, r = small_model.features(i1, i2)
    q, log_b, conf, _ = small_model.head(feats, r.inverse_depth, r.rel_error)
    scale = torch.linspace(-6, 1, 50).reshape(1, 1, 50, 1)
    c = 1 / (1 + (torch.exp(scale) / small_model.confidence_scale) ** 2)
    assert bool((c[:, :, 1:] <= c[:, :, :-1]).all())
    assert torch.allclose(conf, 1 / (1 + (torch.exp(log_b) / small_model.confidence_scale) ** 2))


def test_validation_flag(small_model):
    i1, i2 = _pair(1, 64, 64)
    with pytest.raises(RangeError):
        small_model(i1 * 10, i2)
    with pytest.raises(ShapeError):
        small_model(i1[..., :20, :], i2[..., :20, :])
    small_model.set_validate(False)
    try:
        small_model(i1 * 10, i2)  # no check, still finite
    finally:
        small_model.set_validate(True)


def test_save_load_round_trip(tmp_path):
    torch.manual_seed(2)
    model = DFDModel(REF, tile=32, stride=16, hidden=8, blocks=1, confidence_scale=0.02)
    for p in model.refine.parameters():
        torch.nn.init.normal_(p, std=0.05)
    model.refine.set_normaliser(torch.randn(model.refine.in_channels), torch.rand(model.refine.in_channels) + 0.5)
    w, m = model.save(tmp_path / "m")
    assert w.name == "m.safetensors" and m.name == "m.json"
    raw = w.read_bytes()
    n = int.from_bytes(raw[:8], "little")
    header = json.loads(raw[8 : 8 + n])  # safetensors: length-prefixed JSON header, no pickle
    assert "refine.stem.weight" in header and "refine.feature_mean" in header
    cfg = json.loads(m.read_text())
    assert cfg["camera"] == REF.to_dict() and cfg["tile"] == 32 and cfg["refine"]["hidden"] == 8
    loaded = DFDModel.load(tmp_path / "m.json")
    i1, i2 = _pair(2, 64, 96)
    for a, b in zip(model(i1, i2), loaded(i1, i2)):
        assert torch.equal(a, b)
    assert loaded.confidence_scale == 0.02
    assert loaded.analytic_matches is True
    cfg["analytic_fingerprint"][0] += 1.0  # as if the analytic layer had changed since training
    m.write_text(json.dumps(cfg))
    assert DFDModel.load(tmp_path / "m").analytic_matches is False


def test_load_errors(tmp_path):
    with pytest.raises(ModelError):
        DFDModel.load(tmp_path / "missing")
    model = DFDModel(REF, tile=32, stride=16, hidden=8, blocks=1)
    w, m = model.save(tmp_path / "m")
    w.write_bytes(b"not a safetensors file")
    with pytest.raises(ModelError):
        DFDModel.load(tmp_path / "m")
    model.save(tmp_path / "m")
    cfg = json.loads(m.read_text())
    cfg["refine"]["hidden"] = 16
    m.write_text(json.dumps(cfg))
    with pytest.raises(ModelError):
        DFDModel.load(tmp_path / "m")
    m.write_text("{not json")
    with pytest.raises(ModelError):
        DFDModel.load(tmp_path / "m")


def test_constructor_errors():
    with pytest.raises(InputError):
        DFDModel(REF, analytic={"tile": 32})
    with pytest.raises(InputError):
        DFDModel(REF, bogus=3)
    with pytest.raises(InputError):
        DFDModel(REF, confidence_scale=0)
