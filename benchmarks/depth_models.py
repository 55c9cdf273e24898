"""One interface for the accuracy benchmarks over a trained model: torch weights or ONNX file.

``--model models/reference`` (the safetensors stem, or ``.safetensors`` / ``.json``) runs the
torch :class:`~tdfd.model.DFDModel`; ``--model models/reference.onnx`` runs the exported file in
ONNX Runtime (:meth:`tdfd.runtime.DepthRuntime.run`, the bare session: no pair check), so a
benchmark scores exactly what ships. Both give the depth and the confidence per tile, and the
confidence scale ``b0`` that turns a confidence back into the model's predicted error scale
(:func:`predicted_scale`).

A model with the structure pooling has two depth maps: each tile's own estimate (the ONNX
contract's ``depth`` and ``confidence``, which the autofocus pools) and the map pooled along the
depth structure (:data:`tdfd.contract.POOLED_OUTPUT_NAMES`). ``output="map"`` (the default)
scores the best depth map, the pooled one when the model has it; ``output="tiles"`` the tiles'.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from tdfd.autofocus.evidence import relative_error_scale
from tdfd.contract import MODEL_KEY
from tdfd.errors import InputError, ModelError

__all__ = ["DepthModel", "load_depth_model", "predicted_scale", "OUTPUTS", "add_output_argument"]

#: what :func:`load_depth_model` scores: the best depth map (pooled when the model pools) or each tile's own
OUTPUTS = ("map", "tiles")


@dataclass
class DepthModel:
    """A loaded model as the benchmarks use it.

    Attributes:
        name: the file name shown in reports.
        tile, stride: the tile grid (px).
        confidence_scale: ``b0``, the predicted relative error scale at confidence 0.5.
        camera: the model's :class:`tdfd.Camera`.
        run: ``(image_f1, image_f2)`` float32 ``(N, 1, H, W)`` tensors to ``(depth, confidence,
            depth_analytic)``, each ``(N, 1, h, w)`` float32 tensors.
        run_told: the same, told each sample's PSF family: ``(image_f1, image_f2, params)`` with
            the samples' ``data_synth`` parameter dicts (:func:`tdfd.model.training_codes`, every
            Gaussian or pillbox sample told); ``None`` for a model without the family input or an
            ONNX file (whose family is one per session).
        pooled: whether ``run`` returns the structure-pooled map (``output="map"`` on a model with it).
    """

    name: str
    tile: int
    stride: int
    confidence_scale: float
    camera: object
    run: Callable[[torch.Tensor, torch.Tensor], tuple[torch.Tensor, torch.Tensor, torch.Tensor]]
    run_told: Callable[[torch.Tensor, torch.Tensor, list], tuple[torch.Tensor, torch.Tensor, torch.Tensor]] | None = None
    pooled: bool = False


def add_output_argument(parser) -> None:
    """The benchmarks' ``--output map|tiles`` option (:func:`load_depth_model`'s ``output``)."""
    parser.add_argument("--output", choices=OUTPUTS, default="map",
                        help="which depth a model with the structure pooling is scored on: 'map' (default, the "
                             "pooled depth map) or 'tiles' (each tile's own estimate, the ONNX contract's depth and "
                             "confidence, what the autofocus pools); the same for a model without it")


def load_depth_model(path: str | Path, threads: int = 2, calibrated: bool = True, output: str = "map") -> DepthModel:
    """Load ``path``: an ``.onnx`` file (ONNX Runtime) or a :meth:`tdfd.model.DFDModel.save` stem.

    Args:
        path: the model.
        threads: torch / ONNX Runtime threads.
        calibrated: ``False``: the torch model without its post-hoc scale calibration
            (:mod:`tdfd.model.scale_calibration`), i.e. the CNN's own predicted scale (and
            without the structure pooling, whose weights are that calibrated scale).
        output: ``"map"``: the structure-pooled depth and confidence when the model has the
            stage, else the tiles'; ``"tiles"``: each tile's own estimate.

    Raises:
        ModelError: missing files, an ONNX file without a positive ``confidence_scale`` in
            its ``tdfd.model`` metadata, or ``calibrated=False`` for an ONNX file (the
            calibration is part of its graph).
        InputError: an unknown ``output``.
    """
    if output not in OUTPUTS:
        raise InputError(f"output must be one of {OUTPUTS}, got {output!r}")
    p = Path(path)
    if p.suffix == ".onnx":
        if not calibrated:
            raise ModelError(f"{p}: an ONNX file's scale calibration is part of its graph; load the safetensors stem")
        from tdfd.runtime import DepthRuntime

        rt = DepthRuntime(p, threads=threads)
        meta = rt.metadata.get(MODEL_KEY)
        b0 = meta.get("confidence_scale") if isinstance(meta, dict) else None
        if not isinstance(b0, (int, float)) or not b0 > 0:
            raise ModelError(f"{p} has no positive confidence_scale in its {MODEL_KEY!r} metadata")

        pooled = rt.has_pooled and output == "map"

        def run_onnx(i1: torch.Tensor, i2: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
            a, b = np.ascontiguousarray(i1.numpy(), np.float32), np.ascontiguousarray(i2.numpy(), np.float32)
            out = rt.run_pooled(a, b) if pooled else rt.run(a, b)
            out = (out[3], out[4], out[2]) if pooled else out
            return tuple(torch.from_numpy(np.asarray(o)) for o in out)  # type: ignore[return-value]

        return DepthModel(p.name, rt.tile, rt.stride, float(b0), rt.camera, run_onnx, pooled=pooled)

    from tdfd.model import DFDModel, training_codes
    from tdfd.model.scale_calibration import ScaleCalibration

    torch.set_num_threads(threads)
    model = DFDModel.load(p).eval()
    if not calibrated:
        model.scale_calibration = ScaleCalibration()
    if not calibrated or output == "tiles":  # the stage's map is not scored: do not compute it
        model.set_structure_pooling(None)
    pooled = model.structure_pooling is not None

    def pick(r) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        depth, conf = r.depth_map if pooled else (r.depth, r.confidence)
        return depth, conf, r.depth_analytic

    def run_torch(i1: torch.Tensor, i2: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        with torch.no_grad():
            return pick(model.analyse(i1.float(), i2.float()))

    def run_told(i1: torch.Tensor, i2: torch.Tensor, params: list) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        with torch.no_grad():
            return pick(model.analyse(i1.float(), i2.float(), training_codes(params, 1.0)))

    return DepthModel(p.with_suffix("").name if p.suffix in (".safetensors", ".json") else p.name, model.tile,
                      model.stride, model.confidence_scale, model.camera, run_torch,
                      run_told if model.psf_family_input else None, pooled=pooled)


def predicted_scale(confidence: torch.Tensor, confidence_scale: float) -> torch.Tensor:
    """The Laplace scale ``b`` of the relative inverse-depth error that a confidence stands for.

    :mod:`tdfd.model.combined` maps the predicted scale to ``conf = 1 / (1 + (b / b0)^2)``;
    this inverts it, ``b = b0 sqrt(1 / conf - 1)`` (:func:`tdfd.autofocus.evidence.relative_error_scale`,
    which the autofocus loop uses too). The median of ``|e|`` for that Laplace error is ``b ln 2``.

    Args:
        confidence: any shape, in [0, 1].
        confidence_scale: ``b0`` (> 0).

    Returns:
        ``b``, float64, same shape (0 at confidence 1; huge at confidence 0).

    Raises:
        InputError: a confidence that is not finite or lies outside [0, 1].

    Example:
        >>> predicted_scale(torch.tensor([0.5, 0.8]), 0.01)
        tensor([0.0100, 0.0050], dtype=torch.float64)
    """
    c = torch.as_tensor(confidence, dtype=torch.float64)
    if not bool(torch.isfinite(c).all()) or bool(((c < 0) | (c > 1)).any()):
        raise InputError("confidence must be finite and in [0, 1]")
    return torch.from_numpy(np.asarray(relative_error_scale(c.numpy(), confidence_scale), dtype=np.float64))
