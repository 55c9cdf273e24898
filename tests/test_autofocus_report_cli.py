"""The autofocus report (CONTRACT.md section 3), the CLI, the ONNX estimator and the hardware path."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from tdfd import Camera
from tdfd.autofocus.sim import TrialRecord
from tdfd.autofocus.report import EXTRA_TRIAL_KEYS, TRIAL_KEYS, build_report, format_summary, format_table, summarise, write_report
from tdfd.cli import main

CAM = Camera.preset("reference")
CONTRACT_KEYS = {"target_depth_m", "estimated_depth_m", "ideal_power_dpt", "final_power_dpt", "residual_blur_px",
                 "frames", "lens_commands", "time_ms", "method"}


def _records():
    ok = TrialRecord(0.5, 0.502, 2.0, 2.01, 0.05, 2, 3, 57.4, "dfd", trial=0, compute_ms=3.0, confidence=0.9)
    fb = TrialRecord(0.7, 0.69, 1.43, 1.44, 0.05, 9, 11, 190.0, "contrast", requested="dfd", trial=1,
                     reason="DFD confidence 0.001 below 0.050", confidence=0.001)
    bad = TrialRecord(0.4, None, 2.5, 1.7, 3.8, 1, 3, 30.0, "dfd", status="failed", trial=2,
                      reason="lens did not accept 2.7 dpt after 3 attempts: LensTimeoutError")
    c1 = TrialRecord(0.5, None, 2.0, 2.05, 0.2, 6, 8, 126.0, "contrast", requested="contrast", trial=0)
    return [ok, c1, fb, bad]


def test_report_has_the_contract_keys_and_the_declaration(tmp_path):
    assert set(TRIAL_KEYS) == CONTRACT_KEYS
    recs = _records()
    report = write_report(tmp_path / "sub" / "af.json", recs, {"seed": 0})
    data = json.loads((tmp_path / "sub" / "af.json").read_text())
    assert data == report and set(data) == {"trials", "summary"}
    assert all(set(t) == CONTRACT_KEYS | set(EXTRA_TRIAL_KEYS) for t in data["trials"])
    assert [t["declared"] for t in data["trials"]] == [True, True, True, False]
    assert data["trials"][3]["estimated_depth_m"] is None and data["trials"][2]["method"] == "contrast"
    s = data["summary"]
    dfd = s["methods"]["dfd"]
    assert dfd["trials"] == 3 and dfd["in_focus"] == 2 and dfd["success_rate"] == pytest.approx(2 / 3, abs=1e-4)
    assert dfd["success_rate_max3_frames"] == pytest.approx(1 / 3, abs=1e-4)
    assert dfd["fallbacks"] == 1 and dfd["failures"] == 1
    assert s["methods"]["contrast"]["frames"]["median"] == 6
    assert s["contrast_to_dfd_frames"] == pytest.approx(6 / 2)
    reasons = [n["reason"] for n in s["notes"]]
    assert any("confidence" in r for r in reasons) and any("LensTimeoutError" in r for r in reasons)
    assert s["settings"] == {"seed": 0}


def test_table_and_summary_are_readable():
    recs = _records()
    table = format_table(recs)
    assert "in focus" in table and "FAILED" in table and "fell back to contrast" in table
    assert "declared on" in table
    text = format_summary(summarise(recs))
    assert "dfd" in text and "contrast AF needs 3.00x the frames" in text


def test_nan_is_null():
    r = TrialRecord(0.5, math.nan, 2.0, 2.0, 0.0, 2, 3, math.inf, "dfd")
    t = build_report([r])["trials"][0]
    assert t["estimated_depth_m"] is None and t["time_ms"] is None


def test_cli_sim_end_to_end(tmp_path, capsys):
    out = tmp_path / "af.json"
    rc = main(["autofocus", "--sim", "--trials", "2", "--json", str(out), "--model", "analytic", "--compute", "5",
               "--readout", "192x256", "--no-progress"])
    text = capsys.readouterr().out
    assert "target m" in text and "contrast AF needs" in text and "report written" in text
    data = json.loads(out.read_text())
    assert len(data["trials"]) == 4 and all(set(t) == CONTRACT_KEYS | set(EXTRA_TRIAL_KEYS) for t in data["trials"])
    assert all(t["declared"] == (t["evidence"] is not None) for t in data["trials"])
    assert {t["method"] for t in data["trials"]} <= {"dfd", "contrast"}
    assert data["summary"]["settings"]["compute_ms_per_estimate"] == pytest.approx(5.0)
    assert rc == 0


def test_cli_errors(capsys):
    assert main(["autofocus"]) == 1
    assert "--sim" in capsys.readouterr().err
    assert main(["autofocus", "--sim", "--port", "/dev/null"]) == 1
    assert main(["autofocus", "--sim", "--scene", "x.png", "--model", "analytic"]) == 1
    assert "--scene-depth" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["autofocus", "--sim", "--readout", "big"])


# -------------------------------------------------------------------------- ONNX adapter
def _toy_onnx(path, tile=64, stride=32):
    """A contract-shaped ONNX file: depth = 0.25 + tile mean of image_f1, confidence 0.8."""
    import onnx
    from onnx import TensorProto, helper

    x1 = helper.make_tensor_value_info("image_f1", TensorProto.FLOAT, ["N", 1, "H", "W"])
    x2 = helper.make_tensor_value_info("image_f2", TensorProto.FLOAT, ["N", 1, "H", "W"])
    outs = [helper.make_tensor_value_info(n, TensorProto.FLOAT, None) for n in ("depth", "confidence", "depth_analytic")]
    c = lambda name, v: helper.make_node("Constant", [], [name], value=helper.make_tensor(name, TensorProto.FLOAT, [], [v]))  # noqa: E731
    nodes = [
        helper.make_node("AveragePool", ["image_f1"], ["m1"], kernel_shape=[tile, tile], strides=[stride, stride]),
        helper.make_node("AveragePool", ["image_f2"], ["m2"], kernel_shape=[tile, tile], strides=[stride, stride]),
        c("q", 0.25), c("z", 0.0), c("e", 0.8),
        helper.make_node("Add", ["m1", "q"], ["depth"]),
        helper.make_node("Mul", ["m2", "z"], ["m2z"]),
        helper.make_node("Add", ["m2z", "e"], ["confidence"]),
        helper.make_node("Identity", ["depth"], ["depth_analytic"]),
    ]
    graph = helper.make_graph(nodes, "toy", [x1, x2], outs)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)])
    model.ir_version = 9
    for k, v in {"tdfd.camera": CAM.to_json(), "tdfd.grid": json.dumps({"tile": tile, "stride": stride}),
                 "tdfd.version": json.dumps("0.1.0")}.items():
        model.metadata_props.append(onnx.StringStringEntryProto(key=k, value=v))
    onnx.save(model, str(path))
    return path


def test_onnx_estimator(tmp_path):
    from tdfd.autofocus.estimators import OnnxEstimator, load_estimator
    from tdfd.errors import ModelError

    path = _toy_onnx(tmp_path / "toy.onnx")
    est = OnnxEstimator(path)
    assert est.camera == CAM and (est.tile, est.stride) == (64, 32) and est.backend == "tdfd.runtime"
    f1 = np.full((128, 160), 0.25, np.float32)
    f2 = (0.3 + 0.1 * (np.indices((128, 160)).sum(0) % 2)).astype(np.float32)
    d, c = est(f1, f2)
    assert d.shape == (3, 4) and np.allclose(d, 0.5) and np.allclose(c, 0.8) and est.last_problem is None
    rt = load_estimator(str(path))
    assert isinstance(rt, OnnxEstimator) and rt.camera.to_dict() == CAM.to_dict()
    # a pair that is no DFD pair (the lens did not move): zero confidence and the reason kept
    d2, c2 = rt(f2, f2.copy())
    assert np.all(c2 == 0.0) and "identical" in rt.last_problem
    with pytest.raises(ModelError):
        OnnxEstimator(tmp_path / "missing.onnx")


def test_shipped_model_if_present():
    from tdfd.autofocus.estimators import OnnxEstimator, default_model_path

    assert default_model_path().is_file(), f"the shipped model {default_model_path()} is missing"
    from tdfd.autofocus.sim import SimBench

    with SimBench(estimator=OnnxEstimator(), readout_hw=(192, 256), compute_s=0.005, texture_families=("fractal",)) as b:
        recs = b.run_trials([0.35, 0.8], methods=("dfd",))
    assert all(r.in_focus and r.frames <= 3 for r in recs), [(r.target_depth_m, r.estimated_depth_m, r.reason) for r in recs]


# -------------------------------------------------------------------------- hardware path
class _EmulatedCamera:
    """A 'real' camera looking at a textured plane through the emulated lens (wall clock)."""

    def __init__(self, device, depth_m: float) -> None:
        import torch

        from tdfd.optics.render import render_at_power

        self.device, self.depth = device, depth_m
        g = torch.Generator().manual_seed(0)
        sharp = torch.rand(1, 1, 128, 160, generator=g) * 0.6 + 0.2
        self.render = lambda p: render_at_power(CAM, sharp, torch.full_like(sharp, depth_m), p)[0, 0].numpy()
        self.reads = 0

    def read(self):
        self.reads += 1
        return self.render(self.device.focal_power_dpt).astype(np.float32)

    def close(self):
        pass


def test_hardware_loop_with_emulated_lens():
    from tdfd.autofocus.estimators import AnalyticEstimator
    from tdfd.autofocus.hardware import run_hardware
    from tdfd.driver import EmulatorServer
    from tdfd.optics.thin_lens import camera_blur_radii_px

    with EmulatorServer(temperature_c=22.0) as srv:
        cam = _EmulatedCamera(srv.device, 0.42)
        res = run_hardware(srv.port, 0, AnalyticEstimator(CAM), camera=cam, temperature_limits_c=(15.0, 25.0))
        assert res.status == "focused" and res.frames == 2 and cam.reads == 2
        assert abs(float(camera_blur_radii_px(CAM, 0.42, res.power_dpt))) < 1.0
        assert srv.device.focal_power_setpoint_dpt == pytest.approx(res.power_dpt, abs=0.005)
        res = run_hardware(srv.port, 0, None, method="contrast", camera=cam, temperature_limits_c=(15.0, 25.0))
        assert res.status == "focused" and abs(float(camera_blur_radii_px(CAM, 0.42, res.power_dpt))) < 1.0


def test_hardware_dry_run_from_a_video_file(tmp_path, capsys):
    import cv2

    path = str(tmp_path / "cam.avi")
    writer = cv2.VideoWriter(path, cv2.VideoWriter_fourcc(*"MJPG"), 10, (160, 128), isColor=True)
    rng = np.random.default_rng(0)
    scene = rng.uniform(20, 235, (128, 160, 3))
    for _ in range(8):  # one scene, exposed again and again: sensor noise changes every frame
        writer.write(np.clip(scene + rng.normal(0, 3, scene.shape), 0, 255).astype(np.uint8))
    writer.release()
    rc = main(["autofocus", "--camera", path, "--dry-run", "--model", "analytic"])
    out = capsys.readouterr().out
    assert "dry run: the lens was not moved" in out and "lens commands: 0" in out
    assert rc == 0
    assert main(["autofocus", "--camera", str(tmp_path / "none.avi"), "--dry-run", "--model", "analytic"]) == 1
    assert main(["autofocus", "--camera", path, "--model", "analytic"]) == 1  # no --port, no --dry-run


def test_frame_to_linear():
    from tdfd.autofocus.hardware import frame_to_linear

    bgr = np.zeros((2, 2, 3), np.uint16)
    bgr[...] = 65535
    assert np.allclose(frame_to_linear(bgr), 1.0)
    assert frame_to_linear(np.full((1, 1), 128, np.uint8), linearise=True)[0, 0] == pytest.approx(0.2158, abs=1e-3)
    assert frame_to_linear(np.full((1, 1), 2000, np.uint16), white_level=4095)[0, 0] == pytest.approx(2000 / 4095)


def test_cli_continuous_and_faults(tmp_path, capsys):
    out = tmp_path / "cont.json"
    rc = main(["autofocus", "--sim", "--continuous", "--duration", "0.25", "--model", "analytic", "--compute", "5",
               "--readout", "192x256", "--json", str(out)])
    text = capsys.readouterr().out
    assert rc == 0 and "re-estimates:" in text and "live frames in focus" in text
    data = json.loads(out.read_text())
    assert data["result"]["status"] == "halted" and data["frames"]
    from tdfd.autofocus.cli import _faults

    f = _faults("drop=0.2,bad_crc=0.1", seed=3)
    assert (f.drop, f.bad_crc, f.seed) == (0.2, 0.1, 3) and _faults(None, 0) is None
    assert main(["autofocus", "--sim", "--faults", "explode=1", "--model", "analytic"]) == 1
