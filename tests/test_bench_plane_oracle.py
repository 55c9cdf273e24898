"""The whole-plane oracle of benchmarks/bench_plane_oracle.py: the cross residual vanishes at the true
depth, the taper's model leaves pure noise indifferent to the depth, and bad inputs are refused."""

from __future__ import annotations

import pytest
import torch

from benchmarks.bench_bound import psf_model
from benchmarks.bench_plane_oracle import (CLEAN_WORLD, cross_residual_nll, fit_plane, plane_frames,
                                           tukey_window)
from data_synth import DefocusPairDataset
from data_synth.psf import PSFModel
from tdfd import Camera
from tdfd.errors import InputError, ShapeError
from tdfd.optics.thin_lens import camera_sigmas

REF = Camera.preset("reference")
QS = (1.0, 1.5, 2.0, 2.5, 3.0, 3.5)


def _kernels(shape: str = "gaussian", size: int = 31) -> torch.Tensor:
    sig = torch.tensor([[float(s) for s in camera_sigmas(REF, 1.0 / q)] for q in QS], dtype=torch.float64)
    return PSFModel(shape).kernels(sig.reshape(-1), size=size).reshape(len(QS), 2, size, size)


def _planes(noise: bool, count: int = 6) -> list[dict]:
    ds = DefocusPairDataset(size=160, camera=REF, seed=5, tile=32, stride=32,
                            **{**CLEAN_WORLD, "layouts": {"plane": 1.0}, "families": ["dead_leaves", "fractal"],
                               "noise": noise})
    out = []
    for i in range(count):
        s = ds[i]
        if 0.3 <= float(s["depth"].median()) <= 1.0:
            out.append(s)
    return out


def test_a_noise_free_rendered_plane_is_fitted_to_its_depth():
    planes = _planes(noise=False)
    assert len(planes) >= 3
    for s in planes:
        d = float(s["depth"].median())
        y1, y2 = s["image_f1"][0].double(), s["image_f2"][0].double()
        q, j = fit_plane(y1, y2, REF, [psf_model(s["params"])], 1.0, 1.0, band=0.5)
        assert j == 0
        assert abs(q * d - 1.0) < 3e-3, (s["params"]["index"], d, 1.0 / q)


def test_the_cross_residual_vanishes_only_at_the_true_depth():
    s = _planes(noise=False)[0]
    d = float(s["depth"].median())
    grid = torch.tensor([1.0 / d - 0.2, 1.0 / d, 1.0 / d + 0.2], dtype=torch.float64)
    sig = torch.tensor([[float(v) for v in camera_sigmas(REF, 1.0 / float(q))] for q in grid], dtype=torch.float64)
    k = psf_model(s["params"]).kernels(sig.reshape(-1), size=31).reshape(3, 2, 31, 31)
    nll = cross_residual_nll(s["image_f1"][0], s["image_f2"][0], k[:, 0], k[:, 1], 1e-6, 1e-6)
    assert float(nll[1]) < 1e-3 * float(nll[[0, 2]].min())


def test_with_the_taper_modelled_pure_noise_prefers_no_depth():
    k = _kernels()
    acc = {True: [], False: []}
    for seed in range(8):
        g = torch.Generator().manual_seed(seed)
        y1, y2 = (torch.randn(160, 160, generator=g, dtype=torch.float64) for _ in range(2))
        for modelled in acc:
            acc[modelled].append(cross_residual_nll(y1, y2, k[:, 0], k[:, 1], 1.0, 1.0, 0.25, modelled))
    modelled, plain = (torch.stack(acc[m]).mean(0) for m in (True, False))
    assert float((modelled - 1.0).abs().max()) < 0.04, modelled
    # without it the taper's leakage into the small high-frequency P of a wide kernel inflates some depths
    assert float((plain - 1.0).abs().max()) > 0.1, plain


def test_noise_levels_follow_the_sensor_and_noisy_planes_fit_near_their_depth():
    for s in _planes(noise=True)[:3]:
        y1, y2, nu1, nu2 = plane_frames(s)
        assert abs(nu1 / nu2 - 1.0) < 0.05  # one exposure, one mean level
        q, _ = fit_plane(y1, y2, REF, [psf_model(s["params"])], nu1, nu2)
        assert abs(q * float(s["depth"].median()) - 1.0) < 0.05


def test_tukey_window_and_bad_inputs():
    w = tukey_window(40, 30, fraction=0.2)
    assert w.shape == (40, 30) and float(w.max()) == 1.0 and float(w[0].abs().max()) == 0.0
    assert torch.equal(tukey_window(16, fraction=0.0), torch.ones(16, 16, dtype=torch.float64))
    k = _kernels(size=15)
    y = torch.rand(96, 96, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    with pytest.raises(ShapeError):
        cross_residual_nll(y, y[:, :90], k[:, 0], k[:, 1], 1.0, 1.0)
    with pytest.raises(ShapeError):
        cross_residual_nll(y, y, k[:, 0, :14, :14], k[:, 1, :14, :14], 1.0, 1.0)
    with pytest.raises(ShapeError):
        cross_residual_nll(y[:30, :30], y[:30, :30], k[:, 0], k[:, 1], 1.0, 1.0)
    for band in (0.0, -0.1, 0.6, float("nan")):
        with pytest.raises(InputError):
            cross_residual_nll(y, y, k[:, 0], k[:, 1], 1.0, 1.0, band)
    for nu in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(InputError):
            cross_residual_nll(y, y, k[:, 0], k[:, 1], nu, 1.0)
    with pytest.raises(InputError):
        fit_plane(y, y, REF, [], 1.0, 1.0)
    with pytest.raises(InputError):
        tukey_window(8, fraction=1.5)
