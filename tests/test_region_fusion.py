"""One region's fit over a lit pattern, its uncertainty, and its fusion with the lit tiles."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from tdfd import Camera
from tdfd.autofocus.aggregate import DepthAggregate
from tdfd.autofocus.lit_tiles import fuse_with_region
from tdfd.autofocus.sim import SimBench
from tdfd.dfd.region_fit import fit_region
from tdfd.region_fusion import SHAPE_SIGMA, RegionFit, fuse_inverse_depths, fusion_weight, region_sigma_dpt
from tdfd.errors import InputError, ShapeError
from tdfd.forward import Defocus, DFDForward
from tdfd.illumination import CoherentIllumination, illuminate
from tdfd.light import SimulatedLight

REF = Camera.preset("reference")
Q_EQ = 2.2  # the reference pair (1.7 / 2.7 dpt) blurs both frames equally at 1/2.2 m


def test_fusion_is_the_inverse_variance_mean() -> None:
    q, s, chi = fuse_inverse_depths(2.0, 0.03, 2.2, 0.04)
    assert q == pytest.approx((2.0 / 0.03**2 + 2.2 / 0.04**2) / (1 / 0.03**2 + 1 / 0.04**2))
    assert s == pytest.approx(0.024) and s < 0.03
    assert chi == pytest.approx(0.2 / 0.05)
    assert fuse_inverse_depths(2.0, math.inf, 2.2, 0.04) == (2.2, 0.04, 0.0)
    with pytest.raises(InputError, match="NaN"):
        fuse_inverse_depths(2.0, 0.03, math.nan, 0.1)
    with pytest.raises(InputError, match="infinite"):
        fuse_inverse_depths(2.0, math.inf, 2.1, math.inf)
    with pytest.raises(InputError, match="> 0"):
        fuse_inverse_depths(2.0, 0.0, 2.1, 0.1)


def test_correlated_fusion_of_a_subset_and_its_whole_set() -> None:
    """A subset's mean and the whole set's mean plus an independent systematic error: the
    generalised least-squares weights (covariance = the whole set's noise variance) reach the
    variance they state, below that of the independent inverse-variance mean, which states
    too small a one; the subset gets no weight when the whole set has no systematic term."""
    rng = np.random.default_rng(7)
    n, m, trials, s_b = 400, 100, 20000, 0.02
    noise = rng.normal(0.0, 1.0, (trials, n))
    subset, whole = noise[:, :m].mean(1), noise.mean(1) + rng.normal(0.0, s_b, trials)
    s_t, s_n = 1 / math.sqrt(m), 1 / math.sqrt(n)
    s_r = math.hypot(s_n, s_b)
    se = s_t * s_r / math.sqrt(trials)  # standard error of the sample covariance
    assert np.cov(subset, whole)[0, 1] == pytest.approx(s_n**2, abs=4 * se)  # the subset's noise is the whole's
    fused_corr = np.array([fuse_inverse_depths(a, s_t, b, s_r, covariance=s_n**2)[0] for a, b in zip(subset, whole)])
    fused_ind = np.array([fuse_inverse_depths(a, s_t, b, s_r)[0] for a, b in zip(subset, whole)])
    stated_corr = fuse_inverse_depths(0.0, s_t, 0.0, s_r, covariance=s_n**2)[1]
    stated_ind = fuse_inverse_depths(0.0, s_t, 0.0, s_r)[1]
    assert fused_corr.std() == pytest.approx(stated_corr, rel=0.03)
    assert fused_ind.std() > 1.1 * stated_ind  # independence assumed: overconfident
    assert fused_corr.std() < 0.985 * fused_ind.std()
    # no systematic term: the whole set's mean is sufficient, the subset gets no weight
    assert fusion_weight(s_t, s_n, covariance=s_n**2) == 0.0
    q, s, chi = fuse_inverse_depths(2.3, s_t, 2.0, s_n, covariance=s_n**2)
    assert (q, s) == (2.0, pytest.approx(s_n)) and chi == pytest.approx(0.3 / math.sqrt(s_t**2 - s_n**2))
    assert fusion_weight(0.02, 0.02, covariance=0.02**2) == 0.5  # the same estimate twice
    with pytest.raises(InputError, match="Cauchy-Schwarz"):
        fuse_inverse_depths(2.0, 0.01, 2.1, 0.03, covariance=0.01)
    with pytest.raises(InputError, match="covariance is NaN"):
        fuse_inverse_depths(2.0, 0.01, 2.1, 0.03, covariance=math.nan)


def test_lit_tiles_add_nothing_to_a_region_without_systematic_error() -> None:
    """The region's statistics are the tiles' covariance: a region fit whose uncertainty is its
    noise alone (a Gaussian lens, mu exact) carries the whole weight; a disk lens's shape term
    gives the tiles theirs back."""
    tiles = DepthAggregate(depth_m=1 / 1.45, inverse_depth=1.45, confidence=0.2, spread_dpt=0.02, tiles=20, inliers=12)
    exact = RegionFit(inverse_depth=1.43, sigma_dpt=0.005 * 1.43, rel_error=0.005, confidence=0.9, size_px=512)
    fused, w = fuse_with_region(tiles, 0.04, exact)
    assert w == 1.0 and fused.inverse_depth == 1.43
    disk = RegionFit(inverse_depth=1.43, sigma_dpt=region_sigma_dpt(1.43, 0.005, REF, "pillbox", 0.0), rel_error=0.005,
                     confidence=0.9, size_px=512)
    fused, w = fuse_with_region(tiles, 0.04, disk)
    assert w < 0.01 and fused.inverse_depth == pytest.approx(1.45, abs=2e-4)


def test_region_uncertainty_terms() -> None:
    q, rel, u = 1.2, 0.004, 0.01  # 1.0 dpt from the equal-blur distance
    stat, cal = rel * q, 2 * u * 1.0
    assert region_sigma_dpt(q, rel, REF, "gaussian", u) == pytest.approx(math.hypot(stat, cal))
    for family in ("pillbox", None):
        assert region_sigma_dpt(q, rel, REF, family, u) == pytest.approx(
            math.sqrt(stat**2 + cal**2 + (SHAPE_SIGMA[family] * 1.0) ** 2))
    # at the equal-blur distance the blur difference does not depend on mu or the PSF's shape
    assert region_sigma_dpt(Q_EQ, rel, REF, "pillbox", u) == pytest.approx(rel * Q_EQ)
    with pytest.raises(InputError, match="psf_family"):
        region_sigma_dpt(q, rel, REF, "disk", u)
    with pytest.raises(InputError, match="rel_error"):
        region_sigma_dpt(q, -1.0, REF)


def _lit_pair(depth: float, optics: str, size: int = 256) -> tuple[torch.Tensor, torch.Tensor]:
    """The paper's two bars from the coherent module on a black target, noise-free."""
    d = torch.full((1, 1, size, size), depth, dtype=torch.float64)
    pattern = CoherentIllumination().render(REF, d, generator=torch.Generator().manual_seed(0))
    radiance = illuminate(torch.full_like(d, 0.08), pattern, ambient=0.05, power=1.0)
    frames = DFDForward(Defocus(REF, psf=optics, mu=REF.mu_px_per_m), None)(radiance, d)
    return frames[:, :1], frames[:, 1:]


def test_region_fit_on_a_gaussian_lens_and_its_bias_through_a_disk() -> None:
    fit = fit_region(*_lit_pair(0.6, "gaussian"), REF, psf_family="gaussian")
    assert abs(1 / fit.inverse_depth / 0.6 - 1) < 0.01 and fit.size_px == 256
    # through a disk the Gaussian model is biased by about half the distance from q_eq (module docs) ...
    q_true = 1 / 0.7
    disk = fit_region(*_lit_pair(0.7, "pillbox"), REF, psf_family="pillbox")
    bias = abs(disk.inverse_depth - q_true)
    assert bias > 0.2 * abs(q_true - Q_EQ)
    # ... which the pillbox family's uncertainty covers and the Gaussian one's does not
    assert bias < 2 * disk.sigma_dpt
    told_gaussian = region_sigma_dpt(disk.inverse_depth, disk.rel_error, REF, "gaussian")
    assert bias > 3 * told_gaussian
    with pytest.raises(ShapeError, match="smaller"):
        fit_region(np.zeros((40, 300)), np.zeros((40, 300)), REF)
    with pytest.raises(ShapeError, match="one shape"):
        fit_region(np.zeros((100, 100)), np.zeros((100, 90)), REF)


def test_fusion_keeps_the_tiles_when_the_region_disagrees() -> None:
    tiles = DepthAggregate(depth_m=1 / 1.43, inverse_depth=1.43, confidence=0.2, spread_dpt=0.02, tiles=20, inliers=12)
    wrong = RegionFit(inverse_depth=1.02, sigma_dpt=0.01, rel_error=0.003, confidence=0.9, size_px=512)
    fused, w = fuse_with_region(tiles, 0.04, wrong)
    assert w == 0.0 and fused == tiles  # 10 sigmas apart: one fit over an ROI of two depths is left out
    broad = RegionFit(inverse_depth=1.02, sigma_dpt=0.46, rel_error=0.003, confidence=0.9, size_px=512)
    fused, w = fuse_with_region(tiles, 0.04, broad)  # the same fit told it is a disk lens's: little weight
    assert w < 0.01 and fused.inverse_depth == pytest.approx(1.43, abs=0.005)
    assert (fused.confidence, fused.inliers, fused.spread_dpt) == (0.2, 12, 0.02)
    none = DepthAggregate(depth_m=math.nan, inverse_depth=math.nan, confidence=0.0, spread_dpt=math.nan, tiles=20,
                          inliers=0)
    fused, w = fuse_with_region(none, 0.04, broad)
    assert w == 1.0 and fused.inverse_depth == pytest.approx(1.02)


def test_bench_lit_pair_is_fused_with_the_region_and_focuses() -> None:
    from tdfd.autofocus.estimators import AnalyticEstimator
    from tdfd.autofocus.roi import Roi

    light = SimulatedLight(REF)
    hw = (320, 384)
    with SimBench(estimator=AnalyticEstimator(REF), light=light, controller={"illumination": "coherent"},
                  compute_s=0.001, readout_hw=hw, roi=Roi.centre(hw, 1.0)) as bench:
        told = bench.run_trial(0.6, "dfd", uniform=True, psf_family="gaussian")  # the bench's optics: Gaussian
        assert told.in_focus and told.frames <= 3 and told.extra["region_weight"] > 0.3
        unknown = bench.run_trial(0.6, "dfd", uniform=True)  # a disk lens is possible: the region counts less
        assert unknown.in_focus and unknown.extra["region_weight"] < told.extra["region_weight"] / 3
        off = bench.run_trial(0.6, "dfd", uniform=True, psf_family="gaussian", region_fit=False)
        assert off.in_focus and off.extra["region_weight"] == 0.0
        # at 0.45 m the two bars (about 195 px) reach the ROI's outer ring of tiles: no region is fitted
        near = bench.run_trial(0.45, "dfd", uniform=True, psf_family="gaussian")
        assert near.in_focus and near.extra["region_weight"] == 0.0
    assert not light.is_on


def test_no_region_fit_behind_breathing_registration() -> None:
    """The region fit does not register focus breathing: the bench turns it off for an estimator
    that registers the pair, and keeps it for one that does not."""
    from tdfd.autofocus.estimators import AnalyticEstimator, OnnxEstimator, estimator_breathing
    from tdfd.autofocus.registered import BreathingRegistered

    plain = AnalyticEstimator(REF)
    registered = BreathingRegistered(plain, 0.004)
    assert estimator_breathing(plain) == 0.0 and estimator_breathing(registered) == pytest.approx(0.004)
    assert estimator_breathing(OnnxEstimator()) == 0.0  # the shipped model registers no breathing
    for est, expected in ((plain, True), (registered, False)):
        with SimBench(estimator=est, light=SimulatedLight(REF), controller={"illumination": "coherent"},
                      compute_s=0.001, readout_hw=(192, 224)) as bench:
            assert bench.make_controller("dfd").region_fit is expected
    with pytest.raises(InputError, match="region_mu_uncertainty"):
        from tdfd.autofocus.assist import AssistedDFDController

        AssistedDFDController(REF, illumination="coherent", region_mu_uncertainty=1.5)
