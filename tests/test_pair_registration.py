"""tdfd.dfd.pair_registration and the likelihood stage's opt-in registration: a pair's focus
breathing and shift, fitted to its own cross-residual likelihood, and the phase ramp that moves
frame 2 back in the residual."""

from __future__ import annotations

import math

import pytest
import torch

from tdfd.dfd.cross_residual import independent_bins, tile_cross_residual_nll
from tdfd.dfd.likelihood_stage import LikelihoodStage, valid_tiles
from tdfd.dfd.pair_registration import fit_pair_registration, registration_objective, tile_shifts
from tdfd.dfd.psf_hypotheses import PsfHypothesis
from tdfd.dfd.seeded_fit import kernel_pairs, kernel_side
from tdfd.errors import InputError, ShapeError
from tdfd.warp import misregister
from tests.test_likelihood_stage import CAM, render_plane

F64 = torch.float64
HYP = PsfHypothesis("gaussian")
DEPTH = 0.5
SIZE = 320
BREATHING, SHIFT_ROW, SHIFT_COL = 0.008, 0.3, -0.2  # frame 2 against frame 1 (tdfd.warp.misregister)


def _kernels(q: torch.Tensor) -> torch.Tensor:
    return kernel_pairs(CAM, HYP, q, kernel_side(CAM, (HYP,), q, 65, 64))


def _origins(half: int) -> list[tuple[int, int]]:
    valid = valid_tiles(SIZE, SIZE, 64, 32, half)
    return [(int(i) * 32, int(j) * 32) for i, j in zip(*valid.nonzero(as_tuple=True))]


@pytest.fixture(scope="module")
def pairs():
    i1, i2 = render_plane(DEPTH, HYP, size=SIZE, noise=2e-4, seed=3)
    registered = (i1[0, 0].double(), i2[0, 0].double())
    moved = misregister(torch.cat([i1, i2], 1).double(), BREATHING, SHIFT_ROW, SHIFT_COL)
    return registered, (moved[0, 0], moved[0, 1])


def test_tile_shifts_follow_the_warps_convention():
    """A scene point at p in frame 1 lies at p + beta (p - c) + d in frame 2 (tdfd.warp.misregister)."""
    reg = torch.tensor([0.01, 0.5, -0.25], dtype=F64)
    out = tile_shifts(reg, [(0, 0), (100, 200)], 64, (164, 264))
    # tile centres (31.5, 31.5) and (131.5, 231.5) against the frame's centre (81.5, 131.5)
    torch.testing.assert_close(out, torch.tensor([[-0.5 + 0.5, -1.0 - 0.25], [0.5 + 0.5, 1.0 - 0.25]], dtype=F64))
    with pytest.raises(ShapeError, match="registration"):
        tile_shifts(torch.zeros(2), [(0, 0)], 64, (164, 264))


def test_the_phase_ramp_takes_an_integer_shift_back(pairs):
    """Frame 2 moved by whole pixels: the residual with that shift is the registered pair's (up to
    the region's wrapped border, which the taper keeps small); without it the tile is not fitted."""
    (y1, y2), _ = pairs
    q = torch.tensor([1.0 / DEPTH], dtype=F64)
    ks = _kernels(q)
    half = ks.shape[-1] // 2
    origins = _origins(half)[:4]
    rolled = torch.zeros_like(y2)
    rolled[2:, :] = y2[:-2, :]  # content at p now at p + (2, 0); the top rows are lost
    unit = torch.ones(len(origins), dtype=F64)
    reference = tile_cross_residual_nll(y1, y2, ks[:, 0], ks[:, 1], unit, unit, origins, 64)
    moved_back = tile_cross_residual_nll(y1, rolled, ks[:, 0], ks[:, 1], unit, unit, origins, 64,
                                         shift=torch.tensor([[2.0, 0.0]] * len(origins), dtype=F64))
    unmoved = tile_cross_residual_nll(y1, rolled, ks[:, 0], ks[:, 1], unit, unit, origins, 64)
    torch.testing.assert_close(moved_back, reference, rtol=0.05, atol=0.0)
    assert bool((unmoved > 20 * reference).all())


def test_the_fit_finds_the_pairs_breathing_and_shift(pairs):
    _, (y1, y2) = pairs
    q = torch.tensor([1.0 / DEPTH], dtype=F64)
    half = _kernels(q).shape[-1] // 2
    origins = _origins(half)
    q_fit = torch.full((len(origins),), 1.0 / DEPTH, dtype=F64)
    sigma = torch.full((len(origins),), 0.01, dtype=F64)
    reg = fit_pair_registration(y1, y2, CAM, HYP, origins, 64, q_fit, sigma)
    assert reg.dtype == F64 and reg.shape == (3,)
    assert float(reg[0]) == pytest.approx(BREATHING, abs=0.001)
    assert float(reg[1]) == pytest.approx(SHIFT_ROW, abs=0.1)
    assert float(reg[2]) == pytest.approx(SHIFT_COL, abs=0.1)
    # the objective prefers the fit to the registered assumption by many nats
    kernels = _kernels(q_fit[:3] * torch.tensor([0.98, 1.0, 1.02], dtype=F64))
    mask = torch.eye(3, dtype=torch.bool)
    at_fit = registration_objective(y1, y2, kernels, mask, origins[:3], 64, 0.25, reg)
    at_zero = registration_objective(y1, y2, kernels, mask, origins[:3], 64, 0.25, torch.zeros(3, dtype=F64))
    assert at_zero - at_fit > 50.0


def test_a_minimum_on_its_windows_end_keeps_its_grid_value(pairs):
    """The objective refines a tile's minimum by a parabola only inside its window: a tile whose
    truth lies on its first hypothesis, the first row of the stacked windows, keeps that NLL."""
    (y1, y2), _ = pairs
    origins = _origins(32)[:1]
    q = torch.full((3,), 1.0 / DEPTH, dtype=F64) * torch.tensor([1.0, 1.02, 1.04], dtype=F64)
    kernels = _kernels(q)
    mask = torch.ones(3, 1, dtype=torch.bool)
    unit = torch.ones(1, dtype=F64)
    nll = tile_cross_residual_nll(y1, y2, kernels[:, 0], kernels[:, 1], unit, unit, origins, 64, mask=mask)
    assert int(nll[:, 0].argmin()) == 0
    expected = independent_bins(64, 0.25) * math.log(float(nll[0, 0]))
    got = registration_objective(y1, y2, kernels, mask, origins, 64, 0.25, torch.zeros(3, dtype=F64))
    assert got == pytest.approx(expected, rel=1e-12)


def test_too_few_fitted_tiles_leave_the_pair_as_it_is(pairs):
    _, (y1, y2) = pairs
    origins = _origins(32)[:4]
    q_fit = torch.full((4,), 1.0 / DEPTH, dtype=F64)
    sigma = torch.tensor([0.01, 0.01, math.inf, math.inf], dtype=F64)
    assert fit_pair_registration(y1, y2, CAM, HYP, origins, 64, q_fit, sigma).tolist() == [0.0, 0.0, 0.0]


def test_bad_inputs_are_typed_errors(pairs):
    (y1, y2), _ = pairs
    origins = _origins(32)[:2]
    q = torch.full((2,), 2.0, dtype=F64)
    with pytest.raises(InputError, match="one fit and sigma per tile"):
        fit_pair_registration(y1, y2, CAM, HYP, origins, 64, q[:1], q)
    with pytest.raises(InputError, match="breathing_scan"):
        fit_pair_registration(y1, y2, CAM, HYP, origins, 64, q, q, breathing_scan=0.5)
    ks = _kernels(q[:1])
    unit = torch.ones(2, dtype=F64)
    for bad in (torch.zeros(3, 2, dtype=F64), torch.full((2, 2), math.nan, dtype=F64),
                torch.full((2, 2), float(ks.shape[-1]), dtype=F64)):
        with pytest.raises(InputError, match="shift must be"):
            tile_cross_residual_nll(y1, y2, ks[:, 0], ks[:, 1], unit, unit, origins, 64, shift=bad)


def test_the_stage_registers_a_breathing_pair_and_keeps_its_default(pairs):
    (r1, r2), (y1, y2) = pairs
    grid = (1, 1, 9, 9)  # the 320-px frame's 64/32 grid
    seed = torch.full(grid, DEPTH * 1.02)
    conf = torch.full(grid, 0.3)
    plain = LikelihoodStage(CAM, family="gaussian")(y1.float()[None, None], y2.float()[None, None], seed, conf)
    assert plain.registration is None
    registered = LikelihoodStage(CAM, family="gaussian", register=True)(y1.float()[None, None],
                                                                        y2.float()[None, None], seed, conf)
    assert registered.registration.shape == (1, 3)
    fitted = registered.fitted[0, 0]
    # on the fitted tiles (within 96 px of the centre here) the registration moves frame 2 back to
    # within a sixth of a pixel of where the warp put it
    origins = [(int(i) * 32, int(j) * 32) for i, j in zip(*fitted.nonzero(as_tuple=True))]
    truth = tile_shifts(torch.tensor([BREATHING, SHIFT_ROW, SHIFT_COL], dtype=F64), origins, 64, (SIZE, SIZE))
    found = tile_shifts(registered.registration[0], origins, 64, (SIZE, SIZE))
    assert float((found - truth).abs().max()) < 1 / 6
    err_plain = (plain.depth_fit[0, 0][fitted] / DEPTH - 1).abs().median()
    err_reg = (registered.depth_fit[0, 0][fitted] / DEPTH - 1).abs().median()
    assert float(err_reg) < 0.5 * float(err_plain)
    # a registered pair stays where it was: the fit finds (almost) nothing to move
    again = LikelihoodStage(CAM, family="gaussian", register=True)(r1.float()[None, None], r2.float()[None, None],
                                                                   seed, conf)
    assert float(again.registration[0].abs().max()) < 0.05
