"""The shipped model (models/reference.*): loads, matches its description, beats the analytic
estimate on a handful of held-out procedural planes (a regression guard)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

import data_synth
from tdfd import Camera
from tdfd.model import DFDModel
from training.config import TEXTURED_FAMILIES

ROOT = Path(__file__).resolve().parents[1]
STEM = ROOT / "models" / "reference"


@pytest.fixture(scope="module")
def model():
    for suffix in (".safetensors", ".json"):
        assert STEM.with_suffix(suffix).is_file(), f"the shipped model {STEM.with_suffix(suffix)} is missing"
    return DFDModel.load(STEM)


def test_files_small_and_described(model):
    assert STEM.with_suffix(".safetensors").stat().st_size < 5 * 1024 * 1024
    cfg = json.loads(STEM.with_suffix(".json").read_text())
    assert cfg["camera"] == Camera.preset("reference").to_dict()
    assert (model.tile, model.stride) == (64, 32)
    assert "training" in cfg.get("extra", {})
    # the analytic layer must still produce the features the CNN was trained on
    assert model.analytic_matches is True, "tdfd.dfd changed since models/reference was trained: retrain it"


def test_beats_analytic_on_held_out_planes(model):
    ds = data_synth.DefocusPairDataset(size=192, seed=987_654, layouts={"plane": 1.0}, families=TEXTURED_FAMILIES,
                                       illumination_prob=0.0)
    b = ds.batch(list(range(16)))
    with torch.no_grad():
        depth, conf, depth_a, depth_p, conf_p = model(b["image_f1"], b["image_f2"])
    t = b["tile_depth"]
    keep = (t >= 0.3) & (t <= 1.0)
    err_r = ((depth - t).abs() / t)[keep].median()
    err_a = ((depth_a - t).abs() / t)[keep].median()
    assert float(err_r) < 0.8 * float(err_a), (float(err_r), float(err_a))
    assert bool(((conf >= 0) & (conf <= 1)).all()) and bool(((conf_p >= 0) & (conf_p <= 1)).all())
    # the shipped model's structure-pooled map: no worse than its tiles on these planes
    err_p = ((depth_p - t).abs() / t)[keep].median()
    assert float(err_p) < 1.05 * float(err_r), (float(err_p), float(err_r))


def test_textureless_gets_low_confidence(model):
    ds = data_synth.DefocusPairDataset(size=128, seed=55, layouts={"plane": 1.0}, families=["flat"], illumination_prob=0.0)
    b = ds.batch(list(range(6)))
    with torch.no_grad():
        _, conf, _, _, conf_p = model(b["image_f1"], b["image_f2"])
    assert float(conf.quantile(0.9)) < 0.1 and float(conf_p.quantile(0.9)) < 0.1


def test_takes_the_psf_family_and_is_saved_unknown(model):
    assert model.psf_family_input and model.psf_family is None  # a camera file's family is told at export or run time


def test_the_right_psf_family_beats_the_wrong_one(model):
    """Told its lens's family, the shipped CNN errs less than told the other one (held-out
    Gaussian-PSF planes): the family input is used, and used the right way round."""
    ds = data_synth.DefocusPairDataset(size=192, seed=424_242, layouts={"plane": 1.0}, families=TEXTURED_FAMILIES,
                                       illumination_prob=0.0, psf_shapes=["gaussian"])
    b = ds.batch(list(range(16)))
    t = b["tile_depth"]
    keep = (t >= 0.3) & (t <= 1.0)
    err = {}
    with torch.no_grad():
        for family in ("gaussian", "pillbox"):
            depth = model.set_psf_family(family)(b["image_f1"], b["image_f2"])[0]
            err[family] = float(((depth - t).abs() / t)[keep].median())
    model.set_psf_family(None)
    assert err["gaussian"] < 0.9 * err["pillbox"], err


def test_scale_calibration_has_its_three_parts_and_they_act(model):
    """The shipped confidence comes through the whole calibration (issue 19): the scale, depth
    and edge parts are in the description, and on one pair a tile's calibrated scale moves
    with its depth and its place in the grid as the parts say."""
    cfg = model.scale_calibration.to_config()
    assert set(cfg) == {"log_b", "log_b_calibrated", "inverse_depth_per_m", "depth_log_shift", "border_log_shift"}
    assert cfg["border_log_shift"][-1] == 0.0  # the innermost level is the reference
    fit = DFDModel.read_description(STEM)["extra"]["scale_calibration_fit"]
    assert fit["depth_bins"] == len(cfg["depth_log_shift"]) and fit["border_levels"] == len(cfg["border_log_shift"])
    log_b = torch.full((1, 1, 6, 7), -4.0)
    q = torch.full((1, 1, 6, 7), 2.0)
    out = model.scale_calibration(log_b, q)
    edge_minus_inner = float(out[0, 0, 0, 3] - out[0, 0, 2, 3])  # 0 and 2 tiles from the edge
    assert edge_minus_inner == pytest.approx(cfg["border_log_shift"][0] - cfg["border_log_shift"][2], abs=1e-5)
