r"""Verify an exported ONNX model: checker, contract, and ONNX Runtime versus torch parity.

:func:`verify_onnx` runs, in order:

1. ``onnx.checker.check_model(full_check=True)`` (which includes strict shape inference);
2. :func:`check_contract`: opset >= 18, no external data, input/output names, dtypes and
   ranks, symbolic batch/height/width, and the ``tdfd.*`` metadata (equal to the model's
   camera and grid when the model is given);
3. parity: the file in ONNX Runtime against the torch model in eager mode on realistic
   rendered pairs (:func:`realistic_pairs`: the forward model on library textures, two
   depth planes per sample, sensor noise) at several image sizes, including sizes that are
   no multiple of the stride, and several batch sizes. ``depth`` and ``depth_analytic``
   must agree within ``rtol`` (relative, default ``1e-4``) in every tile with confidence
   >= 0.05 and within ``rtol_all`` (1e-3) in every tile; ``confidence`` within
   ``conf_atol`` (absolute, 1e-3; see the note of :func:`verify_onnx`).

Any failure raises :class:`tdfd.errors.ModelError` whose message names the check, and
for parity the worst discrepancy (size, batch, output, tile, both values).
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np
import onnx
import torch
from torch import nn

from tdfd.breathing import breathing_scales
from tdfd.camera import Camera
from tdfd.errors import InputError, ModelError
from tdfd.forward import Defocus, DFDForward, IdealSensor, PlanePairs
from tdfd.grid import grid_shape
from tdfd.sensor import SensorModel

from tdfd.contract import (BREATHING_KEY, CAMERA_KEY, COVERAGE_KEY, GRID_KEY, INPUT_NAMES, METADATA_KEYS, MIN_OPSET,
                           OUTPUT_NAMES, POOLED_OUTPUT_NAMES)
from tdfd.coverage import camera_coverage, check_coverage

from .onnx_export import _export_mode

__all__ = ["DEFAULT_SIZES", "DEFAULT_BATCHES", "ParityReport", "check_contract", "realistic_pairs", "verify_onnx"]

logger = logging.getLogger(__name__)

#: Image sizes ``(H, W)`` of the parity check: one tile, odd sizes, VGA.
DEFAULT_SIZES: tuple[tuple[int, int], ...] = ((64, 64), (150, 203), (480, 640))
#: Batch sizes of the parity check.
DEFAULT_BATCHES: tuple[int, ...] = (1, 3)


# ---------------------------------------------------------------------------- scenes
def realistic_pairs(camera: Camera, batch: int, height: int, width: int, seed: int = 0,
                    noise: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
    """Rendered DFD pairs ``(image_f1, image_f2)``, each ``(B, 1, H, W)`` float32 in [0, 1].

    The forward model's :class:`tdfd.forward.PlanePairs`: each sample is two fronto-parallel
    planes (random depths in the camera's working range, split at a random column, occluding
    at the step) textured by :func:`tdfd.textures.random_texture` (1/f fractal noise),
    Gaussian PSF, and with ``noise`` the Poisson-Gaussian
    :class:`tdfd.sensor.SensorModel` (10 000 e- full well, 10 e- read noise, 12 bits, no
    black level); without, the noise-free irradiance clipped to [0, 1].
    """
    sensor = SensorModel(full_well_e=10000.0, read_noise_e=10.0, bits=12, black_level_dn=0.0) if noise \
        else IdealSensor()
    # fractal (1/f) texture only: its detail scales with the frame, so every size is textured at
    # the 64-px tile scale; dead leaves at 1200 x 1600 are flat patches (no tile reaches
    # confidence 0.5), which would leave the parity check nothing to check
    frames, _ = PlanePairs(camera, DFDForward(Defocus(camera), sensor), families=("fractal",)).sample(
        batch, height, width, seed)
    return frames[:, 0:1].contiguous(), frames[:, 1:2].contiguous()


# -------------------------------------------------------------------------- contract
def _dims(value_info: onnx.ValueInfoProto) -> list[int | str]:
    return [d.dim_param if d.HasField("dim_param") else (d.dim_value if d.HasField("dim_value") else "?")
            for d in value_info.type.tensor_type.shape.dim]


def check_contract(proto: onnx.ModelProto, model: nn.Module | None = None) -> dict[str, object]:
    """Check a loaded ONNX model against ``CONTRACT.md`` section 2.

    Args:
        proto: the loaded model.
        model: the torch model it was exported from; when given, the ``tdfd.camera`` and
            ``tdfd.grid`` metadata must equal its camera and grid.

    Returns:
        The parsed metadata ``{"tdfd.camera": dict, "tdfd.grid": dict, "tdfd.version": str, ...}``.

    Raises:
        ModelError: naming the first violation found.
    """
    opsets = {o.domain: o.version for o in proto.opset_import}
    if opsets.get("", opsets.get("ai.onnx", 0)) < MIN_OPSET:
        raise ModelError(f"opset {opsets} is below the contract's {MIN_OPSET}")
    for init in proto.graph.initializer:
        if init.data_location == onnx.TensorProto.EXTERNAL:
            raise ModelError(f"initializer {init.name!r} is stored as external data; the contract needs one file")
    names = [i.name for i in proto.graph.input]
    if tuple(names) != INPUT_NAMES:
        raise ModelError(f"graph inputs are {names}, expected {list(INPUT_NAMES)}")
    outs = [o.name for o in proto.graph.output]
    if tuple(outs) not in (OUTPUT_NAMES, OUTPUT_NAMES + POOLED_OUTPUT_NAMES):
        raise ModelError(f"graph outputs are {outs}, expected {list(OUTPUT_NAMES)} (then optionally "
                         f"{list(POOLED_OUTPUT_NAMES)})")
    for kind, values in (("input", proto.graph.input), ("output", proto.graph.output)):
        for v in values:
            if v.type.tensor_type.elem_type != onnx.TensorProto.FLOAT:
                raise ModelError(f"{kind} {v.name!r} has elem_type {v.type.tensor_type.elem_type}, expected float32")
            dims = _dims(v)
            if len(dims) != 4 or dims[1] != 1:
                raise ModelError(f"{kind} {v.name!r} has shape {dims}, expected [N, 1, H, W]")
            fixed = [dims[i] for i in (0, 2, 3) if not isinstance(dims[i], str)]
            if fixed:
                raise ModelError(f"{kind} {v.name!r} has shape {dims}: batch, height and width must be dynamic")
    meta = {p.key: p.value for p in proto.metadata_props}
    parsed: dict[str, object] = {}
    for key in METADATA_KEYS:
        if key not in meta:
            raise ModelError(f"metadata {key!r} is missing (have {sorted(meta)})")
        try:
            parsed[key] = json.loads(meta[key])
        except json.JSONDecodeError as exc:
            raise ModelError(f"metadata {key!r} is not JSON: {exc}") from exc
    try:
        camera = Camera.from_dict(parsed[CAMERA_KEY])  # type: ignore[arg-type]
    except Exception as exc:
        raise ModelError(f"metadata 'tdfd.camera' is not a valid camera: {exc}") from exc
    grid = parsed[GRID_KEY]
    if not isinstance(grid, dict) or sorted(grid) != ["stride", "tile"]:
        raise ModelError(f"metadata 'tdfd.grid' must be {{'tile', 'stride'}}, got {grid!r}")
    if COVERAGE_KEY in meta:  # optional: which cameras the model covers (tdfd.coverage)
        try:
            parsed[COVERAGE_KEY] = json.loads(meta[COVERAGE_KEY])
        except json.JSONDecodeError as exc:
            raise ModelError(f"metadata {COVERAGE_KEY!r} is not JSON: {exc}") from exc
        check_coverage(camera, parsed[COVERAGE_KEY], camera, "the file")  # well formed, covers its own camera
    if BREATHING_KEY in meta:  # optional: the focus breathing the graph registers
        try:
            parsed[BREATHING_KEY] = breathing = json.loads(meta[BREATHING_KEY])
            m = breathing["magnification_per_dpt"]
            scales = breathing_scales(m, camera.lens_powers_dpt)
        except (json.JSONDecodeError, KeyError, TypeError, InputError) as exc:
            raise ModelError(f"metadata {BREATHING_KEY!r} is invalid: {exc}") from exc
        if [float(v) for v in breathing.get("frame_scales", ())] != list(scales):
            raise ModelError(f"metadata {BREATHING_KEY!r} frame_scales {breathing.get('frame_scales')} are not "
                             f"1 + m P at the camera's powers ({list(scales)})")
    if model is not None:
        registration = getattr(model, "registration", None)
        m_model = float(registration.magnification_per_dpt) if registration is not None else 0.0
        m_file = float(parsed[BREATHING_KEY]["magnification_per_dpt"]) if BREATHING_KEY in parsed else 0.0  # type: ignore[index]
        if m_file != m_model:
            raise ModelError(f"metadata breathing {m_file} differs from the model's magnification_per_dpt {m_model}")
        if COVERAGE_KEY in parsed and parsed[COVERAGE_KEY] != camera_coverage(model.camera):
            raise ModelError(f"metadata coverage {parsed[COVERAGE_KEY]} differs from the model's "
                             f"{camera_coverage(model.camera)}")
        if parsed[CAMERA_KEY] != model.camera.to_dict():
            raise ModelError(f"metadata camera {parsed[CAMERA_KEY]} differs from the model's {model.camera.to_dict()}")
        if (grid["tile"], grid["stride"]) != (int(model.tile), int(model.stride)):
            raise ModelError(f"metadata grid {grid} differs from the model's tile={model.tile}, stride={model.stride}")
    del camera
    return parsed


# ---------------------------------------------------------------------------- parity
@dataclass
class ParityCase:
    """One parity measurement: image size, batch and the largest discrepancies."""

    size: tuple[int, int]
    batch: int
    depth_rel: float
    depth_analytic_rel: float
    confidence_abs: float
    depth_rel_all: float = 0.0
    depth_analytic_rel_all: float = 0.0
    trusted_fraction: float = 1.0


@dataclass
class ParityReport:
    """Result of :func:`verify_onnx`.

    Attributes:
        path: the verified file.
        metadata: parsed ``tdfd.*`` metadata.
        cases: one :class:`ParityCase` per (size, batch); empty when no model was given.
        rtol, conf_atol: the tolerances applied.
    """

    path: Path
    metadata: dict[str, object]
    cases: list[ParityCase] = field(default_factory=list)
    rtol: float = 1e-4
    conf_atol: float = 1e-3
    rtol_all: float = 1e-3
    min_confidence: float = 0.05

    @property
    def worst_depth_rel(self) -> float:
        return max((max(c.depth_rel, c.depth_analytic_rel) for c in self.cases), default=0.0)

    @property
    def worst_confidence_abs(self) -> float:
        return max((c.confidence_abs for c in self.cases), default=0.0)

    def __str__(self) -> str:
        lines = [f"{self.path}: checker OK, contract OK"]
        for c in self.cases:
            lines.append(f"  {c.size[0]}x{c.size[1]} batch {c.batch}: depth rel {c.depth_rel:.2e} "
                         f"(all tiles {c.depth_rel_all:.2e}), depth_analytic rel {c.depth_analytic_rel:.2e} "
                         f"(all {c.depth_analytic_rel_all:.2e}), confidence abs {c.confidence_abs:.2e}; "
                         f"{c.trusted_fraction:.0%} of tiles with confidence >= {self.min_confidence:g}")
        if self.cases:
            lines.append(f"  parity OK (depth rtol {self.rtol:g} where confidence >= {self.min_confidence:g}, {self.rtol_all:g} "
                         f"elsewhere; confidence atol {self.conf_atol:g})")
        return "\n".join(lines)


def _session(path: Path, threads: int, optimization: str):
    from tdfd.runtime import make_session

    return make_session(path, threads, optimization)


def verify_onnx(path: str | Path, model: nn.Module | None = None,
                sizes: Sequence[tuple[int, int]] = DEFAULT_SIZES, batches: Sequence[int] = DEFAULT_BATCHES,
                rtol: float = 1e-4, conf_atol: float = 1e-3, threads: int = 2, seed: int = 0,
                optimization: str | None = None, min_confidence: float = 0.05, rtol_all: float = 1e-3) -> ParityReport:
    """Check an exported file and its agreement with the torch model.

    Args:
        path: the ``.onnx`` file.
        model: the torch model it was exported from (parity and metadata equality are
            checked only when given).
        sizes: image sizes ``(H, W)``, each at least one tile.
        batches: batch sizes.
        rtol: largest relative difference allowed on ``depth`` and ``depth_analytic`` in
            every tile whose (torch) confidence is at least ``min_confidence``.
        conf_atol: largest absolute difference allowed on ``confidence``.
        min_confidence: confidence below which a tile counts as unusable (see below).
        rtol_all: largest relative difference allowed on the depths in every tile.
        threads: ONNX Runtime intra-op threads.
        seed: seed of the rendered scenes.
        optimization: ONNX Runtime graph optimisation level (default: the one
            :class:`tdfd.runtime.DepthRuntime` uses).

    Returns:
        A :class:`ParityReport`.

    Raises:
        ModelError: the file is missing or unreadable, fails the checker or the contract,
            or disagrees with the model (the worst discrepancy is in the message).

    Note:
        ONNX Runtime and torch both compute in float32 but sum in different orders. The
        Laplacian pre-whitening leaves the lowest rings with few significant bits, and in
        tiles whose fit rests on them (weak texture: the model's confidence is low) the
        analytic fit amplifies that rounding to ~1e-4 relative; torch float32 differs from
        torch float64 by as much there. The discrepancy falls with the confidence (about
        5e-5 below 0.05, 2e-5 from 0.05 to 0.2, 5e-6 above 0.5 on rendered scenes), so
        tiles below ``min_confidence`` (default 0.05: a predicted relative error above
        ~4%) are held to ``rtol_all`` instead of ``rtol``.
    """
    path = Path(path)
    if not path.is_file():
        raise ModelError(f"ONNX file {path} does not exist")
    try:
        proto = onnx.load(str(path))
    except Exception as exc:
        raise ModelError(f"cannot load {path}: {exc}") from exc
    try:
        onnx.checker.check_model(proto, full_check=True)
    except (onnx.checker.ValidationError, onnx.shape_inference.InferenceError) as exc:
        raise ModelError(f"{path} fails onnx.checker (full check): {exc}") from exc
    metadata = check_contract(proto, model)
    report = ParityReport(path=path, metadata=metadata, rtol=rtol, conf_atol=conf_atol, rtol_all=rtol_all,
                          min_confidence=min_confidence)
    if model is None:
        return report
    from tdfd.runtime import DEFAULT_OPTIMIZATION

    sess = _session(path, threads, optimization or DEFAULT_OPTIMIZATION)
    worst: tuple[float, str] = (-1.0, "")
    failed = False
    names = [o.name for o in sess.get_outputs()]
    with _export_mode(model), torch.no_grad():
        for h, w in sizes:
            for b in batches:
                i1, i2 = realistic_pairs(model.camera, b, h, w, seed=seed + 7919 * h + w + 104729 * b)
                ref = [t.detach().cpu().numpy() for t in model(i1, i2)]
                if len(ref) != len(names):
                    raise ModelError(f"the graph has outputs {names}, the torch model returns {len(ref)} tensors")
                got = sess.run(names, {INPUT_NAMES[0]: i1.numpy(), INPUT_NAMES[1]: i2.numpy()})
                expect_shape = (b, 1, *grid_shape(h, w, int(model.tile), int(model.stride)))
                conf_ref = ref[names.index("confidence")]
                trusted_tiles = conf_ref >= min_confidence
                errs = {}
                checks = []
                for name, r, o in zip(names, ref, got):
                    # a pooled output is trusted where the pooled confidence is
                    trusted = (ref[names.index("confidence_pooled")] >= min_confidence if name.endswith("_pooled")
                               else trusted_tiles)
                    conf_like = name.startswith("confidence")
                    if tuple(o.shape) != expect_shape or tuple(r.shape) != expect_shape:
                        raise ModelError(f"{name} for {b}x1x{h}x{w} has shape ONNX {tuple(o.shape)} / torch "
                                         f"{tuple(r.shape)}, expected {expect_shape}")
                    if not np.isfinite(o).all():
                        raise ModelError(f"ONNX {name} for {b}x1x{h}x{w} contains NaN or inf")
                    if conf_like:
                        e = np.abs(o.astype(np.float64) - r)
                        checks.append((name, "abs", e, np.ones_like(trusted), conf_atol))
                    else:
                        e = np.abs(o.astype(np.float64) - r) / np.maximum(np.abs(r.astype(np.float64)), 1e-12)
                        checks.append((name, f"rel (confidence >= {min_confidence:g})", e, trusted, rtol))
                        checks.append((name, "rel (all tiles)", e, np.ones_like(trusted), rtol_all))
                        errs[name + "_all"] = float(e.max())
                    errs[name] = float(e[trusted].max()) if not conf_like and trusted.any() else (
                        0.0 if not conf_like else float(e.max()))
                for name, kind, e, mask, tol in checks:
                    if not mask.any():
                        continue
                    em = np.where(mask, e, -1.0)
                    idx = np.unravel_index(int(np.argmax(em)), em.shape)
                    err = float(em[idx])
                    o, r = got[names.index(name)], ref[names.index(name)]
                    if err / tol > worst[0]:
                        worst = (err / tol, f"{name} at {b}x1x{h}x{w}, tile {tuple(int(i) for i in idx)} (confidence "
                                            f"{float(conf_ref[idx]):.3g}): ONNX {float(o[idx]):.7g} vs torch "
                                            f"{float(r[idx]):.7g}, {kind} error {err:.3g} > {tol:g}")
                    failed |= err > tol
                report.cases.append(ParityCase((h, w), b, errs["depth"], errs["depth_analytic"], errs["confidence"],
                                               errs["depth_all"], errs["depth_analytic_all"], float(trusted_tiles.mean())))
                logger.info("parity %dx%d batch %d: %s", h, w, b, errs)
    if failed:
        raise ModelError(f"ONNX Runtime disagrees with torch for {path}: worst {worst[1]}")
    return report
