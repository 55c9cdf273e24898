"""Focus breathing registered about the optical centre when the autofocus sends a crop
around an off-centre ROI (issue 18): the controller says where the frame's centre lies in
the crop, and an estimator that registers breathing moves each frame by the breathing's
translation there before registering about the crop's centre."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from tdfd import Camera
from tdfd.autofocus.dfd import DFDController
from tdfd.autofocus.interfaces import run_estimator
from tdfd.autofocus.messages import Estimate
from tdfd.autofocus.registered import BreathingRegistered
from tdfd.autofocus.roi import Roi, roi_crop_box
from tdfd.errors import NonFiniteError
from tdfd.registration import register_breathing

CAM = Camera.preset("reference")
M = 0.02  # a strong breathing (2 %/dpt), so that the crop's translation is several pixels


class Recorder:
    """An estimator that records the frames it is given (and registers nothing itself)."""

    def __init__(self) -> None:
        self.camera, self.tile, self.stride = CAM, 64, 32
        self.seen: list[tuple[np.ndarray, np.ndarray]] = []

    def __call__(self, a: np.ndarray, b: np.ndarray):
        self.seen.append((np.asarray(a), np.asarray(b)))
        return np.full((1, 1), 0.5, np.float32), np.full((1, 1), 0.9, np.float32)


def texture(h: int = 240, w: int = 320, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return cv2.GaussianBlur(rng.random((h, w)).astype(np.float32), (0, 0), 3.0)


@pytest.mark.parametrize("window,equal_with,equal_without", [
    ((32, 160, 192, 320), 0.6, 0.15),  # centre 96 px right of and 24 px above the optical centre
    ((0, 128, 0, 128), 0.4, 0.1),      # the top-left corner
    ((56, 184, 96, 224), 1.0, 1.0),    # centred: the crop's centre is the optical centre
])
def test_an_off_centre_crop_registers_like_the_whole_frame(window, equal_with, equal_without):
    """A crop of a 240x320 pair at 2 %/dpt breathing, registered with the optical centre
    given, matches the same crop of the whole frames registered about their centre: at
    least ``equal_with`` of its interior pixels are the same pixel (the rest one pixel off:
    the translation is applied in whole pixels, as the runtime does); registered about the
    crop's own centre, at most ``equal_without`` are (a centred crop: all, either way)."""
    a_full, b_full = texture(seed=1), texture(seed=2)
    ref = BreathingRegistered(Recorder(), M)
    ra, rb = register_breathing(torch.from_numpy(a_full)[None, None], torch.from_numpy(b_full)[None, None], ref.scales)
    y0, y1, x0, x1 = window
    want = ra[0, 0, y0:y1, x0:x1].numpy(), rb[0, 0, y0:y1, x0:x1].numpy()
    crop = a_full[y0:y1, x0:x1], b_full[y0:y1, x0:x1]
    rec = BreathingRegistered(Recorder(), M)
    rec(*crop, optical_centre=((240 - 1) / 2 - y0, (320 - 1) / 2 - x0))
    rec(*crop)  # about the crop's own centre (what an estimator without the optical centre does)
    inner = (slice(4, -4), slice(4, -4))
    same = [min(float((g[inner] == w[inner]).mean()) for g, w in zip(seen, want)) for seen in rec.estimator.seen]
    assert same[0] >= equal_with
    assert same[1] <= equal_without
    with pytest.raises(NonFiniteError, match="optical_centre"):
        rec(*crop, optical_centre=(float("nan"), 0.0))


def test_the_controller_sends_the_optical_centre_of_its_crop():
    """An off-centre ROI on a 256x320 frame: the Estimate carries the crop and, in its pixels,
    the frame's centre; run_estimator gives it only to an estimator that takes it."""
    from tdfd.autofocus.messages import Frame, LensAck, SetPower

    roi = Roi(200, 16, 96, 96)
    ctrl = DFDController(CAM, grid=(64, 32), roi=roi)
    img = np.clip(texture(256, 320), 0.05, 0.95)
    cmd, power, est_cmd = ctrl.start(), 0.0, None
    for _ in range(10):
        if isinstance(cmd, SetPower):
            power = cmd.power_dpt
            cmd = ctrl.step(LensAck(cmd.power_dpt, 0.0, 0.0))
        elif isinstance(cmd, Estimate):
            est_cmd = cmd
            break
        else:  # a capture; the two frames of the pair differ (a DFD pair)
            lens = None
            if cmd.then_power_dpt is not None:
                lens = LensAck(cmd.then_power_dpt, 0.0, 0.0)
            frame = Frame(img * (1.0 if cmd.tag == "f1" else 0.9) + 0.02, power, 0.0, 0.0, 0.0, cmd.tag, lens=lens)
            if lens is not None:
                power = cmd.then_power_dpt
            cmd = ctrl.step(frame)
    assert est_cmd is not None
    y0, y1, x0, x1 = roi_crop_box(roi, (256, 320), 64, 32)
    assert est_cmd.offset == (y0, x0) and est_cmd.image_f1.shape == (y1 - y0, x1 - x0)
    assert est_cmd.optical_centre == pytest.approx((127.5 - y0, 159.5 - x0))
    rec = Recorder()
    run_estimator(rec, est_cmd)  # no takes_optical_centre: the images only
    assert np.array_equal(rec.seen[0][0], est_cmd.image_f1)
    with_centre, about_crop = BreathingRegistered(Recorder(), M), BreathingRegistered(Recorder(), M)
    run_estimator(with_centre, est_cmd)
    about_crop(est_cmd.image_f1, est_cmd.image_f2)
    assert not np.array_equal(with_centre.estimator.seen[0][1], about_crop.estimator.seen[0][1])


def test_the_onnx_estimator_moves_a_crop_as_the_runtime_moves_its_window():
    """The model trained for the calibrated camera registers its 0.407 %/dpt breathing in its
    graph: a corner crop of a 960x1280 pair (its centre 512 px from the optical centre, where
    the breathing's translation reaches a whole pixel) given with the optical centre reaches
    the graph as the runtime cuts that window of the whole frames (but for the crop's last
    row and column, which repeat its edge), and moved apart from the crop without it."""
    from pathlib import Path

    from tdfd.autofocus.estimators import OnnxEstimator
    from tdfd.runtime import DepthRuntime

    here = Path(__file__).resolve().parents[1] / "models" / "bench_calibrated"
    est = OnnxEstimator(here / "model.onnx", threads=1, camera=here / "CAM-self.json")
    rt = DepthRuntime(here / "model.onnx", threads=1, camera=here / "CAM-self.json")
    fed: list[tuple[np.ndarray, np.ndarray]] = []
    run = est._runtime.run
    est._runtime.run = lambda a, b: (fed.append((a.copy(), b.copy())), run(a, b))[1]
    a_full, b_full = (np.clip(0.2 + 0.6 * texture(960, 1280, seed=s), 0.0, 1.0) for s in (3, 4))
    y0, y1, x0, x1 = 0, 192, 0, 256
    want = rt.window_pair(*(x[None, None].astype(np.float32) for x in (a_full, b_full)), (y0, y1, x0, x1))
    crop = a_full[y0:y1, x0:x1], b_full[y0:y1, x0:x1]
    est(*crop, optical_centre=(479.5 - y0, 639.5 - x0))
    est(*crop)
    inner = (..., slice(0, -1), slice(0, -1))
    for got, w in zip(fed[0], want):
        assert np.array_equal(got[inner], w[inner])
    assert not np.array_equal(fed[1][1][inner], want[1][inner])
