"""The cross-residual likelihood (tdfd/dfd/cross_residual.py) and the oracles built on it: the
residual vanishes at the true depth, the taper's model leaves pure noise indifferent to the depth (whole
frame and per tile), a tile covering the valid region is the whole-frame likelihood, bad inputs are refused."""

from __future__ import annotations

import pytest
import torch

from benchmarks.bench_bound import psf_model
from benchmarks.bench_plane_oracle import CLEAN_WORLD, fit_plane, plane_frames
from tdfd.dfd.cross_residual import cross_residual_nll, tile_cross_residual_nll, tukey_window, valid_residual
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


def test_a_tile_covering_the_valid_region_is_the_whole_frame_likelihood():
    k = _kernels(size=15)
    g = torch.Generator().manual_seed(3)
    y1, y2 = (torch.rand(96, 96, generator=g, dtype=torch.float64) for _ in range(2))
    whole = cross_residual_nll(y1, y2, k[:, 0], k[:, 1], 0.5, 2.0)
    tiles = tile_cross_residual_nll(y1, y2, k[:, 0], k[:, 1], torch.tensor([0.5]), torch.tensor([2.0]), [(7, 7)], 82,
                                    chunk=4)
    assert tiles.shape == (len(QS), 1)
    torch.testing.assert_close(tiles[:, 0], whole, rtol=1e-10, atol=0.0)
    # a tile is cut from the residual at its own place
    v = valid_residual(y1, y2, k[:, 0], k[:, 1])
    assert v.shape == (len(QS), 82, 82)
    one = tile_cross_residual_nll(y1, y2, k[:, 0], k[:, 1], torch.tensor([1.0]), torch.tensor([1.0]), [(20, 30)], 32)
    again = tile_cross_residual_nll(y1[13:59, 23:69], y2[13:59, 23:69],
                                    k[:, 0], k[:, 1], torch.tensor([1.0]), torch.tensor([1.0]), [(7, 7)], 32)
    torch.testing.assert_close(one, again, rtol=1e-9, atol=0.0)


def test_per_tile_pure_noise_prefers_no_depth_and_each_noise_free_tile_finds_its_depth():
    k = _kernels()
    origins = [(16, 16), (16, 80), (80, 16), (80, 80)]
    ones = torch.ones(len(origins), dtype=torch.float64)
    acc = []
    for seed in range(8):
        g = torch.Generator().manual_seed(seed)
        y1, y2 = (torch.randn(160, 160, generator=g, dtype=torch.float64) for _ in range(2))
        acc.append(tile_cross_residual_nll(y1, y2, k[:, 0], k[:, 1], ones, ones, origins, 64))
    mean = torch.cat(acc, 1).mean(1)
    assert float((mean - 1.0).abs().max()) < 0.04, mean
    s = _planes(noise=False)[0]
    d = float(s["depth"].median())
    grid = torch.tensor([1.0 / d - 0.1, 1.0 / d, 1.0 / d + 0.1], dtype=torch.float64)
    sig = torch.tensor([[float(v) for v in camera_sigmas(REF, 1.0 / float(q))] for q in grid], dtype=torch.float64)
    kk = psf_model(s["params"]).kernels(sig.reshape(-1), size=31).reshape(3, 2, 31, 31)
    nll = tile_cross_residual_nll(s["image_f1"][0], s["image_f2"][0], kk[:, 0], kk[:, 1], ones * 1e-6, ones * 1e-6,
                                  origins, 64)
    assert torch.equal(nll.argmin(0), torch.ones(len(origins), dtype=torch.long)), nll


def test_per_tile_bad_inputs_are_refused():
    k = _kernels(size=15)
    y = torch.rand(96, 96, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    one = torch.ones(1, dtype=torch.float64)
    with pytest.raises(ShapeError):  # leaves the valid residual
        tile_cross_residual_nll(y, y, k[:, 0], k[:, 1], one, one, [(6, 7)], 32)
    with pytest.raises(ShapeError):
        tile_cross_residual_nll(y, y, k[:, 0], k[:, 1], one, one, [(7, 60)], 32)
    with pytest.raises(ShapeError):
        tile_cross_residual_nll(y, y, k[:, 0], k[:, 1], one, one, [(7, 7)], 8)
    with pytest.raises(InputError):  # one variance per tile
        tile_cross_residual_nll(y, y, k[:, 0], k[:, 1], torch.ones(2), one, [(7, 7)], 32)
    for bad in (0.0, float("nan"), float("inf")):
        with pytest.raises(InputError):
            tile_cross_residual_nll(y, y, k[:, 0], k[:, 1], one * bad, one, [(7, 7)], 32)
    with pytest.raises(InputError):
        tile_cross_residual_nll(y, y, k[:, 0], k[:, 1], one, one, [(7, 7)], 32, chunk=0)
    with pytest.raises(InputError):
        tile_cross_residual_nll(y, y, k[:, 0], k[:, 1], one, one, [(7, 7)], 32, band=0.7)
