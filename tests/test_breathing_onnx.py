"""Focus-breathing registration in the exported ONNX graph and in DepthRuntime (issue 18).

One model with breathing is exported per module through the CLI (``python -m export
--weights ... --camera FILE``) from the weights of the session's test model
(``export.testing``), which has none.
"""

from __future__ import annotations

import json
import logging
from collections import Counter

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch

from export import check_contract, verify_onnx
from export.__main__ import main as export_main
from export.testing import make_test_model
from tdfd import Camera
from tdfd.breathing import breathing_scales, magnify
from tdfd.camera_file import CameraFile
from tdfd.contract import BREATHING_KEY
from tdfd.errors import ModelError, ShapeError
from tdfd.forward import Defocus, DFDForward, IdealSensor
from tdfd.model import DFDModel
from tdfd.registration import BreathingRegistration, register_breathing
from tdfd.runtime import DepthRuntime
from tdfd.textures import random_texture
from tests.onnx_parity import assert_parity

pytestmark = pytest.mark.usefixtures("one_torch_thread")

REF = Camera.preset("reference")
M = 0.005  # 1/dpt: 0.5 % magnification between the reference camera's frames (1 dpt apart)
#: ops only the registration brings into the graph
REGISTRATION_OPS = ("Round", "Gather", "Transpose")


@pytest.fixture(scope="module")
def breathing_onnx(tmp_path_factory):
    """``(path, torch model)``: the test model exported with a camera file carrying ``M``."""
    d = tmp_path_factory.mktemp("breathing")
    make_test_model(0).save(d / "w")
    cam = CameraFile(REF, magnification_per_dpt=M).write(d / "cam.json")
    out = d / "b.onnx"
    assert export_main(["--weights", str(d / "w.safetensors"), "--camera", str(cam), "--out", str(out),
                        "--no-verify"]) == 0
    return out, DFDModel.load(d / "w").set_breathing(M).eval()


def _plane_pair(h: int, w: int, depth_m: float = 0.6, breathing: float = 0.0, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A textured plane (noise-free) through the forward model, frame 2 magnified by ``1 + breathing``."""
    tex, _ = random_texture(torch.Generator().manual_seed(seed), (h, w), family="fractal", albedo=(0.8, 0.9),
                            contrast=(0.8, 1.0))
    fwd = DFDForward(Defocus(REF), IdealSensor())
    with torch.no_grad():
        frames = fwd(tex.double(), torch.full((1, 1, h, w), depth_m, dtype=torch.float64), breathing=breathing)
    frames = frames.clamp(0.0, 1.0).float().numpy()
    return frames[:, 0:1], frames[:, 1:2]


def test_export_cli_puts_the_camera_breathing_in_graph_and_metadata(breathing_onnx, exported_onnx):
    path, model = breathing_onnx
    proto = onnx.load(str(path))
    meta = {p.key: p.value for p in proto.metadata_props}
    s1, s2 = breathing_scales(M, REF.lens_powers_dpt)
    assert json.loads(meta[BREATHING_KEY]) == {"magnification_per_dpt": M, "frame_scales": [s1, s2]}
    assert json.loads(meta["tdfd.model"])["magnification_per_dpt"] == M
    assert check_contract(proto, model)[BREATHING_KEY]["magnification_per_dpt"] == M
    with pytest.raises(ModelError, match="breathing"):
        check_contract(proto, DFDModel.load(path.parent / "w"))  # the model without breathing differs
    ops = Counter(n.op_type for n in proto.graph.node)
    assert all(ops[o] > 0 for o in REGISTRATION_OPS)
    # without breathing the graph holds no registration at all (no extra latency)
    plain = onnx.load(str(exported_onnx[0]))
    assert json.loads({p.key: p.value for p in plain.metadata_props}[BREATHING_KEY])["magnification_per_dpt"] == 0.0
    assert not any(n.op_type in REGISTRATION_OPS for n in plain.graph.node)
    assert len(plain.graph.node) < len(proto.graph.node)


def test_onnx_matches_torch_with_breathing(breathing_onnx):
    path, model = breathing_onnx
    report = verify_onnx(path, model, sizes=[(64, 64), (97, 161), (200, 330)], batches=[1, 2])
    assert_parity(report, cases=6)


def test_onnx_graph_registers_as_torch_does(breathing_onnx, exported_onnx):
    """A plane pair with 0.5 % breathing: the breathing graph gives what the plain graph gives
    on the pair registered in torch (whose undoing of a known magnification is tested in
    test_registration.py), and differs from the plain graph on the raw pair."""
    h, w = 384, 768  # the sides move by about 1.9 px between the frames
    f1, f2 = _plane_pair(h, w, breathing=(1 + M * 2.7) / (1 + M * 1.7) - 1, seed=3)
    r1, r2 = register_breathing(torch.from_numpy(f1), torch.from_numpy(f2), breathing_scales(M, REF.lens_powers_dpt))
    plain = ort.InferenceSession(str(exported_onnx[0]))
    reg = ort.InferenceSession(str(breathing_onnx[0]))
    q_reg = reg.run(["depth_analytic"], {"image_f1": f1, "image_f2": f2})[0]
    q_torch = plain.run(["depth_analytic"], {"image_f1": r1.numpy(), "image_f2": r2.numpy()})[0]
    q_raw = plain.run(["depth_analytic"], {"image_f1": f1, "image_f2": f2})[0]
    assert np.abs(q_reg - q_torch).max() <= 1e-5 * q_torch.max()
    assert np.abs(q_reg - q_raw).max() > 1e-3 * q_raw.max()


def _pair(h: int, w: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    s1, s2 = breathing_scales(M, REF.lens_powers_dpt)
    f1, f2 = _plane_pair(h, w, depth_m=0.45, seed=seed)
    return (magnify(f1[0, 0], s1).astype(np.float32).clip(0, 1), magnify(f2[0, 0], s2).astype(np.float32).clip(0, 1))


def test_runtime_window_matches_the_whole_frame(breathing_onnx):
    """An off-centre window of the frames gives the depths of the same tiles of the whole
    frame; the plain crop (no breathing translation) does not."""
    rt = DepthRuntime(breathing_onnx[0], threads=1)
    assert rt.magnification_per_dpt == M and rt.frame_scales == pytest.approx(breathing_scales(M, REF.lens_powers_dpt))
    f1, f2 = _pair(640, 896, seed=5)
    full = rt(f1, f2)
    y0, x0 = 0, 32 * 20  # grid-aligned, far from the centre (offsets -256 px, 320 px: shifts of 1 px)
    box = (y0, y0 + 128, x0, x0 + 256)
    win = rt(f1, f2, window=box)
    cells = (slice(y0 // 32, y0 // 32 + win.depth.shape[0]), slice(x0 // 32, x0 // 32 + win.depth.shape[1]))
    ref = 1.0 / full.depth_analytic[cells]
    plain = 1.0 / rt(f1[box[0]:box[1], box[2]:box[3]], f2[box[0]:box[1], box[2]:box[3]]).depth_analytic
    err_win = np.median(np.abs(1.0 / win.depth_analytic - ref) / ref)
    err_plain = np.median(np.abs(plain - ref) / ref)
    assert win.image_size == (128, 256) and win.depth.shape == (3, 7)
    assert err_win < 0.2 * err_plain and err_win < 1e-3, (err_win, err_plain)
    assert np.median(np.abs(win.depth - full.depth[cells]) / full.depth[cells]) < 0.01
    # the centred window needs no translation: exactly the plain crop
    c = (256, 384, 320, 576)
    a, b = rt.window_pair(f1[None, None], f2[None, None], c)
    assert np.array_equal(a[0, 0], f1[c[0]:c[1], c[2]:c[3]]) and np.array_equal(b[0, 0], f2[c[0]:c[1], c[2]:c[3]])


def test_runtime_window_errors_and_camera_check(breathing_onnx, exported_onnx, tmp_path, caplog):
    rt = DepthRuntime(breathing_onnx[0], threads=1)
    f = np.full((128, 160), 0.5, np.float32)
    for bad in ((0, 200, 0, 64), (0, 32, 0, 64), (10, 5, 0, 64), (0, 64)):
        with pytest.raises(ShapeError):
            rt(f, f, window=bad)
    plain = DepthRuntime(exported_onnx[0], threads=1)
    assert plain.magnification_per_dpt == 0.0
    assert np.array_equal(plain.window_pair(f[None, None], f[None, None], (0, 64, 32, 96))[0], f[None, None, :64, 32:96])
    cam = CameraFile(REF, magnification_per_dpt=M).write(tmp_path / "cam.json")
    with caplog.at_level(logging.WARNING, logger="tdfd.runtime"):
        DepthRuntime(breathing_onnx[0], threads=1, camera=cam)
        assert not caplog.records
        DepthRuntime(exported_onnx[0], threads=1, camera=cam)
    assert "differs from the 0 the model registers" in caplog.text and "--camera" in caplog.text


def test_export_cli_refuses_a_bad_breathing_or_a_breathing_analytic_export(tmp_path, capsys):
    (tmp_path / "bad.json").write_text(json.dumps({**REF.to_dict(), "magnification_per_dpt": float("nan")}))
    assert export_main(["--analytic", "--camera", str(tmp_path / "bad.json"), "--out", str(tmp_path / "a.onnx")]) == 1
    assert "magnification_per_dpt" in capsys.readouterr().err
    cam = CameraFile(REF, magnification_per_dpt=M).write(tmp_path / "cam.json")
    assert export_main(["--analytic", "--camera", str(cam), "--out", str(tmp_path / "a.onnx")]) == 1
    assert "no breathing registration" in capsys.readouterr().err
    assert not (tmp_path / "a.onnx").exists()


def test_registration_module_alone_exports_with_dynamic_shapes(tmp_path):
    """The registration stage by itself: ONNX equals torch at sizes the export never saw."""

    class Pair(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.reg = BreathingRegistration(M, REF.lens_powers_dpt)

        def forward(self, a, b):
            return self.reg(a, b)

    x = torch.rand(2, 1, 70, 90)
    dims = {0: torch.export.Dim("n", min=1), 2: torch.export.Dim("h", min=16), 3: torch.export.Dim("w", min=16)}
    prog = torch.onnx.export(Pair().eval(), (x, x.flip(-1)), dynamo=True, opset_version=18, input_names=["a", "b"],
                             dynamic_shapes=(dims, dims), external_data=False, report=False, verbose=False)
    prog.save(str(tmp_path / "r.onnx"))
    sess = ort.InferenceSession(str(tmp_path / "r.onnx"))
    g = torch.Generator().manual_seed(0)
    for h, w in ((16, 16), (33, 47), (130, 201)):
        a, b = torch.rand(2, 1, h, w, generator=g), torch.rand(2, 1, h, w, generator=g)
        want = Pair()(a, b)
        got = sess.run(None, {"a": a.numpy(), "b": b.numpy()})
        for g_, w_ in zip(got, want):
            assert np.array_equal(g_, w_.numpy())  # whole pixels moved: exactly equal
