"""Export of the combined DFD model to ONNX, and verification of the exported file.

Not part of the installed ``tdfd`` package: it imports ``tdfd`` (and torch), never the
other way round. The device side (``tdfd.runtime``) needs only the ``.onnx`` file.

* :func:`export_model`: one self-contained ``.onnx`` file following ``CONTRACT.md``
  section 2 (inputs ``image_f1``/``image_f2``, outputs ``depth``/``confidence``/
  ``depth_analytic``, dynamic batch/height/width, ``tdfd.*`` metadata).
* :func:`verify_onnx`: ``onnx.checker`` full check, contract check and ONNX Runtime
  versus torch parity on rendered pairs; raises :class:`tdfd.errors.ModelError` on any
  failure.

Command line: ``python -m export --weights models/reference.safetensors --out models/reference.onnx``.
"""

from __future__ import annotations

from .onnx_export import INPUT_NAMES, OUTPUT_NAMES, METADATA_KEYS, export_model, onnx_metadata
from .verify import ParityReport, check_contract, realistic_pairs, verify_onnx

__all__ = [
    "INPUT_NAMES",
    "OUTPUT_NAMES",
    "METADATA_KEYS",
    "export_model",
    "onnx_metadata",
    "verify_onnx",
    "check_contract",
    "realistic_pairs",
    "ParityReport",
]
