"""tdfd.dfd.scene_ambiguity and the likelihood stage's opt-in ambiguity check: an image whose
likelihood does not tell its fitted depths from depths far from them has its confidences capped."""

from __future__ import annotations

import math
import sys

import pytest
import torch

from tdfd.dfd.inverse_variance import confidence_from_sigma
from tdfd.dfd.likelihood_stage import LikelihoodStage
from tdfd.dfd.psf_hypotheses import PsfHypothesis
from tdfd.dfd.scene_ambiguity import (AMBIGUITY_FAR, AMBIGUITY_MARGIN, ambiguity_cap, chosen_tiles,
                                      likelihood_margins)
from tdfd.errors import InputError, ShapeError
from tests.test_likelihood_stage import CAM, render_plane

F64 = torch.float64
HYP = PsfHypothesis("gaussian")
ORIGINS = [(64, 64), (64, 128), (128, 64), (128, 128)]


@pytest.fixture(scope="module")
def plane():
    depth = 0.5
    i1, i2 = render_plane(depth, HYP, size=256, noise=2e-4)
    return depth, i1[0, 0].double(), i2[0, 0].double()


def test_the_true_depth_wins_by_a_wide_margin_and_a_wrong_one_loses(plane):
    depth, y1, y2 = plane
    q = torch.full((len(ORIGINS),), 1.0 / depth, dtype=F64)
    at_truth = likelihood_margins(y1, y2, CAM, HYP, ORIGINS, 64, q)
    assert at_truth.shape == (4,) and bool((at_truth > 100.0).all())
    # fitted 20 % off (as a whole scene seeded off can be): the truth, > 10 % away, fits better
    off = likelihood_margins(y1, y2, CAM, HYP, ORIGINS, 64, q * 1.2)
    assert bool((off < 0).all())
    # a "near" wide enough to hold the truth 20 % away takes its minimum as the fit's: positive again
    assert bool((likelihood_margins(y1, y2, CAM, HYP, ORIGINS, 64, q * 1.2, near=0.25, far=0.3) > 0).all())


def test_bad_inputs_are_typed_errors(plane):
    _, y1, y2 = plane
    q = torch.full((4,), 2.0, dtype=F64)
    with pytest.raises(InputError, match="inverse depth"):
        likelihood_margins(y1, y2, CAM, HYP, ORIGINS, 64, q[:3])
    with pytest.raises(InputError, match="inverse depth"):
        likelihood_margins(y1, y2, CAM, HYP, ORIGINS, 64, -q)
    with pytest.raises(InputError, match="near < far"):
        likelihood_margins(y1, y2, CAM, HYP, ORIGINS, 64, q, near=0.2, far=0.1)
    with pytest.raises(ShapeError):
        likelihood_margins(y1, y2, CAM, HYP, [(0, 0)], 64, q[:1])
    assert likelihood_margins(y1, y2, CAM, HYP, [], 64, q[:0]).shape == (0,)
    with pytest.raises(ShapeError):
        chosen_tiles(torch.ones(2, 2))
    with pytest.raises(InputError):
        chosen_tiles(torch.ones(3), tiles=0)


def test_the_most_informative_tiles_decide_and_the_cap_states_the_far_error():
    sigma = torch.tensor([0.3, math.inf, 0.01, 0.02, 0.2], dtype=F64)
    assert chosen_tiles(sigma, tiles=3).tolist() == [2, 3, 4]
    assert chosen_tiles(torch.full((3,), math.inf)).tolist() == []
    cap = ambiguity_cap(0.01)
    assert cap == pytest.approx(1.0 / (1.0 + AMBIGUITY_FAR ** 2 / (2 * 0.01 ** 2)))
    assert cap == pytest.approx(float(confidence_from_sigma(torch.tensor([AMBIGUITY_FAR]), 0.01)[0]))


def test_the_stage_caps_an_ambiguous_image_only(plane, monkeypatch):
    depth, y1, y2 = plane
    i1, i2 = y1.float()[None, None], y2.float()[None, None]
    model_d = torch.full((1, 1, 7, 7), depth * 1.02)
    model_c = torch.full((1, 1, 7, 7), 0.3)
    plain = LikelihoodStage(CAM, 64, 32, 0.01, family="gaussian")(i1, i2, model_d, model_c)
    assert plain.scene_margin is None and plain.ambiguous is None
    checked = LikelihoodStage(CAM, 64, 32, 0.01, family="gaussian", ambiguity=True)(i1, i2, model_d, model_c)
    assert checked.scene_margin.shape == (1,) and float(checked.scene_margin[0]) > AMBIGUITY_MARGIN
    assert checked.ambiguous.tolist() == [False]
    assert torch.equal(checked.depth, plain.depth) and torch.equal(checked.confidence, plain.confidence)
    # the same image under a threshold no margin reaches: ambiguous, its map kept, every confidence capped
    stage_module = sys.modules["tdfd.dfd.likelihood_stage"]
    monkeypatch.setattr(stage_module, "AMBIGUITY_MARGIN", 1e12)
    capped = LikelihoodStage(CAM, 64, 32, 0.01, family="gaussian", ambiguity=True)(i1, i2, model_d, model_c)
    assert torch.equal(capped.depth, plain.depth)
    cap = ambiguity_cap(0.01)
    assert float(capped.confidence.max()) <= cap + 1e-7
    torch.testing.assert_close(capped.confidence, plain.confidence.clamp_max(cap))
