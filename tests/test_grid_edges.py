"""The tile's place in its grid as CNN input (``DFDModel(edge_input=N)``): the maps, the
model that appends them, the training config, save/load and the ONNX export."""

from __future__ import annotations

import pytest
import torch

from tdfd.camera import Camera
from tdfd.errors import InputError, ModelError
from tdfd.model import DFDModel, append_edge_maps, edge_distance_maps, num_features
from tdfd.model.grid_edges import tile_border_distance
from tests.onnx_parity import assert_parity


def _model(edge_input: int = 3, seed: int = 0, **kw) -> DFDModel:
    """A small model with a random (non-zero) CNN."""
    torch.manual_seed(seed)
    m = DFDModel(Camera.preset("reference"), tile=64, stride=32, edge_input=edge_input, hidden=16, blocks=2,
                 dilation_base=2, **kw)
    with torch.no_grad():
        for p in m.refine.parameters():
            p.normal_(0.0, 0.05)
    return m.eval()


def _pair(h: int = 160, w: int = 256) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(3)
    x1 = torch.rand(1, 1, h, w, generator=g) * 0.8 + 0.1
    return x1, x1.roll(2, -1) * 0.9 + 0.05


# ------------------------------------------------------------------ the maps
def test_edge_maps_golden():
    # a 3 x 5 grid, limit 2: rows 0..2 are 0, 1, 2 from the top (held at 2), 2, 1, 0 from the bottom
    got = edge_distance_maps(torch.zeros(2, 7, 3, 5), limit=2)
    assert got.shape == (1, 4, 3, 5)
    top = torch.tensor([0.0, 0.5, 1.0])[:, None].expand(3, 5)
    left = torch.tensor([0.0, 0.5, 1.0, 1.0, 1.0])[None, :].expand(3, 5)
    right = torch.tensor([1.0, 1.0, 1.0, 0.5, 0.0])[None, :].expand(3, 5)
    assert torch.equal(got[0, 0], top)
    assert torch.equal(got[0, 1], top.flip(0))
    assert torch.equal(got[0, 2], left)
    assert torch.equal(got[0, 3], right)


def test_edge_maps_of_a_single_tile_and_a_large_limit():
    assert torch.equal(edge_distance_maps(torch.zeros(1, 1, 1, 1), limit=4), torch.zeros(1, 4, 1, 1))
    # held at a limit no grid reaches, the maps are the raw distances over the limit; their
    # minimum is the scale calibration's border distance
    grid = torch.zeros(1, 1, 6, 9, dtype=torch.float64)
    raw = edge_distance_maps(grid, limit=100) * 100
    assert raw.dtype == torch.float64
    assert torch.allclose(raw.amin(1, keepdim=True), tile_border_distance(grid))


@pytest.mark.parametrize("limit", [0, -1, True, 2.5, "3"])
def test_edge_maps_refuse_a_bad_limit(limit):
    with pytest.raises(InputError, match="edge limit"):
        edge_distance_maps(torch.zeros(1, 1, 3, 3), limit)


def test_edge_maps_refuse_a_grid_that_is_not_4d():
    with pytest.raises(InputError, match=r"\(B, C, h, w\)"):
        edge_distance_maps(torch.zeros(3, 3), 2)


def test_append_edge_maps_repeats_the_maps_per_sample():
    feats = torch.randn(3, 5, 4, 6)
    out = append_edge_maps(feats, limit=2)
    assert out.shape == (3, 9, 4, 6)
    assert torch.equal(out[:, :5], feats)
    assert torch.equal(out[1, 5:], edge_distance_maps(feats, 2)[0]) and torch.equal(out[0, 5:], out[2, 5:])


# ------------------------------------------------------------------ the model
def test_model_features_carry_the_maps_before_the_family_code():
    m = DFDModel(Camera.preset("reference"), edge_input=2, psf_family_input=True, psf_family="pillbox",
                 hidden=8, blocks=1).eval()
    x1, x2 = _pair()
    feats, _ = m.features(x1, x2)
    n = num_features(m.analytic.num_rings)
    assert feats.shape[1] == n + 4 + 2 == m.refine.in_channels
    assert torch.equal(feats[:, n:n + 4], edge_distance_maps(feats, 2))
    assert bool((feats[:, -1] == 1).all())  # the family code stays last
    depth, _, depth_a = m(x1, x2)
    assert torch.equal(depth, depth_a)  # a fresh model is the analytic one


def test_the_maps_let_the_cnn_tell_an_edge_tile_from_an_inner_one():
    """On features equal in every tile, replicate padding makes every tile's output equal;
    with the edge maps the output depends on the place."""
    for edge_input, varies in ((0, False), (3, True)):
        m = _model(edge_input)
        x1, x2 = _pair()
        feats, r = m.features(x1, x2)
        flat = feats.mean((2, 3), keepdim=True).expand_as(feats).clone()
        if edge_input:
            flat[:, -4:] = feats[:, -4:]
        q_in = torch.full_like(r.inverse_depth, 2.0)
        with torch.no_grad():
            q, log_scale, _, _ = m.head(flat, q_in, torch.full_like(q_in, 0.02))
        spread = float(q.amax() - q.amin()) + float(log_scale.amax() - log_scale.amin())
        assert (spread > 1e-4) is varies, (edge_input, spread)


@pytest.mark.parametrize("bad", [-1, 1.5, True, "4"])
def test_model_refuses_a_bad_edge_input(bad):
    with pytest.raises(InputError, match="edge_input"):
        DFDModel(Camera.preset("reference"), edge_input=bad, hidden=8, blocks=1)


def test_save_load_keeps_the_edge_input(tmp_path):
    m = _model(4)
    m.save(tmp_path / "m")
    back = DFDModel.load(tmp_path / "m")
    assert back.edge_input == 4 and back.config()["edge_input"] == 4
    x1, x2 = _pair()
    with torch.no_grad():
        assert torch.equal(back(x1, x2)[0], m(x1, x2)[0])


def test_a_description_without_the_key_loads_without_the_maps():
    cfg = _model(0).config()
    del cfg["edge_input"]
    assert DFDModel.from_config(cfg).edge_input == 0
    with pytest.raises(ModelError, match="invalid model description"):
        DFDModel.from_config({**cfg, "edge_input": -2})


def test_training_config_builds_the_model_and_refuses_a_negative_limit():
    from training.config import ConfigError, load_config
    from training.data import Featurizer

    cfg = load_config(None, ["model.edge_input=3", "model.hidden=8", "model.blocks=1"])
    fz = Featurizer(cfg.model)
    assert fz.model.edge_input == 3
    x1, x2 = _pair(128, 160)
    out = fz({"image_f1": x1, "image_f2": x2, "tile_depth": torch.full((1, 1, 3, 4), 0.5)})
    assert torch.equal(out["features"][:, -4:], edge_distance_maps(out["features"], 3))
    with pytest.raises(ConfigError, match="edge_input"):
        load_config(None, ["model.edge_input=-1"])


def test_reference_config_trains_with_the_maps():
    from training.config import load_config

    assert load_config("training/configs/reference.toml").model.edge_input == 4


# ------------------------------------------------------------------ export
def test_export_computes_the_maps_for_every_grid(tmp_path):
    from export import export_model, verify_onnx

    m = _model(3)
    path = tmp_path / "edges.onnx"
    export_model(m, path)
    # grids 1x1, 2x4 and 5x9: below, at and beyond the limit on each side
    report = verify_onnx(path, m, sizes=[(64, 64), (97, 161), (192, 320)], batches=[1, 2])
    assert_parity(report, cases=6)
