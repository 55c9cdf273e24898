"""The likelihood stage's rows on the structure benchmark's scenes, and its fits fused again with other scales.

Pieces of ``benchmarks/bench_likelihood_stage.py`` (section ``likelihood_stage``):
:func:`refused` (and :func:`refuse`, from the fits' maps) fuses one image's fits again with another
:class:`~tdfd.dfd.inverse_variance.LikelihoodScales` (an A/B of the fusion on the very same
fits, from the fit's own sigma the stage keeps, ``sigma_fit_raw``); :func:`structure_rows` runs
the stage on the structure benchmark's scenes and keeps every tile in the working range;
:func:`structure_table` scores them per layout, away from occlusion edges and all.
"""

from __future__ import annotations

import torch
from tqdm import tqdm

from benchmarks.bench_structure import STRUCTURE_SEED
from benchmarks.depth_edges import edge_tiles, tile_depth_spread
from benchmarks.uncertainty import resample_scenes
from tdfd.dfd.inverse_variance import LikelihoodScales, model_sigma
from tdfd.dfd.likelihood_stage import LikelihoodStage, LikelihoodStageResult, fuse_with_fit
from tdfd.model import DFDModel
from training.data import STRUCTURE_LAYOUTS, textured_scenes
from training.fit_likelihood_stage import black_levels

__all__ = ["refuse", "refused", "structure_rows", "structure_table"]


def refuse(fitted: torch.Tensor, depth_fit: torch.Tensor, sigma_fit_raw: torch.Tensor, slope: torch.Tensor,
           depth: torch.Tensor, confidence: torch.Tensor, confidence_scale: float, scales: LikelihoodScales
           ) -> tuple[torch.Tensor, torch.Tensor]:
    """One image's likelihood fits fused with the model's map by ``scales``, from the stage's
    result fields on its ``(h, w)`` tile grid (``fitted``, ``depth_fit``, ``sigma_fit_raw``,
    ``slope``; :class:`~tdfd.dfd.likelihood_stage.LikelihoodStageResult`) and the model's map
    ``depth``, ``confidence`` ``(h, w)``: the fused depth and confidence maps ``(h, w)``, as the
    stage gives them with those scales (the fits do not depend on the scales)."""
    d, c = depth.clone(), confidence.clone()
    q_fit = 1.0 / depth_fit[fitted].double()
    ii, jj = fitted.nonzero(as_tuple=True)
    q, conf, bias, _ = fuse_with_fit(1.0 / depth[fitted].double(),
                                     model_sigma(confidence[fitted].double(), confidence_scale), q_fit,
                                     sigma_fit_raw[fitted] * q_fit, slope[fitted].double(), scales,
                                     confidence_scale, ii, jj, tuple(fitted.shape))
    d = (d.double() * torch.exp(bias)).to(depth.dtype)
    d[fitted], c[fitted] = (1.0 / q).to(d.dtype), conf.to(c.dtype)
    return d, c


def refused(stage: LikelihoodStage, r: LikelihoodStageResult, depth: torch.Tensor, confidence: torch.Tensor,
            scales: LikelihoodScales) -> tuple[torch.Tensor, torch.Tensor]:
    """The stage's result for one image ``(1, 1, h, w)`` fused again with other ``scales`` (the
    fit's own sigma, ``r.sigma_fit_raw``; :func:`refuse`): the fused depth and confidence maps
    ``(1, 1, h, w)``, for an A/B of the fusion on the same fits."""
    d, c = refuse(r.fitted[0, 0], r.depth_fit[0, 0], r.sigma_fit_raw[0, 0], r.slope[0, 0], depth[0, 0],
                  confidence[0, 0], stage.confidence_scale, scales)
    return d[None, None], c[None, None]


def structure_rows(model: DFDModel, stage: LikelihoodStage, scenes: int, baseline: LikelihoodScales | None = None
                   ) -> dict[str, dict[str, torch.Tensor]]:
    """Per layout of :data:`training.data.STRUCTURE_LAYOUTS`, the first ``scenes`` 480x640 scenes
    of the structure benchmark (seed :data:`benchmarks.bench_structure.STRUCTURE_SEED`): every tile
    in the working range with its true depth, the model's depth and confidence, the stage's fused
    depth and confidence and its own fit, whether it was fitted and whether it lies near an
    occlusion edge (:func:`benchmarks.depth_edges.edge_tiles`), and its scene; with ``baseline``
    also the same fits fused with those scales (``base``, ``base_conf``)."""
    near, far = model.camera.depth_range_m
    out = {}
    for layout in STRUCTURE_LAYOUTS:
        ds = textured_scenes(model.camera, model.tile, model.stride, layout, (480, 640), STRUCTURE_SEED)
        acc: dict[str, list[torch.Tensor]] = {k: [] for k in ("true", "model", "model_conf", "fused", "fused_conf",
                                                             "fit", "fitted", "edge", "spread", "fit_sigma",
                                                             "scene", "base", "base_conf")}
        for i in tqdm(range(scenes), desc=f"likelihood stage: {layout}", mininterval=10.0):
            b = ds.batch([i])
            i1, i2 = b["image_f1"].float(), b["image_f2"].float()
            with torch.no_grad():
                depth, conf = model.analyse(i1, i2).depth_map
            r = stage(i1, i2, depth, conf, black_level=black_levels(b["params"])[0])
            true = b["tile_depth"][0, 0].double()
            keep = (true >= near) & (true <= far)
            if baseline is not None:
                d_b, c_b = refused(stage, r, depth, conf, baseline)
                acc["base"].append(d_b[0, 0][keep].double())
                acc["base_conf"].append(c_b[0, 0][keep].double())
            for key, t in (("true", true), ("model", depth[0, 0]), ("model_conf", conf[0, 0]), ("fused", r.depth[0, 0]),
                           ("fused_conf", r.confidence[0, 0]), ("fit", r.depth_fit[0, 0]), ("fitted", r.fitted[0, 0]),
                           ("edge", edge_tiles(b["depth"][0, 0], model.tile, model.stride)),
                           ("spread", tile_depth_spread(b["depth"][0, 0], model.tile, model.stride)),
                           ("fit_sigma", r.sigma_fit[0, 0])):
                acc[key].append(t[keep].double() if t.dtype != torch.bool else t[keep])
            acc["scene"].append(torch.full((int(keep.sum()),), i))
        out[layout] = {k: torch.cat(v) for k, v in acc.items() if v}
    return out


def structure_table(rows: dict[str, dict[str, torch.Tensor]], reps: int = 200) -> list[list]:
    """Per layout and tile set (away from edges, all): the model's and the fused map's median
    error, on the fitted tiles the stage's own fit's and the model's, the fused - model difference
    with its 95 % interval over a bootstrap of the scenes,
    the share at confidence >= 0.5 and the median error there (model / fused), and where the rows
    carry a baseline fusion (``base``) its median error, share and median there."""
    table = []
    for layout, t in rows.items():
        for label, sel in (("away from edges", ~t["edge"]), ("all tiles", torch.ones_like(t["edge"]))):
            e_m = (t["model"][sel] / t["true"][sel] - 1).abs()
            e_f = (t["fused"][sel] / t["true"][sel] - 1).abs()
            fitted = sel & t["fitted"]
            e_fit = (t["fit"][fitted] / t["true"][fitted] - 1).abs()
            e_mf = (t["model"][fitted] / t["true"][fitted] - 1).abs()
            scene = t["scene"][sel]

            def difference(e_a: torch.Tensor, e_b: torch.Tensor) -> str:
                """median(e_a) - median(e_b) in points, with its 95 % interval over the scenes."""
                diffs = sorted(float(e_a[ix].median() - e_b[ix].median())
                               for ix in resample_scenes(scene, reps, torch.Generator().manual_seed(0)))
                return (f"{100 * (float(e_a.median()) - float(e_b.median())):+.2f} "
                        f"({100 * diffs[int(0.025 * reps)]:+.2f} .. {100 * diffs[int(0.975 * reps) - 1]:+.2f})")
            conf_m, conf_f = t["model_conf"][sel] >= 0.5, t["fused_conf"][sel] >= 0.5
            share = lambda c: f"{100 * float(c.double().mean()):.0f} %"  # noqa: E731
            med = lambda e, c: f"{100 * float(e[c].median()):.2f} %" if bool(c.any()) else "-"  # noqa: E731
            table.append([layout, label, int(sel.sum()), f"{100 * float(e_m.median()):.2f} %",
                          f"{100 * float(e_f.median()):.2f} %",
                          f"{100 * float(e_fit.median()):.2f} % / {100 * float(e_mf.median()):.2f} %"
                          if e_fit.numel() else "-",
                          difference(e_f, e_m),
                          f"{share(conf_m)} / {share(conf_f)}", f"{med(e_m, conf_m)} / {med(e_f, conf_f)}"])
            if "base" in t:
                e_b = (t["base"][sel] / t["true"][sel] - 1).abs()
                conf_b = t["base_conf"][sel] >= 0.5
                table[-1] += [f"{100 * float(e_b.median()):.2f} %", difference(e_f, e_b), share(conf_b),
                              med(e_b, conf_b)]
    return table
