"""A plain (non-editable) install carries the shipped model: the wheel holds
``tdfd/assets/reference.onnx`` (the bytes of ``models/reference.onnx``), and ``tdfd depth`` and
``tdfd autofocus`` run from the installed files, outside the checkout, without naming a model."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import cv2
import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def installed(tmp_path_factory) -> Path:
    """``pip wheel --no-deps`` of a copy of the source (links kept), unpacked as site-packages."""
    tmp = tmp_path_factory.mktemp("pkg")
    src = tmp / "src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(ROOT / name, src / name)
    shutil.copytree(ROOT / "tdfd", src / "tdfd", symlinks=True, ignore=shutil.ignore_patterns("__pycache__"))
    (src / "models").mkdir()
    shutil.copy2(ROOT / "models" / "reference.onnx", src / "models" / "reference.onnx")
    wheels = tmp / "wheels"
    run = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q",
                          "--disable-pip-version-check", "-w", str(wheels), str(src)],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    (wheel,) = wheels.glob("tdfd-*.whl")
    with zipfile.ZipFile(wheel) as z:
        assert "tdfd/assets/reference.onnx" in z.namelist(), "the shipped model is not package data"
        assert z.read("tdfd/assets/reference.onnx") == (ROOT / "models" / "reference.onnx").read_bytes()
        site = tmp / "site"
        z.extractall(site)
    return site


def _run_installed(site: Path, cwd: Path, *argv: str) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k not in ("TDFD_MODEL", "PYTHONPATH")}
    env["PYTHONPATH"] = str(site)
    code = ("import sys, tdfd\n"
            f"assert tdfd.__file__.startswith({str(site)!r}), tdfd.__file__\n"
            "from tdfd.cli import main\n"
            f"sys.exit(main({list(argv)!r}))\n")
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=cwd, env=env, timeout=300)


def test_installed_tdfd_depth_finds_the_shipped_model(installed, plane_pairs, tmp_path):
    f1, f2, truth = plane_pairs[0]
    cv2.imwrite(str(tmp_path / "a.png"), f1)
    cv2.imwrite(str(tmp_path / "b.png"), f2)
    out = _run_installed(installed, tmp_path, "depth", "a.png", "b.png", "--white-level", "4095")
    assert out.returncode == 0, out.stderr
    assert "model reference.onnx" in out.stdout
    centre = float(next(s for s in out.stdout.splitlines() if s.startswith("centre depth:")).split()[2])
    assert abs(centre - truth) / truth < 0.05


def test_installed_tdfd_autofocus_finds_the_shipped_model(installed, tmp_path):
    out = _run_installed(installed, tmp_path, "autofocus", "--sim", "--method", "dfd", "--trials", "1",
                         "--no-progress", "--readout", "192x256")
    assert out.returncode == 0, out.stderr
    assert f"estimator: ONNX {installed / 'tdfd' / 'assets' / 'reference.onnx'}" in out.stdout, out.stdout


def test_without_a_model_the_error_says_how_to_name_one(installed, tmp_path):
    (installed / "tdfd" / "assets" / "reference.onnx").rename(tmp_path / "elsewhere.onnx")
    try:
        cv2.imwrite(str(tmp_path / "a.png"), np.random.default_rng(0).integers(0, 60000, (96, 96), dtype=np.uint16))
        out = _run_installed(installed, tmp_path, "depth", "a.png", "a.png")
    finally:
        (tmp_path / "elsewhere.onnx").rename(installed / "tdfd" / "assets" / "reference.onnx")
    assert out.returncode == 1
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("tdfd depth: error: no model found: name one with --model PATH")
