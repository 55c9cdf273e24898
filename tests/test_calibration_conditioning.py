"""Conditioning of the mu calibration: a pair that blurs both frames equally measures no mu.

The closed forms here are typed in from the thin lens (paper eqs. 3-4): for an ECVFL pair
(one aperture, one sensor distance) ``r_j = c (q - q_j)`` with ``q = 1/d`` and ``q_j`` the
inverse distance frame ``j`` focuses, so ``r_1^2 - r_2^2 = c^2 (q_2 - q_1)(2q - q_1 - q_2)``
vanishes at ``q_eq = (q_1 + q_2)/2`` and ``|a'/a| = 1 / |q - q_eq|``.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from tdfd import Camera
from tdfd.calibration import calibrate_known_distance
from tdfd.calibration.fit import CalibrationError, k_relative_uncertainty
from tdfd.camera_file import CameraFile
from tdfd.capture import capture_session, read_folder
from tdfd.capture.sim import SimulatedRig
from tdfd.cli import main
from tdfd.dfd.calibrate import (PAIR_POWER_SD_DPT, calibrate_mu, equal_blur_distance_m, ill_conditioned_range_m,
                                mu_relative_uncertainty)
from tdfd.errors import InputError
from tdfd.optics import render_pair

REF = Camera.preset("reference")
Q_EQ_REF = (1.7 + 2.7) / 2  # reference camera: 0 dpt focuses at infinity, so frame j focuses at q_j = P_j


def test_equal_blur_distance_is_the_midpoint_of_the_focus_powers() -> None:
    assert equal_blur_distance_m(REF) == pytest.approx(1 / Q_EQ_REF, rel=1e-6)
    paper = Camera.preset("paper")  # F1 = 9.30 cm, F2 = 8.63 cm, d_s = 9.8 cm
    q1, q2 = 1 / 0.0930 - 1 / 0.098, 1 / 0.0863 - 1 / 0.098
    assert equal_blur_distance_m(paper) == pytest.approx(2 / (q1 + q2), rel=1e-4)


@pytest.mark.parametrize("depth", [0.30, 0.40, 0.46, 0.50, 1.0])
def test_mu_uncertainty_of_one_pair_matches_the_closed_form(depth: float) -> None:
    expected = 0.5 * PAIR_POWER_SD_DPT / abs(1 / depth - Q_EQ_REF)
    assert mu_relative_uncertainty(REF, [depth]) == pytest.approx(expected, rel=1e-4)


def test_more_distances_condition_the_fit_better() -> None:
    one = mu_relative_uncertainty(REF, [0.46])
    assert one > 0.05  # the paper's 46 cm is 0.026 dpt from this camera's midpoint
    assert mu_relative_uncertainty(REF, [0.46, 0.30]) < 0.05 < one
    assert mu_relative_uncertainty(REF, [0.30], power_sd_dpt=0.01) == pytest.approx(
        2 * mu_relative_uncertainty(REF, [0.30]), rel=1e-9)
    with pytest.raises(InputError, match="power_sd_dpt"):
        mu_relative_uncertainty(REF, [0.3], power_sd_dpt=0.0)
    with pytest.raises(InputError, match="one weight per distance"):
        mu_relative_uncertainty(REF, [0.3, 0.4], weights=[1.0])


def test_ill_conditioned_range_brackets_the_midpoint() -> None:
    near, far = ill_conditioned_range_m(REF, 0.05)
    # one pair is refused where 0.5 sd / |q - q_eq| > 0.05, i.e. |q - q_eq| < 0.05 dpt
    assert 1 / near == pytest.approx(Q_EQ_REF + 0.05, abs=1e-6)
    assert 1 / far == pytest.approx(Q_EQ_REF - 0.05, abs=1e-6)


def _pair(depth: float, extra_blur_px2: float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
    """A random texture's pair at ``depth``; ``extra_blur_px2``: frame 2 blurred by that much more
    variance (an additive bias of ``D``, as a residual misregistration or a noise model leaves)."""
    x = torch.rand(1, 1, 160, 160, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    i1, i2 = render_pair(REF, x, torch.full_like(x, depth))
    if extra_blur_px2 > 0:  # the 3-tap kernel (v/2, 1 - v, v/2) has variance v per axis
        k = torch.tensor([extra_blur_px2 / 2, 1 - extra_blur_px2, extra_blur_px2 / 2], dtype=torch.float64)
        i2 = torch.nn.functional.conv2d(torch.nn.functional.pad(i2, (1, 1, 1, 1), mode="reflect"),
                                        (k[:, None] * k[None, :])[None, None])
    return i1[..., 16:-16, 16:-16].float(), i2[..., 16:-16, 16:-16].float()


def test_calibrate_mu_refuses_the_equal_blur_distance_and_the_refusal_is_real() -> None:
    i1, i2 = _pair(0.46)
    with pytest.raises(InputError, match=r"0\.4545 m.*outside 0\.444-0\.465 m"):
        calibrate_mu(REF, [(i1, i2, 0.46)], tile=128)
    # what the refusal protects from: a D bias of 0.05 px^2 (frame 2 a little more blurred) moves
    # mu by 0.5 dD / D: about 9 % at 46 cm (D = -0.29 px^2), 0.2 % at 30 cm (D = -12.6 px^2)
    shift = {}
    for depth in (0.46, 0.30):
        clean, biased = (calibrate_mu(REF, [(*_pair(depth, v), depth)], tile=128, max_relative_uncertainty=None)
                         for v in (0.0, 0.05))
        shift[depth] = abs(biased / clean - 1)
    assert shift[0.46] > 0.05 and shift[0.30] < 0.005, shift
    assert calibrate_mu(REF, [(*_pair(0.30), 0.30)], tile=128) == pytest.approx(REF.mu_px_per_m, rel=0.01)
    with pytest.raises(InputError, match="at least one"):
        calibrate_mu(REF, [], tile=128)


def test_k_uncertainty_of_the_known_distance_design() -> None:
    assert k_relative_uncertainty(np.array([[0.05]]), 0.005) == pytest.approx(0.1)
    assert k_relative_uncertainty(np.array([[0.05], [-0.05]]), 0.005) == pytest.approx(0.1 / math.sqrt(2))
    x = np.array([[1.0, -2.0], [-1.0, -2.0], [0.5, -2.0]])
    assert k_relative_uncertainty(x, 0.01) == pytest.approx(0.01 * math.sqrt(np.linalg.inv(x.T @ x)[0, 0]))
    assert k_relative_uncertainty(np.array([[0.0]]), 0.01) == math.inf


# the e2e test's camera (tests/test_calibrate_e2e.py): no preset, an ECVFL offset the datasheet lacks
PITCH = 3.45e-6
NOMINAL = Camera(aperture_m=1.6e-3, sensor_distance_m=16e-3, fixed_focal_length_m=16e-3, lens_powers_dpt=(1.5, 2.5),
                 pixel_pitch_m=PITCH, depth_range_m=(0.3, 1.0), mu_px_per_m=1 / (2 * PITCH), name="nominal")
TRUE = CameraFile(NOMINAL.replace(mu_px_per_m=1.15 / (2 * PITCH)), magnification_per_dpt=0.004, ecvfl_offset_dpt=0.3)


@pytest.fixture(scope="module")
def centred(tmp_path_factory):  # noqa: ANN201
    """A known-distance folder whose one pair sits 0.02 dpt off the target's focus as the datasheet
    predicts it (with one distance the route takes the in-focus offset from the datasheet)."""
    root = tmp_path_factory.mktemp("centred")
    rig = SimulatedRig(TRUE, 0.5, size=(256, 256), seed=3)
    c = float(NOMINAL.in_focus_power_dpt(0.5)) + 0.02
    capture_session(rig, root / "known", pairs=[(c - 0.5, c + 0.5)], distance_m=0.5)
    (root / "nominal.json").write_text(json.dumps(NOMINAL.to_dict()))
    return root


def test_known_distance_route_refuses_a_pair_centred_on_focus(centred) -> None:
    frames = read_folder(centred / "known")
    with pytest.raises(CalibrationError, match=r"leave mu uncertain by .* blurs both frames equally"):
        calibrate_known_distance(frames, CameraFile(NOMINAL))
    r = calibrate_known_distance(frames, CameraFile(NOMINAL), max_mu_uncertainty=None)
    assert r.camera_file.calibration["mu_relative_uncertainty"] > 0.05


def test_calibrate_cli_says_why_in_one_line(centred, tmp_path, capsys) -> None:
    args = ["calibrate", str(centred / "known"), "--camera", str(centred / "nominal.json"), "-o", str(tmp_path / "c.json")]
    assert main(args) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "leave mu uncertain" in err[0], err
    assert not (tmp_path / "c.json").exists()
    assert main(args + ["--max-mu-uncertainty", "0.9", "--no-plot"]) == 0
    assert "mu standard uncertainty" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        main(args + ["--max-mu-uncertainty", "2"])
