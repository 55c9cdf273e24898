"""training/fit_likelihood_stage.py: the black level each sample's frames carry, the two factors
from collected errors, and the whole fit on a few scenes writing a scales file the stage loads."""

from __future__ import annotations

import json

import pytest
import torch

from tdfd.dfd.inverse_variance import LikelihoodScales
from training.fit_likelihood_stage import (black_levels, decile_ratios, fit_fused_scale_map, fit_scales,
                                           fused_errors, main)


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


def test_the_fit_writes_a_scales_file_with_its_provenance(tmp_path, monkeypatch):
    import shutil
    from pathlib import Path

    stem = tmp_path / "m"
    for ext in (".safetensors", ".json"):
        shutil.copy(Path("models") / f"reference{ext}", f"{stem}{ext}")
    assert main(["--model", str(stem), "--planes", "5", "--scenes", "0", "--fused-bins", "3"]) == 0
    scales = LikelihoodScales.load(f"{stem}.likelihood.json")
    assert len(scales.fit) == len(scales.slope_edges) + 1 == 3 and min(scales.fit + scales.model) > 0
    prov = json.loads(Path(f"{stem}.likelihood.json").read_text())["provenance"]
    assert prov["planes"] == 5 and prov["tiles"]["planes"] > 0 and prov["tiles"]["slanted"] == 0
    assert "--planes 5 --scenes 0 --fused-bins 3" in prov["command"] and not scales.shared_bias
    assert scales.bias_radius is None
    # the fused scale's map: as many knots as bins where the tiles allow them (25 each)
    assert prov["fused_bins"] == min(3, sum(prov["tiles"].values()) // 25) >= 2
    assert len(scales.fused_log_b) == prov["fused_bins"]
    assert len(prov["fused_decile_ratios_most_confident_last"]["after_map"]) == 10
    assert main(["--model", str(stem), "--planes", "2", "--scenes", "0", "--shared-bias", "--bias-radius", "2",
                 "--out", str(tmp_path / "b.json")]) == 0
    biased = LikelihoodScales.load(tmp_path / "b.json")
    assert biased.shared_bias and biased.bias_radius == 2
    assert biased.fused_log_b is None  # two planes: too few tiles for a map, said in the log
    assert "--shared-bias --bias-radius 2 --out" in biased.provenance["command"]
    assert set(prov["median_abs_error"]) == {"fit", "model", "model_without_bias", "fused"}
    assert scales.psf == "profiled" and prov["psf"] == "profiled over every shape"
    # --calibrated-psf: each scene's stage told its lens as a focus sweep measures it
    import training.fit_likelihood_stage as fls
    from data_synth.psf import sample_psf_model
    from training.calibrate_scale import calibration_scene_sets
    from tdfd.model import DFDModel

    calls, real = [], fls.sweep_fit

    def spy(camera, lens, seed, frames_per_power, chart):
        calls.append((lens, seed, frames_per_power, chart))
        return real(camera, lens, seed, frames_per_power, chart)

    monkeypatch.setattr(fls, "sweep_fit", spy)
    assert main(["--model", str(stem), "--planes", "1", "--scenes", "0", "--calibrated-psf", "1",
                 "--out", str(tmp_path / "c.json")]) == 0
    first = calibration_scene_sets(DFDModel.load(stem), 1, 0)[0][1].batch([0])["params"][0]
    assert calls == [(sample_psf_model(first), fls.CALIBRATION_SWEEP_SEED, 1, "dead_leaves")]  # the scene's own lens
    measured = LikelihoodScales.load(tmp_path / "c.json")
    assert measured.psf == "measured" and "--calibrated-psf 1" in measured.provenance["command"]
    assert "focus sweep of a dead_leaves chart (1 frame(s) per power" in measured.provenance["psf"]
    with pytest.raises(SystemExit):
        main(["--model", str(stem), "--planes", "1", "--calibrated-psf", "-1"])
    # --register: the stage fits each pair's registration, and the file says so
    stages, for_model = [], fls.LikelihoodStage.for_model

    def spy_stage(model, **kwargs):
        stages.append(kwargs)
        return for_model(model, **kwargs)

    monkeypatch.setattr(fls.LikelihoodStage, "for_model", spy_stage)
    assert main(["--model", str(stem), "--planes", "1", "--scenes", "0", "--register", "--out",
                 str(tmp_path / "r.json")]) == 0
    assert stages == [{"register": True}]
    registered = LikelihoodScales.load(tmp_path / "r.json")
    assert registered.registered and "--register --out" in registered.provenance["command"]
    assert not scales.registered and not measured.registered


def test_saved_errors_refit_to_the_scales_a_full_run_gives(tmp_path):
    import shutil
    from pathlib import Path

    stem = tmp_path / "m"
    for ext in (".safetensors", ".json"):
        shutil.copy(Path("models") / f"reference{ext}", f"{stem}{ext}")
    saved = tmp_path / "errors.pt"
    base = ["--model", str(stem), "--planes", "2", "--scenes", "0", "--fused-bins", "0"]
    assert main(base + ["--shared-bias", "--out", str(tmp_path / "full.json"), "--save-errors", str(saved)]) == 0
    assert main(base + ["--shared-bias", "--out", str(tmp_path / "refit.json"), "--errors", str(saved)]) == 0
    full, refit = LikelihoodScales.load(tmp_path / "full.json"), LikelihoodScales.load(tmp_path / "refit.json")
    assert refit.fit == full.fit and refit.model == full.model and refit.shared_bias
    assert refit.provenance["tiles"] == full.provenance["tiles"]
    assert refit.provenance["median_abs_error"] == full.provenance["median_abs_error"]
    assert refit.provenance["command"].endswith(f"--errors {saved}")
    assert refit.provenance["errors_collection_wall_s"] > 0
    # the variant without the bias removal, on the same tiles: the fit's factors do not depend on it
    assert main(base + ["--out", str(tmp_path / "plain.json"), "--errors", str(saved)]) == 0
    assert LikelihoodScales.load(tmp_path / "plain.json").fit == full.fit
    # an errors file collected for other scenes or another PSF is refused, naming the setting
    with pytest.raises(ValueError, match="planes: file 2, asked 3"):
        main(["--model", str(stem), "--planes", "3", "--scenes", "0", "--errors", str(saved)])
    with pytest.raises(ValueError, match="calibrated_psf: file 0, asked 2"):
        main(base + ["--calibrated-psf", "2", "--errors", str(saved)])
    with pytest.raises(ValueError, match="register: file False, asked True"):
        main(base + ["--register", "--errors", str(saved)])
    data = torch.load(saved, weights_only=True)
    del data["settings"]["register"]  # a file from before --register: collected without it
    torch.save(data, tmp_path / "old.pt")
    assert main(base + ["--shared-bias", "--out", str(tmp_path / "old.json"),
                        "--errors", str(tmp_path / "old.pt")]) == 0
    assert LikelihoodScales.load(tmp_path / "old.json").fit == full.fit
    data = torch.load(saved, weights_only=True)
    del data["errors"]["slope"]
    torch.save(data, tmp_path / "short.pt")
    with pytest.raises(ValueError, match=r"lacks the columns \['slope'\]"):
        main(base + ["--errors", str(tmp_path / "short.pt")])
    torch.save({"fit_error": torch.zeros(3)}, tmp_path / "other.pt")
    with pytest.raises(ValueError, match="not an errors file"):
        main(base + ["--errors", str(tmp_path / "other.pt")])


def _correlated_errors(images: int = 200, tiles: int = 40, seed: int = 5) -> dict[str, torch.Tensor]:
    """Fit and model errors that share half their variance, each at its stated sigma: the
    inverse-variance fusion, taking them for independent, understates its sigma."""
    g = torch.Generator().manual_seed(seed)
    n = images * tiles
    sig = 0.002 * torch.exp(2.0 * torch.rand(n, generator=g, dtype=torch.float64))  # 0.2-1.5 %
    common = torch.randn(n, generator=g, dtype=torch.float64)
    z_fit = (common + torch.randn(n, generator=g, dtype=torch.float64)) / 2 ** 0.5
    z_model = (common + torch.randn(n, generator=g, dtype=torch.float64)) / 2 ** 0.5
    return {"fit_error": z_fit * sig, "fit_sigma": sig, "model_error": z_model * sig, "model_sigma": sig,
            "slope": torch.zeros(n, dtype=torch.float64),
            "image": torch.arange(images, dtype=torch.float64).repeat_interleave(tiles),
            "row": (torch.arange(tiles) // 8).repeat(images).to(torch.float64),
            "col": (torch.arange(tiles) % 8).repeat(images).to(torch.float64)}


def test_the_fused_scales_map_makes_the_correlated_fusion_state_its_error():
    errors = _correlated_errors()
    scales = fit_scales(errors, slope_edges=(), remove_bias=False)
    err, b = fused_errors(errors, scales)
    assert len(decile_ratios(err[:3], b[:3])) == 3 and decile_ratios(err[:0], b[:0]) == []  # fewer tiles than bins
    before = decile_ratios(err, b)
    # correlation 0.5 between equal sigmas: the fused variance is 1.5x what independence says
    assert min(before) > 1.1
    mapped = fit_fused_scale_map(err, b, scales, bins=20)
    assert mapped.fit == scales.fit and mapped.model == scales.model and mapped.fused_log_b is not None
    after = decile_ratios(err, mapped.fused_scale(b))
    assert all(abs(r - 1.0) < 0.1 for r in after), after
    # held out: a second draw of the same world is stated right too
    held = _correlated_errors(seed=6)
    err_h, b_h = fused_errors(held, scales)
    assert all(abs(r - 1.0) < 0.12 for r in decile_ratios(err_h, mapped.fused_scale(b_h)))


def test_the_maps_slope_part_states_the_error_of_steep_and_flat_tiles_alike():
    errors = _correlated_errors()
    n = errors["fit_error"].numel()
    # the error grows with the slope, (slope / 0.01)^0.3 times what the sigmas say (0.5x on the flattest
    # tiles, 2x on the steepest): a map of the scale alone cannot state both
    u = torch.rand(n, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    slope = 0.001 * 100.0 ** u  # log-uniform in 0.001 .. 0.1
    grow = (slope / 0.01) ** 0.3
    errors = {**errors, "slope": slope, "fit_error": errors["fit_error"] * grow,
              "model_error": errors["model_error"] * grow}
    scales = fit_scales(errors, slope_edges=(), remove_bias=False)
    err, b = fused_errors(errors, scales)
    steep = slope > 0.01
    plain = fit_fused_scale_map(err, b, scales, bins=20)
    assert plain.fused_log_slope is None
    ratios = lambda m, sel: decile_ratios(err[sel], m.fused_scale(b, slope)[sel], bins=5)  # noqa: E731
    assert max(ratios(plain, steep)) > 1.3 and min(ratios(plain, ~steep)) < 0.75
    mapped = fit_fused_scale_map(err, b, scales, bins=20, slope=slope, slope_bins=10)
    assert mapped.fused_log_slope is not None
    for sel in (steep, ~steep):
        assert all(abs(r - 1.0) < 0.12 for r in ratios(mapped, sel)), ratios(mapped, sel)


def test_fused_errors_are_the_stages_fusion_per_image():
    errors = _correlated_errors(images=3, tiles=10)
    errors["fit_sigma"] = torch.where(torch.arange(30) % 3 == 0, torch.inf, errors["fit_sigma"])
    scales = LikelihoodScales(fit=2.0, model=0.5)
    err, b = fused_errors(errors, scales)
    q_fit, q_model = 1 / (1 + errors["fit_error"]), 1 / (1 + errors["model_error"])
    s_fit, s_model = 2.0 * errors["fit_sigma"], 0.5 * errors["model_sigma"]
    w_fit = torch.where(torch.isfinite(s_fit), 1 / s_fit.clamp_min(1e-300) ** 2, torch.zeros_like(s_fit))
    w_fit = w_fit * (1 / q_fit ** 2)  # the fit's sigma in 1/m is relative times q
    w_model = 1 / (s_model * q_model) ** 2
    q = (w_fit * q_fit + w_model * q_model) / (w_fit + w_model)
    torch.testing.assert_close(err, q - 1)
    torch.testing.assert_close(b, (w_fit + w_model) ** -0.5 / q / 0.5 / 2 ** 0.5)
    # a tile without a fit is the model's own: its error and its own Laplace scale
    no_fit = ~torch.isfinite(errors["fit_sigma"])
    torch.testing.assert_close(err[no_fit], q_model[no_fit] - 1)
    torch.testing.assert_close(b[no_fit], errors["model_sigma"][no_fit] / 2 ** 0.5)
