"""Whether torch.export / dynamo / the ONNX exporter is tracing the current call.

Used to skip value checks (which need concrete data) and to pick the operator form that
runs fastest in ONNX Runtime when the same arithmetic has a faster form in torch eager.
"""

from __future__ import annotations

import torch

__all__ = ["is_exporting"]


def is_exporting() -> bool:
    """True while torch.export / dynamo / the ONNX exporter traces the model."""
    checks = (getattr(torch.compiler, "is_exporting", None), getattr(torch.compiler, "is_compiling", None),
              torch.jit.is_tracing, torch.onnx.is_in_onnx_export)
    return any(bool(f()) for f in checks if f is not None)
