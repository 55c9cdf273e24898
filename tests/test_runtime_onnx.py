"""tdfd.runtime.DepthRuntime: metadata, layouts, integer normalisation, validation, resampling, no torch."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper

from export import realistic_pairs
from tdfd import Camera
from tdfd.errors import DTypeError, ModelError, NonFiniteError, RangeError, ShapeError
from tdfd.runtime import DepthResult, DepthRuntime, default_model_path, in_focus_power_dpt, resample_to_image

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def exported(exported_onnx):
    return exported_onnx


@pytest.fixture(scope="module")
def rt(exported):
    return DepthRuntime(exported[0], threads=2)


@pytest.fixture(scope="module")
def pair():
    i1, i2 = realistic_pairs(Camera.preset("reference"), 2, 150, 203, seed=11)
    return i1.numpy(), i2.numpy()


def test_metadata_camera_grid_version(rt):
    assert rt.camera == Camera.preset("reference")
    assert (rt.tile, rt.stride) == (64, 32)
    assert rt.version == "0.1.0"
    assert rt.metadata["tdfd.grid"] == {"tile": 64, "stride": 32}
    assert rt.grid_shape(480, 640) == (14, 19)
    assert "tile=64" in repr(rt)


def test_layouts_follow_the_input(rt, pair):
    a, b = pair
    full = rt(a, b)
    assert isinstance(full, DepthResult)
    assert full.depth.shape == full.confidence.shape == full.depth_analytic.shape == (2, 1, 3, 5)
    assert full.depth.dtype == np.float32 and full.grid_shape == (3, 5)
    one = rt(a[0], b[0])  # (1, H, W)
    assert one.depth.shape == (1, 3, 5)
    two = rt(a[0, 0], b[0, 0])  # (H, W)
    assert two.depth.shape == (3, 5)
    np.testing.assert_allclose(two.depth, full.depth[0, 0], rtol=1e-5)
    np.testing.assert_allclose(one.confidence[0], full.confidence[0, 0], atol=1e-6)
    assert np.all(full.depth > 0) and np.all((full.confidence >= 0) & (full.confidence <= 1))


def test_session_matches_bare_onnxruntime(rt, exported, pair):
    import onnxruntime as ort

    a, b = pair
    sess = ort.InferenceSession(str(exported[0]), providers=["CPUExecutionProvider"])
    ref = sess.run(None, {"image_f1": a, "image_f2": b})
    res = rt(a, b)
    for got, want in zip((res.depth, res.confidence, res.depth_analytic), ref):  # graph optimisations may differ
        np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("dtype,level", [(np.uint16, None), (np.uint16, 4095), (np.uint8, None), (np.uint8, 200)])
def test_integer_images_are_normalised_by_the_white_level(rt, pair, dtype, level):
    a, b = pair[0][0, 0], pair[1][0, 0]
    top = level if level is not None else np.iinfo(dtype).max
    ia, ib = (np.round(x * top).astype(dtype) for x in (a, b))
    got = rt(ia, ib, white_level=level)
    want = rt(ia.astype(np.float32) / top, ib.astype(np.float32) / top)
    np.testing.assert_allclose(got.depth, want.depth, rtol=1e-6)
    np.testing.assert_allclose(got.confidence, want.confidence, atol=1e-6)


def test_float_white_level_divides(rt, pair):
    a, b = pair[0][0, 0], pair[1][0, 0]
    np.testing.assert_allclose(rt(a * 4095, b * 4095, white_level=4095).depth, rt(a, b).depth, rtol=1e-5)


def test_validation_errors_are_typed(rt, pair):
    a, b = pair[0][0, 0], pair[1][0, 0]
    with pytest.raises(ShapeError, match="differ in shape"):
        rt(a, b[:, :-1])
    with pytest.raises(ShapeError, match="smaller than one 64x64 tile"):
        rt(a[:63], b[:63])
    with pytest.raises(ShapeError, match="single-channel"):
        rt(np.stack([a, a, a], -1), np.stack([b, b, b], -1))
    with pytest.raises(ShapeError, match="single-channel"):
        rt(a[None, None, None], b[None, None, None])
    nan = a.copy()
    nan[5, 5] = np.nan
    with pytest.raises(NonFiniteError, match="image_f1"):
        rt(nan, b)
    with pytest.raises(RangeError, match=r"image_f2 has values in \[.*\]; float images must be"):
        rt(a, b * 2.0 + 0.01)
    with pytest.raises(RangeError):
        rt(a - 0.5, b)
    with pytest.raises(DTypeError, match="int32"):
        rt(a.astype(np.int32), b.astype(np.int32))
    with pytest.raises(DTypeError, match="bool"):
        rt(a > 0.5, b > 0.5)
    with pytest.raises(DTypeError, match="both frames must have one dtype"):
        rt(a, b.astype(np.float64))
    with pytest.raises(DTypeError, match="numpy array"):
        rt(a.tolist(), b.tolist())
    with pytest.raises(RangeError, match="above the white level"):
        rt(np.full((64, 64), 4096, np.uint16), np.full((64, 64), 100, np.uint16), white_level=4095)
    with pytest.raises(RangeError, match="white_level"):
        rt(np.zeros((64, 64), np.uint16), np.zeros((64, 64), np.uint16), white_level=0)


def test_float16_and_float64_accepted(rt, pair):
    a, b = pair[0][0, 0], pair[1][0, 0]
    ref = rt(a, b).depth
    np.testing.assert_allclose(rt(a.astype(np.float64), b.astype(np.float64)).depth, ref, rtol=1e-6)
    assert rt(a.astype(np.float16), b.astype(np.float16)).depth.shape == ref.shape


def test_full_resolution_is_tile_centre_aligned(rt, pair):
    a, b = pair
    grid = rt(a, b)
    full = rt(a, b, full_resolution=True)
    assert full.full_resolution and full.depth.shape == full.confidence.shape == (2, 1, 150, 203)
    rows, cols = np.arange(3) * 32 + 31.5, np.arange(5) * 32 + 31.5
    # tile centres fall between pixels (31.5 + 32 i): the 2x2 pixels around a centre average to its value up to
    # the kink of the piecewise-linear interpolation (half a pixel of slope change)
    for i, r in enumerate(rows):
        for j, c in enumerate(cols):
            r0, c0 = int(r), int(c)
            block = 1.0 / full.depth[..., r0:r0 + 2, c0:c0 + 2].astype(np.float64)
            np.testing.assert_allclose(block.mean((-2, -1)), 1.0 / grid.depth[..., i, j], rtol=1e-2)
            np.testing.assert_allclose(full.confidence[..., r0:r0 + 2, c0:c0 + 2].mean((-2, -1)),
                                       grid.confidence[..., i, j], atol=2e-2)
    # edge extension: the first 31 rows / columns equal the first centre row / column
    np.testing.assert_allclose(full.depth[..., 0, 0], grid.depth[..., 0, 0], rtol=1e-5)
    np.testing.assert_allclose(full.depth[..., -1, -1], grid.depth[..., -1, -1], rtol=1e-5)
    assert full.at_full_resolution() is full
    # a valid fraction from the full map is close to the grid's
    assert abs(full.valid_fraction(0.5) - grid.valid_fraction(0.5)) < 0.35


def test_resample_to_image_exact_cases():
    g = np.arange(6, dtype=np.float32).reshape(2, 3)
    up = resample_to_image(g, 96, 128, tile=64, stride=32)
    assert up.shape == (96, 128)
    np.testing.assert_allclose(up[:32, :32], 0.0)  # before the first centre (31.5)
    np.testing.assert_allclose(up[64:, 96:], 5.0)  # after the last centre (63.5, 95.5)
    np.testing.assert_allclose(up[0, 32:64], np.linspace(0, 1, 33)[:-1] + 0.5 / 32, atol=1e-6)
    # an odd tile puts the centres on pixels (32 + 32 i): the map is exact there
    rng = np.random.default_rng(0)
    g = rng.random((2, 3, 4))
    up = resample_to_image(g, 65 + 64, 65 + 96, tile=65, stride=32)
    np.testing.assert_allclose(up[:, 32:97:32, 32:129:32], g, rtol=1e-6)
    np.testing.assert_allclose(up[:, 48, 32], 0.5 * (g[:, 0, 0] + g[:, 1, 0]), rtol=1e-6)
    const = resample_to_image(np.full((1, 1, 1, 1), 0.7), 64, 64, 64, 32)
    np.testing.assert_allclose(const, 0.7, rtol=1e-6)


def test_centre_depth_and_valid_fraction():
    depth = np.full((3, 5), 0.8, np.float32)
    depth[1, 1:4] = 0.5
    conf = np.full((3, 5), 0.9, np.float32)
    conf[1, 3] = 0.1
    res = DepthResult(depth, conf, depth, image_size=(128, 192), tile=64, stride=32)
    assert res.centre_depth(0.5, 0.5) == pytest.approx(0.5)  # centre cells (1, 1..3), (1, 3) not confident
    assert res.valid_fraction(0.5) == pytest.approx(14 / 15)
    assert np.isnan(DepthResult(depth, conf * 0, depth, (128, 192), 64, 32).centre_depth())
    batch = DepthResult(depth[None, None].repeat(2, 0), conf[None, None].repeat(2, 0), depth[None, None].repeat(2, 0),
                        (128, 192), 64, 32)
    np.testing.assert_allclose(batch.centre_depth(), [0.5, 0.5])


def test_in_focus_power(rt):
    cam = Camera.preset("reference")
    assert rt.in_focus_power_dpt(0.5) == pytest.approx(cam.in_focus_power_dpt(0.5)) == pytest.approx(2.0)
    np.testing.assert_allclose(rt.in_focus_power_dpt(np.array([0.3, 1.0])), [1 / 0.3, 1.0], rtol=1e-12)
    assert in_focus_power_dpt(cam, 1.0) == pytest.approx(1.0)
    with pytest.raises(RangeError):
        rt.in_focus_power_dpt(0.0)
    with pytest.raises(RangeError):
        rt.in_focus_power_dpt(np.array([0.5, np.nan]))


def _tiny_model(path: Path, metadata: dict | None, outputs=("depth", "confidence", "depth_analytic")) -> Path:
    x1 = helper.make_tensor_value_info("image_f1", TensorProto.FLOAT, ["N", 1, "H", "W"])
    x2 = helper.make_tensor_value_info("image_f2", TensorProto.FLOAT, ["N", 1, "H", "W"])
    outs = [helper.make_tensor_value_info(n, TensorProto.FLOAT, None) for n in outputs]
    nodes = [helper.make_node("Identity", ["image_f1"], [n]) for n in outputs]
    m = helper.make_model(helper.make_graph(nodes, "tiny", [x1, x2], outs), opset_imports=[helper.make_opsetid("", 18)],
                          ir_version=10)
    for k, v in (metadata or {}).items():
        m.metadata_props.add(key=k, value=v)
    onnx.save(m, str(path))
    return path


def test_model_errors(tmp_path):
    with pytest.raises(ModelError, match="does not exist"):
        DepthRuntime(tmp_path / "nope.onnx")
    junk = tmp_path / "junk.onnx"
    junk.write_bytes(b"\x00garbage")
    with pytest.raises(ModelError, match="cannot load"):
        DepthRuntime(junk)
    with pytest.raises(ModelError, match="tdfd.camera"):
        DepthRuntime(_tiny_model(tmp_path / "nometa.onnx", None))
    meta = {"tdfd.camera": json.dumps(Camera.preset("reference").to_dict()), "tdfd.grid": '{"tile": 64, "stride": 32}',
            "tdfd.version": '"0.1.0"'}
    with pytest.raises(ModelError, match="outputs"):
        DepthRuntime(_tiny_model(tmp_path / "names.onnx", meta, outputs=("depth", "conf", "depth_analytic")))
    bad = dict(meta, **{"tdfd.camera": json.dumps({"aperture_m": 1})})
    with pytest.raises(ModelError, match="camera"):
        DepthRuntime(_tiny_model(tmp_path / "badcam.onnx", bad))
    ok = DepthRuntime(_tiny_model(tmp_path / "ok.onnx", meta))
    assert ok.tile == 64 and ok.version == "0.1.0"


def test_default_model_path(monkeypatch, tmp_path, exported):
    monkeypatch.setenv("TDFD_MODEL", str(exported[0]))
    assert default_model_path() == exported[0]
    monkeypatch.setenv("TDFD_MODEL", str(tmp_path / "missing.onnx"))
    with pytest.raises(ModelError, match="TDFD_MODEL"):
        default_model_path()
    monkeypatch.delenv("TDFD_MODEL")
    shipped = ROOT / "models" / "reference.onnx"
    assert default_model_path() == shipped  # through the package's tdfd/assets link
    monkeypatch.setattr("tdfd.runtime.SHIPPED_MODEL", tmp_path / "not_installed.onnx")
    monkeypatch.chdir(ROOT)
    assert default_model_path() == shipped  # models/ of the working directory
    monkeypatch.chdir(tmp_path)
    with pytest.raises(ModelError, match=r"no model found: name one with --model PATH .* or \$TDFD_MODEL"):
        default_model_path()


def test_runtime_imports_no_torch(exported):
    code = ("import sys, numpy as np\n"
            "sys.modules['torch'] = None  # any 'import torch' now fails\n"
            "from tdfd.runtime import DepthRuntime\n"
            f"rt = DepthRuntime({str(exported[0])!r})\n"
            "r = rt(np.random.default_rng(0).random((100, 140), dtype=np.float32), "
            "np.random.default_rng(1).random((100, 140), dtype=np.float32), full_resolution=True)\n"
            "assert r.depth.shape == (100, 140)\n"
            "print('ok', rt.in_focus_power_dpt(0.5))\n")
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd=ROOT, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.startswith("ok 2.0")
    plain = subprocess.run([sys.executable, "-c", "import sys, tdfd.runtime; assert 'torch' not in sys.modules"],
                           capture_output=True, text=True, env=env, cwd=ROOT, timeout=60)
    assert plain.returncode == 0, plain.stderr
