"""The per-tile oracle's pieces (benchmarks/bench_tile_oracle.py): the interior tile grid, the
shared-PSF profile over candidates, and the search seeded by another estimator's map."""

from __future__ import annotations

import pytest
import torch

from benchmarks.bench_plane_oracle import Q_GRID
from benchmarks.bench_tile_oracle import interior_origins, fit_tiles
from tdfd.errors import InputError


def test_interior_origins_leave_out_the_outer_ring():
    origins, inner = interior_origins(256)
    assert len(origins) == 25 and inner == slice(1, 6)
    assert origins[0] == (32, 32) and origins[-1] == (160, 160)
    with pytest.raises(InputError):
        interior_origins(96)  # a 2x2 grid has no interior


def _bowl(centre: float, depth: float) -> torch.Tensor:
    return depth + 40.0 * (Q_GRID - centre) ** 2


def test_the_shared_psf_is_the_candidate_whose_tiles_fit_best_and_minima_are_refined_off_grid():
    # candidate 0: both tiles fit, 1.0 above the noise floor; candidate 1: one tile fits better, the other worse
    c0 = torch.stack([_bowl(1.503, 2.0), _bowl(2.257, 2.0)], 1)
    c1 = torch.stack([_bowl(1.6, 1.5), _bowl(2.4, 3.0)], 1)
    q, j = fit_tiles(torch.stack([c0, c1]))
    assert j == 0
    torch.testing.assert_close(q, torch.tensor([1.503, 2.257], dtype=torch.float64), rtol=0, atol=1e-9)


def test_a_seeded_search_keeps_to_its_window_where_the_global_minimum_lies_elsewhere():
    # a deep wrong minimum at q = 3.0 (a threshold effect) and a shallower right one at 1.8
    nll = torch.minimum(_bowl(1.8, 1.0), _bowl(3.0, 0.5))[None, :, None]
    free, _ = fit_tiles(nll)
    seeded, _ = fit_tiles(nll, seed_q=torch.tensor([1.75], dtype=torch.float64), seed_window=0.05)
    assert abs(float(free[0]) - 3.0) < 1e-9
    assert abs(float(seeded[0]) - 1.8) < 1e-9
    # the window's edge is not extrapolated past: the best inside it, a grid point
    edge, _ = fit_tiles(nll, seed_q=torch.tensor([2.21], dtype=torch.float64), seed_window=0.05)  # from 2.0995
    assert abs(float(edge[0]) - 2.10) < 1e-9
    with pytest.raises(InputError):
        fit_tiles(nll, seed_q=torch.tensor([1.0, 2.0], dtype=torch.float64))
    with pytest.raises(InputError):
        fit_tiles(nll, seed_window=0.0)
