r"""Export a DFD model (analytic layer + CNN) to one self-contained ONNX file.

The model is any ``nn.Module`` with ``forward(image_f1, image_f2) -> (depth, confidence,
depth_analytic)`` and attributes ``camera`` (:class:`tdfd.Camera`), ``tile`` and ``stride``
— :class:`tdfd.model.DFDModel`, or the analytic :class:`tdfd.dfd.FourierRatioDFD` wrapped
to return its depth twice. A model with the structure pooling returns ``(depth_pooled,
confidence_pooled)`` after those three; the graph then has them as two more outputs
(:data:`tdfd.contract.POOLED_OUTPUT_NAMES`, :func:`output_names_for`).

The graph is captured with ``torch.export`` (``dynamo=True``) with symbolic batch, height
and width; the tile-grid arithmetic (``h = (H - tile) // stride + 1``) stays symbolic
because the analytic layer computes it with strided convolutions, slices and reshapes
only. Input validation is switched off while exporting (the runtime validates on the
device, :mod:`tdfd.runtime`). The ONNX optimiser (``optimize=True``) folds ``x + c`` away
for ``|c| <= 1e-8`` and multiplications by constants within ``1e-5`` of 1; the analytic
layer's epsilons are ``>= 1e-6`` in float32, and :func:`export.verify.verify_onnx` checks
parity either way (export with ``optimize=False`` if a model needs smaller constants).

Example:
    >>> import tempfile, pathlib, onnx
    >>> from tdfd import Camera
    >>> from tdfd.model import DFDModel
    >>> model = DFDModel(Camera.preset("reference"), tile=64, stride=32, hidden=8, blocks=1)
    >>> path = export_model(model, pathlib.Path(tempfile.mkdtemp()) / "m.onnx")  # doctest: +SKIP
    >>> [i.name for i in onnx.load(path).graph.input]  # doctest: +SKIP
    ['image_f1', 'image_f2']
"""

from __future__ import annotations

import contextlib
import json
import logging
import warnings
from pathlib import Path
from typing import Iterator

import onnx
import torch
from torch import nn

import tdfd
from tdfd.contract import (BREATHING_KEY, CAMERA_KEY, COVERAGE_KEY, GRID_KEY, INPUT_NAMES, METADATA_KEYS, MIN_OPSET, MODEL_KEY,
                           OUTPUT_NAMES, POOLED_OUTPUT_NAMES, PSF_FAMILY_KEY, VERSION_KEY)
from tdfd.coverage import camera_coverage
from tdfd.errors import ModelError
from tdfd.model.combined import PSF_FAMILY_INITIALIZER

__all__ = ["INPUT_NAMES", "OUTPUT_NAMES", "METADATA_KEYS", "MIN_OPSET", "export_model", "onnx_metadata",
           "output_names_for"]

logger = logging.getLogger(__name__)


def _check_model(model: nn.Module) -> None:
    if not isinstance(model, nn.Module):
        raise ModelError(f"expected a torch.nn.Module, got {type(model).__name__}")
    missing = [a for a in ("camera", "tile", "stride") if not hasattr(model, a)]
    if missing:
        raise ModelError(f"{type(model).__name__} lacks {missing}: the export needs the camera and the tile grid")
    if not hasattr(model.camera, "to_dict"):
        raise ModelError(f"model.camera must be a tdfd.Camera, got {type(model.camera).__name__}")


def onnx_metadata(model: nn.Module) -> dict[str, str]:
    """The ``metadata_props`` written into the ONNX file, each value a JSON string.

    ``tdfd.camera`` is ``json.dumps(model.camera.to_dict())``, ``tdfd.grid`` is
    ``{"tile", "stride"}``, ``tdfd.version`` the exporting package version (a JSON string
    literal such as ``"0.1.0"``), ``tdfd.coverage`` which cameras the model covers (both
    frames' blur range in px over the camera's working range, :mod:`tdfd.coverage`). A model
    with a ``config()`` method (``DFDModel``) also gets ``tdfd.model``, its full description
    (informational). A model with a breathing registration (``model.registration``, a
    :class:`tdfd.registration.BreathingRegistration`) gets ``tdfd.breathing``:
    ``{"magnification_per_dpt", "frame_scales"}`` (:data:`tdfd.contract.BREATHING_KEY`). A model
    with the PSF family input (``model.psf_family_input``) gets ``tdfd.psf_family``:
    ``{"input": true, "family", "initializer"}`` (:data:`tdfd.contract.PSF_FAMILY_KEY`).
    """
    _check_model(model)
    meta = {
        CAMERA_KEY: json.dumps(model.camera.to_dict()),
        GRID_KEY: json.dumps({"tile": int(model.tile), "stride": int(model.stride)}),
        VERSION_KEY: json.dumps(tdfd.__version__),
        COVERAGE_KEY: json.dumps(camera_coverage(model.camera)),
    }
    registration = getattr(model, "registration", None)
    if registration is not None:
        meta[BREATHING_KEY] = json.dumps({"magnification_per_dpt": float(registration.magnification_per_dpt),
                                          "frame_scales": [float(v) for v in registration.scales]})
    if getattr(model, "psf_family_input", False):
        meta[PSF_FAMILY_KEY] = json.dumps({"input": True, "family": model.psf_family,
                                           "initializer": PSF_FAMILY_INITIALIZER})
    config = getattr(model, "config", None)
    if callable(config):
        try:
            meta[MODEL_KEY] = json.dumps(config(), sort_keys=True)
        except (TypeError, ValueError) as exc:  # not JSON-serialisable: informational only
            logger.warning("model config not stored in the ONNX metadata: %s", exc)
    return meta


@contextlib.contextmanager
def _export_mode(model: nn.Module) -> Iterator[None]:
    """``eval()`` and input validation off for every submodule; restored afterwards."""
    saved = [(m, m.validate) for m in model.modules() if isinstance(getattr(m, "validate", None), bool)]
    was_training = model.training
    try:
        for m, _ in saved:
            m.validate = False
        model.eval()
        yield
    finally:
        for m, flag in saved:
            m.validate = flag
        model.train(was_training)


def _example_inputs(tile: int, stride: int, batch: int = 2) -> tuple[torch.Tensor, torch.Tensor]:
    # A size that is no multiple of the stride and not square, so nothing specialises.
    g = torch.Generator().manual_seed(0)
    h, w = 2 * tile + stride + 3, 3 * tile + stride + 5
    x1 = torch.rand(batch, 1, h, w, generator=g) * 0.8 + 0.1
    return x1, (x1.roll(1, -1) * 0.9 + 0.05)


def output_names_for(out: object) -> list[str]:
    """The graph's output names for a model's ``forward`` result: the contract's three, then
    :data:`~tdfd.contract.POOLED_OUTPUT_NAMES` when it returns five.

    Raises:
        ModelError: neither three nor five tensors.
    """
    n = len(out) if isinstance(out, (tuple, list)) else 1
    if not isinstance(out, (tuple, list)) or n not in (len(OUTPUT_NAMES), len(OUTPUT_NAMES) + len(POOLED_OUTPUT_NAMES)):
        raise ModelError(f"the model must return {OUTPUT_NAMES} (then optionally {POOLED_OUTPUT_NAMES}), got "
                         f"{type(out).__name__} of length {n}")
    return list(OUTPUT_NAMES) + (list(POOLED_OUTPUT_NAMES) if n > len(OUTPUT_NAMES) else [])


def export_model(model: nn.Module, path: str | Path, opset: int = MIN_OPSET, optimize: bool = True) -> Path:
    """Export ``model`` to one self-contained ``.onnx`` file following the contract.

    Args:
        model: module with ``forward(image_f1, image_f2) -> (depth, confidence,
            depth_analytic)`` and attributes ``camera``, ``tile``, ``stride``.
        path: output file (parent folders are created).
        opset: ONNX opset, at least 18.
        optimize: run the ONNX optimiser (constant folding, fusions) on the graph.

    Returns:
        ``path`` as a :class:`~pathlib.Path`.

    Raises:
        ModelError: the model lacks the contract's attributes or outputs, the opset is
            below 18, or the exporter fails (its message is included).
    """
    _check_model(model)
    if int(opset) < MIN_OPSET:
        raise ModelError(f"the contract needs opset >= {MIN_OPSET}, got {opset}")
    tile, stride = int(model.tile), int(model.stride)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    x1, x2 = _example_inputs(tile, stride)
    batch = torch.export.Dim("batch", min=1)
    height = torch.export.Dim("height", min=tile)
    width = torch.export.Dim("width", min=tile)
    dims = {0: batch, 2: height, 3: width}
    with _export_mode(model), torch.no_grad():
        out = model(x1, x2)
        outputs = output_names_for(out)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                program = torch.onnx.export(
                    model, (x1, x2), dynamo=True, opset_version=int(opset), input_names=list(INPUT_NAMES),
                    output_names=outputs, dynamic_shapes=(dims, dims), optimize=optimize,
                    external_data=False, verbose=False, report=False)
        except Exception as exc:  # the exporter raises many types; surface them as one
            raise ModelError(f"ONNX export of {type(model).__name__} failed: {type(exc).__name__}: {exc}") from exc
    proto = program.model_proto
    del proto.metadata_props[:]
    for key, value in onnx_metadata(model).items():
        proto.metadata_props.add(key=key, value=value)
    proto.doc_string = (f"tdfd {tdfd.__version__} depth from defocus: image_f1/image_f2 float32 [N,1,H,W] in [0,1] "
                        f"-> {'/'.join(outputs)} [N,1,h,w] on the {tile}/{stride} tile grid (metres).")
    onnx.save_model(proto, str(path), save_as_external_data=False)
    logger.info("exported %s (opset %d, %.1f kB)", path, opset, path.stat().st_size / 1024)
    return path

