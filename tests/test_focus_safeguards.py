"""Safeguards against declaring a wrong focus that no blur model can make (issue 20): the
sharpness order of a run's frames, a contrast peak that must be bracketed, and lens steps
that must stay within the powers that focus the camera's depth range."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tdfd.autofocus import declaration
from tdfd.autofocus.contrast import ContrastController
from tdfd.autofocus.dfd import DFDController
from tdfd.autofocus.evidence import FocusCheck, working_powers_dpt
from tdfd.autofocus.machine import drive
from tdfd.autofocus.sharpness_order import sharpness_bracket
from tdfd.errors import InputError
from tests.test_autofocus_controller import CAM, TRUE_DEPTH, FakePlant, _blur_px


def _box(x: np.ndarray, k: int) -> np.ndarray:
    return sum(np.roll(x, (i, j), (0, 1)) for i in range(k) for j in range(k)) / k**2


SCENE = np.random.default_rng(3).random((96, 96))


def test_the_sharper_frame_holds_focus_on_its_side_of_the_midpoint():
    lo, hi = sharpness_bracket([(_box(SCENE, 1), 2.0), (_box(SCENE, 4), 3.0)])
    assert (lo, hi) == (-math.inf, 2.5)
    lo, hi = sharpness_bracket([(_box(SCENE, 4), 2.0), (_box(SCENE, 1), 3.0)])
    assert (lo, hi) == (2.5, math.inf)
    # three frames: the sharpest in the middle brackets focus on both sides
    lo, hi = sharpness_bracket([(_box(SCENE, 5), 1.0), (_box(SCENE, 1), 2.0), (_box(SCENE, 3), 2.6)])
    assert (lo, hi) == pytest.approx((1.8, 2.3))  # 2.6 is sharper than 1.0 too


def test_frames_that_do_not_compare_leave_focus_open():
    same = [(SCENE, 2.0), (SCENE * 1.0, 3.0)]  # equally sharp: within the margin
    assert sharpness_bracket(same) == (-math.inf, math.inf)
    close = [(_box(SCENE, 1), 2.0), (_box(SCENE, 4), 2.01)]  # closer in power than 0.02 dpt
    assert sharpness_bracket(close) == (-math.inf, math.inf)
    assert sharpness_bracket(close, min_separation_dpt=0.005)[1] == pytest.approx(2.005)


def test_a_contradictory_order_allows_no_power():
    """The middle frame less sharp than both outer ones (contrast reversal): no power satisfies all."""
    lo, hi = sharpness_bracket([(_box(SCENE, 2), 1.0), (_box(SCENE, 5), 2.0), (_box(SCENE, 2), 3.0)])
    assert lo > hi


def test_sharpness_bracket_rejects_bad_input():
    with pytest.raises(InputError, match="finite"):
        sharpness_bracket([(SCENE, math.nan), (SCENE, 1.0)])
    with pytest.raises(InputError, match="margin"):
        sharpness_bracket([(SCENE, 1.0)], margin=-0.1)


def test_working_powers_span_the_depth_range():
    lo, hi = working_powers_dpt(CAM, margin_dpt=0.0)
    near, far = CAM.depth_range_m
    assert lo == pytest.approx(CAM.in_focus_power_dpt(far)) and hi == pytest.approx(CAM.in_focus_power_dpt(near))
    assert working_powers_dpt(CAM) == pytest.approx((lo - 0.15, hi + 0.15))


def test_a_contrast_peak_at_the_edge_of_its_span_is_scanned_past():
    """A search around a power 0.9 dpt from focus (span +-0.6 dpt): its sharpest frame is at the
    span's edge, so the scan goes on outwards and finds the peak; without the extension it
    declares the edge, well out of focus."""
    true_power = CAM.in_focus_power_dpt(TRUE_DEPTH)
    span = (true_power + 0.3, true_power + 1.5)
    res = drive(ContrastController(CAM, span_dpt=span), FakePlant(TRUE_DEPTH))
    assert res.status == "focused" and _blur_px(TRUE_DEPTH, res.power_dpt) < 0.5
    edge = drive(ContrastController(CAM, span_dpt=span, extend=False), FakePlant(TRUE_DEPTH))
    assert edge.power_dpt == pytest.approx(span[0]) and _blur_px(TRUE_DEPTH, edge.power_dpt) > 0.7
    assert res.frames > edge.frames


def test_a_bracketed_peak_is_not_extended():
    true_power = CAM.in_focus_power_dpt(TRUE_DEPTH)
    span = (true_power - 0.6, true_power + 0.6)
    res = drive(ContrastController(CAM, span_dpt=span), FakePlant(TRUE_DEPTH))
    plain = drive(ContrastController(CAM, span_dpt=span, extend=False), FakePlant(TRUE_DEPTH))
    assert res.frames == plain.frames and res.power_dpt == pytest.approx(plain.power_dpt)


def test_a_step_outside_the_working_powers_is_not_taken():
    """A target nearer than the camera's range: the verification frame's error points to a power
    that focuses no target of the range, so no further step goes there (and nothing is declared)."""
    near = 0.26
    assert CAM.in_focus_power_dpt(near) > working_powers_dpt(CAM)[1]
    res = drive(DFDController(CAM, fallback=False), FakePlant(near, scripted=(0.32, 0.05)))
    assert res.status == "unconfirmed" and res.refine_count == 0
    assert "leaves the working powers" in res.fallback_reason
    assert res.power_dpt <= working_powers_dpt(CAM)[1]


def _misled(error_dpt: float, passed: bool):
    """A stand-in for the relative blur misled by a disk PSF on a periodic texture: it reports
    ``error_dpt`` with a tight uncertainty, consistent references, whatever the frames show."""
    def verify_focus(frame, power_dpt, references, camera, roi=None, **kw):
        est = tuple((p, error_dpt, 0.01) for _, p in references) + ((power_dpt, error_dpt, 0.01),)
        return FocusCheck(passed, error_dpt, 0.01, True, est, None if passed else f"focus error {error_dpt:+.3f}")
    return verify_focus


def test_a_verification_the_sharpness_order_contradicts_does_not_pass(monkeypatch):
    """The estimate is 0.6 dpt off and a misled verification 'passes' it: the verification
    frame is visibly less sharp than the DFD pair's frame nearer focus, so focus is not declared."""
    wrong = 1.0 / (1.0 / TRUE_DEPTH - 0.6)
    monkeypatch.setattr(declaration, "verify_focus", _misled(0.0, passed=True))
    res = drive(DFDController(CAM, fallback=False, refine_steps=0, cross_blur=False),
                FakePlant(TRUE_DEPTH, scripted=(wrong, 0.05)))
    assert _blur_px(TRUE_DEPTH, CAM.in_focus_power_dpt(wrong)) > 1.5
    assert res.status == "unconfirmed" and res.verified is False
    assert "sharpness order" in res.fallback_reason
    # the three frames' cross-blur focus then finds the focus the misled relative blur missed
    res = drive(DFDController(CAM, fallback=False, refine_steps=0), FakePlant(TRUE_DEPTH, scripted=(wrong, 0.05)))
    assert res.status == "focused" and res.evidence == "refined" and res.frames == 3 and res.cross_blur_measurements == 1
    assert _blur_px(TRUE_DEPTH, res.power_dpt) < 0.3


def test_a_three_frame_estimate_the_sharpness_order_contradicts_is_not_declared(monkeypatch):
    """A misled verification puts focus a further 0.3 dpt away from the truth: the three-frame
    estimate would declare there; the frames' sharpness order rules that power out."""
    wrong = 1.0 / (1.0 / TRUE_DEPTH - 0.6)
    monkeypatch.setattr(declaration, "verify_focus", _misled(+0.3, passed=False))
    res = drive(DFDController(CAM, fallback=False, refine_steps=0, refine_max_uncertainty_px=0.0, cross_blur=False),
                FakePlant(TRUE_DEPTH, scripted=(wrong, 0.05)))
    assert res.evidence != "refined" and res.status == "unconfirmed"
    # the same run with the order check's frames all equally sharp would declare: the check is what stops it
    monkeypatch.setattr(declaration, "sharpness_bracket", lambda frames, roi=None: (-math.inf, math.inf))
    res = drive(DFDController(CAM, fallback=False, refine_steps=0, refine_max_uncertainty_px=0.0, cross_blur=False),
                FakePlant(TRUE_DEPTH, scripted=(wrong, 0.05)))
    assert res.evidence == "refined" and _blur_px(TRUE_DEPTH, res.power_dpt) > 1.5


def test_the_cross_blur_focus_vetoes_a_three_frame_estimate_it_disagrees_with(monkeypatch):
    """A misled relative blur puts the 3-frame estimate 0.3 dpt further from focus; the cross-blur
    focus, unsure (here: at its span's edge) but elsewhere, does not confirm it: not declared. Sure
    (the real search on these frames), the cross-blur focus itself is declared, in focus."""
    from tdfd.autofocus.cross_blur import CrossBlurFocus

    wrong = 1.0 / (1.0 / TRUE_DEPTH - 0.6)
    monkeypatch.setattr(declaration, "verify_focus", _misled(+0.3, passed=False))
    monkeypatch.setattr(declaration, "sharpness_bracket", lambda frames, roi=None: (-math.inf, math.inf))
    kw = dict(fallback=False, refine_steps=0, refine_max_uncertainty_px=0.0)
    res = drive(DFDController(CAM, **kw), FakePlant(TRUE_DEPTH, scripted=(wrong, 0.05)))
    assert res.evidence == "refined" and _blur_px(TRUE_DEPTH, res.power_dpt) < 0.3 and res.cross_blur_measurements == 1
    unsure = CrossBlurFocus(CAM.in_focus_power_dpt(TRUE_DEPTH), "gaussian", True, 1.0)
    monkeypatch.setattr(declaration, "cross_blur_focus", lambda *a, **k: unsure)
    res = drive(DFDController(CAM, **kw), FakePlant(TRUE_DEPTH, scripted=(wrong, 0.05)))
    assert res.evidence != "refined" and res.status == "unconfirmed"
    res = drive(DFDController(CAM, cross_blur=False, **kw), FakePlant(TRUE_DEPTH, scripted=(wrong, 0.05)))
    assert res.evidence == "refined" and _blur_px(TRUE_DEPTH, res.power_dpt) > 1.5  # what the veto prevents
    with pytest.raises(InputError, match="cross_blur_family_ratio"):
        DFDController(CAM, cross_blur_family_ratio=0.5)


@pytest.mark.parametrize("depth", [0.33, 0.45, 0.8])
def test_no_model_opinion_on_a_textured_roi_uses_the_pairs_own_relative_blur(depth):
    """The model answers confidence 0.001 (below min_confidence) on a textured ROI: the lens
    goes to the in-focus power of the pair's own relative blur and verification frames decide
    (method dfd), with no contrast search and within 4 frames."""
    res = drive(DFDController(CAM), FakePlant(depth, scripted=(0.6, 0.001)))
    assert res.status == "focused" and res.method == "dfd" and res.evidence in ("verification", "refined")
    assert res.frames <= 4 and res.verified is not None
    assert "confidence" in (res.fallback_reason or "")
    assert _blur_px(depth, res.power_dpt) < 0.8


def test_without_the_pair_fallback_or_a_verification_the_contrast_search_decides():
    """``pair_fallback=False``, or ``verify='never'`` (no evidence for a model-free estimate):
    the contrast search, as before."""
    for ctrl in (DFDController(CAM, pair_fallback=False), DFDController(CAM, verify="never")):
        res = drive(ctrl, FakePlant(0.45, scripted=(0.6, 0.001)))
        assert res.method == "contrast" and res.frames > 4


def test_a_confident_estimate_beyond_the_depth_range_is_verified():
    """The model's confidence is calibrated on the camera's depth range only: a confident
    estimate beyond it (an extrapolation) costs a verification frame instead of a 2-frame
    declaration; the same confidence inside the range declares at 2 frames."""
    near, far = CAM.depth_range_m
    inside = drive(DFDController(CAM), FakePlant(0.97 * far, scripted=(0.97 * far, 0.95)))
    assert inside.evidence == "uncertainty" and inside.frames == 2
    beyond = drive(DFDController(CAM), FakePlant(0.97 * far, scripted=(1.05 * far, 0.95)))
    assert beyond.evidence != "uncertainty" and beyond.frames >= 3 and beyond.verified is not None
    assert beyond.status == "focused" and _blur_px(0.97 * far, beyond.power_dpt) < 1.0
    lo, hi = working_powers_dpt(CAM, margin_dpt=0.0)
    assert not lo <= CAM.in_focus_power_dpt(1.05 * far) <= hi


def test_the_pair_fallback_needs_a_texture_well_above_the_noise():
    """Below ``pair_min_texture_snr`` (here set above the plant's texture) the pair's own estimate
    is not tried: the contrast search decides; a negative threshold is refused."""
    strong = drive(DFDController(CAM), FakePlant(0.45, scripted=(0.6, 0.001)))
    assert strong.method == "dfd" and strong.texture_snr > 3.0
    res = drive(DFDController(CAM, pair_min_texture_snr=10 * strong.texture_snr), FakePlant(0.45, scripted=(0.6, 0.001)))
    assert res.method == "contrast"
    with pytest.raises(InputError, match="pair_min_texture_snr"):
        DFDController(CAM, pair_min_texture_snr=-1.0)


def test_cross_blur_focus_finds_the_power_and_the_family():
    """Frames rendered through a Gaussian and through a disk of the same RMS radius: the search
    recovers the in-focus power within 0.05 dpt (the rendered disk is antialiased, the model's is not)
    and names the family; J1 matches its integral."""
    from tdfd.autofocus.cross_blur import bessel_j1, cross_blur_focus

    x = np.linspace(0.0, 30.0, 121)
    tau = np.linspace(0.0, math.pi, 4001)
    ref = np.trapezoid(np.cos(tau[None, :] - x[:, None] * np.sin(tau[None, :])), tau, axis=1) / math.pi
    assert np.abs(bessel_j1(x) - ref).max() < 1e-6
    import torch

    from tdfd.optics.render import render_at_power

    rng = np.random.default_rng(7)
    sharp = torch.from_numpy(rng.random((128, 160)).astype(np.float32))[None, None]
    for depth, shape in ((0.45, "gaussian"), (0.6, "pillbox")):
        d = torch.full_like(sharp, depth)
        truth = CAM.in_focus_power_dpt(depth)
        frames = [(render_at_power(CAM, sharp, d, p, shape=shape)[0, 0].numpy().astype(np.float64), p)
                  for p in (1.7, 2.7, truth + 0.25)]
        est = cross_blur_focus(frames, CAM)
        assert abs(est.power_dpt - truth) < 0.05 and est.shape == shape and not est.at_edge  # 0.14 px
    with pytest.raises(InputError, match="two frames"):
        cross_blur_focus(frames[:1], CAM)
    with pytest.raises(InputError, match="shapes"):
        cross_blur_focus(frames, CAM, shapes=("cauchy",))



def _noisy_frames(texture: float, noise: float, seed: int) -> tuple[list, float]:
    import torch

    from tdfd.optics.render import render_at_power

    rng = np.random.default_rng(seed)
    sharp = torch.from_numpy((0.5 + texture * (rng.random((96, 128)) - 0.5)).astype(np.float32))[None, None]
    depth = float(rng.uniform(0.32, 0.95))
    truth = CAM.in_focus_power_dpt(depth)
    frames = [(render_at_power(CAM, sharp, torch.full_like(sharp, depth), p, shape="gaussian")[0, 0].numpy()
               .astype(np.float64) + rng.normal(0.0, noise, (96, 128)), p) for p in (1.7, 2.7, truth + 0.25)]
    return frames, truth


def test_the_cross_blur_contrast_tells_a_texture_from_noise():
    """A texture well above the noise singles the in-focus power out (contrast over 1, found
    within 0.05 dpt); a texture at a tenth of the noise leaves the cost flat (contrast under
    0.1). A negative minimum is refused."""
    from tdfd.autofocus.cross_blur import cross_blur_focus

    for seed in range(3):
        frames, truth = _noisy_frames(1.0, 0.01, seed)
        strong = cross_blur_focus(frames, CAM)
        assert strong.contrast > 1.0 and abs(strong.power_dpt - truth) < 0.05
        weak = cross_blur_focus(_noisy_frames(0.002, 0.02, seed)[0], CAM)
        assert weak.contrast < 0.1
    with pytest.raises(InputError, match="cross_blur_min_contrast"):
        DFDController(CAM, cross_blur_min_contrast=-0.1)


def test_a_flat_cross_blur_focus_is_not_sure(monkeypatch):
    """After a failed verification the cross-blur focus, right and otherwise sure, is the
    3-frame estimate with a contrast of 0.5, and not with a flat one (0.05): the misled
    relative-blur estimate it disagrees with is vetoed and nothing is declared."""
    from tdfd.autofocus.cross_blur import CrossBlurFocus

    wrong = 1.0 / (1.0 / TRUE_DEPTH - 0.6)
    monkeypatch.setattr(declaration, "verify_focus", _misled(+0.3, passed=False))
    monkeypatch.setattr(declaration, "sharpness_bracket", lambda frames, roi=None: (-math.inf, math.inf))
    kw = dict(fallback=False, refine_steps=0, refine_max_uncertainty_px=0.0)
    for contrast, declared in ((0.5, True), (0.05, False)):
        focus = CrossBlurFocus(CAM.in_focus_power_dpt(TRUE_DEPTH), "gaussian", False, 1.0, contrast=contrast)
        monkeypatch.setattr(declaration, "cross_blur_focus", lambda *a, focus=focus, **k: focus)
        res = drive(DFDController(CAM, **kw), FakePlant(TRUE_DEPTH, scripted=(wrong, 0.05)))
        assert (res.evidence == "refined") == declared and (res.status == "focused") == declared
        if declared:
            assert _blur_px(TRUE_DEPTH, res.power_dpt) < 0.1


@pytest.mark.parametrize("depth", [0.35, 0.7])
def test_no_pair_relative_blur_the_pairs_cross_blur_focus_is_verified(monkeypatch, depth):
    """No model opinion and no usable relative blur from the pair (forced): the lens goes to the
    pair's own cross-blur focus and the frames there decide, in focus within 3 frames, without
    a contrast search. With the cross-blur off, the contrast search decides."""
    def unusable(*a, **k):
        raise InputError("forced: no relative blur")

    monkeypatch.setattr(declaration, "pair_focus_interval", unusable)
    res = drive(DFDController(CAM), FakePlant(depth, scripted=(0.6, 0.001)))
    assert res.method == "dfd" and res.status == "focused" and res.frames <= 3
    assert res.evidence in ("verification", "refined") and res.cross_blur_measurements >= 1
    assert _blur_px(depth, res.power_dpt) < 0.8
    res = drive(DFDController(CAM, cross_blur=False), FakePlant(depth, scripted=(0.6, 0.001)))
    assert res.method == "contrast"


def test_a_three_frame_estimate_must_confirm_the_pairs_cross_blur_focus(monkeypatch):
    """The pair's cross-blur focus (forced 0.4 dpt off, 1.9 px) and the three frames' (right)
    disagree: without a model to arbitrate, the three-frame estimate is not declared and the
    contrast search decides. Where the two agree, the three-frame estimate is declared."""
    from tdfd.autofocus.cross_blur import CrossBlurFocus

    truth = CAM.in_focus_power_dpt(0.5)
    monkeypatch.setattr(declaration, "pair_focus_interval", lambda *a, **k: (math.nan, math.nan))
    monkeypatch.setattr(declaration, "verify_focus", _misled(+0.4, passed=False))
    for pair_off, declared in ((0.4, False), (0.05, True)):
        monkeypatch.setattr(declaration, "cross_blur_focus", lambda frames, *a, off=pair_off, **k: CrossBlurFocus(
            truth + (off if len(frames) == 2 else 0.0), "gaussian", False, 1.0, contrast=5.0))
        res = drive(DFDController(CAM, refine_steps=0), FakePlant(0.5, scripted=(0.6, 0.001)))
        assert res.cross_blur_measurements == 2 and (res.evidence == "refined") == declared
        assert res.method == ("dfd" if declared else "contrast") and res.status == "focused"


def test_the_tabulated_disk_otf_matches_j1():
    """The disk OTF the search uses (``2 J1(a)/a`` tabulated, linear interpolation) matches the
    closed form within 1e-6 inside the table, exactly beyond it, and is 1 at zero frequency."""
    from tdfd.autofocus.cross_blur import bessel_j1, disk_otf

    f = np.linspace(0.0, 0.75, 3001)
    for radius in (0.3, 2.0, 11.7, 84.0, 120.0):  # 2 pi R f_max: 1.4 .. 565 (past the table's 400)
        a = 2.0 * math.pi * radius * f
        exact = np.where(a > 0, 2.0 * bessel_j1(np.where(a > 0, a, 1.0)) / np.where(a > 0, a, 1.0), 1.0)
        assert np.abs(disk_otf(radius, f) - exact).max() < 1e-6, radius
    assert disk_otf(5.0, np.zeros(3)).tolist() == [1.0, 1.0, 1.0]


def test_a_verification_the_cross_blur_focus_contradicts_does_not_pass(monkeypatch):
    """A misled verification 'passes' an estimate 0.35 dpt off (1.7 px) that the sharpness order
    (disabled here) does not rule out: the three frames' sure cross-blur focus lies elsewhere, so
    the verification does not pass and the cross-blur focus is the 3-frame estimate, in focus.
    Without the cross-blur focus the misled pass is declared out of focus."""
    wrong = 1.0 / (1.0 / TRUE_DEPTH - 0.35)
    monkeypatch.setattr(declaration, "verify_focus", _misled(0.0, passed=True))
    monkeypatch.setattr(declaration, "sharpness_bracket", lambda frames, roi=None: (-math.inf, math.inf))
    kw = dict(fallback=False, refine_steps=0)
    res = drive(DFDController(CAM, cross_blur=False, **kw), FakePlant(TRUE_DEPTH, scripted=(wrong, 0.05)))
    assert res.evidence == "verification" and _blur_px(TRUE_DEPTH, res.power_dpt) > 1.5  # what the check prevents
    res = drive(DFDController(CAM, **kw), FakePlant(TRUE_DEPTH, scripted=(wrong, 0.05)))
    assert res.verified is False and res.evidence == "refined" and res.frames == 3 and res.cross_blur_measurements == 1
    assert _blur_px(TRUE_DEPTH, res.power_dpt) < 0.3


def test_a_clear_disk_fit_outweighs_the_sharpness_order(monkeypatch):
    """A disk's MTF has zeros and reversals, so on a periodic texture a blurrier frame can look
    sharper and the sharpness order can exclude the true focus. A cross-blur focus that a disk
    fits 1.5x better than any Gaussian is sure outside that order (declared, in focus); the same
    focus fitted as a Gaussian, or a disk fit less clear, is not (nothing declared)."""
    from tdfd.autofocus.cross_blur import CrossBlurFocus

    truth = CAM.in_focus_power_dpt(TRUE_DEPTH)
    wrong = 1.0 / (1.0 / TRUE_DEPTH - 0.6)
    monkeypatch.setattr(declaration, "verify_focus", _misled(+0.3, passed=False))
    monkeypatch.setattr(declaration, "sharpness_bracket", lambda frames, roi=None: (truth + 0.3, truth + 0.9))
    kw = dict(fallback=False, refine_steps=0, refine_max_uncertainty_px=0.0)
    for shape, ratio, declared in (("pillbox", 2.0, True), ("gaussian", 2.0, False), ("pillbox", 1.2, False)):
        focus = CrossBlurFocus(truth, shape, False, 1.0, other_power_dpt=truth + 0.5, other_cost_ratio=ratio, contrast=5.0)
        monkeypatch.setattr(declaration, "cross_blur_focus", lambda *a, focus=focus, **k: focus)
        res = drive(DFDController(CAM, **kw), FakePlant(TRUE_DEPTH, scripted=(wrong, 0.05)))
        assert (res.evidence == "refined") == declared, (shape, ratio)
        if declared:
            assert _blur_px(TRUE_DEPTH, res.power_dpt) < 0.1
