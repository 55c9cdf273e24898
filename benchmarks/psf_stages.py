"""The likelihood stages section ``psf_model`` compares, built for one lens and run on the structure scenes.

Pieces of ``benchmarks/bench_psf_model.py`` (the planes) and ``benchmarks/bench_psf_structure.py``
(the structure targets): :func:`stages_for` builds the stages of :data:`STAGES` for one lens and
its focus-sweep calibration; :func:`structure_rows` runs them on the structure benchmark's scenes,
each scene's lens calibrated from its own sweep, and keeps each tile in the working range and the
whole grid's fits (so that other scales can fuse the very same fits again,
:func:`benchmarks.stage_rows.refuse`, and pool them: :func:`refuse_rows`); :func:`paired_with` sets
another run's rows of the same scenes beside them.
"""

from __future__ import annotations

import math

import torch
from tqdm import tqdm

from benchmarks.bench_bound import depth_variances, psf_model, psf_prior_variance, tile_fisher
from benchmarks.bench_structure import STRUCTURE_SEED
from benchmarks.depth_edges import edge_tiles
from benchmarks.stage_rows import refuse, refused
from data_synth.params import SynthConfig
from tdfd.calibration.psf_model import PsfModelFit
from tdfd.dfd.inverse_variance import LikelihoodScales
from tdfd.dfd.likelihood_stage import LikelihoodStage
from tdfd.dfd.psf_hypotheses import PsfHypothesis
from tdfd.dfd.stage_pooling import pool_stage_map
from tdfd.model import DFDModel
from tdfd.optics.aberrated_psf import PSFModel
from training.calibrated_lens import SWEEP_CHART, sweep_fit
from training.data import STRUCTURE_LAYOUTS, textured_scenes
from training.fit_likelihood_stage import black_levels

__all__ = ["SWEEP_SEED", "STAGES", "BIAS_STAGE", "POOLED", "FIT_FIELDS", "stages_for", "structure_rows", "refuse_rows",
           "paired_with"]

#: the sweeps' seeds (``training.calibrated_lens.sweep_fit``): planes at +i, structure scenes above
SWEEP_SEED = 7_000_000

#: the stages compared, in the tables' order
STAGES = ("profiled", "calibrated_shipped_scales", "calibrated", "told")
#: ``--bias-scales``: the ``calibrated`` stage's fits fused again with scales that remove the
#: model's bias first (:func:`benchmarks.stage_rows.refused`)
BIAS_STAGE = "calibrated_bias"
#: the stages :func:`refuse_rows` also pools (``tdfd depth --likelihood-pool``), each named ``<stage>_pooled``
POOLED = ("calibrated", BIAS_STAGE)
#: a stage's result fields a structure row keeps on the whole grid (``row["grids"]``)
FIT_FIELDS = ("depth_fit", "sigma_fit_raw", "slope", "fitted")


def _hypothesis(lens: PSFModel) -> PsfHypothesis:
    return PsfHypothesis(lens.shape, lens.diffraction_sigma_px, lens.astigmatism, lens.astigmatism_angle,
                         lens.spherical)


def stages_for(model: DFDModel, scales: tuple[LikelihoodScales, LikelihoodScales], fit: PsfModelFit, lens: PSFModel,
               names: tuple[str, ...] = STAGES, walk: int = 0, register: bool = False) -> dict[str, LikelihoodStage]:
    """The stages ``names`` (of :data:`STAGES`) for one lens; ``scales``: the profiled stage's, the measured PSF's;
    ``walk``: each stage's window moves; ``register``: each stage fits the pair's breathing and shift
    (:class:`~tdfd.dfd.likelihood_stage.LikelihoodStage`)."""
    shipped, measured = scales
    make = {"profiled": lambda: LikelihoodStage.for_model(model, scales=shipped, walk=walk, register=register),
            "calibrated_shipped_scales": lambda: LikelihoodStage.for_model(model, scales=shipped,
                                                                           hypotheses=(fit.hypothesis,), walk=walk,
                                                                           register=register),
            "calibrated": lambda: LikelihoodStage.for_model(model, scales=measured, hypotheses=(fit.hypothesis,),
                                                            walk=walk, register=register),
            "told": lambda: LikelihoodStage.for_model(model, scales=measured, hypotheses=(_hypothesis(lens),),
                                                      walk=walk, register=register)}
    return {name: make[name]() for name in names}


def structure_rows(model: DFDModel, scales: tuple[LikelihoodScales, LikelihoodScales], scenes: int,
                   frames_per_power: int, chart: str = SWEEP_CHART, bias_scales: LikelihoodScales | None = None,
                   stages: tuple[str, ...] = STAGES, bound: bool = False, walk: int = 0,
                   register: bool = False, first: int = 0) -> list[dict]:
    """Per 480x640 structure scene (the first ``scenes`` per layout, from scene ``first`` on: a long
    run in parts; each one's lens calibrated from its own sweep): its tiles in the working range,
    their true, model and each of ``stages``' depth and confidence (with ``bias_scales``
    :data:`BIAS_STAGE`'s too, from the ``calibrated`` stage's fits), ``grids`` (the whole grid's
    ``keep`` mask, the model's map and each stage's :data:`FIT_FIELDS`, to fuse the same fits
    again), ``edge`` (within one tile of an occlusion edge,
    :func:`benchmarks.depth_edges.edge_tiles`) and with ``bound`` ``bound_shared``: the tile's
    relative depth standard deviation at the Cramér-Rao reference of section ``structure``
    (:func:`benchmarks.bench_bound.tile_fisher`, the PSF shared by the image; NaN near edges).
    ``walk``: the stages' window moves (:func:`tdfd.dfd.seeded_fit.seeded_tile_fit`); ``register``: the
    stages fit each pair's breathing and shift (:mod:`tdfd.dfd.pair_registration`).

    Raises:
        ValueError: ``scenes`` over 1000 (the sweeps' seeds of two layouts would meet), ``first``
            not in ``0..scenes``, or ``bias_scales`` without the ``calibrated`` stage.
    """
    if not 0 <= scenes <= 1000:
        raise ValueError(f"structure scenes per layout must be in 0..1000 (the sweeps' seeds), got {scenes}")
    if not 0 <= first <= scenes:
        raise ValueError(f"the first scene must be in 0..{scenes} (the scenes per layout), got {first}")
    if bias_scales is not None and "calibrated" not in stages:
        raise ValueError(f"{BIAS_STAGE} re-fuses the calibrated stage's fits: stages {stages} lack it")
    near, far = model.camera.depth_range_m
    prior_var = psf_prior_variance(SynthConfig(), model.camera) if bound else None
    out = []
    for layout in STRUCTURE_LAYOUTS:
        ds = textured_scenes(model.camera, model.tile, model.stride, layout, (480, 640), STRUCTURE_SEED,
                             return_sharp=bound)
        for i in tqdm(range(first, scenes), desc=f"psf model: {layout}", mininterval=10.0):
            b = ds.batch([i])
            i1, i2 = b["image_f1"].float(), b["image_f2"].float()
            with torch.no_grad():
                depth, conf = model.analyse(i1, i2).depth_map
            lens = psf_model(b["params"][0])
            fit = sweep_fit(model.camera, lens, SWEEP_SEED + 100_000 + 1000 * STRUCTURE_LAYOUTS.index(layout) + i,
                            frames_per_power, chart)
            true = b["tile_depth"][0, 0].double()
            keep = (true >= near) & (true <= far)
            edge = edge_tiles(b["depth"][0, 0], model.tile, model.stride)
            row = {"layout": layout, "scene": i, "true": true[keep], "edge": edge[keep],
                   "model": depth[0, 0][keep].double(), "model_conf": conf[0, 0][keep].double(),
                   "grids": {"keep": keep, "model": depth[0, 0], "model_conf": conf[0, 0]}}
            for name, stage in stages_for(model, scales, fit, lens, stages, walk, register).items():
                r = stage(i1, i2, depth, conf, black_level=black_levels(b["params"])[0])
                row[name] = r.depth[0, 0][keep].double()
                row[f"{name}_conf"] = r.confidence[0, 0][keep].double()
                # the whole grid's fits, for A/Bs of the fusion on the same fits (benchmarks.stage_rows.refused)
                row["grids"].update({f"{name}_{k}": getattr(r, k)[0, 0] for k in FIT_FIELDS})
                if name == "calibrated" and bias_scales is not None:
                    d, c = refused(stage, r, depth, conf, bias_scales)
                    row[BIAS_STAGE], row[f"{BIAS_STAGE}_conf"] = d[0, 0][keep].double(), c[0, 0][keep].double()
            if bound:
                fisher = tile_fisher(model.camera, b["sharp"][0, 0], true, b["params"][0])
                fisher[edge] = 0.0  # no reference at edges; they teach nothing about the shared PSF either
                rel = depth_variances(fisher, prior_var)["tile_shared"].sqrt() * true
                row["bound_shared"] = torch.where(edge, torch.full_like(rel, math.nan), rel)[keep]
            out.append(row)
    return out


def paired_with(rows: list[dict], baseline: list[dict], estimators: tuple[str, ...] = ("calibrated", BIAS_STAGE)
                ) -> list[dict]:
    """``rows`` with each of ``estimators`` from ``baseline`` (another run's rows of the very scenes,
    e.g. without ``--walk``) beside it as ``base <estimator>``: the pairs
    :func:`benchmarks.bench_psf_structure.difference_rows` scores.

    Raises:
        ValueError: a scene of ``rows`` that ``baseline`` lacks or holds with other tiles.
    """
    base = {(r["layout"], r["scene"]): r for r in baseline}
    out = []
    for r in rows:
        b = base.get((r["layout"], r["scene"]))
        if b is None or not torch.equal(b["true"], r["true"]):
            raise ValueError(f"the baseline rows lack {r['layout']} scene {r['scene']}, or hold it with other tiles")
        out.append({**r, **{f"base {k}": b[k] for k in estimators},
                    **{f"base {k}_conf": b[f"{k}_conf"] for k in estimators}})
    return out


def refuse_rows(rows: list[dict], confidence_scale: float, scales: LikelihoodScales, bias_scales: LikelihoodScales,
                pooling=None) -> list[dict]:
    """``rows`` (:func:`structure_rows`, saved with ``--rows``) with ``calibrated`` and :data:`BIAS_STAGE`
    fused again from the calibrated stage's very fits (``row["grids"]``, :func:`benchmarks.stage_rows.refuse`)
    with ``scales`` and ``bias_scales``: what a run with those scales gives, without the sweeps and fits. With
    ``pooling`` (the model's structure pooling) also each of :data:`POOLED` pooled along the depth structure
    as the stage pools it (:func:`tdfd.dfd.stage_pooling.pool_stage_map` on the whole grid), ``<stage>_pooled``,
    its confidence the fused one.

    Raises:
        ValueError: rows without the calibrated stage's grids.
    """
    out = []
    for r in rows:
        g = r.get("grids", {})
        if "calibrated_depth_fit" not in g:
            raise ValueError(f"row {r.get('layout')} {r.get('scene')} has no calibrated fits to fuse again (rows of an "
                             "older run)")
        row = dict(r)
        for name, sc in (("calibrated", scales), (BIAS_STAGE, bias_scales)):
            d, c = refuse(g["calibrated_fitted"], g["calibrated_depth_fit"], g["calibrated_sigma_fit_raw"],
                          g["calibrated_slope"], g["model"], g["model_conf"], confidence_scale, sc)
            row[name], row[f"{name}_conf"] = d[g["keep"]].double(), c[g["keep"]].double()
            if pooling is not None and name in POOLED:
                pooled = pool_stage_map(d[None, None], c[None, None], confidence_scale, pooling)[0, 0]
                row[f"{name}_pooled"], row[f"{name}_pooled_conf"] = pooled[g["keep"]].double(), row[f"{name}_conf"]
        out.append(row)
    return out
