"""The lens's whole PSF from a focus sweep (tdfd.calibration.psf_model), its simplex minimiser,
its place in the camera file, and the likelihood stage told it (issue 19)."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest
import torch

import data_synth.psf
from tdfd import Camera
from tdfd.autofocus.evidence import sigma_px_per_dpt
from tdfd.calibration.nelder_mead import nelder_mead
from tdfd.calibration.psf_model import psf_model_from_frames
from tdfd.camera_file import CameraFile, check_psf_model, load_camera_file
from tdfd.capture import capture_session
from tdfd.capture.sim import SimulatedRig
from tdfd.cli import main
from tdfd.depth_cli import measured_psf_model
from tdfd.dfd.likelihood_stage import LikelihoodStage
from tdfd.dfd.psf_hypotheses import PsfHypothesis
from tdfd.errors import CameraError, InputError, NonFiniteError
from tdfd.optics.aberrated_psf import PSFModel
from tdfd.optics.render import defocus_uniform

CAM = Camera.preset("reference")
M = sigma_px_per_dpt(CAM)
GOOD = {"shape": 4.0, "diffraction_px": 0.0, "astigmatism": 0.1, "astigmatism_angle_rad": 0.5, "spherical": -0.2,
        "sigma_scale": 1.0}


def _sweep(lens: PSFModel, powers, focus: float = 2.2, size: int = 150, seed: int = 0, camera: Camera = CAM) -> list:
    """Noise-free frames of a random texture through ``lens`` (the camera's blur per dioptre)."""
    sharp = torch.rand(1, 1, size, size, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    m = sigma_px_per_dpt(camera)
    out = []
    for p in powers:
        k = lens.kernels(torch.tensor([m * (p - focus)], dtype=torch.float64), 25)[0]
        out.append((torch.nn.functional.conv2d(sharp, k[None, None])[0, 0].numpy(), p))
    return out


# ------------------------------------------------------------------ the PSF model and its hypothesis
def test_the_psf_model_lives_in_tdfd_and_data_synth_renders_with_it():
    assert data_synth.psf.PSFModel is PSFModel


def test_an_aberrated_hypothesis_has_the_renderers_kernels():
    h = PsfHypothesis(5.0, 0.4, 0.12, 1.0, 0.25)
    sigma = torch.tensor([-2.0, -0.7, 0.7, 2.0], dtype=torch.float64)
    size = h.kernel_size(2.0)
    assert size > PsfHypothesis(5.0, 0.4).kernel_size(2.0)  # the stretch needs room
    k = h.kernels(sigma, size)
    assert torch.equal(k, PSFModel(5.0, 0.4, 0.12, 1.0, 0.25).kernels(sigma, size))
    assert torch.allclose(k.sum((-1, -2)), torch.ones(4, dtype=torch.float64))
    # the astigmatism swaps axes across focus: +sigma and -sigma differ, unlike the plain profile's
    assert (k[3] - k[0]).abs().max() > 1e-3
    plain = PsfHypothesis(5.0, 0.4).kernels(sigma, size)
    assert torch.allclose(plain[3], plain[0])


def test_a_blur_scale_scales_the_camera_blur():
    h = PsfHypothesis("pillbox", sigma_scale=1.25)
    sigma = torch.tensor([1.6, -2.4], dtype=torch.float64)
    assert torch.allclose(h.kernels(sigma, 25), PsfHypothesis("pillbox").kernels(sigma * 1.25, 25))
    assert h.kernel_size(4.0) == PsfHypothesis("pillbox").kernel_size(5.0)
    with pytest.raises(InputError, match="sigma_scale"):
        PsfHypothesis(sigma_scale=0.1)
    with pytest.raises(InputError, match="astigmatism"):
        PsfHypothesis(astigmatism=0.5)


def test_the_psf_model_round_trips_through_the_camera_file(tmp_path):
    h = PsfHypothesis(4.0, 0.0, 0.1, 0.5, -0.2, 1.1)
    assert PsfHypothesis.from_dict(h.to_dict()) == h
    path = CameraFile(CAM, psf_model=h.to_dict()).write(tmp_path / "cam.json")
    assert json.loads(path.read_text())["psf_model"]["astigmatism_angle_rad"] == 0.5
    assert PsfHypothesis.from_dict(load_camera_file(path).psf_model) == h
    assert "psf_model" not in CameraFile(CAM).to_dict()
    assert PsfHypothesis.from_dict({**GOOD, "shape": "pillbox"}).shape == "pillbox"


@pytest.mark.parametrize("bad, word", [({k: v for k, v in GOOD.items() if k != "spherical"}, "keys"),
                                       ({**GOOD, "extra": 1}, "keys"), ({**GOOD, "shape": "disk"}, "shape"),
                                       ({**GOOD, "astigmatism": 0.6}, "range"),
                                       ({**GOOD, "spherical": math.nan}, "finite"),
                                       ({**GOOD, "shape": 0.5}, "range"), ({**GOOD, "sigma_scale": 9.0}, "range"),
                                       ({**GOOD, "astigmatism": True}, "finite"), ([1, 2], "mapping")])
def test_a_bad_psf_model_is_a_camera_error(tmp_path, bad, word):
    with pytest.raises(CameraError, match=word):
        check_psf_model(bad)
    path = tmp_path / "cam.json"
    path.write_text(json.dumps({**CAM.to_dict(), "psf_model": bad}))
    with pytest.raises(CameraError, match="cam.json"):
        load_camera_file(path)


# ------------------------------------------------------------------ the simplex
def test_the_simplex_finds_a_curved_valley_minimum():
    rosen = lambda x: float(100 * (x[1] - x[0] ** 2) ** 2 + (1 - x[0]) ** 2)  # noqa: E731
    res = nelder_mead(rosen, np.array([-1.2, 1.0]), np.array([0.5, 0.5]), max_evaluations=3000, x_tol=1e-7,
                      f_tol=1e-12)
    assert res.converged and np.allclose(res.x, [1.0, 1.0], atol=1e-4)
    # an infeasible region (inf) is walked around, not into
    res = nelder_mead(lambda x: math.inf if x[0] < 0.5 else float((x[0] - 0.2) ** 2), np.array([2.0]), np.array([0.3]))
    assert res.x[0] == pytest.approx(0.5, abs=1e-3)


def test_the_simplex_rejects_what_it_cannot_minimise():
    with pytest.raises(NonFiniteError, match="NaN"):
        nelder_mead(lambda x: math.nan if x[0] > 0.5 else 1.0, np.zeros(1), np.ones(1))
    with pytest.raises(NonFiniteError, match="start"):
        nelder_mead(lambda x: math.inf, np.zeros(2), np.ones(2))
    with pytest.raises(InputError, match="non-zero"):
        nelder_mead(lambda x: 0.0, np.zeros(2), np.array([1.0, 0.0]))
    with pytest.raises(InputError, match="max_evaluations"):
        nelder_mead(lambda x: 0.0, np.zeros(2), np.ones(2), max_evaluations=2)


# ------------------------------------------------------------------ the fit
def test_a_noise_free_sweep_gives_the_lens_back():
    """A disk-like profile with astigmatism and a negative spherical weight, its blur 1.2x the
    camera's: every parameter and the in-focus power come back."""
    lens = PSFModel(12.0, 0.0, 0.08, 2.5, -0.25)
    scaled = CAM.replace(mu_px_per_m=CAM.mu_px_per_m / 1.2)  # the camera a Gaussian-blur calibration gives
    frames = _sweep(lens, (1.6, 1.9, 2.2, 2.5, 2.8), seed=1)
    fit = psf_model_from_frames([frames], scaled, region=96)
    h = fit.hypothesis
    assert 8.0 < fit.beta < 20.0
    assert h.astigmatism == pytest.approx(0.08, abs=0.005) and h.astigmatism_angle == pytest.approx(2.5, abs=0.05)
    assert h.spherical == pytest.approx(-0.25, abs=0.03) and h.sigma_scale == pytest.approx(1.2, abs=0.02)
    assert fit.in_focus_power_dpt[0] == pytest.approx(2.2, abs=0.01)
    assert fit.family_cost_ratio > 10 and fit.to_dict()["diffraction_px"] == 0.0


def test_a_noisy_sweep_through_the_simulated_rig_measures_the_aberrations():
    """tdfd's own rig (12-bit, shot and read noise, black level): two frames averaged per power."""
    lens = PSFModel(5.0, 0.4, 0.12, 1.0, 0.25)
    rig = SimulatedRig(CameraFile(CAM), 0.5, size=(160, 160), seed=11, texture="bandlimited", psf=lens)
    centre, half = rig.in_focus_command_dpt(), 3.0 / M
    frames = [(rig.capture(p)[0].astype(float), p) for p in np.linspace(centre - half, centre + half, 7)
              for _ in range(2)]
    fit = psf_model_from_frames([frames], CAM, region=128, max_evaluations=300)
    h = fit.hypothesis
    assert h.astigmatism == pytest.approx(0.12, abs=0.02) and h.spherical == pytest.approx(0.25, abs=0.08)
    assert 3.0 < fit.beta < 9.0 and h.sigma_scale == pytest.approx(1.0, abs=0.05)
    assert fit.in_focus_power_dpt[0] == pytest.approx(centre, abs=0.05 / M)
    assert fit.family_cost_ratio > 1.5


def test_the_rig_renders_a_plain_psf_model_as_its_shape():
    a = SimulatedRig(CameraFile(CAM), 0.5, size=(64, 64), seed=2, psf="pillbox", noise=False)
    b = SimulatedRig(CameraFile(CAM), 0.5, size=(64, 64), seed=2, psf=PSFModel("pillbox"), noise=False)
    p = a.in_focus_command_dpt() + 1.0
    assert np.abs(a.capture(p)[0].astype(int) - b.capture(p)[0].astype(int)).max() <= 1


def test_the_fit_rejects_what_it_cannot_fit():
    frames = _sweep(PSFModel(), (1.8, 2.2, 2.6), size=128)
    with pytest.raises(InputError, match="at least 3 frames"):
        psf_model_from_frames([frames[:2] + [(frames[0][0], 1.8)]], CAM)  # two distinct powers
    with pytest.raises(InputError, match="at least 64"):
        psf_model_from_frames([frames], CAM, region=32)
    with pytest.raises(InputError, match="larger than the frames"):
        psf_model_from_frames([frames], CAM, region=256)
    with pytest.raises(InputError, match="one shape"):
        psf_model_from_frames([frames + [(np.zeros((64, 64)), 3.0)]], CAM, region=96)
    with pytest.raises(InputError, match="spans"):
        psf_model_from_frames([_sweep(PSFModel(), (0.0, 2.2, 4.4), size=128)], CAM, region=64)
    with pytest.raises(InputError, match="non-finite"):
        psf_model_from_frames([[(np.full((128, 128), np.nan), p) for _, p in frames]], CAM, region=96)


# ------------------------------------------------------------------ the stage told it
def test_the_stage_told_the_lens_fits_a_plane_the_profiled_shapes_miss():
    """An astigmatic, spherically aberrated lens: the stage told it reads the plane's depth; the
    same stage profiling the plain shapes does not come as close."""
    lens = PSFModel(4.0, 0.0, 0.15, 0.7, 0.3)
    depth = 0.5
    q = 1.0 / depth
    s1, s2 = (float(v) for v in (CAM.sigma_lines_px()[0][0] - CAM.sigma_lines_px()[0][1] * q,
                                 CAM.sigma_lines_px()[1][0] - CAM.sigma_lines_px()[1][1] * q))
    sharp = torch.rand(1, 1, 224, 224, generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    frames = [torch.nn.functional.conv2d(sharp, lens.kernels(torch.tensor([s], dtype=torch.float64), 25)[None],
                                         padding=12) for s in (s1, s2)]
    i1, i2 = (f[..., 16:208, 16:208].float() for f in frames)
    seed_d = torch.full((1, 1, 5, 5), depth * 1.03)
    conf = torch.full((1, 1, 5, 5), 0.5)
    told = LikelihoodStage(CAM, 64, 32, 0.01, hypotheses=(PsfHypothesis(4.0, 0.0, 0.15, 0.7, 0.3),))
    profiled = LikelihoodStage(CAM, 64, 32, 0.01)
    r_t, r_p = told(i1, i2, seed_d, conf), profiled(i1, i2, seed_d, conf)
    assert r_t.hypotheses[0] == told.hypotheses[0]
    fitted = r_t.fitted[0, 0]
    err_t = (r_t.depth_fit[0, 0][fitted] / depth - 1).abs().max()
    err_p = (r_p.depth_fit[0, 0][fitted] / depth - 1).abs().median()
    assert err_t < 0.002 and err_p > 2 * err_t
    with pytest.raises(InputError, match="PsfHypothesis"):
        LikelihoodStage(CAM, hypotheses=("gaussian",))
    with pytest.raises(InputError, match="PsfHypothesis"):
        LikelihoodStage(CAM, hypotheses=())


def test_depth_takes_the_psf_model_only_from_a_file_that_has_one(tmp_path):
    CameraFile(CAM).write(tmp_path / "plain.json")
    with pytest.raises(CameraError, match="tdfd calibrate .* --psf-model"):
        measured_psf_model(str(tmp_path / "plain.json"))
    CameraFile(CAM, psf_model=GOOD).write(tmp_path / "cam.json")
    assert measured_psf_model(str(tmp_path / "cam.json")) == GOOD
    f = tmp_path / "f.png"
    cv2.imwrite(str(f), np.full((64, 64), 30000, np.uint16))
    assert main(["depth", str(f), str(f), "--psf-model", str(tmp_path / "cam.json")]) == 1  # needs the stage


def test_calibrate_measures_and_writes_the_psf_model(tmp_path):
    """tdfd capture (an aberrated simulated lens, a chart swept through focus) -> tdfd calibrate
    --psf-model: the camera file holds the lens's aberrations."""
    lens = PSFModel(5.0, 0.0, 0.1, 2.0, -0.2)
    rig = SimulatedRig(CameraFile(CAM), 0.5, size=(160, 160), seed=5, texture="bandlimited", psf=lens)
    centre, half = rig.in_focus_command_dpt(), 2.5 / M
    powers = [float(p) for p in np.linspace(centre - half, centre + half, 9)]
    capture_session(rig, tmp_path / "sweep", sweep=powers, pairs=[CAM.lens_powers_dpt])
    (tmp_path / "nominal.json").write_text(json.dumps(CAM.to_dict()))
    base = ["calibrate", str(tmp_path / "sweep"), "--camera", str(tmp_path / "nominal.json"), "--no-plot", "-o"]
    assert main(base + [str(tmp_path / "cam.json"), "--psf-model"]) == 0
    cal = load_camera_file(tmp_path / "cam.json")
    h = PsfHypothesis.from_dict(cal.psf_model)
    assert h.astigmatism == pytest.approx(0.1, abs=0.03) and h.spherical < -0.05
    assert cal.calibration["psf_model"]["regions"] >= 1
    assert main(base + [str(tmp_path / "plain.json")]) == 0
    assert load_camera_file(tmp_path / "plain.json").psf_model is None


def test_a_sweep_that_does_not_bracket_focus_is_refused():
    frames = _sweep(PSFModel(), (1.0, 1.2, 1.4, 1.6), focus=2.2, size=128)  # all on one side of focus
    with pytest.raises(InputError, match="bracket focus"):
        psf_model_from_frames([frames], CAM, region=96)


def test_the_psf_plot_draws_the_measured_kernels(tmp_path):
    from tdfd.calibration.plot import plot_psf_model
    from tdfd.calibration.psf_model import PsfModelFit

    fit = PsfModelFit(PsfHypothesis(4.0, 0.0, 0.1, 0.5, -0.2, 1.1), 1.0, 3.0, [2.2], 1, 7, 100, True)
    png = plot_psf_model(fit, tmp_path / "cam_psf.png")
    image = cv2.imread(str(png))
    assert image is not None and image.shape[0] > 200 and image.std() > 10


def test_a_psf_wider_than_the_tile_is_truncated_not_a_crash():
    """An aberrated disk at twice the camera's blur needs kernels beyond the 64-px tile at the
    working range's far end: the stage truncates them (below the tile) and fits."""
    from tdfd.dfd.seeded_fit import inverse_depth_grid, kernel_side

    wide = PsfHypothesis("pillbox", 0.0, 0.45, 0.0, 0.45, 2.0)
    grid = inverse_depth_grid(CAM, 0.05, 0.002)
    assert kernel_side(CAM, [wide], grid, 65) == 65 and kernel_side(CAM, [wide], grid, 65, 64) == 63
    g = torch.Generator().manual_seed(0)
    i1, i2 = torch.rand(1, 1, 192, 192, generator=g), torch.rand(1, 1, 192, 192, generator=g)
    out = LikelihoodStage(CAM, 64, 32, 0.01, hypotheses=(wide,))(i1, i2, torch.full((1, 1, 5, 5), 0.35),
                                                                 torch.full((1, 1, 5, 5), 0.5))
    assert torch.isfinite(out.depth).all()
