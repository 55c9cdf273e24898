r"""A likelihood stage after the CNN: each tile's cross-residual fit, seeded by the model and fused with it.

Run from the repository root::

    .venv/bin/python -m benchmarks.bench_likelihood_stage [--samples 256] [--world clean,full]
        [--psf product,shape,known] [--structure 32] [--baseline-scales OLD.likelihood.json]

What a model-based stage adds to the shipped model (section ``likelihood_stage``), on the
refinement benchmark's planes (0.3-1.0 m) and, for the product stage, on the structure
benchmark's scenes. Per interior tile of the 64/32 grid
(:func:`benchmarks.bench_tile_oracle.interior_origins`):

- ``product``: the tdfd stage (:mod:`tdfd.dfd.likelihood_stage`) as a user runs it: told only
  each frame's black level (a sensor constant), the PSF profiled over every shape with and
  without the diffraction of the working f-number, the noise estimated from the fit, the two
  sigmas' factors and the map of the fused scale from ``models/reference.likelihood.json`` (fitted
  on training scenes by ``training/fit_likelihood_stage.py``: nothing is fitted on the benchmark); with
  ``--baseline-scales`` the same fits are also fused with another scales file (an A/B of the
  fusion, e.g. with and without the model's bias removed, on the very same fits);
- ``shape`` and ``known``, oracles: the seeded fit of
  :func:`tdfd.dfd.cross_residual.tile_cross_residual_nll` within
  :data:`~tdfd.dfd.seeded_fit.SEED_WINDOW` of the model's inverse depth, the PSF's shape
  profiled over :data:`~benchmarks.bench_plane_oracle.SHAPE_GRID` with its diffraction and
  aberrations told (or the PSF known), the noise told (the sample's sensor); the variance from
  the curvature, ``var(q) = 1 / L''(q)`` (``L`` the summed NLL over the band's independent
  bins); the model's from its confidence ``conf = 1 / (1 + (b / b0)^2)`` (variance ``2 b^2``);
  each variance times a factor fitted on the *other* half of the planes (even / odd sample
  index) so that the median of ``|e| / sigma`` there is 0.674.

Scores: the median relative error over the interior tiles, per plane the median tile's, and the
fused-minus-model difference with a paired bootstrap over planes (95 % interval). The nuisances:
``clean`` switches off breathing, misregistration, vignetting and gain jitter, ``full`` keeps
them (no estimator here models them). On the structure scenes (480x640, the whole world) the
product stage is scored on every tile in the working range (its ring keeps the model's
estimate), away from occlusion edges and all, with a bootstrap over scenes
(:mod:`benchmarks.stage_rows`); its confidence, and the model's, per confidence decile
(:mod:`benchmarks.stage_uncertainty`); and its cost is timed beside the model's.
"""

from __future__ import annotations

import argparse
import random
import statistics
import sys
import time
from dataclasses import replace

import torch
from tqdm import tqdm

from benchmarks.bench_bound import TILE, psf_model
from benchmarks.bench_plane_oracle import CLEAN_WORLD, Q_GRID, SHAPE_GRID, plane_frames
from benchmarks.bench_refinement import BENCH_SEED, bench_grids
from benchmarks.bench_structure import STRUCTURE_SEED
from benchmarks.bench_tile_oracle import SEED_WINDOW, interior_origins, profile_tiles, tile_nll_stack, tile_noise
from benchmarks.report import ROOT, comma_choices, machine, markdown_table, median_time, update_section
from benchmarks.stage_rows import refused, structure_rows, structure_table
from benchmarks.stage_uncertainty import decile_summary, relative_inverse_depth_error
from tdfd.dfd.cross_residual import curvature_sigma, independent_bins
from tdfd.dfd.inverse_variance import LikelihoodScales, fuse, model_sigma, sigma_factor
from tdfd.dfd.likelihood_stage import LikelihoodStage
from tdfd.dfd.seeded_fit import seed_mask
from tdfd.errors import InputError
from tdfd.model import DFDModel
from training.data import textured_scenes
from training.fit_likelihood_stage import black_levels

__all__ = ["seeded_fit", "paired_bootstrap", "run_world", "score_product", "score", "main"]


def seeded_fit(nll: torch.Tensor, grid: torch.Tensor, seed_q: torch.Tensor, bins: float,
               window: float = SEED_WINDOW) -> tuple[torch.Tensor, torch.Tensor, int]:
    """Each tile's seeded minimum and its standard deviation in ``q``.

    Args:
        nll: ``(C, Q, T)`` mean per-bin NLL of ``C`` candidate PSFs (``inf`` where not computed).
        grid: ``(Q,)`` uniform grid of ``q`` (1/m).
        seed_q: ``(T,)`` each tile's seed.
        bins: independent bins per tile (the NLL's sum is ``bins`` times its mean).
        window: relative half-width of each tile's search.

    Returns:
        ``q`` ``(T,)`` (parabolic refinement, at most one step), ``sigma_q`` ``(T,)`` (``inf`` where
        the minimum lies on the window's edge or the curvature is not positive), and the index
        of the candidate shared by the image (:func:`benchmarks.bench_tile_oracle.profile_tiles`).
    """
    if nll.ndim != 3 or nll.shape[1] != grid.shape[0] or seed_q.shape != (nll.shape[2],):
        raise InputError(f"need nll (C, Q, T), grid (Q,), seed_q (T,); got {tuple(nll.shape)}, "
                         f"{tuple(grid.shape)}, {tuple(seed_q.shape)}")
    if not bins > 0:
        raise InputError(f"bins must be > 0, got {bins}")
    q, j, curvature = profile_tiles(nll, grid, seed_mask(grid, seed_q, window))
    return q, curvature_sigma(curvature, bins), j


def paired_bootstrap(a: list[list[float]], b: list[list[float]], resamples: int = 1000, seed: int = 0
                     ) -> tuple[float, float, float]:
    """Mean and 95 % interval of ``median |a| - median |b|`` over tiles pooled from planes drawn
    with replacement (``a``, ``b``: per plane, the tiles' errors of two estimators)."""
    rng = random.Random(seed)
    n = len(a)
    diffs = []
    for _ in range(resamples):
        pick = [rng.randrange(n) for _ in range(n)]
        diffs.append(statistics.median(abs(x) for i in pick for x in a[i])
                     - statistics.median(abs(x) for i in pick for x in b[i]))
    diffs.sort()
    return statistics.mean(diffs), diffs[int(0.025 * resamples)], diffs[int(0.975 * resamples) - 1]


def run_world(world: str, samples: int, model: DFDModel, modes: tuple[str, ...] = ("known", "shape"),
              stage: LikelihoodStage | None = None, baseline: LikelihoodScales | None = None) -> list[dict]:
    """Every plane's interior tiles: true ``q``, the model's ``q``, sigma and confidence, per oracle
    mode the seeded fit's ``q`` and sigma (relative), and with ``stage`` the product stage's fused
    ``q`` and confidence (``product_q``, ``product_conf``) and its own fit's (``product_fit_q``),
    told only the frames' black level; with ``baseline`` also the same fits fused with those
    scales (``baseline_q``, ``baseline_conf``)."""
    over = CLEAN_WORLD if world == "clean" else {}
    camera = model.camera
    grids, ds = bench_grids(model, samples, 256, over)
    true, ref, conf = (grids[k].double() for k in ("true", "refined", "confidence"))
    origins, inner = interior_origins(256)
    bins = independent_bins(TILE)
    rows = []
    for i in tqdm(range(samples), desc=f"likelihood stage ({world})", mininterval=10.0):
        s = ds[i]
        p = s["params"]
        if p["layout"] != "plane" or not 0.3 <= float(true[i].median()) <= 1.0:
            continue
        y1, y2, _, _ = plane_frames(s, match_gain=True)
        nu1, nu2 = tile_noise(p, y1, origins), tile_noise(p, y2, origins)
        seed = 1.0 / ref[i][inner, inner].flatten()
        needed = seed_mask(Q_GRID, seed)  # only the pairs each tile's window searches
        row = {"index": i, "true_q": (1.0 / true[i][inner, inner].flatten()).tolist(), "model_q": seed.tolist(),
               "model_sigma": model_sigma(conf[i][inner, inner].flatten().clamp(1e-9, 1.0),
                                          model.confidence_scale).tolist(),
               "model_conf": conf[i][inner, inner].flatten().tolist()}
        if stage is not None:
            r = stage(s["image_f1"][None].float(), s["image_f2"][None].float(), ref[i][None, None],
                      conf[i][None, None], black_level=black_levels([p])[0])
            if not bool(r.fitted[0, 0, inner, inner].all()):
                raise InputError("the stage left interior tiles unfitted")
            row["product_q"] = (1.0 / r.depth[0, 0, inner, inner].flatten()).tolist()
            row["product_fit_q"] = (1.0 / r.depth_fit[0, 0, inner, inner].flatten()).tolist()
            row["product_conf"] = r.confidence[0, 0, inner, inner].flatten().tolist()
            if baseline is not None:
                d_b, c_b = refused(stage, r, ref[i][None, None], conf[i][None, None], baseline)
                row["baseline_q"] = (1.0 / d_b[0, 0, inner, inner].flatten()).tolist()
                row["baseline_conf"] = c_b[0, 0, inner, inner].flatten().tolist()
        base = psf_model(p)
        for mode in modes:
            cands = [base] if mode == "known" else [replace(base, shape=sh) for sh in SHAPE_GRID]
            stack = tile_nll_stack(y1, y2, camera, cands, nu1, nu2, origins, only=needed)
            q, sq, _ = seeded_fit(stack, Q_GRID, seed, bins)
            row[f"{mode}_q"], row[f"{mode}_sigma"] = q.tolist(), (sq / q).tolist()
        rows.append(row)
    return rows


def score_product(rows: list[dict], fused: str = "product_q") -> dict[str, list[list[float]]]:
    """Per plane, the relative depth errors of the model, the product stage's own fit and its
    fused map (its sigma factors fitted on training scenes: nothing fitted here; ``fused``: the
    row's key of the fused map)."""
    out: dict[str, list[list[float]]] = {"model": [], "seeded": [], "fused": []}
    for r in rows:
        qt = torch.tensor(r["true_q"], dtype=torch.float64)
        for key, name in (("model", "model_q"), ("seeded", "product_fit_q"), ("fused", fused)):
            out[key].append((qt / torch.tensor(r[name], dtype=torch.float64) - 1.0).tolist())
    return out


def score(rows: list[dict], mode: str) -> dict[str, list[list[float]]]:
    """Per plane, the relative depth errors of the model, the seeded fit and the fusion (raw and
    with each sigma's scale fitted on the other half of the planes)."""
    def err(q: torch.Tensor, qt: torch.Tensor) -> list[float]:
        return (qt / q - 1.0).tolist()  # depth / true depth - 1

    t = {k: [torch.tensor(r[k], dtype=torch.float64) for r in rows]
         for k in ("true_q", "model_q", "model_sigma", f"{mode}_q", f"{mode}_sigma")}
    out: dict[str, list[list[float]]] = {"model": [], "seeded": [], "raw": [], "fused": []}
    factors = {}
    for half in (0, 1):
        cal = [j for j, r in enumerate(rows) if r["index"] % 2 != half]
        e_l = torch.cat([t["true_q"][j] / t[f"{mode}_q"][j] - 1 for j in cal])
        e_c = torch.cat([t["true_q"][j] / t["model_q"][j] - 1 for j in cal])
        factors[half] = (sigma_factor(e_l, torch.cat([t[f"{mode}_sigma"][j] for j in cal])),
                         sigma_factor(e_c, torch.cat([t["model_sigma"][j] for j in cal])))
    for j, r in enumerate(rows):
        ql, qc, qt = t[f"{mode}_q"][j], t["model_q"][j], t["true_q"][j]
        sl, sc = t[f"{mode}_sigma"][j] * ql, t["model_sigma"][j] * qc
        fl, fc = factors[r["index"] % 2]
        out["model"].append(err(qc, qt))
        out["seeded"].append(err(ql, qt))
        out["raw"].append(err(fuse(ql, sl, qc, sc)[0], qt))
        out["fused"].append(err(fuse(ql, fl * sl, qc, fc * sc)[0], qt))
    return out


def stage_timing(model: DFDModel, stage: LikelihoodStage, repeats: int = 3) -> list[list[str]]:
    """Median wall time of the model (torch) and of the stage after it on a 256x256 plane and a
    480x640 slanted scene (each pair's own black level), side by side."""
    out = []
    for layout, size in (("plane", (256, 256)), ("slanted", (480, 640))):
        s = textured_scenes(model.camera, model.tile, model.stride, layout, size, BENCH_SEED).batch([0])
        i1, i2 = s["image_f1"].float(), s["image_f2"].float()
        black = black_levels(s["params"])[0]
        with torch.no_grad():
            depth, conf = model.analyse(i1, i2).depth_map
            t_model, _ = median_time(lambda: model.analyse(i1, i2), repeats, warmup=1)
        r = stage(i1, i2, depth, conf, black_level=black)
        t_stage, _ = median_time(lambda: stage(i1, i2, depth, conf, black_level=black), repeats, warmup=0)
        out.append([f"{layout} {size[0]}x{size[1]}", int(r.fitted.sum()), f"{1000 * t_model:.0f} ms",
                    f"{1000 * t_stage:.0f} ms"])
    return out


def confidence_rows(planes: dict[str, list[dict]], structure: dict[str, dict[str, torch.Tensor]],
                    confidence_scale: float, labels: dict[str, str], reps: int = 100) -> list[list[object]]:
    """The model's, the stage's and the baseline fusion's confidence per decile
    (:func:`benchmarks.stage_uncertainty.decile_summary`): on each world's planes (interior
    tiles; the bootstrap draws planes) and on the structure scenes of every layout together, all
    tiles and away from edges (it draws scenes). A set of fewer than two planes or scenes, or of
    fewer than ten tiles, is left out (a short run)."""
    out = []
    for world, rows in planes.items():
        if len(rows) < 2:
            continue
        scene = torch.cat([torch.full((len(r["true_q"]),), r["index"]) for r in rows])
        true = torch.tensor([x for r in rows for x in r["true_q"]], dtype=torch.float64)
        for key, name in (("model", "model"), ("product", "product"), ("baseline", "baseline")):
            if f"{key}_conf" not in rows[0]:
                continue
            q = torch.tensor([x for r in rows for x in r[f"{key}_q"]], dtype=torch.float64)
            conf = torch.tensor([x for r in rows for x in r[f"{key}_conf"]], dtype=torch.float64)
            out.append([f"planes, {world}", labels[name], int(q.numel())]
                       + decile_summary(conf, relative_inverse_depth_error(1.0 / q, 1.0 / true), scene,
                                        confidence_scale, reps))
    if structure:
        cat = {k: torch.cat([t[k] for t in structure.values()]) for k in next(iter(structure.values()))}
        scene = torch.cat([t["scene"] + k * 1_000_000 for k, t in enumerate(structure.values())])
        for label, sel in (("all tiles", torch.ones_like(cat["edge"])), ("away from edges", ~cat["edge"])):
            if int(sel.sum()) < 10 or torch.unique(scene[sel]).numel() < 2:
                continue
            for key, ckey, name in (("model", "model_conf", "model"), ("fused", "fused_conf", "product"),
                                    ("base", "base_conf", "baseline")):
                if key not in cat:
                    continue
                err = relative_inverse_depth_error(cat[key][sel], cat["true"][sel])
                out.append([f"structure scenes, {label}", labels[name], int(sel.sum())]
                           + decile_summary(cat[ckey][sel], err, scene[sel], confidence_scale, reps))
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--samples", type=int, default=256, help="the refinement benchmark's first N samples")
    p.add_argument("--world", default="clean,full", help="comma list of: clean, full")
    p.add_argument("--psf", default="product,shape,known",
                   help="comma list of: product (the tdfd stage, PSF and noise not told), shape, known (oracles)")
    p.add_argument("--model", default=str(ROOT / "models" / "reference"))
    p.add_argument("--scales", default="", help="the product stage's sigma factors (default: MODEL.likelihood.json)")
    p.add_argument("--baseline-scales", default="",
                   help="also fuse the stage's fits with these scales (an A/B of the fusion on the same fits)")
    p.add_argument("--structure", type=int, default=32, help="structure scenes per layout for the tdfd stage (0: none)")
    p.add_argument("--no-write", action="store_true", help="print only; leave docs/ alone")
    p.add_argument("--rows", default="", help="also save every plane's and structure tile's figures (torch.save)")
    args = p.parse_args(argv)
    if args.structure < 0:
        p.error("--structure must be >= 0")
    worlds = comma_choices(p, args.world, ("clean", "full"), "--world")
    modes = comma_choices(p, args.psf, ("product", "shape", "known"), "--psf")
    torch.set_num_threads(2)
    model = DFDModel.load(args.model)
    scales = LikelihoodScales.load(args.scales or f"{args.model}.likelihood.json")
    stage = LikelihoodStage.for_model(model, scales=scales) if "product" in modes else None
    baseline = LikelihoodScales.load(args.baseline_scales) if args.baseline_scales and stage is not None else None
    oracles = tuple(m for m in modes if m != "product")
    med = statistics.median
    pct = lambda x: f"{100 * x:.2f} %"  # noqa: E731
    table, lines = [], []
    labels = {"product": "tdfd stage: PSF profiled over every shape and diffraction, noise not told"
                         + ((", the model's bias removed" + (f" (within {scales.bias_radius} tiles)"
                                                            if scales.bias_radius else " (image-wide)"))
                            if scales.shared_bias else ""),
              "shape": "oracle: PSF shape profiled", "known": "oracle: PSF known",
              "baseline": f"the same fits fused with `{args.baseline_scales}`"
                          + (" (the model's bias removed)" if baseline is not None and baseline.shared_bias
                             else " (the model's map as it is)")}
    t0 = time.perf_counter()
    saved: dict[str, list[dict]] = {}
    for world in worlds:
        rows = run_world(world, args.samples, model, oracles, stage, baseline)
        saved[world] = rows
        for mode in list(modes) + (["baseline"] if baseline is not None else []):
            sc = score_product(rows, f"{mode}_q") if mode in ("product", "baseline") else score(rows, mode)
            tile = {k: med(abs(x) for pl in v for x in pl) for k, v in sc.items()}
            plane = {k: med(abs(med(pl)) for pl in v) for k, v in sc.items()}
            table.append([world, labels[mode], len(rows)] + [f"{pct(tile[k])} / {pct(plane[k])}" if k in tile else "-"
                                                             for k in ("model", "seeded", "raw", "fused")])
            mt, lo, hi = paired_bootstrap(sc["fused"], sc["model"])
            mp, plo, phi = paired_bootstrap([[med(pl)] for pl in sc["fused"]], [[med(pl)] for pl in sc["model"]])
            lines.append(f"- {world}, {labels[mode]}: fused - model per tile {100 * mt:+.2f} points (95 %: "
                         f"{100 * lo:+.2f} .. {100 * hi:+.2f}), per plane {100 * mp:+.2f} ({100 * plo:+.2f} .. "
                         f"{100 * phi:+.2f})")
    srows = structure_rows(model, stage, args.structure, baseline) if stage and args.structure else {}
    structure = structure_table(srows) if srows else []
    calibration = (confidence_rows(saved, srows, model.confidence_scale, {**labels, "model": "the model"})
                   if stage is not None else [])
    if args.rows:
        torch.save({"planes": saved, "structure": srows}, args.rows)
    wall = time.perf_counter() - t0
    timing = stage_timing(model, stage) if stage is not None else []
    factors = (f"{', '.join(f'{x:.2f}' for x in scales.fit)}, model {', '.join(f'{x:.2f}' for x in scales.model)} "
               f"in the bands of the tile's slope split at {', '.join(f'{100 * e:.0f} %' for e in scales.slope_edges)}"
               + (f"; the fused scale mapped through {len(scales.fused_log_b)} knots" if scales.fused_log_b else
                  "; no map of the fused scale"))
    body = "\n".join([
        f"Machine: {machine()}; the refinement benchmark's first {args.samples} samples (seed {BENCH_SEED}, 256 px), "
        f"its planes in 0.3-1.0 m, the 25 interior tiles of each (the ring keeps the model's estimate and is not "
        f"scored); wall time {wall:.0f} s. Each cell: median over tiles / median over planes of the median tile. "
        f"`seeded`: the cross-residual fit within {100 * SEED_WINDOW:.0f} % of the model's estimate; `fused, raw`: "
        f"inverse-variance mean with the curvature's and the confidence's sigmas as they are; `fused`: each sigma's "
        f"scale fitted on the other half of the planes (even / odd sample index) for the oracles, on training "
        f"scenes for the tdfd stage (`{scales.provenance.get('command', 'no provenance')}`: fit {factors}). The "
        f"oracles are told the PSF's diffraction and aberrations "
        f"and the noise; the tdfd stage (`tdfd.dfd.likelihood_stage`) only each frame's black level.",
        "",
        markdown_table(["world", "estimator", "planes", "model", "seeded", "fused, raw", "fused"], table),
        "",
        "Paired bootstrap over planes (1000 resamples, seed 0):",
        "",
        *lines,
        *(["", f"The tdfd stage on the structure benchmark's first {args.structure} scenes per layout (480x640, seed "
               f"{STRUCTURE_SEED}, the whole world, the tiles in the working range; `near an edge`: as in section "
               f"`structure`). Interval: 95 % over 200 bootstrap resamples of the scenes. The last two columns: model "
               f"/ fused.", "",
               *([f"The last four columns: the same fits fused with `{args.baseline_scales}`: its median error, "
                  f"the fused map's minus it (95 % over the scenes), its share at confidence >= 0.5 and its median "
                  f"error there.", ""] if baseline is not None else []),
               markdown_table(["layout", "tiles", "count", "model", "fused", "fitted tiles: fit / model",
                               "fused - model (points)", "confidence >= 0.5", "median error there"]
                              + (["baseline fused", "fused - baseline (points)", "baseline >= 0.5", "there"]
                                 if baseline is not None else []),
                              structure)] if structure else []),
        *(["", "The confidence as an uncertainty (issue 19: observed / predicted median error within 20 % in every "
               "confidence decile; the deciles and the bootstrap of section `uncertainty`, 100 resamples of the "
               "planes or scenes; the stage states its fused sigma on the model's scale, through the scales file's map of "
               "the fused scale where it has one):", "",
           markdown_table(["tiles", "confidence of", "count", "deciles within 20 %", "outside by > 2 s.e.",
                           "ratio range", "worst ratio"], calibration)] if calibration else []),
        *(["", "The tdfd stage's cost (median of 3, torch, 2 threads; the model's torch forward beside it):", "",
           markdown_table(["pair", "tiles fitted", "model", "stage"], timing)] if timing else []),
    ])
    print(body)
    if not args.no_write:
        cmd = (f".venv/bin/python -m benchmarks.bench_likelihood_stage --samples {args.samples} --world {args.world} "
               f"--psf {args.psf} --structure {args.structure}" + (f" --scales {args.scales}" if args.scales else "")
               + (f" --baseline-scales {args.baseline_scales}" if baseline is not None else ""))
        update_section("likelihood_stage", "A likelihood stage after the CNN, fused by inverse variance (issue 19)",
                       body, cmd)
    return 0


if __name__ == "__main__":
    sys.exit(main())
