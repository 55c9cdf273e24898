r"""Issue 19's structure targets for the likelihood stage told each lens's PSF from a focus sweep.

Run from the repository root::

    .venv/bin/python -m benchmarks.bench_psf_structure [--scenes 128] [--frames-per-power 2]
        [--sweep-chart dead_leaves] [--scales S.json] [--bias-scales S.json] [--walk N] [--register] [--no-write]
        [--rows R.pt] [--first-scene N] [--from-rows R.pt [R2.pt ...] [--paired-with BASE.pt] [--skip-scenes N]]

The structure benchmark's scenes (section ``structure``: 480x640, seed 53000017, slanted planes,
piecewise-planar layouts with occlusion edges, smooth surfaces; the whole world), each scene's
lens calibrated as a user calibrates theirs (a simulated focus sweep,
:func:`training.calibrated_lens.sweep_fit`, the sweeps of ``benchmarks/bench_psf_model.py``),
and three estimators on the same tiles: the shipped model's pooled map (``model``), the
likelihood stage told the sweep's PSF (``calibrated``: ``tdfd depth --likelihood-stage
models/reference.likelihood-calibrated.json --psf-model CAM.json``) and its very fits fused
again with the model's bias removed first (``calibrated_bias``:
``models/reference.likelihood-calibrated-bias.json``, :func:`benchmarks.stage_rows.refused`).
With ``--register`` the stage fits each pair's focus breathing and shift first
(``tdfd depth --likelihood-register``), and the scales default to those fitted so
(``models/reference.likelihood-calibrated-registered.json`` and ``...-registered-bias.json``,
``training.fit_likelihood_stage --register``); scales fitted the other way are used with a warning.

Reports issue 19's three structure targets per layout and estimator (median error per tile
<= 2 %; >= 50 % of the tiles at confidence >= 0.5 with a median error <= 1 % there), on the
tiles away from occlusion edges and on all tiles, each judged over a bootstrap of the scenes
(:func:`benchmarks.bench_structure.judge_over_scenes`); the paired differences between the
estimators over the scenes; the Cramér-Rao reference of section ``structure`` on the same tiles
(away from edges; the ratio issue 19 reports); the same scored apart on the informative and the
information-poor scenes (:mod:`benchmarks.scene_information`); and each confidence per decile (observed /
predicted median error within 20 %, the deciles of section ``uncertainty``), plotted in
``docs/psf_structure_calibration.png``. Writes section ``psf_structure`` of docs/BENCHMARKS.md.
With ``--paired-with`` it prints instead the paired differences of saved rows against another
run's rows of the same scenes (an A/B of a stage option, e.g. ``--walk``).
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
import time
from collections.abc import Iterator

import torch

from benchmarks.bench_bound import median_at_bound
from benchmarks.bench_structure import (BOOTSTRAP_REPS, CONF, SCENE_ID_STEP, STRUCTURE_SEED, judge_over_scenes,
                                        largest_share, scene_intervals)
from benchmarks.depth_models import predicted_scale
from benchmarks.psf_stages import BIAS_STAGE, POOLED, paired_with, refuse_rows, structure_rows
from benchmarks.report import ROOT, given_options, machine, markdown_table, repo_path, update_section
from benchmarks.scene_information import POOR_SCENE_STD, information_rows, plane_pooled_std
from benchmarks.stage_uncertainty import decile_summary, relative_inverse_depth_error
from benchmarks.uncertainty import decile_table, plot_calibration, resample_scenes
from tdfd.dfd.inverse_variance import LikelihoodScales, confidence_from_sigma
from tdfd.model import DFDModel
from training.calibrated_lens import SWEEP_CHART, SWEEP_CHARTS
from training.data import STRUCTURE_LAYOUTS

__all__ = ["ESTIMATORS", "TARGET_HEADER", "merge_scenes", "refuse_rows", "with_plane_pooled", "target_rows",
           "difference_rows", "bound_rows", "information_table", "confidence_rows", "main"]

log = logging.getLogger("benchmarks.bench_psf_structure")

#: the estimators scored, in the tables' order (``<stage>_pooled``: its fused map pooled along the depth structure,
#: :func:`benchmarks.psf_stages.refuse_rows`)
ESTIMATORS = ("model", "calibrated", BIAS_STAGE, *(f"{k}_pooled" for k in POOLED))
#: the bias stage's map pooled along the depth structure (the pooled estimator the section's pairs and A/Bs compare)
POOLED_BIAS = f"{BIAS_STAGE}_pooled"
#: issue 19's structure targets: median error per tile, share at confidence >= 0.5, median error there
MEDIAN_LIMIT, SHARE_LIMIT, CONFIDENT_LIMIT = 0.02, 0.5, 0.01
#: the columns of :func:`target_rows`' table
TARGET_HEADER = ["layout", "tiles", "estimator", "count", "median error", "at confidence >= 0.5", "median there",
                 "median <= 2 %", "share >= 50 %", "there <= 1 %"]
#: the calibration plot
FIGURE = ROOT / "docs" / "psf_structure_calibration.png"


def merge_scenes(rows: list[dict], layouts: tuple[str, ...] = STRUCTURE_LAYOUTS) -> dict[str, torch.Tensor]:
    """The rows of :func:`benchmarks.psf_stages.structure_rows` (``layouts``' scenes) as one
    set of flat tensors, with ``scene`` unique across layouts and ``layout`` the layout's index.

    Raises:
        ValueError: no rows, or a row of a layout outside ``layouts``.
    """
    rows = [r for r in rows if r["layout"] in layouts]
    if not rows:
        raise ValueError(f"no structure rows of layouts {layouts}")
    keys = [k for k in rows[0] if isinstance(rows[0][k], torch.Tensor)]
    out = {k: torch.cat([r[k] for r in rows]) for k in keys}
    n = [r["true"].numel() for r in rows]
    lay = [layouts.index(r["layout"]) for r in rows]
    out["layout"] = torch.cat([torch.full((k,), j) for k, j in zip(n, lay)])
    out["scene"] = torch.cat([torch.full((k,), j * SCENE_ID_STEP + r["scene"]) for k, j, r in zip(n, lay, rows)])
    return out


def with_plane_pooled(rows: list[dict], overlap: float) -> list[dict]:
    """``rows`` with ``plane_pooled``: on the slanted scenes each tile's reference for an estimator
    told the scene is one plane (:func:`benchmarks.scene_information.plane_pooled_std` of the tiles'
    ``bound_shared`` at their places in ``grids["keep"]``), ``nan`` on the other layouts.

    Raises:
        ValueError: a row without ``bound_shared`` (a run without the bound).
    """
    out = []
    for r in rows:
        if "bound_shared" not in r:
            raise ValueError(f"row {r.get('layout')} {r.get('scene')} has no Cramér-Rao reference (bound_shared)")
        row = dict(r)
        if r["layout"] == "slanted":
            ii, jj = r["grids"]["keep"].nonzero(as_tuple=True)
            row["plane_pooled"] = plane_pooled_std(r["bound_shared"], 1.0 / r["true"].double(), ii, jj, overlap)
        else:
            row["plane_pooled"] = torch.full_like(r["true"].double(), float("nan"))
        out.append(row)
    return out


def _groups(rows: list[dict]) -> Iterator[tuple[str, dict[str, torch.Tensor]]]:
    """Each layout that ``rows`` hold, then all layouts: its name and its tiles (:func:`merge_scenes`)."""
    groups = [(layout, (layout,)) for layout in STRUCTURE_LAYOUTS] + [("all layouts", STRUCTURE_LAYOUTS)]
    for name, layouts in groups:
        if any(r["layout"] in layouts for r in rows):
            yield name, merge_scenes(rows, layouts)


def _sets(t: dict[str, torch.Tensor]) -> tuple[tuple[str, torch.Tensor], ...]:
    return (("away from edges", ~t["edge"]), ("all tiles", torch.ones_like(t["edge"])))


def _error(t: dict[str, torch.Tensor], estimator: str) -> torch.Tensor:
    return (t[estimator] / t["true"] - 1).abs()


def _pct(x: float) -> str:
    return f"{100 * x:.2f} %"


def target_rows(rows: list[dict], estimators: tuple[str, ...] = ESTIMATORS, reps: int = BOOTSTRAP_REPS
                ) -> list[list[object]]:
    """Per layout (and all layouts), tile set and estimator: the median error per tile with its
    interval over the scenes, the share at confidence >= 0.5 with its interval, the median error
    there, and issue 19's verdict on each (:func:`benchmarks.bench_structure.judge_over_scenes`;
    the share's median judged without an interval, as section ``structure`` does)."""
    out = []
    for name, t in _groups(rows):
        for label, sel in _sets(t):
            for k in estimators:
                e, c = _error(t, k)[sel], t[f"{k}_conf"][sel]
                iv = scene_intervals(e, c, t["scene"][sel], reps)
                med, share = float(e.median()), float((c >= CONF).double().mean())
                there = float(e[c >= CONF].median()) if bool((c >= CONF).any()) else float("nan")
                verdicts = [judge_over_scenes(med, iv["refined_lo"], iv["refined_hi"], MEDIAN_LIMIT, True),
                            judge_over_scenes(share, iv["share_lo"], iv["share_hi"], SHARE_LIMIT, False),
                            ("yes" if there <= CONFIDENT_LIMIT else "**no**") if there == there else "-"]
                out.append([name, label, k, int(sel.sum()), f"{_pct(med)} ({_pct(iv['refined_lo'])} .. "
                            f"{_pct(iv['refined_hi'])})", f"{100 * share:.0f} % ({100 * iv['share_lo']:.0f} .. "
                            f"{100 * iv['share_hi']:.0f} %)", _pct(there) if there == there else "-", *verdicts])
    return out


#: the pairs :func:`difference_rows` scores by default
PAIRS = ((BIAS_STAGE, "calibrated"), ("calibrated", "model"), (BIAS_STAGE, "model"), (POOLED_BIAS, BIAS_STAGE))


def difference_rows(rows: list[dict], pairs: tuple[tuple[str, str], ...] = PAIRS,
                    reps: int = BOOTSTRAP_REPS) -> list[list[object]]:
    """Per layout (and all layouts) and tile set, each pair's difference of median errors (points) with its 95 %
    interval over a bootstrap of the scenes (the same resamples for every pair, seed 0)."""
    out = []
    for layout, t in _groups(rows):
        for label, sel in _sets(t):
            errors = {k: _error(t, k)[sel] for k in {x for p in pairs for x in p}}
            draws = list(resample_scenes(t["scene"][sel], reps, torch.Generator().manual_seed(0)))
            cells = []
            for a, b in pairs:
                d = sorted(float(errors[a][ix].median() - errors[b][ix].median()) for ix in draws)
                cells.append(f"{100 * (float(errors[a].median()) - float(errors[b].median())):+.2f} "
                             f"({100 * d[int(0.025 * reps)]:+.2f} .. {100 * d[int(0.975 * reps) - 1]:+.2f})")
            out.append([layout, label, *cells])
    return out


def bound_rows(rows: list[dict], confidence_scale: float, estimators: tuple[str, ...] = ESTIMATORS
               ) -> list[list[object]]:
    """Per layout (and all), the tiles away from edges: the score at the Cramér-Rao reference
    (PSF shared; :func:`benchmarks.bench_bound.median_at_bound`); the share of the tiles an
    estimator at the bound would state at confidence >= 0.5 if its confidence told its own sigma
    on the model's scale ``confidence_scale`` (:func:`tdfd.dfd.inverse_variance.confidence_from_sigma`:
    what a calibrated confidence can give), with its score there; each estimator's median error
    over the bound, and the largest share of the tiles, the most confident first, whose median
    error is <= 1 % (:func:`benchmarks.bench_structure.largest_share`; at the bound ranked by the bound)."""
    out = []
    for name, t in _groups(rows):
        sel = ~t["edge"] & torch.isfinite(t["bound_shared"])
        if not bool(sel.any()):
            continue
        bound = t["bound_shared"][sel]
        at_bound = median_at_bound(bound)
        by_bound = bound.sort().values
        share_at_bound = largest_share(lambda k: median_at_bound(by_bound[:k]), by_bound.numel(), CONFIDENT_LIMIT)
        sure = confidence_from_sigma(bound, confidence_scale) >= CONF
        sure_cell = (f"{100 * float(sure.double().mean()):.0f} % ({_pct(median_at_bound(bound[sure]))})"
                     if bool(sure.any()) else "0 %")
        cells = [_pct(at_bound), f"{100 * share_at_bound:.0f} %", sure_cell]
        for k in estimators:
            e = _error(t, k)[sel]
            ranked = e[torch.argsort(t[f"{k}_conf"][sel], descending=True, stable=True)]
            share = largest_share(lambda n: float(ranked[:n].median()), ranked.numel(), CONFIDENT_LIMIT)
            cells.append(f"{_pct(float(e.median()))} ({float(e.median()) / at_bound:.2f}x); {100 * share:.0f} %")
        out.append([name, int(sel.sum()), *cells])
    return out


def information_table(rows: list[dict], estimators: tuple[str, ...] = ESTIMATORS) -> list[list[object]]:
    """:func:`benchmarks.scene_information.information_rows` of each layout (and all) of ``rows``."""
    return information_rows(list(_groups(rows)), estimators, CONF)


def confidence_rows(rows: list[dict], confidence_scale: float, estimators: tuple[str, ...] = ESTIMATORS,
                    reps: int = 100) -> tuple[list[list[object]], dict[str, list[dict]]]:
    """Each estimator's confidence per decile on every layout's scenes together, all tiles and away
    from edges (:func:`benchmarks.stage_uncertainty.decile_summary`, the bootstrap drawing scenes),
    and the decile tables of all tiles for the plot."""
    t = merge_scenes(rows)
    out, tables = [], {}
    for label, sel in _sets(t):
        for k in estimators:
            err = relative_inverse_depth_error(t[k][sel], t["true"][sel])
            out.append([label, k, int(sel.sum())] + decile_summary(t[f"{k}_conf"][sel], err, t["scene"][sel],
                                                                  confidence_scale, reps))
            if label == "all tiles":
                conf = t[f"{k}_conf"][sel]
                tables[k] = decile_table(conf, predicted_scale(conf.double(), confidence_scale), err)
    return out, tables


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenes", type=int, default=128, help="structure scenes per layout (1-1000)")
    p.add_argument("--frames-per-power", type=int, default=2, help="sweep frames averaged at each power")
    p.add_argument("--sweep-chart", default=SWEEP_CHART, choices=SWEEP_CHARTS,
                   help="the texture family the calibration sweeps see")
    p.add_argument("--model", default=str(ROOT / "models" / "reference"))
    p.add_argument("--scales", default="", help="the calibrated stage's sigma factors (default: "
                                                "MODEL.likelihood-calibrated.json, with --register "
                                                "MODEL.likelihood-calibrated-registered.json)")
    p.add_argument("--bias-scales", default="", help="the scales that remove the model's bias (default: "
                                                     "MODEL.likelihood-calibrated-bias.json, with --register "
                                                     "MODEL.likelihood-calibrated-registered-bias.json)")
    p.add_argument("--register", action="store_true",
                   help="the stage fits each pair's focus breathing and shift first (tdfd depth --likelihood-register)")
    p.add_argument("--walk", type=int, default=0, metavar="N",
                   help="let the stage move a window whose minimum lies on its edge up to N times (default 0)")
    p.add_argument("--paired-with", default="", metavar="ROWS.pt",
                   help="with --from-rows: print the paired differences against another run's saved rows of the "
                        "same scenes (e.g. without --walk), fused with the same scales; implies --no-write")
    p.add_argument("--skip-scenes", type=int, default=0, metavar="N",
                   help="with --from-rows: score only the scenes from N on (e.g. those an A/B was not designed on)")
    p.add_argument("--no-write", action="store_true", help="print only; leave docs/ alone")
    p.add_argument("--rows", default="", help="also save every scene's tiles and fits (torch.save)")
    p.add_argument("--from-rows", nargs="+", default=[], metavar="PATH",
                   help="score the fits runs saved with --rows (several: a run in parts, --first-scene), fused "
                        "again with --scales and --bias-scales, instead of running the sweeps and the stage (the "
                        "fits do not depend on the scales)")
    p.add_argument("--first-scene", type=int, default=0, metavar="N",
                   help="run only the scenes from N on (a long run in parts: save each part's --rows and score "
                        "them together with --from-rows); implies --no-write")
    args = p.parse_args(argv)
    if not 1 <= args.scenes <= 1000 or args.frames_per_power < 1 or args.walk < 0:
        p.error("need 1 <= --scenes <= 1000, --frames-per-power >= 1 and --walk >= 0")
    if (args.walk or args.register) and args.from_rows:
        p.error("--from-rows fuses saved fits again; --walk and --register need new fits")
    if (args.paired_with or args.skip_scenes) and not args.from_rows:
        p.error("--paired-with and --skip-scenes score saved rows: give --from-rows")
    if not 0 <= args.first_scene < args.scenes or (args.first_scene and args.from_rows):
        p.error("need 0 <= --first-scene < --scenes, and --first-scene only for a run (not with --from-rows)")
    if args.first_scene and not args.rows:
        p.error("--first-scene runs part of the scenes: save them with --rows, to score with the other parts")
    if not 0 <= args.skip_scenes < args.scenes:
        p.error("need 0 <= --skip-scenes < --scenes")
    if args.skip_scenes and not (args.paired_with or args.no_write):
        p.error("--skip-scenes scores part of a run: print it (--no-write or --paired-with), the section keeps "
                "every scene")
    args.no_write = args.no_write or bool(args.first_scene)
    torch.set_num_threads(2)
    model = DFDModel.load(args.model)
    fitted_as = "-registered" if args.register else ""
    paths = (args.scales or f"{args.model}.likelihood-calibrated{fitted_as}.json",
             args.bias_scales or f"{args.model}.likelihood-calibrated{fitted_as}-bias.json")
    scales, bias_scales = LikelihoodScales.load(paths[0]), LikelihoodScales.load(paths[1])
    for path, s in zip(paths, (scales, bias_scales)):
        if s.registered != args.register and not args.from_rows:  # an A/B of the scales may want this
            log.warning("%s was fitted %s each pair's registration, this run's stage %s: its confidences are "
                        "not the ones it states", path, "with" if s.registered else "without",
                        "fits it (--register)" if args.register else "does not")
    if not bias_scales.shared_bias:
        p.error(f"{paths[1]} does not remove the model's bias (fitted without --shared-bias)")
    if model.structure_pooling is None:
        p.error(f"{args.model} has no structure pooling: the pooled stages pool with the model's own")
    t0 = time.perf_counter()
    if args.from_rows:
        kept = range(args.skip_scenes, args.scenes)
        rows = [r for path in args.from_rows for r in torch.load(path, weights_only=True) if r["scene"] in kept]
        have = sorted({(r["layout"], r["scene"]) for r in rows})
        if len(have) != len(rows) or len(have) != len(STRUCTURE_LAYOUTS) * len(kept):
            p.error(f"the rows of {' '.join(args.from_rows)} hold {len(rows)} scene(s), {len(have)} distinct, where "
                    f"scenes {kept.start}-{kept.stop - 1} of {len(STRUCTURE_LAYOUTS)} layouts are "
                    f"{len(STRUCTURE_LAYOUTS) * len(kept)}")
        if args.paired_with:
            base = refuse_rows([r for r in torch.load(args.paired_with, weights_only=True) if r["scene"] in kept],
                               model.confidence_scale, scales, bias_scales, model.structure_pooling)
            paired = paired_with(refuse_rows(rows, model.confidence_scale, scales, bias_scales,
                                             model.structure_pooling), base, ESTIMATORS[1:])
            pairs = (*((k, f"base {k}") for k in ESTIMATORS[1:]), (POOLED_BIAS, f"base {BIAS_STAGE}"))
            print(markdown_table(["layout", "tiles", *(f"{a} - {b.replace('base ', 'baseline ')}" for a, b in pairs)],
                                 difference_rows(paired, pairs)))
            print(markdown_table(TARGET_HEADER, target_rows(paired, tuple(x for k in ESTIMATORS[1:]
                                                                          for x in (f"base {k}", k)))))
            return 0
    else:  # the profiled stage's scales are not used: only the calibrated stage runs
        rows = structure_rows(model, (scales, scales), args.scenes, args.frames_per_power, args.sweep_chart,
                              bias_scales, stages=("calibrated",), bound=True, walk=args.walk,
                              register=args.register, first=args.first_scene)
    # the pooled stages (and, on saved fits, the fusion with these scales)
    rows = refuse_rows(rows, model.confidence_scale, scales, bias_scales, model.structure_pooling)
    wall = time.perf_counter() - t0
    if args.rows:
        torch.save(rows, args.rows)
    rows = with_plane_pooled(rows, (model.tile / model.stride) ** 2)
    calibration, tables = confidence_rows(rows, model.confidence_scale)
    if not args.no_write:
        plot_calibration(tables, FIGURE, f"Structure scenes ({args.scenes} per layout): confidence per decile")
    shown = [repo_path(x) for x in paths]
    body = "\n".join([
        f"Machine: {machine()}; the structure benchmark's "
        + (f"scenes {args.skip_scenes or args.first_scene}-{args.scenes - 1}" if args.skip_scenes or args.first_scene
           else f"first {args.scenes} scenes")
        + f" per layout (480x640, seed "
        f"{STRUCTURE_SEED}, the whole world; the tiles in the working range; *away from edges* as in section "
        f"`structure`); wall time {wall:.0f} s"
        + (" (the fits a full run saved, fused again with these scales: `--from-rows`)" if args.from_rows else "")
        + (f"; the stage's windows walk up to {args.walk} times" if args.walk else "")
        + ("; the stage fits each pair's breathing and shift first" if args.register else "")
        + ". Each scene's lens calibrated from its own simulated sweep "
        f"(`{args.sweep_chart}` chart, {args.frames_per_power} frame(s) per power: section `psf_model`'s sweeps). "
        f"`model`: the shipped model's pooled map; `calibrated`: the likelihood stage told the sweep's PSF, scales "
        f"`{shown[0]}`; `{BIAS_STAGE}`: its very fits fused again with `{shown[1]}` (the model's bias within "
        f"{bias_scales.bias_radius} tiles removed first); `<stage>_pooled`: that stage's map pooled along the depth "
        f"structure by the model's own structure pooling, each tile weighted by its fused confidence, which it keeps "
        f"(`tdfd depth --likelihood-pool`, `tdfd.dfd.stage_pooling`).",
        "",
        "Issue 19's structure targets (median error per tile <= 2 %; >= 50 % of the tiles at confidence >= 0.5, "
        "their median error <= 1 %). Intervals: 2.5-97.5 % over 200 bootstrap resamples of the scenes; *yes* only "
        "when the whole interval meets the target:",
        "",
        markdown_table(TARGET_HEADER, target_rows(rows)),
        "",
        "Paired differences of the median error (points; 95 % over the same 200 resamples of the scenes):",
        "",
        markdown_table(["layout", "tiles", f"{BIAS_STAGE} - calibrated", "calibrated - model",
                        f"{BIAS_STAGE} - model", f"{POOLED_BIAS} - {BIAS_STAGE}"], difference_rows(rows)),
        "",
        "Against the information limit (away from edges; section `structure`'s per-tile Cramér-Rao reference, the "
        "PSF shared by the image): the score of an unbiased estimator at the bound, and each estimator's median "
        "error with its ratio to it; after the semicolon the largest share of the tiles, the most confident first "
        "(at the bound: the best bound first), whose median error is <= 1 %. *At the bound, confident*: the share "
        f"of the tiles at confidence >= {CONF} had that estimator stated its own sigma on the model's scale "
        f"(b0 = {model.confidence_scale:g}: sigma <= {100 * math.sqrt(2.0) * model.confidence_scale:.2f} %), and "
        "its score on them: what a calibrated confidence can reach tile by tile:",
        "",
        markdown_table(["layout", "tiles", "at the bound", "at the bound: share <= 1 %", "at the bound, confident",
                        *ESTIMATORS], bound_rows(rows, model.confidence_scale)),
        "",
        "By the information the scenes hold (away from edges): a scene is *information-poor* when the median of "
        f"its tiles' Cramér-Rao reference exceeds {100 * POOR_SCENE_STD:.2f} % (an unbiased estimator at the bound "
        "would have a median error above 2 % there; `benchmarks/scene_information.py`). Per group the scenes, the "
        "tiles (share of the layout's), the score at the bound and, on the slanted scenes, at the reference for "
        "an estimator told the scene is one plane (the tiles' information pooled under that model, overlapping "
        "tiles counted once: a rough limit); per estimator the median error; the share of the tiles within 2 %; "
        "the share at confidence >= 0.5; the median over the scenes of |the scene's median signed error| (the "
        "part its tiles share):",
        "",
        markdown_table(["layout", "scenes", "count", "tiles (share)", "at the bound", "at the bound, one plane told",
                        *ESTIMATORS], information_table(rows)),
        "",
        "The confidence as an uncertainty (observed / predicted median error within 20 % in every confidence "
        "decile; every layout's scenes together, 100 resamples of the scenes"
        + (f"; plot `{repo_path(FIGURE)}`" if not args.no_write else "") + "):",
        "",
        markdown_table(["tiles", "confidence of", "count", "deciles within 20 %", "outside by > 2 s.e.",
                        "ratio range", "worst ratio"], calibration),
    ])
    print(body)
    if not args.no_write:
        cmd = (f".venv/bin/python -m benchmarks.bench_psf_structure --scenes {args.scenes} "
               f"--frames-per-power {args.frames_per_power} --sweep-chart {args.sweep_chart}"
               + given_options(args, "scales", "bias_scales", "walk") + (" --register" if args.register else ""))
        update_section("psf_structure", "Structure targets with each lens's PSF measured from a focus sweep "
                                        "(issue 19)", body, cmd)
    return 0


if __name__ == "__main__":
    sys.exit(main())
