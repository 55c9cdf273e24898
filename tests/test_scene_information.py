"""benchmarks/scene_information.py: the scenes split by their information, the one-plane reference,
and bench_psf_structure's table of them."""

from __future__ import annotations

import math

import pytest
import torch

from benchmarks.bench_psf_model import BIAS_STAGE
from benchmarks.bench_psf_structure import information_table, main, with_plane_pooled
from benchmarks.scene_information import (POOR_SCENE_STD, information_groups, information_rows, plane_pooled_std,
                                          scene_medians)

F64 = torch.float64


def test_the_poor_scene_limit_is_where_the_median_at_the_bound_reaches_two_percent():
    assert 0.6744897501960817 * POOR_SCENE_STD == pytest.approx(0.02, rel=1e-12)


def test_scenes_split_at_their_median_bound_and_scenes_without_one_join_neither():
    bound = torch.tensor([0.01, 0.05, 0.01, 0.04, 0.04, 0.001, math.nan, math.nan], dtype=F64)
    scene = torch.tensor([0, 0, 0, 1, 1, 1, 2, 2])
    g = information_groups(bound, scene)
    assert g["informative"].tolist() == [True] * 3 + [False] * 5  # scene 0's median 0.01
    assert g["information-poor"].tolist() == [False] * 3 + [True] * 3 + [False] * 2  # scene 1's median 0.04
    assert scene_medians(bound, scene) == {0: pytest.approx(0.01), 1: pytest.approx(0.04)}
    with pytest.raises(ValueError, match="shape"):
        information_groups(bound, scene[:3])
    with pytest.raises(ValueError, match="limit"):
        information_groups(bound, scene, 0.0)


def test_one_plane_pools_the_tiles_information_as_least_squares_does():
    g = torch.Generator().manual_seed(3)
    rows, cols = torch.arange(20) // 5, torch.arange(20) % 5
    q = 2.0 + 0.05 * cols + 0.02 * rows
    std = 0.01 + 0.05 * torch.rand(20, generator=g, dtype=F64)
    pooled = plane_pooled_std(std, q, rows, cols, overlap=4.0)
    # against weighted least squares of the plane, its covariance propagated to each tile
    jac = torch.stack([torch.ones(20, dtype=F64), cols.double(), rows.double()], 1)
    w = 1.0 / (4.0 * (std * q) ** 2)
    cov = torch.linalg.inv(jac.T @ (jac * w[:, None]))
    expected = torch.einsum("ti,ij,tj->t", jac, cov, jac).sqrt() / q
    assert torch.allclose(pooled, expected, rtol=1e-10)
    # told the plane, the best unbiased estimate of a tile's q is never worse than the tile alone
    assert bool((plane_pooled_std(std, q, rows, cols, overlap=1.0) <= std).all())
    # a tile with no information adds none; two tiles cannot hold a plane
    with_blind = plane_pooled_std(torch.cat([std, torch.tensor([math.inf], dtype=F64)]), torch.cat([q, q[:1]]),
                                  torch.cat([rows, rows[:1]]), torch.cat([cols, cols[:1]]), 4.0)
    assert torch.allclose(with_blind[:20], pooled, rtol=1e-10)
    assert bool(torch.isinf(plane_pooled_std(std[:2], q[:2], rows[:2], cols[:2], 1.0)).all())
    assert bool(torch.isinf(plane_pooled_std(std[:5], q[:5], rows[:5], cols[:5], 1.0)).all())  # one line
    with pytest.raises(ValueError, match="overlap"):
        plane_pooled_std(std, q, rows, cols, 0.5)
    with pytest.raises(ValueError, match="one shape"):
        plane_pooled_std(std, q[:3], rows, cols, 1.0)


def _scene(layout: str, scene: int, bound: float, err: float, conf: float, n: int = 30) -> dict:
    true = torch.full((n,), 0.5, dtype=F64)
    edge = torch.arange(n) >= n - 6
    keep = torch.zeros(6, 6, dtype=torch.bool)
    keep.view(-1)[:n] = True
    row = {"layout": layout, "scene": scene, "true": true, "edge": edge, "grids": {"keep": keep},
           "bound_shared": torch.where(edge, math.nan, bound).to(F64)}
    for k in ("model", "calibrated", BIAS_STAGE, "calibrated_pooled", f"{BIAS_STAGE}_pooled"):
        row[k] = true * (1 + err)
        row[f"{k}_conf"] = torch.full((n,), conf, dtype=F64)
    return row


def test_the_table_scores_each_group_away_from_edges_with_its_shared_error():
    rows = [_scene("slanted", 0, 0.005, 0.01, 0.9), _scene("slanted", 1, 0.005, -0.01, 0.9),
            _scene("slanted", 2, 0.2, 0.3, 0.0)]
    rows = with_plane_pooled(rows, 4.0)
    table = {(r[0], r[1]): r for r in information_table(rows)}
    good, poor = table[("slanted", "informative")], table[("slanted", "information-poor")]
    assert good[2] == 2 and good[3] == "48 (67 %)" and poor[2] == 1 and poor[3] == "24 (33 %)"
    assert good[4] == f"{100 * 0.6744897501960817 * 0.005:.2f} %"
    assert good[5] != "-" and float(good[5].split()[0]) < 0.337  # one plane pools 24 tiles each
    assert good[6] == "1.00 %; 100 %; 100 %; 1.00 %" and poor[6] == "30.00 %; 0 %; 0 %; 30.00 %"
    assert ("all layouts", "informative") in table
    # other layouts carry no one-plane reference
    other = with_plane_pooled([_scene("smooth", 0, 0.005, 0.01, 0.9)], 4.0)
    assert information_rows([("smooth", {**{k: v for k, v in other[0].items() if isinstance(v, torch.Tensor)},
                                         "scene": torch.zeros(30, dtype=torch.long)})], ("model",), 0.5)[0][5] == "-"
    with pytest.raises(ValueError, match="bound_shared"):
        with_plane_pooled([{k: v for k, v in rows[0].items() if k != "bound_shared"}], 4.0)


def test_the_benchmark_refuses_a_walk_on_saved_fits(capsys):
    for option in (["--walk", "2"], ["--register"]):
        with pytest.raises(SystemExit):
            main(["--from-rows", "rows.pt", *option, "--no-write"])
        assert "--walk and --register need new fits" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["--walk", "-1", "--no-write"])
