"""DepthRuntime on what a camera really delivers: depth against the truth on rendered planes
(the shipped model), pairs that are no DFD pair, empty arrays and onnxruntime failures."""

from __future__ import annotations

import numpy as np
import pytest

from tdfd.errors import ModelError, ShapeError
from tdfd.pair_check import pair_problem
from tdfd.runtime import DepthRuntime

#: Relative error allowed for the centre depth of a rendered plane. Measured: at most 2.3 %
#: over the six planes; with the frames swapped the error is 16-140 %.
DEPTH_TOLERANCE = 0.05


@pytest.fixture(scope="module")
def rt(shipped_onnx):
    return DepthRuntime(shipped_onnx, threads=2)


def test_depth_of_rendered_planes_matches_the_truth(rt, plane_pairs):
    """Threshold 0.05: the plane at 0.7 m is estimated within 2 % but stated near 3 % (confidence
    about 0.09, below the default 0.1; the shipped model's planes err 3.7 % at 0.6-0.7 m)."""
    for f1, f2, truth in plane_pairs:
        res = rt(f1, f2, white_level=4095)
        assert res.problem is None
        centre = res.centre_depth(threshold=0.05)
        assert abs(centre - truth) / truth < DEPTH_TOLERANCE, (truth, centre)
        assert abs(float(np.median(res.depth)) - truth) / truth < DEPTH_TOLERANCE, (truth, np.median(res.depth))


def test_swapped_frames_give_the_wrong_depth(rt, plane_pairs):
    """The frame order matters: the same planes with f1 and f2 exchanged are far off."""
    for f1, f2, truth in plane_pairs:
        swapped = float(np.median(rt(f2, f1, white_level=4095).depth))
        assert abs(swapped - truth) / truth > 3 * DEPTH_TOLERANCE, (truth, swapped)


def test_batch_keeps_pair_order(rt, plane_pairs):
    f1 = np.stack([p[0] for p in plane_pairs])[:, None]
    f2 = np.stack([p[1] for p in plane_pairs])[:, None]
    res = rt(f1, f2, white_level=4095)
    truth = np.array([p[2] for p in plane_pairs])
    np.testing.assert_allclose(np.median(res.depth.reshape(len(truth), -1), 1), truth, rtol=DEPTH_TOLERANCE)
    assert res.problems == (None,) * len(truth)


def test_identical_frames_are_unconfident(rt, plane_pairs):
    f1, _, _ = plane_pairs[0]
    raw = DepthRuntime.run(rt, *(np.ascontiguousarray(x.astype(np.float32)[None, None] / 4095) for x in (f1, f1)))
    assert float(np.median(raw[1])) > 0.5  # the bare model would vouch for it
    res = rt(f1, f1.copy(), white_level=4095)
    assert res.problem == "frames are identical: the lens did not move"
    assert float(res.confidence.max()) < 0.1 and res.valid_fraction() == 0.0
    assert np.isnan(res.centre_depth())
    assert np.all(np.isfinite(res.depth)) and np.all(res.depth > 0)
    full = res.at_full_resolution()
    assert full.problem == res.problem and float(full.confidence.max()) < 0.1


@pytest.mark.parametrize("which", [0, 1])
def test_a_black_frame_is_unconfident(rt, plane_pairs, which):
    f1, f2, _ = plane_pairs[1]
    frames = [f1, f2]
    frames[which] = np.zeros_like(f1)
    res = rt(*frames, white_level=4095)
    assert res.problem.startswith(("first" if which == 0 else "second") + " frame is black"), res.problem
    assert float(res.confidence.max()) < 0.1


def test_a_black_level_frame_is_unconfident(rt, plane_pairs):
    """A dark frame as a real sensor reads it: black level (64 DN) plus read noise."""
    f1, _, _ = plane_pairs[2]
    dark = (64 + np.random.default_rng(5).normal(0, 3, f1.shape)).round().astype(np.uint16)
    res = rt(f1, dark, white_level=4095)
    assert res.problem is not None and "second frame" in res.problem
    assert float(res.confidence.max()) < 0.1


def test_problems_are_per_pair_in_a_batch(rt, plane_pairs):
    f1, f2, truth = plane_pairs[3]
    a = np.stack([f1, f1, f1])[:, None]
    b = np.stack([f2, f1, np.zeros_like(f1)])[:, None]
    res = rt(a, b, white_level=4095)
    assert res.problems[0] is None and "identical" in res.problems[1] and "black" in res.problems[2]
    assert float(res.confidence[0].max()) > 0.1 and float(res.confidence[1:].max()) == 0.0
    assert abs(float(np.median(res.depth[0])) - truth) / truth < DEPTH_TOLERANCE


def test_pair_problem_cases():
    rng = np.random.default_rng(0)
    f = rng.random((64, 80), dtype=np.float32) * 0.8 + 0.1
    g = np.clip(f + rng.normal(0, 0.01, f.shape).astype(np.float32), 0, 1)
    assert pair_problem(f, g) is None
    assert pair_problem(f, f.copy()) == "frames are identical: the lens did not move"
    nearly = f.copy()
    nearly[0, :10] += 0.01  # a few changed pixels (< 0.5 %) are still the same frame
    assert pair_problem(f, nearly) == "frames are identical: the lens did not move"
    assert pair_problem(f, np.zeros_like(f)).startswith("second frame is black")
    assert pair_problem(np.zeros_like(f), f).startswith("first frame is black")
    assert pair_problem(np.zeros_like(f), np.zeros_like(f)).startswith("both frames are black")
    assert pair_problem(f, 0.3 * f).startswith("second frame is much darker than the first")
    assert pair_problem(0.3 * f, f).startswith("first frame is much darker than the second")
    sat = np.ones_like(f)
    sat[:10] = f[:10]
    assert pair_problem(sat, np.clip(sat * 1.01, 0, 1)).startswith("first frame is saturated")
    u16 = np.round(f * 4095).astype(np.uint16)
    assert pair_problem(u16, np.round(g * 4095).astype(np.uint16), white_level=4095) is None
    assert pair_problem(u16, u16 // 8, white_level=4095).startswith("second frame is")
    with pytest.raises(ShapeError, match="empty"):
        pair_problem(np.zeros((0, 4)), np.zeros((0, 4)))
    with pytest.raises(ShapeError, match="differ in shape"):
        pair_problem(f, f[:-1])


@pytest.mark.parametrize("shape", [(0, 64), (64, 0), (0, 1, 64, 64), (1, 0, 64)])
def test_empty_arrays_raise_a_typed_error(rt, shape):
    for dtype in (np.float32, np.uint16):
        with pytest.raises(ShapeError):
            rt(np.zeros(shape, dtype), np.zeros(shape, dtype))


def test_onnxruntime_failure_is_a_model_error(rt, plane_pairs):
    f1, f2, _ = plane_pairs[0]
    a = f1.astype(np.float64)[None, None] / 4095
    with pytest.raises(ModelError, match="onnxruntime failed running reference.onnx"):
        rt.run(a, f2.astype(np.float64)[None, None] / 4095)  # float64 where the graph takes float32
    with pytest.raises(ModelError, match="onnxruntime failed"):
        rt.run(np.ones((64, 64), np.float32), np.ones((64, 64), np.float32))  # rank 2 where it takes rank 4


def test_a_model_that_fails_while_running_is_a_model_error(tmp_path, plane_pairs):
    """A model file that loads but fails inside the session: a Reshape to an impossible shape."""
    import json

    import onnx
    from onnx import TensorProto, helper

    from tdfd import Camera

    x1 = helper.make_tensor_value_info("image_f1", TensorProto.FLOAT, ["N", 1, "H", "W"])
    x2 = helper.make_tensor_value_info("image_f2", TensorProto.FLOAT, ["N", 1, "H", "W"])
    names = ("depth", "confidence", "depth_analytic")
    outs = [helper.make_tensor_value_info(n, TensorProto.FLOAT, None) for n in names]
    shape = helper.make_tensor("shape", TensorProto.INT64, [2], [7, 11])
    nodes = [helper.make_node("Reshape", ["image_f1", "shape"], [n]) for n in names]
    m = helper.make_model(helper.make_graph(nodes, "broken", [x1, x2], outs, initializer=[shape]),
                          opset_imports=[helper.make_opsetid("", 18)], ir_version=10)
    meta = {"tdfd.camera": json.dumps(Camera.preset("reference").to_dict()), "tdfd.grid": '{"tile": 64, "stride": 32}',
            "tdfd.version": '"0.1.0"'}
    for k, v in meta.items():
        m.metadata_props.add(key=k, value=v)
    path = tmp_path / "broken.onnx"
    onnx.save(m, str(path))
    f1, f2, _ = plane_pairs[0]
    with pytest.raises(ModelError, match="onnxruntime failed running broken.onnx"):
        DepthRuntime(path)(f1, f2, white_level=4095)


def test_a_truncated_model_file_is_a_model_error(tmp_path, shipped_onnx):
    cut = tmp_path / "cut.onnx"
    cut.write_bytes(shipped_onnx.read_bytes()[: shipped_onnx.stat().st_size // 2])
    with pytest.raises(ModelError, match="cannot load"):
        DepthRuntime(cut)
