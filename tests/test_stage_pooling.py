"""tdfd.dfd.stage_pooling and the likelihood stage's opt-in pooling: the fused map pooled along the
depth structure by the model's own structure pooling, each tile weighted by its fused confidence."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
import torch

from tdfd.dfd.likelihood_stage import LikelihoodStage
from tdfd.dfd.psf_hypotheses import PsfHypothesis
from tdfd.dfd.stage_pooling import POOL_SCALE_CAP, pool_stage_map
from tdfd.errors import InputError, ShapeError
from tdfd.model.structure_pooling import StructurePooling, pool_inverse_depth
from tests.test_likelihood_stage import CAM, render_plane

F64 = torch.float64


def _slanted(h: int = 6, w: int = 7) -> torch.Tensor:
    """A slanted plane's distances (B, 1, h, w), metres: linear in inverse depth."""
    yy, xx = torch.meshgrid(torch.arange(float(h), dtype=F64), torch.arange(float(w), dtype=F64), indexing="ij")
    return (1.0 / (2.0 + 0.05 * yy - 0.03 * xx)).reshape(1, 1, h, w)


def test_the_weights_are_the_scales_the_confidences_state():
    # against the pooling fed b = b0 sqrt(1/c - 1) by hand: the confidence's Laplace scale
    d = _slanted() * (1 + 0.01 * torch.randn(1, 1, 6, 7, generator=torch.Generator().manual_seed(0), dtype=F64))
    c = torch.rand(1, 1, 6, 7, generator=torch.Generator().manual_seed(1), dtype=F64) * 0.9 + 0.05
    pooling = StructurePooling(radius=2, degree=2, curvature_test=1.0)
    expected = 1.0 / pool_inverse_depth(1.0 / d, 0.01 * (1.0 / c - 1.0).sqrt(), 2, 2, curvature_test=1.0)
    torch.testing.assert_close(pool_stage_map(d, c, 0.01, pooling), expected, rtol=1e-12, atol=0)
    # a plane is kept (the local quadratic holds it, without the ridge), and noise on it is lowered
    clean = _slanted()
    torch.testing.assert_close(pool_stage_map(clean, c, 0.01, StructurePooling(radius=2, ridge=0.0)), clean,
                               rtol=1e-9, atol=0)
    assert float((pool_stage_map(d, c, 0.01, pooling) / clean - 1).abs().mean()) < float((d / clean - 1).abs().mean())
    assert pool_stage_map(d.float(), c.float(), 0.01, pooling).dtype == torch.float32


def test_a_tile_at_confidence_zero_moves_no_neighbour():
    truth = _slanted()
    c = torch.full_like(truth, 0.5)
    pooling = StructurePooling(radius=2, degree=1)
    base = pool_stage_map(truth, c, 0.01, pooling)
    wild, c0 = truth.clone(), c.clone()
    wild[0, 0, 3, 3] *= 1.015  # 1.5 % off (inside the robust kernel), stated as knowing nothing
    c0[0, 0, 3, 3] = 0.0
    out = pool_stage_map(wild, c0, 0.01, pooling)
    others = torch.ones_like(truth, dtype=torch.bool)
    others[0, 0, 3, 3] = False
    silent = pool_stage_map(truth, c0, 0.01, pooling)  # the tile on the surface, at confidence 0 too
    assert float((out[others] / silent[others] - 1).abs().max()) < 1e-7  # a weight ~1e-6 of theirs
    stated = pool_stage_map(wild, c, 0.01, pooling)  # the same tile at the others' confidence moves them
    assert float((stated[others] / base[others] - 1).abs().max()) > 3e-4
    assert float(out[0, 0, 3, 3] / truth[0, 0, 3, 3] - 1) == pytest.approx(0.0, abs=1e-3)  # back on the surface
    assert POOL_SCALE_CAP >= 10.0


def test_bad_maps_are_typed_errors():
    d, c = _slanted(), torch.full((1, 1, 6, 7), 0.5, dtype=F64)
    pooling = StructurePooling()
    with pytest.raises(ShapeError, match="one"):
        pool_stage_map(d, c[..., :-1], 0.01, pooling)
    with pytest.raises(ShapeError):
        pool_stage_map(d[0], c[0], 0.01, pooling)
    with pytest.raises(InputError, match="> 0"):
        pool_stage_map(-d, c, 0.01, pooling)
    with pytest.raises(InputError, match=r"\[0, 1\]"):
        pool_stage_map(d, c + 1.0, 0.01, pooling)
    with pytest.raises(InputError, match="confidence_scale"):
        pool_stage_map(d, c, 0.0, pooling)


def test_the_stage_pools_its_fused_map_only_when_asked():
    depth = 0.55
    i1, i2 = render_plane(depth, PsfHypothesis("pillbox"), size=224, noise=2e-4)
    model_d = torch.full((1, 1, 6, 6), depth * 1.03)
    model_c = torch.full((1, 1, 6, 6), 0.2)
    plain = LikelihoodStage(CAM, 64, 32, 0.01, family="pillbox")(i1, i2, model_d, model_c)
    assert plain.depth_pooled is None
    pooling = StructurePooling(radius=2, degree=2, curvature_test=1.0)
    stage = LikelihoodStage(CAM, 64, 32, 0.01, family="pillbox", pooling=pooling)
    r = stage(i1, i2, model_d, model_c)
    # the same fusion, then the fused map pooled with the fused confidences as weights
    assert torch.equal(r.depth, plain.depth) and torch.equal(r.confidence, plain.confidence)
    torch.testing.assert_close(r.depth_pooled, pool_stage_map(r.depth, r.confidence, 0.01, pooling))
    # the ring keeps the model's 3 % at confidence 0.2, the fitted tiles are within 0.02 % at a higher
    # confidence: pooled, the ring is pulled towards the fitted tiles' plane (the one-sided windows of
    # the corners least), and the fitted tiles stay within 0.5 %
    ring = ~r.fitted
    assert float((r.depth[ring] / depth - 1).abs().median()) == pytest.approx(0.03, rel=1e-4)
    assert float((r.depth_pooled[ring] / depth - 1).abs().median()) < 0.022
    assert float((r.depth_pooled[r.fitted] / depth - 1).abs().max()) < 0.005


def test_the_stage_takes_the_models_pooling_or_refuses():
    model = SimpleNamespace(camera=CAM, tile=64, stride=32, confidence_scale=0.01, structure_pooling=None)
    assert LikelihoodStage.for_model(model).pooling is None
    with pytest.raises(InputError, match="has none"):
        LikelihoodStage.for_model(model, pool=True)
    model.structure_pooling = StructurePooling(radius=1)
    assert LikelihoodStage.for_model(model, pool=True).pooling is model.structure_pooling
    with pytest.raises(InputError, match="callable"):
        LikelihoodStage(CAM, pooling=math.pi)
