"""The walking window's check against the fitted neighbours (tdfd.dfd.walk_gate): the consensus's
neighbourhood and count, the rejection rule, and the stage keeping a rescue and undoing a drift."""

from __future__ import annotations

import math
import sys

import pytest
import torch

from tdfd.dfd.likelihood_stage import LikelihoodStage
from tdfd.dfd.psf_hypotheses import PsfHypothesis
from tdfd.dfd.walk_gate import WALK_NEIGHBOURS, WALK_RADIUS, neighbour_consensus, walk_rejected
from tdfd.errors import InputError
from tests.test_likelihood_stage import CAM, render_plane


def _grid(h: int, w: int) -> tuple[torch.Tensor, torch.Tensor]:
    r, c = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
    return r.reshape(-1), c.reshape(-1)


def test_the_consensus_is_the_median_of_the_usable_neighbours_within_the_radius():
    rows, cols = _grid(5, 5)
    q = (rows * 10 + cols).to(torch.float64)
    every = torch.ones(25, dtype=torch.bool)
    c = neighbour_consensus(q, every, rows, cols, (5, 5), radius=1, least=3)
    # the centre's 8 neighbours: 11 12 13 21 23 31 32 33, median (torch: the lower middle) 21
    assert float(c[12]) == 21.0
    # a corner has 3 neighbours (1, 5, 6 -> q 1, 10, 11): median 10
    assert float(c[0]) == 10.0
    # the tile itself never counts: a lone usable tile has no consensus
    alone = torch.zeros(25, dtype=torch.bool)
    alone[12] = True
    assert bool(torch.isnan(neighbour_consensus(q, alone, rows, cols, (5, 5), 1, 1)[12]))
    assert float(neighbour_consensus(q, alone, rows, cols, (5, 5), 1, 1)[13]) == 22.0
    # too few usable neighbours: nan; the radius widens the neighbourhood
    some = torch.zeros(25, dtype=torch.bool)
    some[[0, 4, 20]] = True
    assert bool(torch.isnan(neighbour_consensus(q, some, rows, cols, (5, 5), 1, 1)[12]))
    assert float(neighbour_consensus(q, some, rows, cols, (5, 5), 2, 3)[12]) == 4.0  # 0, 4, 20
    assert bool(torch.isnan(neighbour_consensus(q, some, rows, cols, (5, 5), 2, 4)[12]))
    assert (WALK_RADIUS, WALK_NEIGHBOURS) == (2, 3)
    assert neighbour_consensus(q[:0], every[:0], rows[:0], cols[:0], (5, 5)).shape == (0,)


def test_the_consensus_refuses_bad_input():
    rows, cols = _grid(2, 2)
    q, ok = torch.ones(4, dtype=torch.float64), torch.ones(4, dtype=torch.bool)
    with pytest.raises(InputError, match="alike"):
        neighbour_consensus(q, ok[:3], rows, cols, (2, 2))
    with pytest.raises(InputError, match="alike"):
        neighbour_consensus(q, ok.int(), rows, cols, (2, 2))
    with pytest.raises(InputError, match="grid"):
        neighbour_consensus(q, ok, rows + 1, cols, (2, 2))
    with pytest.raises(InputError, match="radius"):
        neighbour_consensus(q, ok, rows, cols, (2, 2), radius=0)
    with pytest.raises(InputError, match="cell of its own"):
        neighbour_consensus(q, ok, rows, torch.zeros_like(cols), (2, 2))


def test_the_consensus_is_every_pair_within_the_radius_on_a_random_sparse_grid():
    # the windowed computation against its definition, pair by pair
    g = torch.Generator().manual_seed(5)
    h, w = 9, 13
    cells = torch.randperm(h * w, generator=g)[:70]
    rows, cols = cells // w, cells % w
    q = 1.0 + torch.rand(70, generator=g, dtype=torch.float64)
    usable = torch.rand(70, generator=g) < 0.6
    for radius, least in ((1, 1), (2, 3), (3, 5)):
        got = neighbour_consensus(q, usable, rows, cols, (h, w), radius, least)
        for t in range(70):
            near = ((rows - rows[t]).abs() <= radius) & ((cols - cols[t]).abs() <= radius) & usable
            near[t] = False
            want = q[near].median() if int(near.sum()) >= least else torch.tensor(math.nan, dtype=torch.float64)
            torch.testing.assert_close(got[t], want.to(torch.float64), rtol=0, atol=0, equal_nan=True)


def test_a_walk_is_undone_only_when_it_ends_farther_from_the_consensus_than_its_seed():
    consensus = torch.tensor([2.0, 2.0, 2.0, math.nan, 2.0], dtype=torch.float64)
    seed = torch.tensor([2.4, 2.4, 2.4, 2.4, 2.4], dtype=torch.float64)
    walked_q = torch.tensor([2.1, 2.8, 1.5, 3.0, 2.8], dtype=torch.float64)
    walked = torch.tensor([True, True, True, True, False])
    # towards it: kept; past the seed away from it: undone; overshooting to 0.5 off against the
    # seed's 0.4: undone; no consensus: kept; a tile that did not walk: never undone
    assert walk_rejected(walked_q, seed, consensus, walked).tolist() == [False, True, True, False, False]


def test_the_stage_keeps_a_walk_that_rescues_a_tile_and_undoes_one_the_neighbours_refute():
    depth = 0.55
    hyp = PsfHypothesis("pillbox")
    i1, i2 = render_plane(depth, hyp, size=192, noise=2e-4)
    model_d = torch.full((1, 1, 5, 5), depth * 1.03)
    model_d[0, 0, 2, 2] = depth * 1.25  # the model 25 % off at the centre: outside its +-5 % window
    model_c = torch.full((1, 1, 5, 5), 0.05)
    stay = LikelihoodStage(CAM, 64, 32, 0.01, family="pillbox")(i1, i2, model_d, model_c)
    walk = LikelihoodStage(CAM, 64, 32, 0.01, family="pillbox", walk=6)(i1, i2, model_d, model_c)
    assert math.isinf(float(stay.sigma_fit[0, 0, 2, 2]))
    # the walk reaches the neighbours' depth, nearer their consensus than the seed: kept
    assert abs(float(walk.depth_fit[0, 0, 2, 2]) / depth - 1.0) < 0.005
    assert math.isfinite(float(walk.sigma_fit[0, 0, 2, 2]))
    others = stay.fitted[0, 0].clone()
    others[2, 2] = False  # the tiles whose first window held the truth do not walk
    torch.testing.assert_close(walk.depth_fit[0, 0][others], stay.depth_fit[0, 0][others], rtol=0, atol=0)
    # neighbours that said the surface lay beyond the seed would refute the same walk: undone,
    # the tile as without walking (no weight, the model's depth after the fusion)
    stage_module = sys.modules["tdfd.dfd.likelihood_stage"]
    real = stage_module.neighbour_consensus
    try:
        stage_module.neighbour_consensus = lambda q, *a, **k: torch.full_like(real(q, *a, **k), 1.0 / (depth * 1.6))
        refuted = LikelihoodStage(CAM, 64, 32, 0.01, family="pillbox", walk=6)(i1, i2, model_d, model_c)
    finally:
        stage_module.neighbour_consensus = real
    for field in ("depth", "confidence", "depth_fit", "sigma_fit", "sigma_fit_raw"):
        torch.testing.assert_close(getattr(refuted, field), getattr(stay, field), rtol=0, atol=0, equal_nan=True)
