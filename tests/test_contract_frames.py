"""The contract's names, raw-frame conversion and the in-focus power, each written once
(tdfd/contract.py, tdfd/frames.py, tdfd/camera.py) and torch-free."""

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tdfd import Camera
from tdfd.camera import in_focus_power_dpt
from tdfd.contract import DEFAULT_MODEL_RELPATH, INPUT_NAMES, METADATA_KEYS, OUTPUT_NAMES, POOLED_OUTPUT_NAMES
from tdfd.errors import DTypeError, NonFiniteError, RangeError
from tdfd.frames import raw_to_linear

ROOT = Path(__file__).resolve().parents[1]
CAM = Camera.preset("reference")


def test_contract_matches_the_written_contract_and_the_shipped_file():
    import onnx

    # typed in from CONTRACT.md section 2
    assert INPUT_NAMES == ("image_f1", "image_f2") and OUTPUT_NAMES == ("depth", "confidence", "depth_analytic")
    assert METADATA_KEYS == ("tdfd.camera", "tdfd.grid", "tdfd.version")
    shipped = onnx.load(str(ROOT / DEFAULT_MODEL_RELPATH), load_external_data=False)
    assert tuple(i.name for i in shipped.graph.input) == INPUT_NAMES
    # the contract's three outputs first, in its order; the shipped model adds its structure-pooled map after them
    assert tuple(o.name for o in shipped.graph.output) == OUTPUT_NAMES + ("depth_pooled", "confidence_pooled")
    assert POOLED_OUTPUT_NAMES == ("depth_pooled", "confidence_pooled")
    assert set(METADATA_KEYS) <= {p.key for p in shipped.metadata_props}
    import export
    import tdfd.runtime as rt

    assert export.INPUT_NAMES is INPUT_NAMES and rt.OUTPUT_NAMES is OUTPUT_NAMES  # one definition


def test_contract_frames_and_camera_import_without_torch():
    code = ("import sys; sys.modules['torch'] = None\n"
            "import tdfd.contract, tdfd.frames, tdfd.camera, tdfd.runtime\nprint('ok')")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr


def test_raw_to_linear_scales_and_raises_above_white():
    a = np.array([[0, 2048, 4095]], np.uint16)
    np.testing.assert_array_equal(raw_to_linear(a, 4095), np.array([[0, 2048 / 4095, 1]], np.float32))
    assert raw_to_linear(np.array([255], np.uint8)).tolist() == [1.0]
    with pytest.raises(RangeError, match="image_f2 has values up to 4096, above the white level 4095"):
        raw_to_linear(np.array([4096], np.uint16), 4095, name="image_f2")
    with pytest.raises(RangeError, match="white_level"):
        raw_to_linear(a, 0)
    with pytest.raises(RangeError, match="frame has values in"):
        raw_to_linear(np.array([0.5, 1.01], np.float32))
    assert raw_to_linear(np.array([1.0 + 5e-7, -5e-7])).tolist() == [1.0, 0.0]  # rounding only: clipped
    with pytest.raises(NonFiniteError):
        raw_to_linear(np.array([np.nan], np.float32))
    with pytest.raises(DTypeError):
        raw_to_linear(np.array([1], np.int32))
    with pytest.raises(DTypeError):
        raw_to_linear([0.5])


def test_in_focus_power_formula_infinity_and_errors():
    assert CAM.in_focus_power_dpt(0.5) == pytest.approx(2.0)
    assert in_focus_power_dpt(CAM, 0.5) == CAM.in_focus_power_dpt(0.5)
    # infinity focuses at infinity: the reference camera's ECVFL at 0 dpt
    assert CAM.in_focus_power_dpt(math.inf) == pytest.approx(1 / CAM.sensor_distance_m - 1 / CAM.fixed_focal_length_m)
    assert CAM.focus_distance_m(CAM.in_focus_power_dpt(math.inf)) == math.inf
    # outside the working range the formula holds
    assert CAM.in_focus_power_dpt(5.0) == pytest.approx(0.2) and CAM.in_focus_power_dpt(0.1) == pytest.approx(10.0)
    np.testing.assert_allclose(CAM.in_focus_power_dpt(np.array([0.25, np.inf])), [4.0, 0.0], atol=1e-9)
    for bad in (0.0, -0.3, math.nan, -math.inf, np.array([0.5, np.nan]), "far"):
        with pytest.raises(RangeError):
            CAM.in_focus_power_dpt(bad)
