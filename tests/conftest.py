"""Shared test fixtures and options."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
#: The shipped model; tests that use it fail (never skip) when it is missing.
SHIPPED_ONNX = ROOT / "models" / "reference.onnx"
#: Plane depths (metres) of :func:`plane_pairs`: near, middle and far part of the working range,
#: away from the distance where the two frames are equally blurred (~0.45 m), so that swapping
#: the frames moves the estimate by far more than the tolerance.
PLANE_DEPTHS_M = (0.32, 0.5, 0.7)


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--ecvfl-port", default=None, help="serial port of a real Optotune Lens Driver 4 (enables hardware tests)")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    if config.getoption("--ecvfl-port"):
        return
    skip = pytest.mark.skip(reason="hardware test: pass --ecvfl-port PORT to run")
    for item in items:
        if "hardware" in item.keywords:
            item.add_marker(skip)


@pytest.fixture
def one_torch_thread():
    """Small tensors: one intra-op thread is faster, and immune to other load on the cores.

    Use with ``pytestmark = pytest.mark.usefixtures("one_torch_thread")``.
    """
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="session")
def exported_onnx(tmp_path_factory):
    """``(path, model)``: a small model exported once per session (``export.testing``)."""
    from export.testing import session_onnx_model

    return session_onnx_model(tmp_path_factory)


@pytest.fixture(scope="session")
def shipped_onnx() -> Path:
    """``models/reference.onnx``, which must be shipped."""
    assert SHIPPED_ONNX.is_file(), f"the shipped model {SHIPPED_ONNX} is missing"
    return SHIPPED_ONNX


@pytest.fixture(scope="session")
def plane_pairs() -> list[tuple[np.ndarray, np.ndarray, float]]:
    """Rendered DFD pairs of textured fronto-parallel planes at known depth.

    ``(image_f1, image_f2, depth_m)`` per plane: 192 x 256 uint16 12-bit codes (white level
    4095) of a fractal and a dead-leaves texture at each of :data:`PLANE_DEPTHS_M`, rendered
    by :func:`tdfd.optics.render_pair` for the ``reference`` camera (Gaussian PSF) with
    Poisson-Gaussian noise (``var = 1e-4 x + 1e-6``). About 2 s.
    """
    import torch

    from tdfd import Camera
    from tdfd.optics import render_pair
    from tdfd.textures import dead_leaves, fractal

    cam = Camera.preset("reference")
    g = torch.Generator().manual_seed(3)
    h, w = 192, 256
    sharp = torch.cat([fractal((h, w), g, 1), dead_leaves((h, w), g, 1)]) * 0.6 + 0.2
    noise = torch.Generator().manual_seed(7)

    def sensor(im: torch.Tensor) -> np.ndarray:
        im = im + torch.sqrt(1e-4 * im.clamp_min(0) + 1e-6) * torch.randn(im.shape, generator=noise)
        return torch.round(im.clamp(0, 1) * 4095).numpy().astype(np.uint16)[0, 0]

    out = []
    for k in range(sharp.shape[0]):
        for d in PLANE_DEPTHS_M:
            a, b = render_pair(cam, sharp[k:k + 1], torch.full((1, 1, h, w), d))
            out.append((sensor(a), sensor(b), d))
    return out
