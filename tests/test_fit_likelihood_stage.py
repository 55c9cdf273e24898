"""training/fit_likelihood_stage.py: the black level each sample's frames carry, the two factors
from collected errors, and the whole fit on a few scenes writing a scales file the stage loads."""

from __future__ import annotations

import json

import pytest
import torch

from tdfd.dfd.inverse_variance import LikelihoodScales
from training.fit_likelihood_stage import black_levels, fit_scales, main


def test_black_levels_are_fractions_of_full_scale():
    assert black_levels([{"black_level_dn": 64.0, "bits": 12}, {"black_level_dn": 0.0, "bits": 8}]) == \
        [pytest.approx(64 / 4095), 0.0]


def test_fit_scales_calibrates_each_sigma_on_its_own_errors():
    g = torch.Generator().manual_seed(2)
    e_fit = 0.01 * torch.randn(8000, generator=g, dtype=torch.float64)
    e_model = 0.03 * torch.randn(8000, generator=g, dtype=torch.float64)
    slope = torch.where(torch.arange(8000) % 2 == 0, 0.005, 0.05).to(torch.float64)
    e_fit = torch.where(slope > 0.01, 3.0 * e_fit, e_fit)  # sloped tiles: the fit errs 3x more
    errors = {"fit_error": e_fit, "fit_sigma": torch.full_like(e_fit, 0.005),
              "model_error": e_model, "model_sigma": torch.full_like(e_model, 0.06), "slope": slope}
    s = fit_scales(errors, slope_edges=(0.01, 0.03), remove_bias=False)
    assert s.slope_edges == (0.01, 0.03)
    assert s.fit[0] == pytest.approx(2.0, rel=0.05) and s.fit[2] == pytest.approx(6.0, rel=0.05)
    assert all(m == pytest.approx(0.5, rel=0.07) for m in s.model)
    # the empty middle band takes the factors of all tiles
    pooled = fit_scales(errors, slope_edges=(), remove_bias=False)
    assert s.fit[1] == pooled.fit[0] and s.model[1] == pooled.model[0]


def test_the_models_factor_is_that_of_its_errors_without_each_images_bias():
    g = torch.Generator().manual_seed(3)
    images, tiles = 60, 40
    shared = 0.03 * torch.randn(images, generator=g, dtype=torch.float64)
    e_model = (shared[:, None] + 0.005 * torch.randn(images, tiles, generator=g, dtype=torch.float64)).flatten()
    e_fit = 0.005 * torch.randn(images * tiles, generator=g, dtype=torch.float64)
    errors = {"fit_error": e_fit, "fit_sigma": torch.full_like(e_fit, 0.005), "model_error": e_model,
              "model_sigma": torch.full_like(e_model, 0.01), "slope": torch.zeros_like(e_fit),
              "image": torch.arange(images, dtype=torch.float64).repeat_interleave(tiles),
              "row": (torch.arange(tiles) // 8).repeat(images).to(torch.float64),
              "col": (torch.arange(tiles) % 8).repeat(images).to(torch.float64)}
    raw = fit_scales(errors, slope_edges=(), remove_bias=False)
    debiased = fit_scales(errors, slope_edges=(), remove_bias=True, bias_radius=None)
    assert debiased.shared_bias and not raw.shared_bias and debiased.fit == raw.fit
    assert raw.bias_radius is None
    assert fit_scales(errors, slope_edges=(), remove_bias=True, bias_radius=2).bias_radius == 2
    assert raw.model[0] > 2.0  # the shared 3 % against a stated 1 %
    # what is left is the 0.5 % of each tile and the bias's own error (0.7 % / sqrt(40) by tile)
    assert 0.4 < debiased.model[0] < 0.8


def test_the_fit_writes_a_scales_file_with_its_provenance(tmp_path):
    import shutil
    from pathlib import Path

    stem = tmp_path / "m"
    for ext in (".safetensors", ".json"):
        shutil.copy(Path("models") / f"reference{ext}", f"{stem}{ext}")
    assert main(["--model", str(stem), "--planes", "2", "--scenes", "0"]) == 0
    scales = LikelihoodScales.load(f"{stem}.likelihood.json")
    assert len(scales.fit) == len(scales.slope_edges) + 1 == 3 and min(scales.fit + scales.model) > 0
    prov = json.loads(Path(f"{stem}.likelihood.json").read_text())["provenance"]
    assert prov["planes"] == 2 and prov["tiles"]["planes"] > 0 and prov["tiles"]["slanted"] == 0
    assert "--planes 2 --scenes 0" in prov["command"] and not scales.shared_bias and scales.bias_radius is None
    assert main(["--model", str(stem), "--planes", "2", "--scenes", "0", "--shared-bias", "--bias-radius", "2",
                 "--out", str(tmp_path / "b.json")]) == 0
    biased = LikelihoodScales.load(tmp_path / "b.json")
    assert biased.shared_bias and biased.bias_radius == 2 and biased.fit == scales.fit
    assert "--shared-bias --bias-radius 2 --out" in biased.provenance["command"]
    assert set(prov["median_abs_error"]) == {"fit", "model", "model_without_bias"}
