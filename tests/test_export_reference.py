"""The shipped model: ``models/reference.onnx`` passes the checker and the contract, matches
``models/reference.safetensors`` in torch, and is what the runtime finds by default.

Both files are shipped and these tests fail (never skip) when either is missing (export
the ONNX file with ``python -m export --weights models/reference.safetensors --out
models/reference.onnx``). When the library's analytic layer or model code changes, the
parity test fails until the file is exported again.
"""

from __future__ import annotations

from pathlib import Path

import onnx
import pytest

from export import check_contract, verify_onnx

ROOT = Path(__file__).resolve().parents[1]
ONNX = ROOT / "models" / "reference.onnx"
WEIGHTS = ROOT / "models" / "reference.safetensors"

@pytest.fixture(scope="module")
def model():
    from tdfd.model import DFDModel

    assert WEIGHTS.is_file(), f"the shipped weights {WEIGHTS} (that {ONNX} is exported from) are missing"
    return DFDModel.load(WEIGHTS).eval()


def test_reference_onnx_exists_and_passes_the_checker():
    assert ONNX.is_file(), f"{WEIGHTS} is shipped but {ONNX} is not: run python -m export --weights {WEIGHTS} --out {ONNX}"
    proto = onnx.load(str(ONNX))
    onnx.checker.check_model(proto, full_check=True)
    assert not list(ONNX.parent.glob("reference.onnx.data")), "the ONNX file must be self-contained"


def test_reference_onnx_follows_the_contract_and_the_weights(model):
    proto = onnx.load(str(ONNX))
    meta = check_contract(proto, model)
    assert meta["tdfd.grid"] == {"tile": model.tile, "stride": model.stride}


def test_reference_onnx_matches_torch(model):
    report = verify_onnx(ONNX, model, sizes=[(64, 64), (150, 203), (256, 320)], batches=[1, 2])
    assert report.worst_depth_rel <= 1e-4


def test_runtime_finds_the_shipped_model(monkeypatch):
    from tdfd.runtime import DepthRuntime, default_model_path

    monkeypatch.delenv("TDFD_MODEL", raising=False)
    assert default_model_path() == ONNX
    rt = DepthRuntime()
    assert rt.path == ONNX and (rt.tile, rt.stride) == (64, 32)
