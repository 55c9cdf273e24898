"""training/calibrated_lens.py: a synthetic sample's lens calibrated from a simulated focus sweep."""

from __future__ import annotations

import pytest

from data_synth import DefocusPairDataset
from data_synth.psf import sample_psf_model
from tdfd.camera import Camera
from tdfd.errors import InputError
from tdfd.optics.aberrated_psf import PSFModel
from training.calibrated_lens import sweep_fit

CAM = Camera.preset("reference")


def test_a_samples_lens_is_the_one_it_was_rendered_with():
    p = DefocusPairDataset(size=64, camera=CAM, seed=4, psf_shapes=["beta"])[0]["params"]
    lens = sample_psf_model(p)
    assert lens.shape == pytest.approx(float(p["psf_beta"]))
    assert (lens.astigmatism, lens.astigmatism_angle, lens.spherical, lens.diffraction_sigma_px) == (
        pytest.approx(p["astigmatism"]), pytest.approx(p["astigmatism_angle"]), pytest.approx(p["spherical"]),
        pytest.approx(p["diffraction_sigma_px"]))
    assert sample_psf_model({**p, "psf_shape": "gaussian"}).shape == "gaussian"


def test_the_sweep_measures_the_lens_and_refuses_no_frames():
    lens = PSFModel(5.0, 0.5, 0.1, 0.6, -0.2)
    fit = sweep_fit(CAM, lens, seed=3, frames_per_power=1)
    h = fit.hypothesis
    assert h.astigmatism == pytest.approx(0.1, abs=0.03) and h.spherical == pytest.approx(-0.2, abs=0.1)
    assert h.sigma_scale == pytest.approx(1.0, abs=0.06) and h.diffraction_px == 0.0  # the sweep cannot see it
    with pytest.raises(InputError, match="frames_per_power"):
        sweep_fit(CAM, lens, seed=3, frames_per_power=0)


def test_a_chart_with_detail_at_every_scale_gives_the_blur_scale_a_band_limited_one_loses():
    # benchmarks/bench_psf_model.py's plane 243 (sweep seed 7 000 000 + 243): a plain Gaussian lens whose
    # band-limited sweep fitted a blur scale of 1.9 (kernels 70 % off) at a slightly lower cost than the truth
    lens = PSFModel("gaussian")
    band_limited = sweep_fit(CAM, lens, seed=7_000_243, frames_per_power=2, chart="bandlimited").hypothesis
    dead_leaves = sweep_fit(CAM, lens, seed=7_000_243, frames_per_power=2).hypothesis
    assert band_limited.sigma_scale > 1.5
    assert dead_leaves.sigma_scale == pytest.approx(1.0, abs=0.02)
    assert dead_leaves.astigmatism < 0.02 and abs(dead_leaves.spherical) < 0.05
    with pytest.raises(InputError, match="chart"):
        sweep_fit(CAM, lens, seed=3, frames_per_power=1, chart="flat")
