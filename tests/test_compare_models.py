"""benchmarks.compare_models: the paired scene bootstrap."""

import pytest
import torch

from benchmarks.compare_models import paired_group_median, paired_tile_median


def _scenes(n_scenes: int, tiles: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Errors whose level varies by scene (a scene-shared factor) and by tile."""
    g = torch.Generator().manual_seed(seed)
    level = torch.rand(n_scenes, generator=g, dtype=torch.float64) * 0.04 + 0.005
    group = torch.arange(n_scenes).repeat_interleave(tiles)
    err = level[group] * torch.rand(n_scenes * tiles, generator=g, dtype=torch.float64) * 2
    return err, group


def test_identical_models_differ_by_nothing():
    err, group = _scenes(40, 30, 0)
    r = paired_tile_median(err, err.clone(), group, reps=100)
    assert r["diff"] == 0.0 and r["se"] == 0.0 and r["lo"] == 0.0 and r["hi"] == 0.0


def test_scene_bootstrap_is_wider_than_the_tile_count_suggests_and_catches_a_real_gain():
    err, group = _scenes(40, 30, 1)
    # B's error is A's scaled down by 10 %: a real, paired improvement
    r = paired_tile_median(err, err * 0.9, group, reps=200, generator=torch.Generator().manual_seed(3))
    assert r["diff"] < 0 and r["hi"] < 0  # the interval excludes no change
    # an unpaired look at two independent draws of scenes scatters by far more than the paired difference
    err2, _ = _scenes(40, 30, 2)
    assert abs(float(err2.median()) - float(err.median())) > 5 * r["se"]


def test_per_scene_error_uses_the_median_tile_depth():
    true = torch.tensor([1.0, 1.0, 1.0, 0.5, 0.5, 0.5])
    group = torch.tensor([0, 0, 0, 1, 1, 1])
    depth_a = torch.tensor([1.1, 1.0, 5.0, 0.5, 0.5, 0.1])  # medians 1.1 and 0.5: errors 10 %, 0 %
    depth_b = torch.tensor([1.02, 1.02, 0.2, 0.51, 0.51, 9.0])  # medians 1.02 and 0.51: 2 %, 2 %
    r = paired_group_median(depth_a, depth_b, true, group, reps=20)
    assert r["a"] == pytest.approx(0.0)  # lower median of (0.10, 0.00)
    assert r["b"] == pytest.approx(0.02)


def test_mismatched_inputs_are_refused():
    with pytest.raises(ValueError, match="equal"):
        paired_tile_median(torch.ones(3), torch.ones(4), torch.zeros(3))
    with pytest.raises(ValueError, match="no tiles"):
        paired_tile_median(torch.ones(0), torch.ones(0), torch.zeros(0))


def test_structure_rows_are_the_same_from_worker_processes():
    """``--jobs``: the structure scenes spread over processes give the rows one process gives;
    the workers need the models' paths."""
    from benchmarks.compare_models import compare
    from benchmarks.depth_models import load_depth_model
    from benchmarks.report import ROOT

    path = str(ROOT / "models" / "reference")
    model = load_depth_model(path, threads=1)
    one = compare(model, model, planes=0, scenes=2, reps=20)
    split = compare(model, model, planes=0, scenes=2, reps=20, jobs=2, paths=(path, path))
    assert [name for name, _ in one] == [name for name, _ in split] and len(one) == 4
    for (_, r1), (_, r2) in zip(one, split):
        assert r1 == r2 and r1["diff"] == 0.0
    with pytest.raises(ValueError, match="paths"):
        compare(model, model, planes=0, scenes=2, jobs=2)


def test_plane_rows_split_by_texture_family_cover_every_plane_once():
    """The per-family rows: each textured plane in range in exactly one family's row; the same
    model against itself differs by nothing in each."""
    from benchmarks.bench_uncertainty import plane_tiles
    from benchmarks.compare_models import compare
    from benchmarks.depth_models import load_depth_model
    from benchmarks.report import ROOT
    from training.config import TEXTURED_FAMILIES

    model = load_depth_model(str(ROOT / "models" / "reference"), threads=1)
    tiles = plane_tiles(model, 12, 256)
    per_scene = tiles["family"].view(12, -1)
    assert bool((per_scene == per_scene[:, :1]).all())  # one family per plane
    assert set(per_scene[:, 0].tolist()) <= set(range(len(TEXTURED_FAMILIES))) and per_scene[:, 0].unique().numel() > 2
    rows = dict(compare(model, model, planes=12, scenes=0, reps=5))
    family_rows = {name: r for name, r in rows.items() if "per tile, " in name}
    planes = sum(int(name.rsplit("(", 1)[1].split()[0]) for name in family_rows)
    near, far = model.camera.depth_range_m
    in_range = tiles["scene"][(tiles["true"] >= near) & (tiles["true"] <= far)].unique().numel()
    assert planes == in_range > 6 and all(r["diff"] == 0.0 for r in family_rows.values())
