r"""The lens's whole PSF measured from a focus sweep, and the likelihood stage told it (issue 19).

Run from the repository root::

    .venv/bin/python -m benchmarks.bench_psf_model [--samples 256] [--world full] [--structure 16]
        [--frames-per-power 2] [--sweep-chart dead_leaves] [--scales S.json] [--calibrated-scales S.json]
        [--bias-scales S.json] [--no-write]

Every sample of the benchmarks has its own lens (``data_synth``'s draw: a shape between Gaussian
and disk, diffraction, astigmatism, spherical aberration). Here each is calibrated as a user
calibrates theirs (:func:`training.calibrated_lens.sweep_fit`): a focus sweep of a chart
(``--sweep-chart``, default dead leaves: detail at every scale) at 0.5 m through that lens
(:class:`tdfd.capture.sim.SimulatedRig`: 256x256, 12-bit, shot and read noise), 7 powers over
+-3 px of blur, ``--frames-per-power`` frames at each averaged, fitted by
:func:`tdfd.calibration.psf_model.psf_model_from_frames` on its 2 central 128-px regions. Then four likelihood stages (:mod:`tdfd.dfd.likelihood_stage`) run on the sample's pair
after the shipped model, on the same model map:

- ``profiled``: the stage as shipped, the PSF profiled over every shape, with and without the
  working f-number's diffraction, its scales ``models/reference.likelihood.json``;
- ``calibrated_shipped_scales``: the sweep's PSF as its one hypothesis, with the same scales
  (what ``tdfd depth --psf-model`` did before scales were fitted for it);
- ``calibrated``: the sweep's PSF, with the scales fitted with every training scene's lens
  calibrated the same way (``models/reference.likelihood-calibrated.json``,
  ``training.fit_likelihood_stage --calibrated-psf``: ``tdfd depth --psf-model CAM.json``);
- ``told``: the sample's true PSF as its one hypothesis, with those scales (the oracle a
  calibration aims at);
- ``calibrated_bias`` (with ``--bias-scales``): the ``calibrated`` stage's very fits fused again
  with scales fitted with ``--shared-bias`` (the model's bias, measured against the fit on the
  whole tile grid, removed first; :func:`benchmarks.stage_rows.refused`).

Reports the calibration's error (the kernels at +-1, +-2, +-3 px of blur against the true
lens's without its diffraction, which the sweep cannot see: relative L2; astigmatism and
spherical weight; the profiled stage's chosen PSF beside it) and each stage's median error on the
planes' 25 interior tiles (per tile and per plane, paired bootstrap over planes; against the
Cramér-Rao bound on the same tiles with the PSF shared by the image,
:mod:`benchmarks.bench_bound`'s model: overall as the at-bound score, and per texture family as
the ratio issue 19 caps at 2x) and on the structure benchmark's first scenes (away from occlusion
edges), and writes section ``psf_model`` of docs/BENCHMARKS.md. ``--rows`` also saves every
plane's tiles (each stage's fused and fitted inverse depth, the fit's raw sigma and slope, so that
other scales can fuse the very same fits again) and every scene's.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import sys
import time

import numpy as np
import torch
from tqdm import tqdm

from benchmarks.bench_bound import (MEDIAN_ABS, depth_variances, median_at_bound, plane_fisher, psf_model,
                                    psf_prior_variance)
from benchmarks.bench_likelihood_stage import paired_bootstrap
from benchmarks.bench_plane_oracle import CLEAN_WORLD
from benchmarks.bench_refinement import BENCH_SEED, bench_grids
from benchmarks.bench_structure import STRUCTURE_SEED
from benchmarks.bench_tile_oracle import interior_origins
from benchmarks.psf_stages import BIAS_STAGE, STAGES, SWEEP_SEED, stages_for, structure_rows
from benchmarks.report import ROOT, comma_choices, given_options, machine, markdown_table, repo_path, update_section
from benchmarks.stage_rows import refused
from benchmarks.stage_uncertainty import decile_summary, relative_inverse_depth_error
from data_synth.params import SynthConfig
from tdfd.calibration.psf_model import PsfModelFit
from tdfd.dfd.inverse_variance import LikelihoodScales
from tdfd.dfd.psf_hypotheses import PsfHypothesis
from tdfd.model import DFDModel
from tdfd.optics.aberrated_psf import PSFModel
from training.calibrated_lens import (SWEEP_CHART, SWEEP_CHARTS, SWEEP_DISTANCE_M, SWEEP_HALF_SPAN_PX, SWEEP_POWERS,
                                      SWEEP_REGIONS, SWEEP_SIZE, sweep_fit)
from training.data import STRUCTURE_LAYOUTS
from training.fit_likelihood_stage import black_levels

__all__ = ["kernel_error", "STAGES", "BIAS_STAGE", "stages_of", "main"]

#: the blurs (px) at which the kernels are compared
KERNEL_SIGMAS = (-3.0, -2.0, -1.0, 1.0, 2.0, 3.0)


def stages_of(rows: list[dict]) -> tuple[str, ...]:
    """The stages ``rows`` hold, in the tables' order: those of :data:`STAGES` that were run, then
    :data:`BIAS_STAGE` where it was."""
    return tuple(k for k in (*STAGES, BIAS_STAGE) if rows and f"{k}_conf" in rows[0])


def kernel_error(fitted: PsfHypothesis, lens: PSFModel) -> float:
    """The largest relative L2 distance over :data:`KERNEL_SIGMAS` between ``fitted``'s kernels (its
    blur scale included) and the true ``lens``'s, both without diffraction (a blur common to every frame, which a sweep
    cannot see and the stage's likelihood does not depend on)."""
    sig = torch.tensor(KERNEL_SIGMAS, dtype=torch.float64)
    bare = PsfHypothesis(fitted.shape, 0.0, fitted.astigmatism, fitted.astigmatism_angle, fitted.spherical,
                         fitted.sigma_scale)
    truth = PSFModel(lens.shape, 0.0, lens.astigmatism, lens.astigmatism_angle, lens.spherical)
    size = max(bare.kernel_size(3.0), truth.kernel_size(3.0))
    a, b = bare.kernels(sig, size), truth.kernels(sig, size)
    return float(((a - b).norm(dim=(-1, -2)) / b.norm(dim=(-1, -2))).max())


def plane_rows(model: DFDModel, scales: tuple[LikelihoodScales, LikelihoodScales], samples: int, world: str,
               frames_per_power: int, chart: str = SWEEP_CHART, bias_scales: LikelihoodScales | None = None
               ) -> list[dict]:
    """Per plane (0.3-1.0 m) of the refinement benchmark's first ``samples``: its interior tiles'
    true, model and stages' inverse depths and confidences, and its lens's calibration; with
    ``bias_scales`` also :data:`BIAS_STAGE`'s."""
    over = CLEAN_WORLD if world == "clean" else {}
    grids, ds = bench_grids(model, samples, 256, over, return_sharp=True)
    true, ref, conf = (grids[k] for k in ("true", "refined", "confidence"))
    _, inner = interior_origins(256)
    prior_var = psf_prior_variance(SynthConfig(), model.camera)
    rows = []
    for i in tqdm(range(samples), desc=f"psf model: planes ({world})", mininterval=10.0):
        s = ds[i]
        p = s["params"]
        if p["layout"] != "plane" or not 0.3 <= float(true[i].median()) <= 1.0:
            continue
        lens = psf_model(p)
        t0 = time.perf_counter()
        fit = sweep_fit(model.camera, lens, SWEEP_SEED + i, frames_per_power, chart)
        row = {"index": i, "seconds": time.perf_counter() - t0, "lens": lens, "fit": fit,
               "true_q": (1.0 / true[i][inner, inner].flatten().double()),
               "model_q": (1.0 / ref[i][inner, inner].flatten().double()),
               "model_conf": conf[i][inner, inner].flatten().double(),
               "family": json.loads(p["details"])["textures"][0]["family"]}
        d = float(true[i].median())  # the bound at the plane's depth, the PSF shared by the image (bench_bound)
        var = depth_variances(plane_fisher(model.camera, s["sharp"][0], d, p), prior_var)["tile_shared"]
        row["bound"] = (var.sqrt() * d)[inner, inner].flatten()
        for name, stage in stages_for(model, scales, fit, lens).items():
            r = stage(s["image_f1"][None].float(), s["image_f2"][None].float(), ref[i][None, None],
                      conf[i][None, None], black_level=black_levels([p])[0])
            row[f"{name}_q"] = 1.0 / r.depth[0, 0, inner, inner].flatten().double()
            row[f"{name}_conf"] = r.confidence[0, 0, inner, inner].flatten().double()
            if name == "calibrated" and bias_scales is not None:
                d, c = refused(stage, r, ref[i][None, None], conf[i][None, None], bias_scales)
                row[f"{BIAS_STAGE}_q"] = 1.0 / d[0, 0, inner, inner].flatten().double()
                row[f"{BIAS_STAGE}_conf"] = c[0, 0, inner, inner].flatten().double()
            # the fit alone, for A/Bs of the fusion on the same fits (benchmarks.stage_rows.refused's inputs)
            row[f"{name}_fit_q"] = 1.0 / r.depth_fit[0, 0, inner, inner].flatten().double()
            row[f"{name}_fit_sigma_raw"] = r.sigma_fit_raw[0, 0, inner, inner].flatten()
            row[f"{name}_slope"] = r.slope[0, 0, inner, inner].flatten().double()
            if name == "profiled":
                row["profiled_psf"] = r.hypotheses[0]
        rows.append(row)
    return rows


def _plain(value: object) -> object:
    """A row's value as tensors, numbers and dicts only (a file ``torch.load(weights_only=True)`` reads)."""
    if isinstance(value, PsfModelFit):
        return value.summary()
    if isinstance(value, PsfHypothesis):
        return value.to_dict()
    if isinstance(value, PSFModel):
        return dataclasses.asdict(value)
    return value


def _pct(x: float) -> str:
    return f"{100 * x:.2f} %"


def plane_table(rows: list[dict]) -> tuple[list[list[object]], list[str]]:
    med = statistics.median
    errors = {k: [(r["true_q"] / r[f"{k}_q"] - 1.0).tolist() for r in rows] for k in ("model", *stages_of(rows))}
    table = [[k, _pct(med(abs(x) for pl in v for x in pl)), _pct(med(abs(med(pl)) for pl in v))]
             for k, v in errors.items()]
    lines = []
    pairs = [("calibrated", "profiled"), ("calibrated", "model"), ("calibrated", "calibrated_shipped_scales"),
             ("told", "calibrated")] + ([(BIAS_STAGE, "calibrated")] if BIAS_STAGE in errors else [])
    for a, b in pairs:
        mt, lo, hi = paired_bootstrap(errors[a], errors[b])
        mp, plo, phi = paired_bootstrap([[med(pl)] for pl in errors[a]], [[med(pl)] for pl in errors[b]])
        lines.append(f"- {a} - {b}: per tile {100 * mt:+.2f} points (95 %: {100 * lo:+.2f} .. {100 * hi:+.2f}), "
                     f"per plane {100 * mp:+.2f} ({100 * plo:+.2f} .. {100 * phi:+.2f})")
    return table, lines


def tile_errors(rows: list[dict], estimator: str) -> torch.Tensor:
    """Every row's tiles' absolute relative depth error of ``estimator`` (``model`` or a stage), in one tensor."""
    return torch.cat([(r["true_q"] / r[f"{estimator}_q"] - 1).abs() for r in rows])


def bound_line(rows: list[dict]) -> str:
    """The planes' interior tiles at the Cramér-Rao bound (PSF shared by the image): the median an
    unbiased estimator reaching it on every tile would score (:func:`benchmarks.bench_bound.median_at_bound`),
    and each estimator's per-tile median over it."""
    at_bound = median_at_bound(torch.cat([r["bound"] for r in rows]))
    ratios = ", ".join(f"{k} {float(tile_errors(rows, k).median()) / at_bound:.2f}x"
                       for k in ("model", *stages_of(rows)))
    return (f"At the bound (PSF shared by the image, the same interior tiles, `bench_bound`'s model): "
            f"{_pct(at_bound)} per tile; each estimator's median per tile over it: {ratios}.")


def family_table(rows: list[dict]) -> list[list[object]]:
    """Per texture family (the plane's first texture): planes, the per-tile bound (PSF shared:
    0.674 times its median standard deviation, as ``bench_bound``'s family table) and each
    estimator's median error per tile with its ratio to that bound."""
    table = []
    for name in sorted({r["family"] for r in rows}):
        sel = [r for r in rows if r["family"] == name]
        bound = MEDIAN_ABS * float(torch.cat([r["bound"] for r in sel]).median())
        cells = []
        for k in ("model", *stages_of(rows)):
            e = float(tile_errors(sel, k).median())
            cells.append(f"{_pct(e)} ({e / bound:.1f}x)")
        table.append([name, len(sel), _pct(bound), *cells])
    return table


def calibration_table(rows: list[dict]) -> list[list[object]]:
    """The calibration's and the profiled stage's PSF error, quartiles over the lenses."""
    def q(values: list[float]) -> str:
        a = np.percentile(values, [25, 50, 75])
        return f"{a[1]:.3f} ({a[0]:.3f} .. {a[2]:.3f})"
    cal = [kernel_error(r["fit"].hypothesis, r["lens"]) for r in rows]
    prof = [kernel_error(r["profiled_psf"], r["lens"]) for r in rows]
    ast = [abs(r["fit"].hypothesis.astigmatism - r["lens"].astigmatism) for r in rows]
    sph = [abs(r["fit"].hypothesis.spherical - r["lens"].spherical) for r in rows]
    sec = [r["seconds"] for r in rows]
    return [["sweep's PSF (calibrated)", q(cal), q(ast), q(sph), f"{statistics.median(sec):.1f} s"],
            ["the profiled stage's choice per image", q(prof), "-", "-", "-"]]


def structure_table(rows: list[dict]) -> list[list[object]]:
    """Per layout, the tiles away from occlusion edges: each estimator's median error, its share at
    confidence >= 0.5 and the median error there."""
    table = []
    for layout in STRUCTURE_LAYOUTS:
        sel = [r for r in rows if r["layout"] == layout]
        if not sel:
            continue
        away = [~r["edge"] for r in sel]
        true = torch.cat([r["true"][a] for r, a in zip(sel, away)])
        cells = []
        for k in ("model", *stages_of(rows)):
            est = torch.cat([r[k][a] for r, a in zip(sel, away)])
            conf = torch.cat([r[f"{k}_conf"][a] for r, a in zip(sel, away)])
            e = (est / true - 1).abs()
            c = conf >= 0.5
            cells.append(f"{_pct(float(e.median()))}; {100 * float(c.double().mean()):.0f} % at >= 0.5"
                         + (f", {_pct(float(e[c].median()))} there" if bool(c.any()) else ""))
        table.append([layout, len(sel), int(true.numel()), *cells])
    return table


def confidence_table(rows: list[dict], confidence_scale: float) -> list[list[object]]:
    scene = torch.cat([torch.full((r["true_q"].numel(),), r["index"]) for r in rows])
    true = torch.cat([r["true_q"] for r in rows])
    out = []
    for k in ("model", *stages_of(rows)):
        q, conf = torch.cat([r[f"{k}_q"] for r in rows]), torch.cat([r[f"{k}_conf"] for r in rows])
        out.append([k, int(q.numel())] + decile_summary(conf, relative_inverse_depth_error(1.0 / q, 1.0 / true),
                                                        scene, confidence_scale))
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--samples", type=int, default=256, help="the refinement benchmark's first N samples")
    p.add_argument("--world", default="full", help="clean or full (the benchmark's whole world)")
    p.add_argument("--structure", type=int, default=16, help="structure scenes per layout (0: none)")
    p.add_argument("--frames-per-power", type=int, default=2, help="sweep frames averaged at each power")
    p.add_argument("--sweep-chart", default=SWEEP_CHART, choices=SWEEP_CHARTS,
                   help="the texture family the calibration sweeps see")
    p.add_argument("--model", default=str(ROOT / "models" / "reference"))
    p.add_argument("--scales", default="", help="the profiled stage's sigma factors (default: MODEL.likelihood.json)")
    p.add_argument("--calibrated-scales", default="",
                   help="the sigma factors fitted with each lens calibrated, for the stages told a PSF (default: "
                        "MODEL.likelihood-calibrated.json)")
    p.add_argument("--bias-scales", default="",
                   help="also fuse the calibrated stage's fits with these scales (fitted with --shared-bias): "
                        f"stage {BIAS_STAGE}")
    p.add_argument("--no-write", action="store_true", help="print only; leave docs/ alone")
    p.add_argument("--rows", default="", help="also save every plane's and scene's figures (torch.save)")
    args = p.parse_args(argv)
    if args.samples < 1 or args.structure < 0 or args.frames_per_power < 1:
        p.error("need --samples >= 1, --structure >= 0 and --frames-per-power >= 1")
    world = comma_choices(p, args.world, ("clean", "full"), "--world")
    if len(world) != 1:
        p.error("--world takes one world")
    torch.set_num_threads(2)
    model = DFDModel.load(args.model)
    scales_paths = (args.scales or f"{args.model}.likelihood.json",
                    args.calibrated_scales or f"{args.model}.likelihood-calibrated.json")
    scales = (LikelihoodScales.load(scales_paths[0]), LikelihoodScales.load(scales_paths[1]))
    bias_scales = LikelihoodScales.load(args.bias_scales) if args.bias_scales else None
    if bias_scales is not None and not bias_scales.shared_bias:
        p.error(f"--bias-scales {args.bias_scales} does not remove the model's bias (fitted without --shared-bias)")
    shown = [repo_path(x) for x in scales_paths]
    t0 = time.perf_counter()
    rows = plane_rows(model, scales, args.samples, world[0], args.frames_per_power, args.sweep_chart, bias_scales)
    srows = (structure_rows(model, scales, args.structure, args.frames_per_power, args.sweep_chart, bias_scales)
             if args.structure else [])
    wall = time.perf_counter() - t0
    if args.rows:
        torch.save({"planes": [{k: _plain(v) for k, v in r.items()} for r in rows], "structure": srows}, args.rows)
    planes, lines = plane_table(rows)
    body = "\n".join([
        f"Machine: {machine()}; the refinement benchmark's first {args.samples} samples (seed {BENCH_SEED}, 256 px, "
        f"world `{world[0]}`), {len(rows)} planes in 0.3-1.0 m, their 25 interior tiles; wall time {wall:.0f} s. Each "
        f"lens calibrated from a sweep of {SWEEP_POWERS} powers over +-{SWEEP_HALF_SPAN_PX:.0f} px of blur, "
        f"{args.frames_per_power} frame(s) averaged per power, a `{args.sweep_chart}` chart at {SWEEP_DISTANCE_M} m "
        f"({SWEEP_SIZE[0]}x{SWEEP_SIZE[1]}, 12-bit, noise on; {SWEEP_REGIONS} regions of 128 px). The stages' scales: "
        f"`{shown[0]}` (`profiled`, `calibrated_shipped_scales`: the shipped stage's, fitted with the PSF "
        f"profiled), `{shown[1]}` (`calibrated`, `told`: fitted with each training scene's lens calibrated "
        f"from its own sweep, `training.fit_likelihood_stage --calibrated-psf`)"
        + (f"; `{BIAS_STAGE}`: the `calibrated` stage's very fits fused again with `{repo_path(args.bias_scales)}`, "
           f"the model's bias within {bias_scales.bias_radius} tiles removed first (fitted with `--shared-bias`)"
           if bias_scales is not None else "") + ".",
        "",
        "The PSF's error over the lenses (median, quartiles): the kernels' largest relative L2 distance at "
        f"{', '.join(f'{s:+.0f}' for s in KERNEL_SIGMAS)} px of blur, both without diffraction (which cancels "
        "from the cross residual); the astigmatism's and the spherical weight's absolute error:",
        "",
        markdown_table(["PSF", "kernel error", "astigmatism error", "spherical error", "calibration time"],
                       calibration_table(rows)),
        "",
        "Median error on the planes' interior tiles, per tile / per plane:",
        "",
        markdown_table(["estimator", "per tile", "per plane"], planes),
        "",
        bound_line(rows),
        "",
        "Per texture family (the plane's first texture), median error per tile and its ratio to the family's "
        "per-tile bound (PSF shared by the image; issue 19 asks <= 2x):",
        "",
        markdown_table(["family", "planes", "per tile: bound", "model", *stages_of(rows)], family_table(rows)),
        "",
        "Paired bootstrap over planes (1000 resamples, seed 0):",
        "",
        *lines,
        "",
        "Confidence per decile on the planes (observed / predicted median error within 20 %, section "
        "`uncertainty`'s deciles, 100 resamples of the planes):",
        "",
        markdown_table(["confidence of", "tiles", "deciles within 20 %", "outside by > 2 s.e.", "ratio range",
                        "worst ratio"], confidence_table(rows, model.confidence_scale)),
        *(["", f"The structure benchmark's first {args.structure} scenes per layout (480x640, seed {STRUCTURE_SEED}, "
               "the whole world; tiles in the working range away from occlusion edges), each scene's lens calibrated "
               "as above. Each cell: median error; share at confidence >= 0.5, median error there.", "",
           markdown_table(["layout", "scenes", "tiles", "model", *stages_of(srows)],
                          structure_table(srows))] if srows else []),
    ])
    print(body)
    if not args.no_write:
        cmd = (f".venv/bin/python -m benchmarks.bench_psf_model --samples {args.samples} --world {world[0]} "
               f"--structure {args.structure} --frames-per-power {args.frames_per_power} "
               f"--sweep-chart {args.sweep_chart}"
               + given_options(args, "scales", "calibrated_scales", "bias_scales"))
        update_section("psf_model", "The lens's PSF measured from a focus sweep, the likelihood stage told it "
                                    "(issue 19)", body, cmd)
    return 0


if __name__ == "__main__":
    sys.exit(main())
