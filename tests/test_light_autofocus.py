"""The assist-light policy in the autofocus loop: lit pairs, lit-tile pooling, and the bench."""

from __future__ import annotations

import numpy as np
import pytest

from tdfd import Camera
from tdfd.autofocus.assist import AssistedDFDController
from tdfd.autofocus.dfd import DFDController
from tdfd.autofocus.estimators import AnalyticEstimator
from tdfd.errors import InputError
from tdfd.autofocus.messages import Capture, Done, Estimate, Estimation, Frame, LensAck, SetPower
from tdfd.autofocus.sim import SimBench
from tdfd.light import SimulatedLight

CAM = Camera.preset("reference")
HW = (192, 224)


def _noise(rng, img, s=0.004):
    return (img + s * rng.standard_normal(img.shape)).astype(np.float32)


def _answer(cmd, image, t):
    """The observation a perfect plant gives ``cmd`` (frames from ``image(cmd)``)."""
    if isinstance(cmd, SetPower):
        return LensAck(cmd.power_dpt, t, t + cmd.settle_s)
    lens = LensAck(cmd.then_power_dpt, t + 0.002, t + 0.017) if cmd.then_power_dpt is not None else None
    return Frame(image(cmd), 0.0, t, t + 0.002, t + 0.005, cmd.tag, lens=lens)


def _run_until_estimate(ctrl, image):
    cmds, t = [], 0.0
    cmd = ctrl.start(0.0)
    while not isinstance(cmd, (Estimate, Done)):
        cmds.append(cmd)
        t += 0.02
        cmd = ctrl.step(_answer(cmd, image, t))
    return cmds, cmd


def test_without_an_ambient_frame_the_pair_is_lit_from_its_first_frame():
    """The default: two lit frames at P_e1 then P_e2 (plain DFD's order and commands), no unlit frame."""
    rng = np.random.default_rng(0)
    stripes = np.full(HW, 0.5)
    stripes[:, 60:100] += 0.35
    ctrl = AssistedDFDController(CAM, illumination="coherent", grid=(64, 32))
    assert ctrl.ambient_frame is False
    cmds, est = _run_until_estimate(ctrl, lambda cmd: _noise(rng, stripes) if cmd.light else pytest.fail("unlit"))
    caps = [c for c in cmds if isinstance(c, Capture)]
    p1, p2 = CAM.lens_powers_dpt
    assert [(c.tag, c.light, c.then_power_dpt) for c in caps] == [("f1 lit", "coherent", p2), ("f2 lit", "coherent", None)]
    assert [c.power_dpt for c in cmds if isinstance(c, SetPower)] == [p1]
    assert isinstance(est, Estimate) and ctrl.result.frames == 2 and ctrl.lit.ambient_f1 is None


def test_a_lit_pair_that_clips_is_taken_again_unlit():
    """A bright texture under the pattern clips: no estimate from that pair, plain DFD's unlit pair instead."""
    rng = np.random.default_rng(7)
    tex = np.full(HW, 0.6)
    tex[:, ::8] = 0.9
    clipped = np.clip(tex * 1.8, 0, 1)  # lit: most of the frame at full scale

    ctrl = AssistedDFDController(CAM, illumination="coherent", grid=(64, 32))
    cmds, est = _run_until_estimate(ctrl, lambda cmd: (clipped if cmd.light else _noise(rng, tex)).astype(np.float32))
    caps = [(c.tag, c.light) for c in cmds if isinstance(c, Capture)]
    assert caps == [("f1 lit", "coherent"), ("f2", None), ("f1", None)]  # the lens was at P_e2 already
    p1, p2 = CAM.lens_powers_dpt
    assert [c.then_power_dpt for c in cmds if isinstance(c, Capture)] == [p2, p1, None]
    assert ctrl.lit is None and "clips" in ctrl.lit_dropped and ctrl.result.frames == 3
    assert float(est.image_f1.max()) < 0.99  # the unlit frames are estimated
    # a lit pair that does not clip (a texture-less target) is estimated as it is
    flat = AssistedDFDController(CAM, illumination="coherent", grid=(64, 32))
    cmds, _ = _run_until_estimate(flat, lambda cmd: _noise(rng, np.full(HW, 0.5 if not cmd.light else 0.9)))
    assert [c.light for c in cmds if isinstance(c, Capture)] == ["coherent", "coherent"] and flat.lit_dropped is None


def test_subtraction_takes_the_ambient_frame():
    assert AssistedDFDController(CAM, illumination="coherent", subtract_ambient=True).ambient_frame is True
    with pytest.raises(InputError, match="ambient frame"):
        AssistedDFDController(CAM, illumination="coherent", subtract_ambient=True, ambient_frame=False)


def test_with_the_ambient_frame_a_texture_less_target_gets_a_lit_pair_of_three_frames():
    rng = np.random.default_rng(0)
    flat = np.full(HW, 0.5)
    stripes = flat.copy()
    stripes[:, 60:100] += 0.35

    def image(cmd):
        return _noise(rng, stripes if cmd.light else flat)

    ctrl = AssistedDFDController(CAM, illumination="coherent", grid=(64, 32), ambient_frame=True)
    cmds, est = _run_until_estimate(ctrl, image)
    caps = [c for c in cmds if isinstance(c, Capture)]
    assert [(c.tag, c.light) for c in caps] == [("f1", None), ("f2 lit", "coherent"), ("f1 lit", "coherent")]
    p1, p2 = CAM.lens_powers_dpt
    assert caps[0].then_power_dpt == p2 and caps[1].then_power_dpt == p1 and caps[2].then_power_dpt is None
    assert isinstance(est, Estimate) and est.image_f1.std() > 0.1  # the lit frames are estimated
    assert ctrl.result.frames == 3


def test_with_the_ambient_frame_a_textured_target_never_asks_for_the_light():
    import cv2

    rng = np.random.default_rng(1)
    tex = np.clip(0.5 + cv2.GaussianBlur(0.6 * rng.standard_normal(HW), (0, 0), 2.0), 0, 1)  # 6-12 px texture
    for ctrl in (AssistedDFDController(CAM, illumination="coherent", ambient_frame=True), DFDController(CAM)):
        cmds, est = _run_until_estimate(ctrl, lambda cmd: _noise(rng, tex))
        assert [c.light for c in cmds if isinstance(c, Capture)] == [None, None]
    # without a light named the policy is plain DFD even on a texture-less target
    ctrl = AssistedDFDController(CAM, illumination=None)
    cmds, _ = _run_until_estimate(ctrl, lambda cmd: _noise(rng, np.full(HW, 0.5)))
    assert all(c.light is None for c in cmds if isinstance(c, Capture))


@pytest.mark.parametrize("ambient", [True, False])
def test_dark_tiles_do_not_vote(ambient):
    """Confident wrong depths on the tiles the pattern does not cover must not move the ROI depth."""
    rng = np.random.default_rng(2)
    flat = np.full(HW, 0.3)
    lit = flat.copy()
    lit[:, 100:124] += 0.4  # one stripe, 24 px wide

    # (the frames here carry no defocus, only the estimate does: no region fit over them)
    ctrl = AssistedDFDController(CAM, illumination="coherent", grid=(64, 32), roi=None, ambient_frame=ambient,
                                 region_fit=False)
    _, est = _run_until_estimate(ctrl, lambda cmd: _noise(rng, lit if cmd.light else flat))
    h = (est.image_f1.shape[0] - 64) // 32 + 1
    w = (est.image_f1.shape[1] - 64) // 32 + 1
    depth = np.full((h, w), 0.95)  # dark tiles: confidently wrong
    conf = np.full((h, w), 0.9)
    x0 = est.offset[1]
    edged = [j for j in range(w) if any(x0 + 32 * j <= e < x0 + 32 * j + 64 for e in (100, 124))]
    assert 0 < len(edged) < w
    depth[:, edged] = 0.5  # tiles holding the stripe's edges: right
    cmd = ctrl.step(Estimation(depth, conf, 64, 32, t_s=1.0))
    assert isinstance(cmd, SetPower)
    assert ctrl.last_aggregate.depth_m == pytest.approx(0.5)
    assert cmd.power_dpt == pytest.approx(CAM.in_focus_power_dpt(0.5))
    assert 0 < ctrl.lit.lit_tiles < ctrl.lit.roi_tiles
    # plain DFD on the same estimate lets the dark tiles vote: a wrong depth
    plain = DFDController(CAM, grid=(64, 32))
    _run_until_estimate(plain, lambda cmd: _noise(rng, lit))
    plain.step(Estimation(depth, conf, 64, 32, t_s=1.0))
    assert abs(1 / plain.last_aggregate.depth_m - 1 / 0.5) > 0.4


@pytest.mark.parametrize("ambient", [True, False])
def test_pattern_missing_the_roi_falls_back_to_contrast(ambient):
    rng = np.random.default_rng(3)
    flat = np.full(HW, 0.4)
    ctrl = AssistedDFDController(CAM, illumination="coherent", grid=(64, 32), ambient_frame=ambient)
    _, est = _run_until_estimate(ctrl, lambda cmd: _noise(rng, flat))  # the light shows nothing
    h, w = ((s - 64) // 32 + 1 for s in est.image_f1.shape)
    cmd = ctrl.step(Estimation(np.full((h, w), 0.6), np.full((h, w), 0.9), 64, 32, t_s=1.0))
    assert ctrl.lit.lit_tiles == 0
    assert isinstance(cmd, (SetPower, Capture)) and ctrl.state.name == "CONTRAST"
    assert "texture-less" in ctrl.result.fallback_reason


@pytest.fixture(scope="module")
def analytic():
    return AnalyticEstimator(CAM)


@pytest.mark.parametrize("pattern", ["coherent", "projector"])
def test_bench_lights_a_texture_less_target_into_focus(analytic, pattern):
    light = SimulatedLight(CAM)
    with SimBench(estimator=analytic, light=light, controller={"illumination": pattern}, compute_s=0.001,
                  readout_hw=HW) as bench:
        rec = bench.run_trial(0.5, "dfd", uniform=True)
        # the lit pair, and a lit verification frame if the estimate's uncertainty asks for one
        assert rec.in_focus and rec.frames <= 3 and rec.method == "dfd"
        assert rec.extra["light"] == pattern and rec.extra["lit_tiles"] > 0
        assert rec.extra["light_on_ms"] == pytest.approx(rec.frames * bench.timing.exposure_s * 1e3)
        assert not light.is_on and light.switch_count == rec.frames
        unlit = bench.run_trial(0.5, "dfd", uniform=True, illumination=None)
        assert unlit.method == "contrast" and unlit.frames > 3  # plain DFD falls back on the same target
        assert light.switch_count == rec.frames


def test_bench_textured_target_is_not_lit_with_the_ambient_frame(analytic):
    light = SimulatedLight(CAM)
    # evidence_s fixed: the default calibrates the evidence's compute time on each bench (wall clock)
    with SimBench(estimator=analytic, light=light, controller={"illumination": "coherent", "ambient_frame": True},
                  compute_s=0.001, evidence_s=0.005, readout_hw=HW, seed=4) as bench:
        rec = bench.run_trial(0.6, "dfd", trial=1)
    with SimBench(estimator=analytic, compute_s=0.001, evidence_s=0.005, readout_hw=HW, seed=4) as bench:
        ref = bench.run_trial(0.6, "dfd", trial=1)
    assert light.switch_count == 0 and rec.extra["light"] is None
    assert (rec.frames, rec.final_power_dpt, rec.time_ms) == (ref.frames, ref.final_power_dpt, ref.time_ms)


@pytest.mark.parametrize("amplitude,retried", [(0.0012, True), (0.2, False)])
def test_untrusted_unlit_estimate_is_retried_lit_only_on_a_weak_texture(amplitude, retried):
    import cv2

    from tdfd.autofocus.roi import Roi
    from tdfd.autofocus.sharpness import pair_texture_snr

    rng = np.random.default_rng(5)
    tex = 0.5 + cv2.GaussianBlur(amplitude * rng.standard_normal(HW), (0, 0), 2.0) / 0.14  # unit-ish variance
    frames = [_noise(rng, tex, 0.002) for _ in range(2)]
    snr = pair_texture_snr(*frames, Roi.centre(HW))
    assert (1.2 < snr < 3.0) if retried else snr > 3.0
    it = iter(frames * 3)
    ctrl = AssistedDFDController(CAM, illumination="coherent", grid=(64, 32), ambient_frame=True)
    cmds, est = _run_until_estimate(ctrl, lambda cmd: next(it))
    assert [c.light for c in cmds if isinstance(c, Capture)] == [None, None]  # textured in f1: unlit pair
    h, w = ((s - 64) // 32 + 1 for s in est.image_f1.shape)
    cmd = ctrl.step(Estimation(np.full((h, w), 0.6), np.full((h, w), 1e-4), 64, 32, t_s=1.0))  # not trusted
    if retried:
        assert isinstance(cmd, Capture) and cmd.light == "coherent" and cmd.tag == "f2 lit"
        assert cmd.then_power_dpt == CAM.lens_powers_dpt[0]
    else:
        assert ctrl.state.name == "CONTRAST" and getattr(cmd, "light", None) is None


# ------------------------------------------------ the contrast search lit with a sharp pattern
_PAPER = Camera.preset("paper")
#: the paper camera binned 4x (benchmarks/paper_experiment.py): 21.2 um pixels, 300 x 400
PAPER4 = _PAPER.replace(pixel_pitch_m=4 * _PAPER.pixel_pitch_m, sensor_size_px=(300, 400),
                        mu_px_per_m=1 / (2 * 4 * _PAPER.pixel_pitch_m), name="paper4")


@pytest.mark.parametrize("pattern", ["coherent", "projector"])
def test_a_near_texture_less_target_is_searched_lit_only_with_a_sharp_pattern(pattern):
    """The paper camera at 0.33 m: both frames of the pair blur the pattern into the noise, so
    DFD sees no texture and contrast-detect AF takes over. Lit with the coherent pattern (sharp at
    every distance) the search finds focus, scanning again around its coarse peak (one 0.4 dpt
    step is 9 px of blur here); a projector's search stays unlit and declares nothing."""
    from tdfd.autofocus.roi import Roi

    light = SimulatedLight(PAPER4)
    est = AnalyticEstimator(PAPER4, tile=128, stride=32)
    with SimBench(estimator=est, light=light, controller={"illumination": pattern}, compute_s=0.005,
                  evidence_s=0.005, readout_hw=PAPER4.sensor_size_px, roi=Roi.centre(PAPER4.sensor_size_px, 0.9),
                  seed=0) as bench:
        rec = bench.run_trial(0.33, "dfd", uniform=True)
    assert rec.method == "contrast" and "texture-less" in rec.reason
    assert not light.is_on
    if pattern == "coherent":
        assert rec.in_focus and rec.status == "focused" and rec.frames >= 15  # coarse scan + fine scan
        assert light.switch_count == rec.frames  # every frame lit: the pair and the whole search
    else:
        assert rec.status == "unconfirmed" and not rec.declared
        assert light.switch_count == 2  # the pair only


def test_the_fine_scan_is_only_for_a_shallow_depth_of_field():
    from tdfd.autofocus.contrast import ContrastSearch
    from tdfd.autofocus.evidence import blur_px_per_dpt

    ref, search = Camera.preset("reference"), ContrastSearch(CAM)
    assert blur_px_per_dpt(ref) * search.step_dpt < search.fine_scan_px < blur_px_per_dpt(PAPER4) * search.step_dpt
    with pytest.raises(InputError, match="fine_scan_px"):
        ContrastSearch(CAM, fine_scan_px=-1)
