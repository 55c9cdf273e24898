"""benchmarks/bench_psf_structure.py and bench_psf_refused.py: the structure targets' verdicts, and the
saved fits fused again with other scales."""

from __future__ import annotations

import math

import pytest
import torch

from benchmarks.bench_psf_model import BIAS_STAGE
from benchmarks.bench_psf_refused import refuse_planes
from benchmarks.bench_psf_structure import bound_rows, difference_rows, main, merge_scenes, refuse_rows, target_rows
from benchmarks.bench_structure import SCENE_ID_STEP
from benchmarks.psf_stages import paired_with, structure_rows
from benchmarks.stage_rows import refuse
from tdfd.dfd.stage_pooling import pool_stage_map
from tdfd.model.structure_pooling import StructurePooling
from tdfd.dfd.inverse_variance import LikelihoodScales

F64 = torch.float64


def _scene(layout: str, scene: int, n: int = 40) -> dict:
    """A scene whose calibrated stage errs 0.8 % at confidence 0.9, the bias stage 0.5 % at 0.9, their
    pooled maps 0.7 % and 0.4 % at 0.9 and the model 3 % at 0.1 (the last 10 tiles near an edge,
    every estimator 10 % off there)."""
    true = torch.full((n,), 0.5, dtype=F64)
    edge = torch.arange(n) >= n - 10
    row = {"layout": layout, "scene": scene, "true": true, "edge": edge,
           "bound_shared": torch.where(edge, math.nan, 0.004).to(F64)}
    for k, err, conf in (("model", 0.03, 0.1), ("calibrated", 0.008, 0.9), (BIAS_STAGE, 0.005, 0.9),
                         ("calibrated_pooled", 0.007, 0.9), (f"{BIAS_STAGE}_pooled", 0.004, 0.9)):
        row[k] = torch.where(edge, true * 1.1, true * (1 + err))
        row[f"{k}_conf"] = torch.full((n,), conf, dtype=F64)
    return row


def test_scenes_merge_with_ids_unique_across_layouts():
    t = merge_scenes([_scene("slanted", 0), _scene("smooth", 0), _scene("smooth", 1)])
    assert t["true"].numel() == 120
    assert torch.unique(t["scene"]).tolist() == [0, 2 * SCENE_ID_STEP, 2 * SCENE_ID_STEP + 1]
    assert torch.unique(t["layout"]).tolist() == [0, 2]
    with pytest.raises(ValueError, match="no structure rows"):
        merge_scenes([_scene("slanted", 0)], ("layout",))


def test_the_targets_are_judged_per_estimator_and_tile_set():
    rows = [_scene("slanted", i) for i in range(6)]
    table = target_rows(rows, reps=50)
    cells = {(r[0], r[1], r[2]): r for r in table}
    assert len(table) == 2 * 2 * 5  # slanted and all layouts, two tile sets, five estimators
    away = cells[("slanted", "away from edges", "calibrated")]
    assert away[3] == 180 and away[4].startswith("0.80 %") and away[5].startswith("100 %") and away[6] == "0.80 %"
    assert away[7:] == ["yes", "yes", "yes"]
    model = cells[("slanted", "away from edges", "model")]
    assert model[7] == "**no**" and model[8] == "**no**" and model[6] == "-"
    every = cells[("slanted", "all tiles", BIAS_STAGE)]
    assert every[3] == 240 and every[4].startswith("0.50 %")  # the edge tiles are a quarter: the median stays
    assert every[7:] == ["yes", "yes", "yes"]


def test_differences_and_the_bound_are_scored_away_from_edges():
    rows = [_scene("layout", i) for i in range(4)]
    diff = {r[1]: r for r in difference_rows(rows, reps=20)}
    assert diff["away from edges"][2] == "-0.30 (-0.30 .. -0.30)"  # bias stage - calibrated
    assert diff["away from edges"][3].startswith("-2.20")  # calibrated - model
    assert diff["away from edges"][5] == "-0.10 (-0.10 .. -0.10)"  # the bias stage pooled - the bias stage
    (layout, everything) = bound_rows(rows, 0.01)
    assert layout[:2] == ["layout", 120]
    at_bound = float(layout[2].split()[0]) / 100
    assert at_bound == pytest.approx(0.6745 * 0.004, rel=0.02)  # the median |e| of a normal of that sigma
    assert layout[4] == "100 % (0.27 %)"  # sigma 0.4 % <= sqrt(2) b0: every tile would be confident
    assert layout[7] == "0.50 % (1.85x); 100 %" and layout[5].endswith("; 0 %")  # the model's 3 %: no share
    # with b0 = 0.2 %, sigma 0.4 % states 1 / (1 + 0.004^2 / (2 * 0.002^2)) = 1/3: none is confident
    assert bound_rows(rows, 0.002)[0][4] == "0 %"


def _grids(h: int = 4, w: int = 5) -> dict:
    g = torch.Generator().manual_seed(0)
    fitted = torch.ones(h, w, dtype=torch.bool)
    fitted[0, 0] = False
    return {"keep": torch.ones(h, w, dtype=torch.bool), "model": torch.full((h, w), 0.5) * 1.02,
            "model_conf": torch.full((h, w), 0.6), "calibrated_fitted": fitted,
            "calibrated_depth_fit": 0.5 * (1 + 0.002 * torch.randn(h, w, generator=g)),
            "calibrated_sigma_fit_raw": torch.full((h, w), 0.004, dtype=F64),
            "calibrated_slope": torch.full((h, w), 0.01, dtype=F64)}


def test_saved_fits_fused_again_follow_the_scales():
    rows = [{**_scene("slanted", 0, 20), "grids": _grids()}]
    # a fit weighed far above the model: the fused map is the fit's; far below: the model's
    fit_wins = LikelihoodScales(1e-3, 1e3)
    model_wins = LikelihoodScales(1e3, 1e-3, shared_bias=True)
    (r,) = refuse_rows(rows, 0.01, fit_wins, model_wins)
    g = rows[0]["grids"]
    fitted = g["calibrated_fitted"].flatten()
    torch.testing.assert_close(r["calibrated"][fitted], g["calibrated_depth_fit"].flatten()[fitted].double(),
                               rtol=1e-5, atol=0)
    assert float(r["calibrated"][0]) == pytest.approx(0.51)  # an unfitted tile keeps the model's estimate
    # the model, its bias (2 %, measured against the fits) removed, stands for the bias stage
    assert float((r[BIAS_STAGE][fitted] / 0.5 - 1).abs().max()) < 0.003
    with pytest.raises(ValueError, match="no calibrated fits"):
        refuse_rows([_scene("slanted", 0, 20)], 0.01, fit_wins, model_wins)
    assert r["calibrated_pooled"] is rows[0]["calibrated_pooled"]  # pooled again only when given the pooling


def test_saved_fits_are_pooled_as_the_stage_pools_them():
    g = _grids()
    g["calibrated_depth_fit"] = g["calibrated_depth_fit"] * (1 + 0.01 * torch.arange(5.0))  # a slope across
    rows = [{**_scene("slanted", 0, 20), "grids": g}]
    scales, bias = LikelihoodScales(2.0, 1.0), LikelihoodScales(2.0, 1.0, shared_bias=True)
    pooling = StructurePooling(radius=2, degree=2, curvature_test=1.0)
    (r,) = refuse_rows(rows, 0.01, scales, bias, pooling)
    for name, sc in (("calibrated", scales), (BIAS_STAGE, bias)):
        d, c = refuse(g["calibrated_fitted"], g["calibrated_depth_fit"], g["calibrated_sigma_fit_raw"],
                      g["calibrated_slope"], g["model"], g["model_conf"], 0.01, sc)
        expected = pool_stage_map(d[None, None], c[None, None], 0.01, pooling)[0, 0]
        torch.testing.assert_close(r[f"{name}_pooled"], expected.flatten().double())
        assert torch.equal(r[f"{name}_pooled_conf"], r[f"{name}_conf"])  # the fused confidence, kept
        assert not torch.equal(r[f"{name}_pooled"], r[name])


def test_plane_fits_fused_again_follow_the_scales():
    n = 25
    q_true = torch.full((n,), 2.0, dtype=F64)
    fits = {"fit_q": q_true * 1.001, "fit_sigma_raw": torch.full((n,), 0.004, dtype=torch.float32),
            "slope": torch.zeros(n, dtype=F64)}
    row = {"index": 0, "true_q": q_true, "model_q": q_true / 1.03, "model_conf": torch.full((n,), 0.5, dtype=F64),
           **{f"{s}_{k}": v for s in ("calibrated", "told") for k, v in fits.items()}}
    (r,) = refuse_planes([row], 0.01, LikelihoodScales(1e-3, 1e3), LikelihoodScales(1e3, 1e-3, shared_bias=True))
    torch.testing.assert_close(r["calibrated_q"], q_true * 1.001, rtol=1e-5, atol=0)
    torch.testing.assert_close(r["told_q"], q_true * 1.001, rtol=1e-5, atol=0)
    torch.testing.assert_close(r[f"{BIAS_STAGE}_q"], q_true * 1.001, rtol=2e-3, atol=0)  # the model, debiased
    assert bool((r["calibrated_conf"] > 0.5).all())
    with pytest.raises(ValueError, match="square grid"):
        refuse_planes([{**row, "true_q": q_true[:24]}], 0.01, LikelihoodScales(), None)


def test_a_run_is_paired_with_a_baseline_of_the_same_scenes():
    rows = [_scene("layout", i) for i in range(3)] + [_scene("smooth", i) for i in range(3)]
    base = [dict(r, calibrated=r["calibrated"] * 1.01) for r in rows]  # the baseline 1 % further off
    paired = paired_with(rows, base)
    assert torch.equal(paired[0]["base calibrated"], base[0]["calibrated"])
    assert torch.equal(paired[0][f"base {BIAS_STAGE}_conf"], rows[0][f"{BIAS_STAGE}_conf"])
    diff = {(r[0], r[1]): r for r in difference_rows(paired, (("calibrated", "base calibrated"),), reps=20)}
    # away from edges 0.8 % against 1.808 %: -1.01 points in every resample; the layouts together too
    assert diff[("layout", "away from edges")][2] == "-1.01 (-1.01 .. -1.01)"
    assert diff[("all layouts", "away from edges")][2] == "-1.01 (-1.01 .. -1.01)"
    with pytest.raises(ValueError, match="baseline"):
        paired_with(rows, base[1:])
    other = [dict(r, true=r["true"] * 2) if r["scene"] == 0 else r for r in base]
    with pytest.raises(ValueError, match="other tiles"):
        paired_with(rows, other)


def test_pairing_and_skipping_need_saved_rows(capsys):
    for option in (["--paired-with", "b.pt"], ["--skip-scenes", "2"]):
        with pytest.raises(SystemExit):
            main([*option, "--no-write"])
        assert "give --from-rows" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["--from-rows", "r.pt", "--scenes", "4", "--skip-scenes", "4", "--no-write"])
    with pytest.raises(SystemExit):  # part of a run is printed, never written as the section
        main(["--from-rows", "r.pt", "--scenes", "4", "--skip-scenes", "2"])
    assert "--skip-scenes scores part of a run" in capsys.readouterr().err


def test_a_run_in_parts_is_scored_only_whole(tmp_path, capsys):
    """``--first-scene`` runs part of the scenes and must save them (never the section); the parts'
    ``--from-rows`` files are scored together only when they hold every scene asked for, once."""
    for argv, said in ((["--first-scene", "2", "--scenes", "4"], "save them with --rows"),
                       (["--first-scene", "4", "--scenes", "4", "--rows", "r.pt"], "0 <= --first-scene < --scenes"),
                       (["--first-scene", "2", "--scenes", "4", "--from-rows", "r.pt"], "only for a run")):
        with pytest.raises(SystemExit):
            main(argv)
        assert said in capsys.readouterr().err
    layouts = ("slanted", "layout", "smooth")
    torch.save([_scene(k, i) for k in layouts for i in (0, 1)], tmp_path / "a.pt")
    torch.save([_scene(k, i) for k in layouts for i in (2, 3)], tmp_path / "b.pt")
    for parts, said in (([tmp_path / "a.pt"], "hold 6 scene(s), 6 distinct, where scenes 0-3 of 3 layouts are 12"),
                        ([tmp_path / "a.pt", tmp_path / "a.pt"], "hold 12 scene(s), 6 distinct")):
        with pytest.raises(SystemExit):
            main(["--from-rows", *map(str, parts), "--scenes", "4", "--no-write"])
        assert said in capsys.readouterr().err
    for first in (-1, 5):
        with pytest.raises(ValueError, match="first scene must be in 0..4"):
            structure_rows(None, (None, None), 4, 1, first=first)
