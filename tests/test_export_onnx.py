"""ONNX export of the combined model: checker, contract, metadata, parity with torch.

The model is exported once per session (``export.testing.session_onnx_model``). Nothing
here is skipped on an exception: a broken export fails these tests.
"""

from __future__ import annotations

import json

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch

import tdfd
from export import INPUT_NAMES, OUTPUT_NAMES, check_contract, export_model, realistic_pairs, verify_onnx
from export.standin import analytic_model
from export.testing import session_onnx_model
from tdfd import Camera
from tdfd.errors import ModelError
from tests.onnx_parity import assert_parity


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    return session_onnx_model(tmp_path_factory)


@pytest.fixture(scope="module")
def proto(exported):
    return onnx.load(str(exported[0]))


def test_checker_full_check_passes(proto):
    onnx.checker.check_model(proto, full_check=True)


def test_single_file_opset_and_no_external_data(exported, proto):
    path = exported[0]
    assert [p.name for p in path.parent.iterdir() if p.name.startswith(path.stem)] == [path.name]
    assert all(init.data_location != onnx.TensorProto.EXTERNAL for init in proto.graph.initializer)
    assert {o.domain: o.version for o in proto.opset_import}.get("", 0) >= 18


def _dims(v):
    return [d.dim_param if d.HasField("dim_param") else d.dim_value for d in v.type.tensor_type.shape.dim]


def test_inputs_outputs_names_dtypes_ranks_dynamic(proto):
    assert [i.name for i in proto.graph.input] == ["image_f1", "image_f2"]
    assert [o.name for o in proto.graph.output] == ["depth", "confidence", "depth_analytic"]
    for v in list(proto.graph.input) + list(proto.graph.output):
        assert v.type.tensor_type.elem_type == onnx.TensorProto.FLOAT
        dims = _dims(v)
        assert len(dims) == 4 and dims[1] == 1
        assert all(isinstance(dims[i], str) and dims[i] for i in (0, 2, 3)), dims
    assert _dims(proto.graph.input[0]) == _dims(proto.graph.input[1])


def test_metadata_json_matches_model(exported, proto):
    _, model = exported
    meta = {p.key: p.value for p in proto.metadata_props}
    assert json.loads(meta["tdfd.camera"]) == model.camera.to_dict() == Camera.preset("reference").to_dict()
    assert json.loads(meta["tdfd.grid"]) == {"tile": 64, "stride": 32}
    assert json.loads(meta["tdfd.version"]) == tdfd.__version__
    assert Camera.from_dict(json.loads(meta["tdfd.camera"])) == model.camera
    parsed = check_contract(proto, model)
    assert parsed["tdfd.grid"] == {"tile": 64, "stride": 32}


def test_parity_with_torch_sizes_and_batches(exported):
    path, model = exported
    # one tile (h = w = 1), sizes that are no multiple of the stride, batches 1 and 3
    report = verify_onnx(path, model, sizes=[(64, 64), (97, 161), (200, 330)], batches=[1, 3])
    assert_parity(report, cases=6)
    assert "parity OK" in str(report)


def test_refinement_is_exercised_and_grid_is_symbolic(exported):
    path, model = exported
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    for h, w in [(64, 200), (131, 64), (333, 250)]:
        i1, i2 = realistic_pairs(model.camera, 2, h, w, seed=h + w)
        depth, conf, depth_a = sess.run(None, {"image_f1": i1.numpy(), "image_f2": i2.numpy()})
        gh, gw = (h - 64) // 32 + 1, (w - 64) // 32 + 1
        assert depth.shape == conf.shape == depth_a.shape == (2, 1, gh, gw)
        assert not np.allclose(depth, depth_a)  # the CNN changes the analytic depth
        assert np.all((conf >= 0) & (conf <= 1)) and np.all(depth > 0)


def test_verify_fails_loudly_when_onnx_and_torch_disagree(exported):
    path, model = exported
    with torch.no_grad():
        model.refine.head.bias[0] += 0.05  # 0.05 dpt shift: ~2.5% depth at 0.5 m
    try:
        with pytest.raises(ModelError, match=r"disagrees with torch.*worst depth"):
            verify_onnx(path, model, sizes=[(96, 128)], batches=[1])
    finally:
        with torch.no_grad():
            model.refine.head.bias[0] -= 0.05
    verify_onnx(path, model, sizes=[(96, 128)], batches=[1])


def test_contract_check_rejects_broken_files(exported, proto, tmp_path):
    _, model = exported
    bad = onnx.ModelProto()
    bad.CopyFrom(proto)
    del bad.metadata_props[:]
    with pytest.raises(ModelError, match="tdfd.camera"):
        check_contract(bad, model)
    bad.CopyFrom(proto)
    for p in bad.metadata_props:
        if p.key == "tdfd.grid":
            p.value = json.dumps({"tile": 32, "stride": 32})
    with pytest.raises(ModelError, match="grid"):
        check_contract(bad, model)
    bad.CopyFrom(proto)
    bad.graph.input[0].type.tensor_type.shape.dim[2].dim_value = 480
    with pytest.raises(ModelError, match="dynamic"):
        check_contract(bad, model)
    bad.CopyFrom(proto)
    bad.graph.output[0].name = "distance"
    with pytest.raises(ModelError, match="outputs"):
        check_contract(bad, model)
    with pytest.raises(ModelError, match="does not exist"):
        verify_onnx(tmp_path / "missing.onnx")
    junk = tmp_path / "junk.onnx"
    junk.write_bytes(b"not a model")
    with pytest.raises(ModelError):
        verify_onnx(junk)


def test_export_rejects_bad_models_and_opsets(tmp_path):
    with pytest.raises(ModelError, match="opset"):
        export_model(analytic_model(), tmp_path / "a.onnx", opset=17)

    class NoCamera(torch.nn.Module):
        def forward(self, a, b):
            return a, a, a

    with pytest.raises(ModelError, match="camera"):
        export_model(NoCamera(), tmp_path / "b.onnx")

    class TwoOutputs(torch.nn.Module):
        camera, tile, stride = Camera.preset("reference"), 64, 32

        def forward(self, a, b):
            return a, b

    with pytest.raises(ModelError, match="must return"):
        export_model(TwoOutputs(), tmp_path / "c.onnx")


def test_export_mode_disables_validation_and_restores_it():
    from export.onnx_export import _export_mode
    from export.testing import make_test_model

    model = make_test_model()
    model.train()
    flags = lambda: [m.validate for m in model.modules() if isinstance(getattr(m, "validate", None), bool)]  # noqa: E731
    before = flags()
    assert True in before
    with _export_mode(model):
        assert not any(flags()) and not model.training
    assert flags() == before and model.training
    assert len(INPUT_NAMES) == 2 and len(OUTPUT_NAMES) == 3


def test_ring_sums_from_coefficients_equal_per_bin_powers():
    """TileSpectra.ring_weights: the cross terms of +ky/-ky bins cancel in half-plane ring sums,
    so squared DFT coefficients give the ring powers without per-bin powers (the fast path)."""
    import torch.nn.functional as F

    from tdfd.dfd import FourierRatioDFD

    analytic = FourierRatioDFD(Camera.preset("reference"), tile=64, stride=32).double()
    spec = analytic.spectra
    x = torch.rand(2, 1, 150, 203, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    rings = torch.arange(analytic.min_bin, spec.max_bin + 1)
    a = spec.coefficients(x)
    assert a.shape == (2, 4 * (spec.max_bin + 1) ** 2, 3, 5)
    fast = F.conv2d(a * a, spec.ring_weights(rings)[:, :, None, None])
    radius = torch.round(torch.sqrt(spec.ky.double() ** 2 + spec.kx.double() ** 2))
    member = (radius[None, :] == rings.double()[:, None]).double()  # (R, bins): each half-plane bin once
    slow = F.conv2d(spec(x), member[:, :, None, None])
    torch.testing.assert_close(fast, slow, rtol=1e-12, atol=0.0)
