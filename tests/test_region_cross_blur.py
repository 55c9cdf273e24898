"""A disk lens's one-region fit: the pair's disk cross-blur over the region (tdfd.autofocus.region_cross_blur)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from tdfd import Camera
from tdfd.autofocus.region_cross_blur import fit_region_cross_blur
from tdfd.autofocus.roi import Roi
from tdfd.autofocus.sim import SimBench
from tdfd.dfd.region_fit import fit_region
from tdfd.errors import InputError, RangeError, ShapeError
from tdfd.forward import Defocus, DFDForward
from tdfd.illumination import CoherentIllumination, illuminate
from tdfd.light import SimulatedLight
from tdfd.sensor import SensorModel

REF = Camera.preset("reference")
POWERS = REF.lens_powers_dpt


def _lit_pair(depth: float, scale: float = 1.0, size: int = 256, sensor: SensorModel | None = None,
              seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """The paper's two bars on a black target through a disk lens whose RMS blur is ``scale``
    times the camera's Gaussian sigma (the pillbox of radius ``2 sigma``)."""
    g = torch.Generator().manual_seed(seed)
    d = torch.full((1, 1, size, size), depth, dtype=torch.float64)
    pattern = CoherentIllumination().render(REF, d, generator=g)
    radiance = illuminate(torch.full_like(d, 0.08), pattern, ambient=0.05, power=1.0)
    frames = DFDForward(Defocus(REF, psf="pillbox", mu=REF.mu_px_per_m * scale), sensor)(radiance, d, generator=g)
    return frames[0, 0].numpy(), frames[0, 1].numpy()


@pytest.mark.parametrize("depth", [0.35, 0.7, 0.95])
def test_the_disk_fit_is_exact_where_the_gaussian_fit_is_biased(depth):
    a, b = _lit_pair(depth)
    q_true = 1.0 / depth
    disk = fit_region_cross_blur(a, b, POWERS, REF, psf_family="pillbox", mu_uncertainty=0.0)
    assert abs(disk.inverse_depth - q_true) < min(0.015, 2 * disk.sigma_dpt)  # the window's bias at 256 px: 1 %
    gauss = fit_region(a, b, REF, psf_family="pillbox", mu_uncertainty=0.0)
    assert abs(gauss.inverse_depth - q_true) > 5 * abs(disk.inverse_depth - q_true)  # what the disk model is for
    # told the lens is a disk, the fit carries no shape term: its uncertainty is the statistics and mu's
    assert disk.sigma_dpt < 0.1 * gauss.sigma_dpt and disk.size_px == 256 and 0 < disk.confidence <= 1


def test_the_blur_scale_matters_and_is_used():
    a, b = _lit_pair(0.8, scale=1.1)
    q_true = 1 / 0.8
    told = fit_region_cross_blur(a, b, POWERS, REF, psf_family="pillbox", sigma_scale=1.1)
    untold = fit_region_cross_blur(a, b, POWERS, REF, psf_family="pillbox")
    assert abs(told.inverse_depth - q_true) < 0.01
    assert abs(untold.inverse_depth - q_true) > 3 * abs(told.inverse_depth - q_true)


def test_the_stated_uncertainty_covers_the_scatter_over_noisy_captures():
    sensor = SensorModel(full_well_e=20000.0, read_noise_e=3.0, bits=12)
    fits = [fit_region_cross_blur(*_lit_pair(0.9, sensor=sensor, seed=s), POWERS, REF, psf_family="pillbox",
                                  mu_uncertainty=0.0) for s in range(6)]
    qs = np.array([f.inverse_depth for f in fits])
    stated = float(np.median([f.sigma_dpt for f in fits]))
    assert np.abs(qs - 1 / 0.9).max() < 3 * stated and qs.std(ddof=1) < 1.5 * stated


def test_a_small_region_states_the_windows_bias():
    """Noise-free, a 128-px region of the bars is off by several hundredths of a dioptre (the
    window does not commute with the blur); the stated uncertainty covers it, a 384-px one's is
    a fifth of it."""
    for depth in (0.7, 1.0):
        small = fit_region_cross_blur(*_lit_pair(depth, size=128), POWERS, REF, psf_family="pillbox",
                                      mu_uncertainty=0.0)
        large = fit_region_cross_blur(*_lit_pair(depth, size=384), POWERS, REF, psf_family="pillbox",
                                      mu_uncertainty=0.0)
        assert abs(small.inverse_depth - 1 / depth) < 1.5 * small.sigma_dpt
        assert abs(large.inverse_depth - 1 / depth) < 0.01 and large.sigma_dpt < 0.2 * small.sigma_dpt


def test_bad_input_is_refused():
    a, b = _lit_pair(0.6, size=128)
    with pytest.raises(InputError, match="psf_family"):
        fit_region_cross_blur(a, b, POWERS, REF, psf_family="disk")
    with pytest.raises(ShapeError, match="one shape"):
        fit_region_cross_blur(a, b[:, :100], POWERS, REF, psf_family="pillbox")
    with pytest.raises(ShapeError, match="smaller"):
        fit_region_cross_blur(a[:40], b[:40], POWERS, REF, psf_family="pillbox")
    with pytest.raises(InputError, match="NaN"):
        fit_region_cross_blur(np.full_like(a, math.nan), b, POWERS, REF, psf_family="pillbox")
    with pytest.raises(InputError, match="0.02 dpt apart"):
        fit_region_cross_blur(a, b, (1.7, 1.71), REF, psf_family="pillbox")
    for powers in ((1.7,), (1.7, math.nan), (1.7, 2.7, 3.0)):
        with pytest.raises(InputError, match="two finite powers"):
            fit_region_cross_blur(a, b, powers, REF, psf_family="pillbox")
    with pytest.raises(InputError, match="sigma_scale"):
        fit_region_cross_blur(a, b, POWERS, REF, psf_family="pillbox", sigma_scale=0.0)
    far_a, far_b = _lit_pair(20.0, size=128)  # focus far beyond the camera's range: the minimum sits at the edge
    with pytest.raises(RangeError, match="edge"):
        fit_region_cross_blur(far_a, far_b, POWERS, REF, psf_family="pillbox")


def test_the_assisted_controller_fits_a_disk_lens_with_the_disk():
    """On a disk lens's bench, a controller told pillbox fuses the lit tiles with the disk
    cross-blur (charged at its own cost); told nothing it keeps the Gaussian fit."""
    from tdfd.autofocus.estimators import AnalyticEstimator

    light = SimulatedLight(REF)
    hw = (320, 384)
    with SimBench(estimator=AnalyticEstimator(REF), light=light, controller={"illumination": "coherent"},
                  compute_s=0.001, readout_hw=hw, roi=Roi.centre(hw, 1.0), psf="pillbox") as bench:
        # Both fits' costs are measured when the bench opens; which one a trial is charged is checked
        # with charges set apart by far more than a trial's bench time (no wall times compared).
        assert bench.disk_region_fit_charge_s > 0 and bench.region_fit_charge_s > 0
        bench.region_fit_charge_s, bench.disk_region_fit_charge_s = 0.0, 1.0
        told = bench.run_trial(0.7, "dfd", uniform=True, psf_family="pillbox", psf_sigma_scale=1.0)
        assert told.extra["region_model"] == "disk cross-blur" and told.extra["region_weight"] > 0.5
        assert told.in_focus and told.frames <= 3
        assert told.time_ms > 1000.0
        unknown = bench.run_trial(0.7, "dfd", uniform=True)
        assert unknown.extra["region_model"] == "Gaussian Fourier ratio"
        assert unknown.extra["region_weight"] < told.extra["region_weight"] / 3
        assert unknown.time_ms < 1000.0
    assert not light.is_on
