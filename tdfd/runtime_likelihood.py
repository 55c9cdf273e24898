"""The likelihood stage after an exported model: an ONNX Runtime result refined tile by tile.

``tdfd depth F1 F2 --likelihood-stage SCALES.json`` runs the ONNX file
(:class:`tdfd.runtime.DepthRuntime`), then :class:`tdfd.dfd.likelihood_stage.LikelihoodStage`
(torch) on the same normalised frames, the file's camera, grid and confidence scale, the
lens's PSF family the CNN is told (``--psf-family``; unknown: every shape), or the whole PSF a
focus sweep measured (``--psf-model CAM.json``, :mod:`tdfd.calibration.psf_model`), and the sigma factors
of ``SCALES.json`` (``python -m training.fit_likelihood_stage``; the shipped model's:
``models/reference.likelihood.json``). The best map of the result (the pooled one, else the
tiles') is replaced by the stage's fused map (with ``--likelihood-pool`` that map pooled along
the depth structure by the file's own structure pooling, :mod:`tdfd.dfd.stage_pooling`); each
tile's own estimate stays as the file gave it. The stage is not in the ONNX graph (its cost is
seconds per pair; docs/ARCHITECTURE.md).

The stage models neither focus breathing nor a camera other than the model's (its blur per
inverse depth is the file's camera), so a file that registers breathing, or a runtime covering
another camera, is refused; so is a result at full resolution (the stage works on the tile grid).
"""

from __future__ import annotations

import logging
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from .contract import MODEL_KEY
from .dfd.inverse_variance import LikelihoodScales
from .dfd.likelihood_stage import LikelihoodStage
from .dfd.psf_hypotheses import PsfHypothesis
from .dfd.scene_ambiguity import ambiguity_cap
from .errors import InputError, ModelError
from .model.structure_pooling import StructurePooling
from .runtime import DepthResult, DepthRuntime

log = logging.getLogger(__name__)

__all__ = ["stage_for_runtime", "refine_result"]

#: what to use instead, per PSF the stage is told, when its scales were fitted for the other
_SCALES_HINT = {"measured": "fit the scales with --calibrated-psf, or use the shipped "
                            "models/reference.likelihood-calibrated.json",
                "profiled": "use scales fitted without --calibrated-psf, e.g. models/reference.likelihood.json"}


def stage_for_runtime(rt: DepthRuntime, scales_path: str | Path, black_level: float = 0.0,
                      psf_model: dict | None = None, walk: int = 0, pool: bool = False,
                      ambiguity: bool = False, register: bool = False) -> LikelihoodStage:
    """The likelihood stage for ``rt``'s file: its camera, grid, confidence scale and told family.

    Args:
        rt: the runtime whose results the stage refines.
        scales_path: the sigma factors (:meth:`~tdfd.dfd.inverse_variance.LikelihoodScales.load`).
        black_level: the frames' black level as a fraction of full scale (``[0, 1)``).
        psf_model: the lens's PSF measured from a focus sweep (a camera file's ``psf_model``,
            ``tdfd calibrate --psf-model``): the stage's one hypothesis instead of the family's.
            Scales fitted for the other case (:attr:`~tdfd.dfd.inverse_variance.LikelihoodScales.psf`)
            are used with a warning.
        walk: how many times a fit whose minimum lies on its window's edge may move its window
            (:func:`~tdfd.dfd.seeded_fit.seeded_tile_fit`; 0: never).
        pool: also pool the fused map along the depth structure with the file's own structure
            pooling (its ``structure_pooling`` metadata; :mod:`tdfd.dfd.stage_pooling`).
        ambiguity: also check each pair's fit against the likelihood over the whole range and cap
            the confidences of a pair it does not tell (:mod:`tdfd.dfd.scene_ambiguity`).
        register: fit each pair's focus breathing and shift to its own likelihood before the fit
            (:mod:`tdfd.dfd.pair_registration`); a file that registers breathing needs it. Scales
            fitted the other way (:attr:`~tdfd.dfd.inverse_variance.LikelihoodScales.registered`) are
            used with a warning.

    Raises:
        InputError: a file with focus breathing without ``register``, a runtime for another camera, a
            bad black level or ``walk``.
        CameraError: a ``psf_model`` that is not valid.
        ModelError: a scales file that cannot be read, a file without a positive
            ``confidence_scale`` in its metadata, or ``pool`` for a file without a structure pooling.
    """
    if rt.magnification_per_dpt and not register:
        raise InputError(f"{rt.path.name} registers focus breathing, which the likelihood stage models only when it "
                         f"fits each pair's registration itself (register, tdfd depth --likelihood-register)")
    if rt.inverse_depth_offset_dpt:
        raise InputError(f"the runtime covers camera {rt.camera.name!r} with another camera's model; the likelihood "
                         f"stage needs the model's own camera")
    if not 0.0 <= black_level < 1.0:
        raise InputError(f"the black level must be a fraction of full scale in [0, 1), got {black_level}")
    meta = rt.metadata.get(MODEL_KEY)
    b0 = meta.get("confidence_scale") if isinstance(meta, dict) else None
    if not isinstance(b0, (int, float)) or not b0 > 0:
        raise ModelError(f"{rt.path} has no positive confidence_scale in its {MODEL_KEY!r} metadata")
    pooling = None
    if pool:
        options = meta.get("structure_pooling")
        if not isinstance(options, dict):
            raise ModelError(f"{rt.path} has no structure pooling in its {MODEL_KEY!r} metadata to pool the likelihood "
                             f"stage's map with")
        pooling = StructurePooling.from_config(options)
    hypotheses = None if psf_model is None else (PsfHypothesis.from_dict(psf_model),)
    scales = LikelihoodScales.load(scales_path)
    told = "profiled" if psf_model is None else "measured"
    if scales.psf != told:
        log.warning("%s was fitted for the stage with the PSF %s, this one has it %s: the fusion's weights and "
                    "confidences will be off (%s)", scales_path, scales.psf, told, _SCALES_HINT[told])
    if scales.registered != register:
        log.warning("%s was fitted for the stage %s each pair's registration, this one %s it: the fusion's weights "
                    "and confidences will be off (fit the scales %s --register%s)", scales_path,
                    "fitting" if scales.registered else "without", "fits" if register else "does not fit",
                    "with" if register else "without",
                    ", or use the shipped models/reference.likelihood-calibrated-registered.json with --psf-model"
                    if register else "")
    return LikelihoodStage(rt.camera, rt.tile, rt.stride, float(b0), scales=scales,
                           family=rt.psf_family, hypotheses=hypotheses, black_level=black_level, walk=walk,
                           pooling=pooling, ambiguity=ambiguity, register=register)


def refine_result(rt: DepthRuntime, stage: LikelihoodStage, image_f1: np.ndarray, image_f2: np.ndarray,
                  result: DepthResult, white_level: float | None = None) -> DepthResult:
    """``result`` (of ``rt`` on these frames, on the tile grid) with its best map refined by ``stage``
    (pooled, where the stage pools; a pair the runtime found to be no DFD pair keeps its map, at confidence 0).

    Raises:
        InputError: a result at full resolution, or one whose grid is not the frames'.
    """
    if result.full_resolution:
        raise InputError("the likelihood stage refines a result on the tile grid, not one at full resolution")
    a, b, _ = rt.prepare(image_f1, image_f2, white_level)
    depth, conf = result.depth_map
    grid = (a.shape[0], 1, *depth.shape[-2:])
    if int(np.prod(depth.shape)) != int(np.prod(grid)):
        raise InputError(f"the result's map {depth.shape} is not the frames' tile grid {grid}")
    d = torch.from_numpy(np.asarray(depth, np.float32).reshape(grid).copy())
    c = torch.from_numpy(np.asarray(conf, np.float32).reshape(grid).copy())
    out = stage(torch.from_numpy(a), torch.from_numpy(b), d, c)
    for k in ([] if out.ambiguous is None else out.ambiguous.nonzero().flatten().tolist()):
        log.warning("likelihood stage: pair %d is ambiguous (its likelihood prefers depths 10 %% from its fits: "
                    "margin %.1f nats, e.g. a narrow-band or periodic texture); its confidences are capped at "
                    "%.3f", k, float(out.scene_margin[k]), ambiguity_cap(stage.confidence_scale))
    if out.registration is not None:
        for k, (beta, dr, dc) in enumerate(out.registration.tolist()):
            log.info("likelihood stage: pair %d registered: frame 2 magnified by %+.4f %%, shifted by "
                     "(%+.2f, %+.2f) px", k, 100 * beta, dr, dc)
    if stage.scales.shared_bias:
        log.info("likelihood stage: the model's bias removed, median %s %% in inverse depth per pair",
                 ", ".join(f"{100 * (np.exp(float(x.median())) - 1):+.2f}" for x in out.bias))
    best = out.depth if out.depth_pooled is None else out.depth_pooled
    new_d, new_c = best.numpy().copy(), out.confidence.numpy().copy()
    for k, problem in enumerate(result.problems):  # no DFD pair: keep its map and its confidence 0
        if problem and k < len(new_d):
            new_d[k], new_c[k] = d[k].numpy(), c[k].numpy()
    return replace(result, depth_pooled=new_d.reshape(depth.shape).astype(np.float32),
                   confidence_pooled=new_c.reshape(conf.shape).astype(np.float32))
