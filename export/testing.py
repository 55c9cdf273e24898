"""Test helpers: a deterministic combined model and one export of it per pytest session.

Exporting takes several seconds, so the test modules of the export, the runtime and the
``tdfd depth`` CLI share one file written under pytest's session temporary directory.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from tdfd.camera import Camera

from .onnx_export import export_model

__all__ = ["make_test_model", "session_onnx_model"]


def make_test_model(seed: int = 0, tile: int = 64, stride: int = 32) -> torch.nn.Module:
    """A :class:`tdfd.model.DFDModel` for the reference camera with a random, non-zero
    refinement head (so ``depth`` differs from ``depth_analytic`` and the CNN is exercised)."""
    from tdfd.model import DFDModel

    with torch.random.fork_rng():
        torch.manual_seed(seed)
        model = DFDModel(Camera.preset("reference"), tile=tile, stride=stride)
        with torch.no_grad():
            for p in model.refine.head.parameters():
                p.normal_(0.0, 0.05)
    return model.eval()


def session_onnx_model(tmp_path_factory: Any, seed: int = 0) -> tuple[Path, torch.nn.Module]:
    """``(path, model)``: :func:`make_test_model` exported once per pytest session."""
    model = make_test_model(seed)
    path = Path(tmp_path_factory.getbasetemp()) / "tdfd_onnx" / f"test_model_{seed}.onnx"
    if not path.is_file():
        export_model(model, path)
    return path, model
