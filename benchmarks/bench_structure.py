"""Depth accuracy on scenes with depth structure: slanted planes, piecewise-planar layouts with occlusion edges, smooth surfaces.

Run from the repository root::

    .venv/bin/python -m benchmarks.bench_structure [--model models/reference] [--scenes 128] [--jobs 1]

``--model`` is the safetensors stem (torch) or an ``.onnx`` file (ONNX Runtime), see
:mod:`benchmarks.depth_models`. Scenes: ``data_synth``'s ``slanted``, ``layout`` and
``smooth`` depth layouts, one row each, 480x640 px, every textured family, ambient light,
the synthesiser's full realism (sensor noise, random PSF, breathing, misregistration), seed
:data:`STRUCTURE_SEED`, which no training run or other benchmark uses (training 0,
validation 1 000 003, the training report 2 000 003, the refinement and bound benchmarks
31 337 000). Scored on the model's tile grid, over the tiles whose true depth lies in the
camera's working range:

* median absolute relative depth error per tile (refined, and the analytic stage);
* the share of tiles at confidence >= 0.5 and their median error;
* tiles within one tile of an occlusion edge (their 3x3 tile neighbourhood covers a depth
  discontinuity of the true depth map, :func:`benchmarks.depth_edges.edge_tiles`) apart.

Issue 19's targets (median per tile <= 2 %; at least half of the tiles at confidence >= 0.5
with a median error <= 1 % there) are judged on the tiles away from edges, and shown for all
tiles too. With the 64/32 grid it also computes, per tile, the Cramér-Rao reference of
:func:`benchmarks.bench_bound.tile_fisher` (each tile a fronto-parallel plane at its own true
depth, the PSF unknown but shared by the image) on the tiles away from edges, and reports the
ratio of the model's median error to the score of an estimator at that bound. Writes the
``structure`` section of ``docs/BENCHMARKS.md``.

The tiles of one scene share its texture, PSF and sensor, so the scenes are the samples: every
target figure comes with its interval over a bootstrap of the scenes (:func:`scene_intervals`).
On 32 scenes per layout the per-tile medians moved by up to 4 points against 384
(``models/README.md``, "How many structure scenes"); the default is 128. ``--jobs N`` spreads
the scenes over ``N`` worker processes (the same tiles as one process, in the same order).
"""

from __future__ import annotations

import argparse
import json
import math
import multiprocessing
import sys
import time
from typing import Callable

import torch
from tqdm import tqdm

from benchmarks.bench_bound import (MEDIAN_ABS, STRIDE, TILE, depth_variances, median_at_bound, psf_prior_variance,
                                    tile_fisher)
from benchmarks.depth_edges import EDGE_JUMP, EDGE_RATIO, edge_tiles, tile_depth_spread
from benchmarks.depth_models import DepthModel, add_output_argument, load_depth_model
from benchmarks.report import ROOT, markdown_table, update_section, with_model_option
from benchmarks.uncertainty import resample_scenes
from data_synth import DefocusPairDataset
from data_synth.params import SynthConfig
from training.data import STRUCTURE_LAYOUTS, textured_scenes

__all__ = ["STRUCTURE_SEED", "structure_dataset", "collect_structure", "collect_layouts", "merge_layouts",
           "summarise_structure", "scene_intervals", "largest_share", "main", "judge_over_scenes"]

#: seed of the structure scenes (no training run or other benchmark uses it)
STRUCTURE_SEED = 53_000_017
#: the target's confidence threshold
CONF = 0.5


def structure_dataset(model: DepthModel, layout: str, size: tuple[int, int], seed: int = STRUCTURE_SEED,
                      return_sharp: bool = False) -> DefocusPairDataset:
    """The benchmark's scenes of one ``layout`` on the model's camera and tile grid."""
    return textured_scenes(model.camera, model.tile, model.stride, layout, size, seed, return_sharp=return_sharp)


def collect_structure(model: DepthModel, layout: str, scenes: int, size: tuple[int, int], seed: int = STRUCTURE_SEED,
                      bound: bool = False, chunk: int = 4, told: bool = False, first: int = 0) -> dict[str, torch.Tensor]:
    """Run ``model`` on scenes ``first .. first+scenes-1`` of ``layout``; per-tile results, flattened.

    Returns:
        ``true``, ``refined``, ``analytic`` depths (m), ``confidence``, ``edge`` (bool: within
        one tile of an occlusion edge), ``spread`` (the tile's relative inverse-depth range,
        :func:`~benchmarks.depth_edges.tile_depth_spread`), ``scene`` (index), ``psf`` (the scene's PSF family: 0
        Gaussian, 1 pillbox, 2 other); with ``told`` (a model with ``run_told``) also
        ``refined_told`` and ``confidence_told``, every Gaussian or pillbox scene told its
        family; with ``bound``, ``bound_shared`` and
        ``bound_known``: the relative depth standard deviation of the per-tile reference bound
        (PSF shared by the image / known; NaN at edge tiles).
    """
    ds = structure_dataset(model, layout, size, seed, return_sharp=bound)
    prior_var = psf_prior_variance(SynthConfig(), model.camera) if bound else None
    if told and model.run_told is None:
        raise ValueError(f"model {model.name} cannot be told the PSF family (no family input, or an ONNX file)")
    keys = (["true", "refined", "analytic", "confidence", "edge", "spread", "scene", "psf"]
            + (["refined_told", "confidence_told"] if told else []) + (["bound_shared", "bound_known"] if bound else []))
    out: dict[str, list[torch.Tensor]] = {k: [] for k in keys}
    if first < 0 or scenes < 1:
        raise ValueError(f"need first >= 0 and scenes >= 1, got {first}, {scenes}")
    for start in tqdm(range(first, first + scenes, chunk), desc=layout, mininterval=10.0):
        idx = list(range(start, min(first + scenes, start + chunk)))
        batch = ds.batch(idx)
        depth, conf, depth_a = model.run(batch["image_f1"].float(), batch["image_f2"].float())
        params = list(batch["params"])
        if told:
            depth_t, conf_t, _ = model.run_told(batch["image_f1"].float(), batch["image_f2"].float(), params)
        true = batch["tile_depth"].float()
        if true.shape != depth.shape:
            raise ValueError(f"model grid {tuple(depth.shape)} differs from the dataset's {tuple(true.shape)}")
        for k, i in enumerate(idx):
            edge = edge_tiles(batch["depth"][k, 0], model.tile, model.stride)
            out["true"].append(true[k, 0].flatten())
            out["refined"].append(depth[k, 0].flatten())
            out["analytic"].append(depth_a[k, 0].flatten())
            out["confidence"].append(conf[k, 0].flatten())
            out["edge"].append(edge.flatten())
            out["spread"].append(tile_depth_spread(batch["depth"][k, 0], model.tile, model.stride).float().flatten())
            out["scene"].append(torch.full((edge.numel(),), i))
            shape = params[k].get("psf_shape") if isinstance(params[k], dict) else None
            out["psf"].append(torch.full((edge.numel(),), {"gaussian": 0, "pillbox": 1}.get(shape, 2)))
            if told:
                out["refined_told"].append(depth_t[k, 0].flatten())
                out["confidence_told"].append(conf_t[k, 0].flatten())
            if bound:
                fisher = tile_fisher(model.camera, batch["sharp"][k, 0], true[k, 0].double(), batch["params"][k])
                fisher[edge] = 0.0  # no reference at edges; they teach nothing about the shared PSF either
                var = depth_variances(fisher, prior_var)
                for name, key in (("bound_shared", "tile_shared"), ("bound_known", "tile_known")):
                    rel = var[key].sqrt() * true[k, 0].double()  # std of q / q = relative depth std
                    out[name].append(torch.where(edge, torch.full_like(rel, math.nan), rel).flatten())
    return {k: torch.cat(v) for k, v in out.items()}


def _rel(depth: torch.Tensor, true: torch.Tensor) -> torch.Tensor:
    return (depth - true).abs() / true


def _median(x: torch.Tensor) -> float:
    return float(x.median()) if x.numel() else math.nan


#: bootstrap resamples of the scenes behind each interval of the report
BOOTSTRAP_REPS = 200
#: scene numbers of the merged layouts: layout ``n``'s scene ``i`` is ``n * SCENE_ID_STEP + i``
SCENE_ID_STEP = 1_000_000
#: the concentration the report states: the share of a subset's tiles in its this many largest scenes
TOP_SCENES = 4
#: equal-count bins of the tiles' depth variation in the report
SPREAD_BINS = 4
#: bands of a tile's Cramér-Rao relative depth standard deviation (PSF shared) in the report
INFORMATION_BANDS = ((0.0, 0.005), (0.005, 0.01), (0.01, 0.02), (0.02, 0.05), (0.05, math.inf))


def largest_share(score: Callable[[int], float], count: int, limit: float, steps: int = 400) -> float:
    """The largest share ``k / count`` of the tiles, taken in a fixed order (the best first), whose
    median error ``score(k)`` is at most ``limit``; 0 if even the best tile's is above it.

    The shares are scanned on ``steps`` equal steps (and the first tile), from the largest down.

    Example:
        >>> err = torch.tensor([0.001, 0.004, 0.008, 0.02, 0.05])
        >>> largest_share(lambda k: float(err[:k].quantile(0.5)), 5, 0.005)  # 3 tiles: 0.004; 4: 0.006
        0.6
    """
    if count <= 0:
        return 0.0
    ks = sorted({max(1, round(count * i / steps)) for i in range(1, steps + 1)}, reverse=True)
    return next((k / count for k in ks if score(k) <= limit), 0.0)


def scene_intervals(err: torch.Tensor, conf: torch.Tensor, scene: torch.Tensor, reps: int = BOOTSTRAP_REPS,
                    generator: torch.Generator | None = None) -> dict[str, float]:
    """How far a subset's figures can move with its scenes: the tiles of one scene share its
    texture, PSF and sensor, so a few scenes with many tiles can carry a median.

    Args:
        err: ``(N,)`` relative error per tile.
        conf: ``(N,)`` confidence per tile.
        scene: ``(N,)`` integer scene of each tile (unique across layouts).
        reps: bootstrap resamples of the scenes (:func:`benchmarks.uncertainty.resample_scenes`).
        generator: the resampling's random source (default: seeded 0).

    Returns:
        ``refined_lo``, ``refined_hi``: the 2.5 and 97.5 percentiles of the median error over
        the resamples; ``share_lo``, ``share_hi``: the same for the share of tiles at
        confidence >= 0.5; ``scenes``: the number of scenes; ``top_scenes_share``: the share
        of the tiles held by the :data:`TOP_SCENES` scenes with the most tiles.

    Example:
        >>> e = torch.tensor([0.01, 0.01, 0.05, 0.05]); c = torch.tensor([0.9, 0.9, 0.1, 0.1])
        >>> r = scene_intervals(e, c, torch.tensor([0, 0, 1, 1]), reps=50)
        >>> r["refined_lo"], r["refined_hi"], r["scenes"]
        (0.009999999776482582, 0.05000000074505806, 2)
    """
    if not (err.shape == conf.shape == scene.shape) or err.dim() != 1 or err.numel() == 0:
        raise ValueError(f"err, conf and scene must be equal non-empty (N,) tensors, got {tuple(err.shape)}, "
                         f"{tuple(conf.shape)}, {tuple(scene.shape)}")
    gen = generator if generator is not None else torch.Generator().manual_seed(0)
    medians, shares = [], []
    for idx in resample_scenes(scene, reps, gen):
        medians.append(float(err[idx].median()))
        shares.append(float((conf[idx] >= CONF).double().mean()))
    m, s = torch.tensor(medians, dtype=torch.float64), torch.tensor(shares, dtype=torch.float64)
    counts = torch.unique(scene, return_counts=True)[1].sort(descending=True).values
    return {"refined_lo": float(m.quantile(0.025)), "refined_hi": float(m.quantile(0.975)),
            "share_lo": float(s.quantile(0.025)), "share_hi": float(s.quantile(0.975)), "scenes": int(counts.numel()),
            "top_scenes_share": float(counts[:TOP_SCENES].sum()) / err.numel()}


def judge_over_scenes(value: float, lo: float, hi: float, limit: float, at_most: bool) -> str:
    """A target's verdict from its figure and the figure's interval over the scenes
    (:func:`scene_intervals`): ``"yes"`` only when the whole interval meets ``limit``
    (``value <= limit`` for ``at_most``, else ``>=``), ``"**no**"`` when the figure itself misses
    it, and ``"**undecided**"`` when the figure meets it but the interval reaches past it (more
    scenes decide).

    Example:
        >>> judge_over_scenes(0.0198, 0.0156, 0.0256, 0.02, at_most=True)
        '**undecided** (the interval reaches past the target)'
        >>> judge_over_scenes(0.0150, 0.0120, 0.0190, 0.02, at_most=True), judge_over_scenes(0.13, 0.1, 0.16, 0.5, False)
        ('yes', '**no**')
    """
    meets = (lambda x: x <= limit) if at_most else (lambda x: x >= limit)
    if not meets(value):
        return "**no**"
    return "yes" if meets(hi if at_most else lo) else "**undecided** (the interval reaches past the target)"


def _collect_part(job: tuple) -> dict[str, torch.Tensor]:
    """One worker's share (:func:`collect_layouts`): its own model, one thread."""
    path, layout, first, count, size, bound, told, output = job
    torch.set_num_threads(1)
    return collect_structure(load_depth_model(path, threads=1, output=output), layout, count, size, bound=bound,
                             told=told, first=first)


def collect_layouts(model: DepthModel, path: str, scenes: int, size: tuple[int, int], bound: bool, told: bool,
                    jobs: int = 1, output: str = "map") -> dict[str, dict[str, torch.Tensor]]:
    """:func:`collect_structure` for every layout of :data:`training.data.STRUCTURE_LAYOUTS`;
    with ``jobs > 1`` the scenes are split into runs of consecutive scenes over that many
    spawned processes (each loads ``path`` itself, with :func:`~benchmarks.depth_models.load_depth_model`'s
    defaults and ``output``, which should be what ``model`` was loaded with), and the runs are
    joined in scene order."""
    if jobs <= 1:
        return {lay: collect_structure(model, lay, scenes, size, bound=bound, told=told) for lay in STRUCTURE_LAYOUTS}
    per = max(1, math.ceil(scenes * len(STRUCTURE_LAYOUTS) / (2 * jobs)))  # about two runs per worker
    parts = [(path, lay, a, min(per, scenes - a), size, bound, told, output) for lay in STRUCTURE_LAYOUTS
             for a in range(0, scenes, per)]
    with multiprocessing.get_context("spawn").Pool(jobs) as pool:
        results = pool.map(_collect_part, parts, chunksize=1)
        pool.close()  # let the workers exit on their own (the context's terminate would kill them)
        pool.join()
    out: dict[str, dict[str, torch.Tensor]] = {}
    for lay in STRUCTURE_LAYOUTS:
        mine = [r for job, r in zip(parts, results) if job[1] == lay]
        out[lay] = {k: torch.cat([r[k] for r in mine]) for k in mine[0]}
    return out


def merge_layouts(per_layout: dict[str, dict[str, torch.Tensor]]) -> dict[str, torch.Tensor]:
    """The tiles of every layout (:func:`collect_structure`'s dicts) as one set. Each layout
    numbers its scenes from 0; here layout ``n``'s scene ``i`` becomes ``n * SCENE_ID_STEP + i``,
    so that the scene bootstrap of the merged set resamples every scene on its own."""
    if not per_layout:
        raise ValueError("no layouts to merge")
    keys = next(iter(per_layout.values())).keys()
    return {k: torch.cat([v[k] + SCENE_ID_STEP * n if k == "scene" else v[k] for n, v in enumerate(per_layout.values())])
            for k in keys}


def summarise_structure(tiles: dict[str, torch.Tensor], depth_range: tuple[float, float],
                        reps: int = BOOTSTRAP_REPS) -> dict[str, dict]:
    """Figures of one layout (or all): per tile subset (``all``, ``interior`` away from
    edges, ``edge``) the tile count, the refined and analytic median error, the share of
    tiles at confidence >= 0.5 and their median error, and with ``scene`` in ``tiles`` and
    ``reps > 0`` their intervals over the scenes (:func:`scene_intervals`); and the bound
    comparison if present."""
    near, far = depth_range
    t = tiles["true"]
    keep = (t >= near) & (t <= far)
    er, ea = _rel(tiles["refined"], t), _rel(tiles["analytic"], t)
    conf = tiles["confidence"]
    out: dict[str, dict] = {}
    for name, sel in (("all", keep), ("interior", keep & ~tiles["edge"]), ("edge", keep & tiles["edge"])):
        hi = sel & (conf >= CONF)
        out[name] = {"tiles": int(sel.sum()), "refined": _median(er[sel]), "analytic": _median(ea[sel]),
                     "share_confident": float(hi.sum()) / max(1, int(sel.sum())), "confident": _median(er[hi])}
        if "scene" in tiles and reps > 0 and bool(sel.any()):
            out[name].update(scene_intervals(er[sel], conf[sel], tiles["scene"][sel], reps))
    if "bound_shared" in tiles:
        sel = keep & ~tiles["edge"] & torch.isfinite(tiles["bound_shared"])
        if bool(sel.any()):
            shared, known = tiles["bound_shared"][sel], tiles["bound_known"][sel]
            out["bound"] = {"tiles": int(sel.sum()), "shared_median": MEDIAN_ABS * float(shared.median()),
                            "shared_score": median_at_bound(shared), "known_score": median_at_bound(known),
                            "refined": _median(er[sel])}
            out["bound"]["ratio"] = out["bound"]["refined"] / out["bound"]["shared_score"]
            # issue 19's ">= 50 % of the tiles at confidence >= 0.5, median <= 1 % there" without the confidence's
            # scale: the largest share of the tiles, the best first, whose median error is <= 1 %; at the bound
            # (an unbiased estimator at the limit, the tiles ranked by their own bound: a perfect confidence) and
            # for the model (its tiles ranked by its confidence)
            by_bound = shared.sort().values
            by_conf = er[sel][torch.argsort(conf[sel], descending=True, stable=True)]
            out["bound"]["share_at_bound"] = largest_share(lambda k: median_at_bound(by_bound[:k]), by_bound.numel(), 0.01)
            out["bound"]["share_refined"] = largest_share(lambda k: _median(by_conf[:k]), by_conf.numel(), 0.01)
            # where the error above the limit lies: the tiles by their own information
            bands = []
            for lo, hi in INFORMATION_BANDS:
                part = (shared >= lo) & (shared < hi)
                if bool(part.any()):
                    bands.append({"lo": lo, "hi": hi, "share": float(part.double().mean()), "tiles": int(part.sum()),
                                  "refined": _median(er[sel][part]), "analytic": _median(ea[sel][part]),
                                  "at_bound": median_at_bound(shared[part]),
                                  "confidence": _median(conf[sel][part])})
            out["bound"]["by_information"] = bands
    out["edge_share"] = {"value": float((keep & tiles["edge"]).sum()) / max(1, int(keep.sum()))}
    if "spread" in tiles:  # away from edges, by quartile of the tile's depth variation
        sel = keep & ~tiles["edge"]
        if int(sel.sum()) >= SPREAD_BINS:
            sp, e, c = tiles["spread"][sel].double(), er[sel], conf[sel]
            order = torch.argsort(sp, stable=True)
            out["by_spread"] = [{"lo": float(sp[part].min()), "hi": float(sp[part].max()), "tiles": int(part.numel()),
                                 "refined": _median(e[part]), "confidence": _median(c[part])}
                                for part in torch.tensor_split(order, SPREAD_BINS)]
    if "refined_told" in tiles:  # the Gaussian and pillbox scenes' tiles away from edges, untold and told
        sel = keep & ~tiles["edge"] & (tiles["psf"] < 2)
        et, ct = _rel(tiles["refined_told"], t), tiles["confidence_told"]
        out["told"] = {"tiles": int(sel.sum()), "untold": _median(er[sel]), "told": _median(et[sel]),
                       "share_untold": float((sel & (conf >= CONF)).sum()) / max(1, int(sel.sum())),
                       "share_told": float((sel & (ct >= CONF)).sum()) / max(1, int(sel.sum())),
                       "confident_told": _median(et[sel & (ct >= CONF)])}
    return out


def _pct(x: float) -> str:
    return "-" if not math.isfinite(x) else f"{100 * x:.2f} %"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--model", default=str(ROOT / "models" / "reference"),
                   help="model: safetensors stem (torch) or .onnx file (ONNX Runtime)")
    p.add_argument("--scenes", type=int, default=128, help="scenes per layout")
    p.add_argument("--jobs", type=int, default=1, help="worker processes (the same tiles as 1; default 1)")
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--no-bound", action="store_true", help="skip the Cramér-Rao reference")
    p.add_argument("--no-told", action="store_true",
                   help="skip the second run told each Gaussian or pillbox scene's PSF family")
    p.add_argument("--no-write", action="store_true", help="print only; leave docs/ alone")
    add_output_argument(p)
    args = p.parse_args(argv)
    if args.height < 480 or args.width < 640:
        p.error("issue 19 scores frames of at least 480x640")
    if args.scenes < 1 or args.jobs < 1:
        p.error(f"need --scenes >= 1 and --jobs >= 1, got {args.scenes}, {args.jobs}")
    torch.set_num_threads(2)
    model = load_depth_model(args.model, output=args.output)
    bound = not args.no_bound and (model.tile, model.stride) == (TILE, STRIDE)
    rng = model.camera.depth_range_m
    t0 = time.perf_counter()
    told = not args.no_told and model.run_told is not None
    per_layout = collect_layouts(model, args.model, args.scenes, (args.height, args.width), bound, told, args.jobs,
                                 args.output)
    wall = time.perf_counter() - t0
    merged = merge_layouts(per_layout)
    summary = {lay: summarise_structure(v, rng) for lay, v in per_layout.items()}
    summary["all layouts"] = summarise_structure(merged, rng)
    print(json.dumps({"summary": summary, "wall_s": round(wall, 1)}, indent=2))
    if args.no_write:
        return 0

    def met(ok: bool) -> str:
        return "yes" if ok else "**no**"

    rows = []
    for lay, s in summary.items():
        for sub, label in (("interior", "away from edges"), ("edge", "near an edge"), ("all", "all tiles")):
            f = s[sub]
            rows.append([lay, label, f["tiles"], _pct(f["refined"]), _pct(f["analytic"]),
                         f"{100 * f['share_confident']:.0f} %", _pct(f["confident"])])
    targets = []
    for lay, s in summary.items():
        for sub, label in (("interior", "away from edges"), ("all", "all tiles")):
            f = s[sub]
            targets += [
                [f"{lay}, {label}: median error per tile", "<= 2 %", _pct(f["refined"]),
                 f"{_pct(f['refined_lo'])} .. {_pct(f['refined_hi'])}",
                 judge_over_scenes(f["refined"], f["refined_lo"], f["refined_hi"], 0.02, at_most=True)],
                [f"{lay}, {label}: tiles at confidence >= 0.5", ">= 50 %", f"{100 * f['share_confident']:.0f} %",
                 f"{100 * f['share_lo']:.0f} .. {100 * f['share_hi']:.0f} %",
                 judge_over_scenes(f["share_confident"], f["share_lo"], f["share_hi"], 0.5, at_most=False)],
                [f"{lay}, {label}: median error at confidence >= 0.5", "<= 1 %", _pct(f["confident"]), "",
                 met(f["confident"] <= 0.01)],
            ]
    body = (
        f"Model `{model.name}` on {args.scenes} held-out `data_synth` scenes per layout, {args.height}x{args.width} px "
        f"(seed {STRUCTURE_SEED}, which no training run or other benchmark uses), every textured family, ambient light, "
        "the synthesiser's full realism (sensor noise, a random PSF per scene, breathing, misregistration, frame gain "
        "jitter). Layouts: `slanted` (a tilted plane), `layout` (piecewise-planar: a background and 1-4 objects, "
        "fronto-parallel or slanted, whose outlines are occlusion edges), `smooth` (a tilted plane plus a smooth relief). "
        f"Errors: median of |d - d_true| / d_true over the {model.tile}-px tiles (stride {model.stride}) whose true "
        f"depth lies in {rng[0]:g}-{rng[1]:g} m. *Near an edge*: the tile's 3x3 tile neighbourhood covers a depth "
        "discontinuity of the true depth map (a step between neighbouring pixels of more than "
        f"{100 * EDGE_JUMP:g} % in inverse depth and {EDGE_RATIO:g}x the steps two pixels before and after it, "
        "`benchmarks/depth_edges.py`); such a tile mixes two surfaces and has no single true depth. "
        f"Near an edge: {100 * summary['layout']['edge_share']['value']:.0f} % of the `layout` scenes' tiles "
        f"({100 * summary['slanted']['edge_share']['value']:.0f} % of `slanted`, "
        f"{100 * summary['smooth']['edge_share']['value']:.0f} % of `smooth`).\n\n"
        + markdown_table(["layout", "tiles", "count", "refined median", "analytic median", "confidence >= 0.5",
                          "refined median there"], rows)
        + "\n\nIssue 19's targets, judged on the tiles away from edges (and shown for all tiles); met only when the "
        "figure's interval over the scenes meets the target (`judge_over_scenes`). *Over the scenes*: "
        f"the 2.5-97.5 percentiles of the figure over {BOOTSTRAP_REPS} bootstrap resamples of the scenes "
        "(`scene_intervals`): the tiles of one scene share its texture, PSF and sensor, so the scenes, not the tiles, "
        f"are the samples. Away from edges, the {TOP_SCENES} scenes with the most such tiles hold "
        + ", ".join(f"{100 * s['interior']['top_scenes_share']:.0f} % of `{lay}`'s" for lay, s in summary.items()
                    if lay in per_layout)
        + " tiles.\n\n"
        + markdown_table(["requirement", "target", "measured", "over the scenes", "met"], targets) + "\n")
    srows = [[lay] + [f"{100 * b['lo']:.1f}-{100 * b['hi']:.1f} %: {_pct(b['refined'])} (conf {b['confidence']:.3f})"
                      for b in s["by_spread"]]
             for lay, s in summary.items() if "by_spread" in s]
    if srows:
        body += (
            "\nWhere the error lies away from edges: the tiles by quartile of their depth variation (the relative range "
            "of inverse depth over the tile, `tile_depth_spread`: 0 for a fronto-parallel face; a slanted tile's blur "
            "changes across it by that fraction), each cell the quartile's spread, its refined median error and its median confidence. On a "
            "slanted or curved surface the error grows with the variation (one Fourier-ratio fit per tile mixes the "
            "blurs a steep tile shows); a `layout` quartile at 0 % holds its fronto-parallel faces.\n\n"
            + markdown_table(["layout"] + [f"quartile {k + 1}" for k in range(SPREAD_BINS)], srows) + "\n")
    if told:
        trows = [[lay, s["told"]["tiles"], _pct(s["told"]["untold"]), _pct(s["told"]["told"]),
                  f"{100 * s['told']['share_untold']:.0f} % / {100 * s['told']['share_told']:.0f} %",
                  _pct(s["told"]["confident_told"])] for lay, s in summary.items() if "told" in s]
        body += (
            "\n### Told the lens's PSF family\n\n"
            "The same scenes run again with each Gaussian or pillbox scene's family told to the CNN (as a calibrated "
            "lens's is, `tdfd calibrate`; the other scenes' power-exponential PSFs stay unknown): the tiles away from "
            "edges of the Gaussian and pillbox scenes, untold and told.\n\n"
            + markdown_table(["layout", "tiles", "refined median, untold", "refined median, told",
                              "confidence >= 0.5, untold / told", "refined median there, told"], trows) + "\n")
    if bound:
        brows = [[lay, s["bound"]["tiles"], _pct(s["bound"]["shared_median"]), _pct(s["bound"]["shared_score"]),
                  _pct(s["bound"]["known_score"]), _pct(s["bound"]["refined"]), f"{s['bound']['ratio']:.2f}x",
                  f"{100 * s['bound']['share_at_bound']:.0f} %", f"{100 * s['bound']['share_refined']:.0f} %"]
                 for lay, s in summary.items() if "bound" in s]
        body += (
            "\n### Against the information limit\n\n"
            "Cramér-Rao reference per tile (`benchmarks/bench_bound.py`, `tile_fisher`): each tile away from edges as a "
            "fronto-parallel plane at its own true depth, with the scene's own texture, PSF and sensor noise, the "
            "texture unknown, the PSF unknown but shared by the image (learnt from its tiles away from edges) or known. "
            "It leaves out the blur's variation across a slanted tile (to first order the slant, odd about the tile "
            "centre, decouples from the depth, even) and a curved surface's relief inside the tile, so it is a "
            "reference rather than a strict bound; it is exact for fronto-parallel faces. *At the bound*: the median "
            "error of an unbiased estimator reaching it on every tile (`median_at_bound`); the ratio is the refined "
            "model's median error on the same tiles over that score (issue 19's target on planes: <= 1.3x). *Share "
            "with median <= 1 %*: issue 19's confident-tile target without the confidence's scale, the largest "
            "share of the tiles, the best first, whose median error is at most 1 % (`largest_share`); at the bound "
            "the tiles ranked by their own bound (an unbiased estimator at the limit with a perfect confidence), "
            "refined the model's tiles ranked by its confidence. The target asks for 50 %.\n\n"
            + markdown_table(["layout", "tiles", "bound median (PSF shared)", "at the bound (PSF shared)",
                              "at the bound (PSF known)", "refined, measured", "ratio refined / at-bound",
                              "share with median <= 1 %: at the bound", "refined, by confidence"], brows)
            + "\n\nNot computed: tiles near an occlusion edge (two surfaces, a mixed blur: no tile-local model of "
            "the kind above holds there).\n")
        def band_cell(bands: list[dict], lo: float) -> str:
            b = next((x for x in bands if x["lo"] == lo), None)
            if b is None:
                return "-"
            return (f"{100 * b['share']:.0f} %: {_pct(b['refined'])} / {_pct(b['analytic'])} / {_pct(b['at_bound'])} "
                    f"(conf {b['confidence']:.2f})")

        irows = [[lay] + [band_cell(s["bound"]["by_information"], lo) for lo, _ in INFORMATION_BANDS]
                 for lay, s in summary.items() if "bound" in s]
        body += (
            "\nWhere the error above the limit lies: the same tiles by their own information, the band of their "
            "bound's relative standard deviation (PSF shared); each cell the band's share of the tiles, then refined "
            "/ analytic median error / the score at the bound on the band, and the band's median confidence. A "
            "model at the limit would follow the last figure in every band; the tiles with the most information "
            "show how far the model is from it where it matters most, the tiles with the least what it does where "
            "no estimator can measure (a texture outside the estimator's band of frequencies, too little "
            "contrast, a frame far out of focus).\n\n"
            + markdown_table(["layout"] + [f"{100 * lo:g}-{100 * hi:g} %" if math.isfinite(hi) else f">= {100 * lo:g} %"
                                           for lo, hi in INFORMATION_BANDS], irows) + "\n")
    body += (f"\nWall time: {wall:.0f} s ({len(STRUCTURE_LAYOUTS) * args.scenes} scenes, "
             f"{args.jobs} process{'es' if args.jobs > 1 else ''}). Scored: "
             + ("the depth map pooled along the depth structure (`depth_pooled`, `confidence_pooled`; `--output tiles`"
                " scores each tile's own estimate)" if model.pooled else "each tile's own estimate (`depth`, `confidence`)")
             + ".\n")
    cmd = f".venv/bin/python -m benchmarks.bench_structure --scenes {args.scenes}" + (f" --jobs {args.jobs}" if args.jobs > 1 else "")
    cmd += "" if args.output == "map" else f" --output {args.output}"
    cmd = with_model_option(cmd, args.model)
    update_section("structure", "Depth structure: slanted planes, occlusion layouts, smooth surfaces", body, cmd)
    return 0


if __name__ == "__main__":
    sys.exit(main())
