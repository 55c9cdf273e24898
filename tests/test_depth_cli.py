"""``tdfd depth``: on 16-bit PNGs written by the synthesis CLI, outputs, one-line errors, no torch."""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from tdfd.cli import main
from tdfd.contract import MODEL_KEY
from tdfd.depth_cli import _nice_ticks, colorize_depth, read_frame
from tdfd.errors import InputError, ModelError
from tdfd.runtime import DepthRuntime
from tdfd.runtime_likelihood import refine_result, stage_for_runtime

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def model_path(exported_onnx):
    return exported_onnx[0]


@pytest.fixture(scope="module")
def synth_pngs(tmp_path_factory):
    """Two pairs from ``python -m data_synth --png16`` (the synthesis CLI), 160x224 pixels."""
    out = tmp_path_factory.mktemp("synth")
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    run = subprocess.run([sys.executable, "-m", "data_synth", "--out", str(out), "--count", "2", "--size", "160x224",
                          "--families", "fractal,dead_leaves", "--png16", "-q"],
                         capture_output=True, text=True, cwd=ROOT, env=env, timeout=300)
    assert run.returncode == 0, run.stderr
    pngs = out / "png16"
    return [(pngs / f"pair_{i:05d}_f1.png", pngs / f"pair_{i:05d}_f2.png", pngs / f"pair_{i:05d}_depth.npy")
            for i in range(2)]


def _run(capsys, *args):
    rc = main(["depth", *map(str, args)])
    out = capsys.readouterr()
    return rc, out.out, out.err


def test_depth_on_synthesis_pngs_npy(synth_pngs, model_path, tmp_path, capsys):
    f1, f2, truth = synth_pngs[0]
    assert cv2.imread(str(f1), cv2.IMREAD_UNCHANGED).dtype == np.uint16
    out = tmp_path / "depth.npy"
    rc, stdout, err = _run(capsys, f1, f2, "--model", model_path, "-o", out)
    assert rc == 0, err
    assert "centre depth:" in stdout and "valid:" in stdout and "cells (confidence >= 0.1)" in stdout
    depth = np.load(out)
    assert depth.shape == ((160 - 64) // 32 + 1, (224 - 64) // 32 + 1) and depth.dtype == np.float32
    assert np.all(depth > 0)
    colour = cv2.imread(str(tmp_path / "depth_color.png"), cv2.IMREAD_UNCHANGED)
    assert colour.ndim == 3 and colour.shape[2] == 3 and colour.shape[0] > 160 and colour.shape[1] >= 224
    assert np.isfinite(np.load(truth)).all()


def test_depth_tiff_full_resolution_and_png_mm(synth_pngs, model_path, tmp_path, capsys):
    f1, f2, _ = synth_pngs[1]
    rc, _, err = _run(capsys, f1, f2, "--model", model_path, "-o", tmp_path / "d.tiff", "--full-resolution")
    assert rc == 0, err
    tiff = cv2.imread(str(tmp_path / "d.tiff"), cv2.IMREAD_UNCHANGED)
    assert tiff.shape == (160, 224) and tiff.dtype == np.float32
    rc, _, err = _run(capsys, f1, f2, "--model", model_path, "-o", tmp_path / "d.png", "--threshold", "0")
    assert rc == 0, err
    mm = cv2.imread(str(tmp_path / "d.png"), cv2.IMREAD_UNCHANGED)
    assert mm.dtype == np.uint16 and mm.shape == (4, 6)
    np.testing.assert_allclose(mm / 1000.0, cv2.resize(tiff, (6, 4), interpolation=cv2.INTER_AREA), rtol=0.5)
    assert (tmp_path / "d_color.png").is_file() and (tmp_path / "d_color.png").stat().st_size > 1000


def test_env_model_and_eight_bit(synth_pngs, model_path, tmp_path, capsys, monkeypatch):
    f1, f2, _ = synth_pngs[0]
    for src, name in ((f1, "a.png"), (f2, "b.png")):
        im = cv2.imread(str(src), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(tmp_path / name), (im // 257).astype(np.uint8))
    monkeypatch.setenv("TDFD_MODEL", str(model_path))
    rc, stdout, err = _run(capsys, tmp_path / "a.png", tmp_path / "b.png")
    assert rc == 0, err
    assert "uint8" in stdout


def _one_line_error(rc, err, pattern):
    assert rc == 1
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("tdfd depth: error: ")
    assert pattern in lines[0], lines[0]


def test_errors_are_one_line(synth_pngs, model_path, tmp_path, capsys):
    f1, f2, _ = synth_pngs[0]
    im = cv2.imread(str(f1), cv2.IMREAD_UNCHANGED)
    small = tmp_path / "small.png"
    cv2.imwrite(str(small), im[:100, :150])
    _one_line_error(*_run(capsys, f1, small, "--model", model_path)[::2], "same size")
    _one_line_error(*_run(capsys, f1, tmp_path / "missing.png", "--model", model_path)[::2], "no such file")
    junk = tmp_path / "junk.png"
    junk.write_bytes(b"\x89PNG\r\n\x1a\n" + b"garbage" * 10)
    _one_line_error(*_run(capsys, junk, f2, "--model", model_path)[::2], "cannot read")
    colour = tmp_path / "colour.png"
    cv2.imwrite(str(colour), np.stack([im] * 3, -1))
    _one_line_error(*_run(capsys, colour, colour, "--model", model_path)[::2], "3 channels")
    f64 = tmp_path / "f64.tiff"
    cv2.imwrite(str(f64), im.astype(np.float64) / 65535.0)
    _one_line_error(*_run(capsys, f64, f64, "--model", model_path)[::2], "float64")
    i16 = tmp_path / "i16.tiff"
    cv2.imwrite(str(i16), (im // 2).astype(np.int16))
    _one_line_error(*_run(capsys, i16, i16, "--model", model_path)[::2], "int16")
    eight = tmp_path / "eight.png"
    cv2.imwrite(str(eight), (im // 257).astype(np.uint8))
    _one_line_error(*_run(capsys, f1, eight, "--model", model_path)[::2], "uint8")
    _one_line_error(*_run(capsys, f1, f2, "--model", tmp_path / "none.onnx")[::2], "does not exist")
    _one_line_error(*_run(capsys, f1, f2, "--model", model_path, "-o", tmp_path / "d.jpg")[::2], ".npy")
    _one_line_error(*_run(capsys, f1, f2, "--model", model_path, "--white-level", "1000")[::2], "white level")
    tiny = tmp_path / "tiny.png"
    cv2.imwrite(str(tiny), im[:40, :40])
    _one_line_error(*_run(capsys, tiny, tiny, "--model", model_path)[::2], "smaller than one 64x64 tile")


def test_float32_tiff_accepted(synth_pngs, model_path, tmp_path, capsys):
    f1, f2, _ = synth_pngs[0]
    for src, name in ((f1, "a.tiff"), (f2, "b.tiff")):
        cv2.imwrite(str(tmp_path / name), cv2.imread(str(src), cv2.IMREAD_UNCHANGED).astype(np.float32) / 65535.0)
    assert read_frame(tmp_path / "a.tiff").dtype == np.float32
    rc, stdout, err = _run(capsys, tmp_path / "a.tiff", tmp_path / "b.tiff", "--model", model_path)
    assert rc == 0, err
    assert "float32" in stdout


def test_cli_needs_no_torch(synth_pngs, model_path, tmp_path):
    f1, f2, _ = synth_pngs[0]
    code = ("import sys\nsys.modules['torch'] = None\nfrom tdfd.cli import main\n"
            f"sys.exit(main(['depth', {str(f1)!r}, {str(f2)!r}, '--model', {str(model_path)!r}, '-o', "
            f"{str(tmp_path / 'x.npy')!r}]))\n")
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, env=env, timeout=120)
    assert out.returncode == 0, out.stderr
    assert (tmp_path / "x.npy").is_file() and (tmp_path / "x_color.png").is_file()


def test_colorize_and_ticks():
    depth = np.linspace(0.3, 1.0, 64 * 80, dtype=np.float32).reshape(64, 80)
    conf = np.ones_like(depth)
    conf[:10] = 0
    pic = colorize_depth(depth, conf, (0.3, 1.0))
    assert pic.dtype == np.uint8 and pic.shape[1] >= 480 and pic.shape[0] == 64 * 6 + 60
    assert _nice_ticks(0.3, 1.0) == [0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0]
    assert _nice_ticks(0.2, 3.0)[0] == 0.5


# ------------------------------------------------------------------ against the truth (shipped model)
def _write_pair(tmp_path, f1, f2, name):
    a, b = tmp_path / f"{name}_f1.png", tmp_path / f"{name}_f2.png"
    assert cv2.imwrite(str(a), f1) and cv2.imwrite(str(b), f2)
    return a, b


def test_depth_of_rendered_planes_matches_the_truth(plane_pairs, shipped_onnx, tmp_path, capsys):
    """12-bit frames in 16-bit PNGs: the printed centre depth and the written map are the plane's.

    The threshold is 0.05, not the default 0.1: the plane at 0.7 m is estimated within 2 %, but
    the shipped model states a median error near 3 % there (confidence about 0.09; its planes
    err 3.7 % at 0.6-0.7 m, docs/BENCHMARKS.md), which the default calls unreliable."""
    for k, (f1, f2, truth) in enumerate(plane_pairs):
        a, b = _write_pair(tmp_path, f1, f2, f"plane{k}")
        out = tmp_path / f"plane{k}.npy"
        rc, stdout, err = _run(capsys, a, b, "--model", shipped_onnx, "--white-level", "4095", "--threshold", "0.05",
                               "-o", out)
        assert rc == 0, err
        line = next(s for s in stdout.splitlines() if s.startswith("centre depth:"))
        centre = float(line.split()[2])
        assert abs(centre - truth) / truth < 0.05, (truth, line)
        assert abs(float(np.median(np.load(out))) - truth) / truth < 0.05
        power = float(line.split("in-focus ECVFL power")[1].split()[0])
        assert power == pytest.approx(1.0 / centre, abs=2e-3)  # reference camera: P = 1/d


def test_identical_and_black_frames_are_reported(plane_pairs, shipped_onnx, tmp_path, capsys):
    f1, _, _ = plane_pairs[0]
    a, _ = _write_pair(tmp_path, f1, f1, "same")
    rc, stdout, err = _run(capsys, a, a, "--model", shipped_onnx, "--white-level", "4095")
    assert rc == 0, err
    assert "no DFD pair: frames are identical: the lens did not move" in stdout
    assert "UNRELIABLE" in stdout and "valid: 0.0%" in stdout
    black = tmp_path / "black.png"
    cv2.imwrite(str(black), np.zeros_like(f1))
    rc, stdout, err = _run(capsys, a, black, "--model", shipped_onnx, "--white-level", "4095")
    assert rc == 0 and "no DFD pair: second frame is black" in stdout, stdout


def test_unwritable_output_is_one_line(plane_pairs, shipped_onnx, tmp_path, capsys):
    f1, f2, _ = plane_pairs[0]
    a, b = _write_pair(tmp_path, f1, f2, "w")
    blocker = tmp_path / "file"
    blocker.write_text("x")
    rc, stdout, err = _run(capsys, a, b, "--model", shipped_onnx, "-o", blocker / "sub" / "d.npy")
    _one_line_error(rc, err, "cannot write")
    assert stdout == ""  # checked before any work
    # the folder exists and passes the check, but the write itself fails (procfs takes no new files, even from root)
    rc, stdout, err = _run(capsys, a, b, "--model", shipped_onnx, "-o", "/proc/tdfd_depth.npy")
    _one_line_error(rc, err, "cannot write /proc/tdfd_depth.npy")
    assert "centre depth:" in stdout
    folder = tmp_path / "x.npy"
    folder.mkdir()
    _one_line_error(*_run(capsys, a, b, "--model", shipped_onnx, "-o", folder)[::2], "it is a folder")
    if os.geteuid() != 0:  # root writes anywhere
        ro = tmp_path / "ro"
        ro.mkdir()
        ro.chmod(0o500)
        try:
            _one_line_error(*_run(capsys, a, b, "--model", shipped_onnx, "-o", ro / "d.png")[::2], "not writable")
        finally:
            ro.chmod(0o700)


def test_psf_family_reaches_the_model(plane_pairs, shipped_onnx, tmp_path, capsys):
    """The shipped model takes the lens's PSF family: told by name or by a calibrated camera
    file, it changes the refined depth; the default keeps the exported (unknown) family."""
    from tdfd.camera import Camera
    from tdfd.camera_file import CameraFile

    f1, f2, _ = plane_pairs[0]
    a, b = _write_pair(tmp_path, f1, f2, "fam")
    cam = CameraFile(Camera.preset("reference"), psf_family="pillbox").write(tmp_path / "cam.json")
    maps = {}
    for option in ("exported", "pillbox", str(cam)):
        out = tmp_path / f"d_{len(maps)}.npy"
        rc, stdout, err = _run(capsys, a, b, "--model", shipped_onnx, "--white-level", "4095", "--psf-family", option,
                               "-o", out)
        assert rc == 0, err
        maps[option] = np.load(out)
        told = "unknown" if option == "exported" else "pillbox"
        assert f"told PSF family {told}" in stdout.splitlines()[0], stdout
    assert not np.array_equal(maps["exported"], maps["pillbox"])
    np.testing.assert_array_equal(maps["pillbox"], maps[str(cam)])


def test_psf_family_errors_are_one_line(synth_pngs, model_path, shipped_onnx, capsys):
    a, b, _ = synth_pngs[0]
    rc, _, err = _run(capsys, a, b, "--model", model_path, "--psf-family", "pillbox")
    _one_line_error(rc, err, "without the PSF family input")
    rc, _, err = _run(capsys, a, b, "--model", shipped_onnx, "--psf-family", "disk")
    _one_line_error(rc, err, "--psf-family must be one of")
    rc, _, err = _run(capsys, a, b, "--model", shipped_onnx, "--psf-family", "missing.json")
    _one_line_error(rc, err, "missing.json")


def test_likelihood_stage_refines_the_map_and_keeps_problems(plane_pairs, shipped_onnx, tmp_path, capsys):
    """``--likelihood-stage``: the map written is the stage's (the interior tiles change, the ring
    is the model's), the plane's depth stays right, and a pair of identical frames keeps its
    confidence 0; bad combinations are one-line errors."""
    scales = ROOT / "models" / "reference.likelihood.json"
    f1, f2, truth = plane_pairs[0]
    a, b = _write_pair(tmp_path, f1, f2, "stage")
    base, staged = tmp_path / "base.npy", tmp_path / "staged.npy"
    rc, _, err = _run(capsys, a, b, "--model", shipped_onnx, "--white-level", "4095", "--threshold", "0", "-o", base)
    assert rc == 0, err
    rc, stdout, err = _run(capsys, a, b, "--model", shipped_onnx, "--white-level", "4095", "--threshold", "0",
                           "--likelihood-stage", scales, "-o", staged)
    assert rc == 0, err
    assert "refined by the likelihood stage" in stdout
    d0, d1 = np.load(base), np.load(staged)
    assert d0.shape == d1.shape == (5, 7)
    assert np.array_equal(d0[0], d1[0]) and np.array_equal(d0[:, 0], d1[:, 0])  # the ring: the model's
    assert not np.array_equal(d0[1:-1, 1:-1], d1[1:-1, 1:-1])
    assert abs(float(np.median(d1[1:-1, 1:-1])) - truth) / truth < 0.03
    # scales that remove the model's bias (within 3 tiles): the ring is the model's without it
    assert not json.loads(scales.read_text()).get("shared_bias", False)
    rc, _, err = _run(capsys, a, b, "--model", shipped_onnx, "--white-level", "4095", "--threshold", "0",
                      "--likelihood-stage", ROOT / "models" / "reference.likelihood-bias.json",
                      "-o", tmp_path / "bias.npy")
    assert rc == 0, err
    d2 = np.load(tmp_path / "bias.npy")
    ring = np.ones((5, 7), bool)
    ring[1:-1, 1:-1] = False
    assert float(np.abs(np.log(d2[ring] / d0[ring])).max()) < 0.05 and not np.array_equal(d1, d2)
    same, _ = _write_pair(tmp_path, f1, f1, "same_stage")
    rc, stdout, err = _run(capsys, same, same, "--model", shipped_onnx, "--white-level", "4095",
                           "--likelihood-stage", scales)
    assert rc == 0 and "valid: 0.0%" in stdout, stdout
    rc, _, err = _run(capsys, a, b, "--model", shipped_onnx, "--likelihood-stage", scales, "--tiles")
    _one_line_error(rc, err, "--tiles")
    rc, _, err = _run(capsys, a, b, "--model", shipped_onnx, "--likelihood-stage", tmp_path / "none.json")
    _one_line_error(rc, err, "likelihood scales")
    rc, _, err = _run(capsys, a, b, "--model", shipped_onnx, "--white-level", "4095", "--likelihood-stage", scales,
                      "--black-level", "5000")
    _one_line_error(rc, err, "black level")
    # --likelihood-walk: the same plane's depth (the model is within its windows), and only with the stage
    rc, _, err = _run(capsys, a, b, "--model", shipped_onnx, "--white-level", "4095", "--threshold", "0",
                      "--likelihood-stage", scales, "--likelihood-walk", "3", "-o", tmp_path / "walk.npy")
    assert rc == 0, err
    assert abs(float(np.median(np.load(tmp_path / "walk.npy")[1:-1, 1:-1])) - truth) / truth < 0.03
    rc, _, err = _run(capsys, a, b, "--model", shipped_onnx, "--likelihood-walk", "3")
    _one_line_error(rc, err, "--likelihood-walk")
    rc, _, err = _run(capsys, a, b, "--model", shipped_onnx, "--likelihood-stage", scales, "--likelihood-walk", "-1")
    _one_line_error(rc, err, "walk")
    # --likelihood-pool: the stage's map pooled by the file's own structure pooling, only with the stage
    rc, stdout, err = _run(capsys, a, b, "--model", shipped_onnx, "--white-level", "4095", "--threshold", "0",
                           "--likelihood-stage", scales, "--likelihood-pool", "-o", tmp_path / "pooled.npy")
    assert rc == 0, err
    assert "refined by the likelihood stage, pooled along the depth structure" in stdout
    d3 = np.load(tmp_path / "pooled.npy")
    assert not np.array_equal(d3, d1) and abs(float(np.median(d3[1:-1, 1:-1])) - truth) / truth < 0.03
    rc, _, err = _run(capsys, a, b, "--model", shipped_onnx, "--likelihood-pool")
    _one_line_error(rc, err, "--likelihood-pool")
    # --likelihood-ambiguity: a textured plane's fit is not ambiguous, so the map stays the stage's; only
    # with the stage
    rc, stdout, err = _run(capsys, a, b, "--model", shipped_onnx, "--white-level", "4095", "--threshold", "0",
                           "--likelihood-stage", scales, "--likelihood-ambiguity", "-o", tmp_path / "checked.npy")
    assert rc == 0, err
    assert "ambiguous" not in err
    np.testing.assert_array_equal(np.load(tmp_path / "checked.npy"), d1)
    rc, _, err = _run(capsys, a, b, "--model", shipped_onnx, "--likelihood-ambiguity")
    _one_line_error(rc, err, "--likelihood-ambiguity")
    # --likelihood-register: the pair is registered already, so the plane's depth stays; only with the stage
    rc, stdout, err = _run(capsys, a, b, "--model", shipped_onnx, "--white-level", "4095", "--threshold", "0",
                           "--likelihood-stage", scales, "--likelihood-register", "-o", tmp_path / "registered.npy")
    assert rc == 0, err
    assert abs(float(np.median(np.load(tmp_path / "registered.npy")[1:-1, 1:-1])) - truth) / truth < 0.03
    rc, _, err = _run(capsys, a, b, "--model", shipped_onnx, "--likelihood-register")
    _one_line_error(rc, err, "--likelihood-register")


def test_an_ambiguous_pair_keeps_its_map_with_capped_confidences(plane_pairs, shipped_onnx, monkeypatch, caplog):
    """The runtime's stage with the ambiguity check: a pair it finds ambiguous (here every pair, by a
    threshold no margin reaches) is logged and keeps its refined map, every confidence capped."""
    import logging
    import sys as _sys

    from tdfd.dfd.scene_ambiguity import ambiguity_cap

    f1, f2, _ = plane_pairs[0]
    rt = DepthRuntime(shipped_onnx)
    scales = ROOT / "models" / "reference.likelihood.json"
    base = rt(f1, f2, white_level=4095, pooled=True)
    plain = refine_result(rt, stage_for_runtime(rt, scales), f1, f2, base, 4095)
    monkeypatch.setattr(_sys.modules["tdfd.dfd.likelihood_stage"], "AMBIGUITY_MARGIN", 1e12)
    with caplog.at_level(logging.WARNING, logger="tdfd"):
        checked = refine_result(rt, stage_for_runtime(rt, scales, ambiguity=True), f1, f2, base, 4095)
    assert "pair 0 is ambiguous" in caplog.text
    (d0, c0), (d1, c1) = plain.depth_map, checked.depth_map
    np.testing.assert_array_equal(d0, d1)
    cap = ambiguity_cap(rt.metadata[MODEL_KEY]["confidence_scale"])
    np.testing.assert_allclose(c1, np.minimum(c0, cap), rtol=1e-6)
    assert float(c0.max()) > cap


def test_the_stage_pools_with_the_files_own_pooling(shipped_onnx):
    rt = DepthRuntime(shipped_onnx)
    scales = ROOT / "models" / "reference.likelihood.json"
    assert stage_for_runtime(rt, scales).pooling is None
    stage = stage_for_runtime(rt, scales, pool=True)
    assert stage.pooling.to_config() == rt.metadata[MODEL_KEY]["structure_pooling"]
    bare = SimpleNamespace(**{k: getattr(rt, k) for k in ("magnification_per_dpt", "inverse_depth_offset_dpt", "camera",
                                                          "tile", "stride", "psf_family", "path")},
                           metadata={MODEL_KEY: {k: v for k, v in rt.metadata[MODEL_KEY].items()
                                                 if k != "structure_pooling"}})
    assert stage_for_runtime(bare, scales).pooling is None
    with pytest.raises(ModelError, match="no structure pooling"):
        stage_for_runtime(bare, scales, pool=True)


def test_a_file_that_registers_breathing_needs_the_stages_own_registration(shipped_onnx, tmp_path, caplog):
    rt = DepthRuntime(shipped_onnx)
    scales = ROOT / "models" / "reference.likelihood.json"
    breathing = SimpleNamespace(**{k: getattr(rt, k) for k in ("inverse_depth_offset_dpt", "camera", "tile", "stride",
                                                               "psf_family", "path", "metadata")},
                                magnification_per_dpt=0.004)
    with pytest.raises(InputError, match="likelihood-register"):
        stage_for_runtime(breathing, scales)
    with caplog.at_level(logging.WARNING, logger="tdfd"):
        assert stage_for_runtime(breathing, scales, register=True).options["register"] is True
    assert "fitted for the stage without each pair's registration, this one fits it" in caplog.text
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="tdfd"):
        assert stage_for_runtime(rt, scales).options["register"] is False
    assert "registration" not in caplog.text
    registered = tmp_path / "registered.json"
    registered.write_text(json.dumps({**json.loads(scales.read_text()), "format": "tdfd.likelihood_scales/5",
                                      "registered": True}))
    with caplog.at_level(logging.WARNING, logger="tdfd"):
        stage_for_runtime(breathing, registered, register=True)
    assert "registration" not in caplog.text
    with caplog.at_level(logging.WARNING, logger="tdfd"):
        stage_for_runtime(rt, registered)
    assert "fitted for the stage fitting each pair's registration, this one does not fit it" in caplog.text


def test_likelihood_stage_takes_the_measured_psf_model(plane_pairs, shipped_onnx, tmp_path, capsys, caplog):
    """``--psf-model CAM.json``: the stage fits with the camera file's measured PSF (here the
    Gaussian the planes were rendered with) and reads the plane, with the scales fitted for a measured
    PSF (the shipped ``reference.likelihood-calibrated.json``); scales fitted for the other case are
    used with a warning that names the right ones; an unusable file is a one-line error."""
    from tdfd import Camera
    from tdfd.camera_file import CameraFile

    scales = ROOT / "models" / "reference.likelihood-calibrated.json"
    assert json.loads(scales.read_text())["psf"] == "measured"
    profiled = ROOT / "models" / "reference.likelihood.json"
    f1, f2, truth = plane_pairs[0]
    a, b = _write_pair(tmp_path, f1, f2, "measured")
    model = {"shape": "gaussian", "diffraction_px": 0.0, "astigmatism": 0.0, "astigmatism_angle_rad": 0.0,
             "spherical": 0.0, "sigma_scale": 1.0}
    cam = CameraFile(Camera.preset("reference"), psf_model=model).write(tmp_path / "cam.json")
    out = tmp_path / "measured.npy"
    rc, stdout, err = _run(capsys, a, b, "--model", shipped_onnx, "--white-level", "4095", "--threshold", "0",
                           "--likelihood-stage", scales, "--psf-model", cam, "-o", out)
    assert rc == 0, err
    assert abs(float(np.median(np.load(out)[1:-1, 1:-1])) - truth) / truth < 0.03
    assert "fitted for the stage with the PSF" not in caplog.text
    rc, _, err = _run(capsys, a, b, "--model", shipped_onnx, "--white-level", "4095", "--threshold", "0",
                      "--likelihood-stage", profiled, "--psf-model", cam, "-o", tmp_path / "mismatch.npy")
    assert rc == 0, err
    assert "with the PSF profiled, this one has it measured" in caplog.text and "--calibrated-psf" in caplog.text
    caplog.clear()
    rc, _, err = _run(capsys, a, b, "--model", shipped_onnx, "--white-level", "4095", "--threshold", "0",
                      "--likelihood-stage", scales, "-o", tmp_path / "other_way.npy")
    assert rc == 0, err
    assert "with the PSF measured, this one has it profiled" in caplog.text
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({**Camera.preset("reference").to_dict(), "psf_model": {**model, "spherical": 0.9}}))
    rc, _, err = _run(capsys, a, b, "--model", shipped_onnx, "--likelihood-stage", scales, "--psf-model", bad)
    _one_line_error(rc, err, "psf_model")
