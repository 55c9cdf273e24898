"""Fit the likelihood stage's two sigma factors for a trained model, on held-out training scenes.

Run from the repository root (the shipped model's command and log: ``models/README.md``)::

    .venv/bin/python -m training.fit_likelihood_stage --model models/reference [--planes 128] [--scenes 6]
        [--calibrated-psf FRAMES] [--register]

The likelihood stage (:mod:`tdfd.dfd.likelihood_stage`) fuses the model's map with each tile's
cross-residual fit by inverse variance. Both sigmas are off by a factor (the fit's tapered bins
are correlated, the model's confidence is calibrated on its own errors, not on what is left when
another estimator agrees), so each gets the factor that makes the median of ``|e| / sigma``
0.674 (:func:`tdfd.dfd.inverse_variance.sigma_factor`), one per band of the tile's slope in the
model's map (:data:`SLOPE_EDGES`; the fit takes each tile for fronto-parallel), over the fitted tiles whose true depth is
in the working range, on the scale calibration's scenes (:func:`training.calibrate_scale.
calibration_scene_sets`: textured planes 256x256 and the three depth-structure layouts 480x640,
seeds no training run or benchmark uses), every nuisance of the training world on. The stage is
told each frame's black level (a sensor constant) and nothing else: PSF profiled over every
shape (the model's family is unknown), noise not told.

The model's bias, measured against the fit on the fitted tiles within ``--bias-radius`` tiles
(:data:`BIAS_RADIUS`; 0: over the whole image), is removed before the fusion with
``--shared-bias`` (:mod:`tdfd.dfd.shared_bias`; measured on the planes and scenes of
``docs/BENCHMARKS.md``, section ``likelihood_stage``, and not the shipped default): its weights
need the factors, and the model's factor belongs to the map without it, so the model's factor is
refitted on the debiased errors :data:`BIAS_ITERATIONS` times.

Last, the fused Laplace scale the factors give is mapped once more (``log b' = log b + s(log b)``,
:func:`tdfd.model.scale_calibration_fit.fit_scale_calibration` in ``--fused-bins`` equal-count bins
of the same tiles' fused errors, :func:`fused_errors`): the fusion takes the two errors for
independent and the fit's curvature sigma for proportional to its error, and neither holds, so
without the map the stage's confidence overstated its certainty in its most confident deciles
(``docs/BENCHMARKS.md``, section ``likelihood_stage``). The map has a second part in the tile's
slope, ``+ g(log max(slope, 1e-4))`` in ``--fused-slope-bins`` equal-count bands, backfitted with
the first (:func:`tdfd.model.scale_calibration_fit.fit_covariate_calibration`): with the scale
part alone the planes' most confident tiles erred half what it stated and the occlusion layouts'
more (the fit takes each tile for fronto-parallel, and the planes' tiles are flat).

With ``--register`` each scene's stage fits the pair's focus breathing and shift first
(:mod:`tdfd.dfd.pair_registration`): the scales of ``tdfd depth --likelihood-register`` (the file's
``registered`` is then true; the fit's errors, hence its factors, change with it).

With ``--calibrated-psf FRAMES`` each scene's stage is told its own lens's PSF as a focus sweep
measures it (:func:`training.calibrated_lens.sweep_fit`, FRAMES frames per power), not the PSF
profiled: the scales of ``tdfd depth --psf-model`` (the shipped
``models/reference.likelihood-calibrated.json``; the file's ``psf`` is then ``"measured"``).

``--save-errors PATH`` also saves the collected tiles (the run's long part: each scene's stage,
and with ``--calibrated-psf`` its sweep); ``--errors PATH`` fits on them instead of collecting, so
the ``--shared-bias`` variant of a run costs seconds (:func:`save_stage_errors`,
:func:`load_stage_errors`).

Writes ``<model>.likelihood.json`` (:class:`tdfd.dfd.inverse_variance.LikelihoodScales`, with the
command, the scene counts, the tile counts, the medians and the in-sample decile ratios of the
fused scale before and after its map as provenance).
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import sys
import time
from pathlib import Path

import torch
from tqdm import tqdm

from data_synth.psf import sample_psf_model
from tdfd.dfd.inverse_variance import SLOPE_FLOOR, LikelihoodScales, model_sigma, sigma_factor
from tdfd.dfd.likelihood_stage import LikelihoodStage, fuse_with_fit
from tdfd.dfd.shared_bias import bias_map
from tdfd.model import DFDModel
from tdfd.model.scale_calibration_fit import (fit_covariate_calibration, fit_scale_calibration,
                                             laplace_mixture_median)

from .calibrate_scale import PLANE_SEED, STRUCTURE_SEED, calibration_scene_sets
from .calibrated_lens import SWEEP_CHART, SWEEP_CHARTS, sweep_fit

__all__ = ["SLOPE_EDGES", "MIN_BAND_TILES", "BIAS_ITERATIONS", "BIAS_RADIUS", "FUSED_BINS", "FUSED_SLOPE_BINS",
           "FUSED_MIN_TILES_PER_BIN",
           "CALIBRATION_SWEEP_SEED", "black_levels", "collect_stage_errors", "image_biases", "model_error_without_bias",
           "fit_scales", "fused_errors", "fit_fused_scale_map", "decile_ratios", "ERROR_COLUMNS", "save_stage_errors",
           "load_stage_errors", "main"]

#: the inner edges of the slope bands (:func:`tdfd.dfd.inverse_variance.tile_slope`)
SLOPE_EDGES = (0.01, 0.03)
#: the fewest tiles a band's own factors are fitted on
MIN_BAND_TILES = 100
#: how often the model's factor is refitted on the errors left after the model's bias
BIAS_ITERATIONS = 3
#: the model's bias at a tile is measured on the fitted tiles within this many tiles
#: (:func:`tdfd.dfd.shared_bias.bias_map`)
BIAS_RADIUS = 3
#: equal-count bins of the fused scale, one knot of its map each
FUSED_BINS = 40
#: equal-count bands of the tiles' slope, one knot of that map's slope part each
FUSED_SLOPE_BINS = 10
#: the fewest tiles per bin of that map (fewer tiles: fewer bins, and below two bins no map)
FUSED_MIN_TILES_PER_BIN = 25
#: the columns :func:`collect_stage_errors` returns and an errors file must hold
ERROR_COLUMNS = ("fit_error", "fit_sigma", "model_error", "model_sigma", "slope", "set", "image", "row", "col")
#: ``--calibrated-psf``: the focus sweeps' seeds (the benchmark's are ``benchmarks/bench_psf_model.py``'s)
CALIBRATION_SWEEP_SEED = 8_000_000

logger = logging.getLogger("training.fit_likelihood_stage")


def black_levels(params: list[dict]) -> list[float]:
    """Each sample's black level as a fraction of full scale (the frames' units)."""
    return [float(p["black_level_dn"]) / (2.0 ** int(p["bits"]) - 1.0) for p in params]


def _calibrated_stage(model: DFDModel, params: dict, frames_per_power: int, seed: int, chart: str = SWEEP_CHART,
                      register: bool = False) -> LikelihoodStage:
    """The stage told the PSF of a scene's lens (``params``) as a focus sweep of ``chart`` with
    ``frames_per_power`` frames per power measures it (:func:`training.calibrated_lens.sweep_fit`)."""
    fit = sweep_fit(model.camera, sample_psf_model(params), seed, frames_per_power, chart)
    return LikelihoodStage.for_model(model, hypotheses=(fit.hypothesis,), register=register)


@torch.no_grad()
def collect_stage_errors(model: DFDModel, planes: int, scenes: int, calibrated_psf: int = 0,
                         sweep_chart: str = SWEEP_CHART, register: bool = False) -> dict[str, torch.Tensor]:
    """The fit's and the model's relative errors (``q_true / q - 1``, the depth's) and raw
    sigmas on every fitted tile in the working range of the calibration scenes; ``set``: 0
    planes, 1.. the structure layouts; ``image``: the image's running index; ``row``, ``col``:
    the tile's cell on the grid. ``calibrated_psf`` > 0: each scene's stage is told its lens's
    PSF as a focus sweep with that many frames per power measures it (seed
    :data:`CALIBRATION_SWEEP_SEED` + 100000 x set + scene; the chart ``sweep_chart``); 0: the PSF
    profiled, as shipped. ``register``: the stage fits each pair's focus breathing and shift
    first (:mod:`tdfd.dfd.pair_registration`; the scales of ``tdfd depth --likelihood-register``)."""
    model.eval()
    near, far = model.camera.depth_range_m
    out: dict[str, list[torch.Tensor]] = {k: [] for k in ERROR_COLUMNS}
    profiled = LikelihoodStage.for_model(model, register=register)  # raw sigmas: the factors are what this fits
    for k, (name, ds, count, _) in enumerate(calibration_scene_sets(model, planes, scenes)):
        for i in tqdm(range(count), desc=f"likelihood stage: {name}", mininterval=10.0):
            s = ds.batch([i])
            stage = (_calibrated_stage(model, s["params"][0], calibrated_psf,
                                       CALIBRATION_SWEEP_SEED + 100_000 * k + i, sweep_chart, register)
                     if calibrated_psf else profiled)
            i1, i2 = s["image_f1"].float(), s["image_f2"].float()
            depth, conf = model.analyse(i1, i2).depth_map
            r = stage(i1, i2, depth, conf, black_level=black_levels(s["params"])[0])
            true = s["tile_depth"].double()
            keep = r.fitted & (true >= near) & (true <= far) & torch.isfinite(r.sigma_fit_raw)
            out["fit_error"].append(r.depth_fit.double()[keep] / true[keep] - 1.0)
            out["fit_sigma"].append(r.sigma_fit_raw[keep])
            out["model_error"].append(depth.double()[keep] / true[keep] - 1.0)
            out["model_sigma"].append(model_sigma(conf.double(), model.confidence_scale)[keep])
            out["slope"].append(r.slope.double()[keep])
            out["set"].append(torch.full((int(keep.sum()),), float(k), dtype=torch.float64))
            out["image"].append(torch.full((int(keep.sum()),), float(len(out["image"])), dtype=torch.float64))
            rows, cols = torch.meshgrid(torch.arange(keep.shape[-2]), torch.arange(keep.shape[-1]), indexing="ij")
            out["row"].append(rows.expand(keep.shape)[keep].double())
            out["col"].append(cols.expand(keep.shape)[keep].double())
    return {key: torch.cat(v) for key, v in out.items()}


def _band_factors(err: torch.Tensor, sig: torch.Tensor, band: torch.Tensor, bands: int, min_tiles: int,
                  name: str) -> tuple[float, ...]:
    pooled = sigma_factor(err, sig)
    out = []
    for k in range(bands):
        sel = band == k
        if int(sel.sum()) < min_tiles:
            logger.warning("slope band %d has %d tiles (< %d): its %s factor is that of all tiles", k, int(sel.sum()),
                           min_tiles, name)
            out.append(pooled)
            continue
        out.append(sigma_factor(err[sel], sig[sel]))
    return tuple(out)


def image_biases(errors: dict[str, torch.Tensor], fit_factor: torch.Tensor, model_factor: torch.Tensor,
                 radius: int | None = None) -> torch.Tensor:
    """``(N,)`` the model's bias at each tile (:func:`tdfd.dfd.shared_bias.bias_map` of its image's
    scored tiles, ``radius`` as there) with the tiles' factors ``(N,)``, as the stage measures it
    (``q_model / q_fit = d_fit / d_model``)."""
    out = torch.zeros_like(errors["model_error"])
    for img in torch.unique(errors["image"]):
        sel = errors["image"] == img
        q_fit, q_model = 1.0 / (1.0 + errors["fit_error"][sel]), 1.0 / (1.0 + errors["model_error"][sel])
        rows, cols = errors["row"][sel].long(), errors["col"][sel].long()
        grid = (int(rows.max()) + 1, int(cols.max()) + 1)
        out[sel] = bias_map(q_model, errors["model_sigma"][sel] * model_factor[sel], q_fit,
                            errors["fit_sigma"][sel] * fit_factor[sel], rows, cols, grid, radius)[rows, cols]
    return out


def model_error_without_bias(errors: dict[str, torch.Tensor], biases: torch.Tensor) -> torch.Tensor:
    """The model's relative depth errors once its bias in ``log q`` (:func:`image_biases`) is removed."""
    return (1.0 + errors["model_error"]) * torch.exp(biases) - 1.0


def fit_scales(errors: dict[str, torch.Tensor], slope_edges: tuple[float, ...] = SLOPE_EDGES,
               min_tiles: int = MIN_BAND_TILES, remove_bias: bool = False, bias_radius: int | None = BIAS_RADIUS
               ) -> LikelihoodScales:
    """The factors of :func:`collect_stage_errors`'s tiles, one pair per band of the tiles' slope
    (a band with fewer than ``min_tiles`` tiles takes the factors of all tiles); with
    ``remove_bias`` the model's factors are those of its errors after the model's bias, measured
    within ``bias_radius`` tiles (:data:`BIAS_ITERATIONS` refits, the bias's weights from the
    factors before)."""
    bands = len(slope_edges) + 1
    band = LikelihoodScales(slope_edges=slope_edges, fit=(1.0,) * bands, model=(1.0,) * bands).band(errors["slope"])
    fit = _band_factors(errors["fit_error"], errors["fit_sigma"], band, bands, min_tiles, "fit")
    mod = _band_factors(errors["model_error"], errors["model_sigma"], band, bands, min_tiles, "model")
    for _ in range(BIAS_ITERATIONS if remove_bias else 0):
        b = image_biases(errors, torch.tensor(fit, dtype=torch.float64)[band],
                         torch.tensor(mod, dtype=torch.float64)[band], bias_radius)
        mod = _band_factors(model_error_without_bias(errors, b), errors["model_sigma"], band, bands, min_tiles, "model")
    return LikelihoodScales(fit=fit, model=mod, slope_edges=slope_edges, shared_bias=remove_bias,
                            bias_radius=bias_radius if remove_bias else None)


def fused_errors(errors: dict[str, torch.Tensor], scales: LikelihoodScales) -> tuple[torch.Tensor, torch.Tensor]:
    """``(error, scale)`` ``(N,)``: each of :func:`collect_stage_errors`'s tiles fused as the stage
    fuses it with ``scales`` (:func:`tdfd.dfd.likelihood_stage.fuse_with_fit`, per image, the
    model's bias removed where ``scales`` say so): the fused relative inverse-depth error
    ``(q - q_true) / q_true`` and the fused Laplace scale before the map."""
    err, scale = torch.zeros_like(errors["model_error"]), torch.zeros_like(errors["model_error"])
    for img in torch.unique(errors["image"]):
        sel = errors["image"] == img
        q_fit, q_model = 1.0 / (1.0 + errors["fit_error"][sel]), 1.0 / (1.0 + errors["model_error"][sel])  # q_true = 1
        rows, cols = errors["row"][sel].long(), errors["col"][sel].long()
        q, _, _, b = fuse_with_fit(q_model, errors["model_sigma"][sel], q_fit, errors["fit_sigma"][sel] * q_fit,
                                   errors["slope"][sel], scales, 1.0, rows, cols,
                                   (int(rows.max()) + 1, int(cols.max()) + 1))
        err[sel], scale[sel] = q - 1.0, b
    return err, scale


def fit_fused_scale_map(error: torch.Tensor, scale: torch.Tensor, scales: LikelihoodScales, bins: int = FUSED_BINS,
                        slope: torch.Tensor | None = None, slope_bins: int = FUSED_SLOPE_BINS) -> LikelihoodScales:
    """``scales`` with the map of their fused scale (:meth:`LikelihoodScales.fused_scale`) fitted on
    the tiles' fused ``error`` and ``scale`` ``(N,)`` (:func:`fused_errors` with these ``scales``;
    ``bins`` equal-count bins of the scale, their log factors smoothed over 3 bins); with ``slope``
    ``(N,)`` (the tiles' slopes) and ``slope_bins`` >= 2 also its slope part, backfitted with the
    scale part (:func:`tdfd.model.scale_calibration_fit.fit_covariate_calibration` on
    ``log max(slope, SLOPE_FLOOR)``)."""
    if slope is None or slope_bins == 0:
        kx, ky = fit_scale_calibration(scale, error, bins=bins, smooth=3)
        return dataclasses.replace(scales, fused_log_b=tuple(kx.tolist()), fused_log_b_calibrated=tuple(ky.tolist()),
                                   fused_log_slope=None, fused_slope_log_shift=None)
    kx, ky, sx, sy = fit_covariate_calibration(scale, error, slope.double().clamp_min(SLOPE_FLOOR).log(), bins=bins,
                                               smooth=3, covariate_bins=slope_bins)
    return dataclasses.replace(scales, fused_log_b=tuple(kx.tolist()), fused_log_b_calibrated=tuple(ky.tolist()),
                               fused_log_slope=tuple(sx.tolist()), fused_slope_log_shift=tuple(sy.tolist()))


def decile_ratios(error: torch.Tensor, scale: torch.Tensor, bins: int = 10) -> list[float]:
    """Per equal-count bin of ``scale`` (the most confident last): the observed median ``|error|``
    over the Laplace mixture median of the bin's scales (1 where the scale is calibrated); fewer
    tiles than ``bins``: one bin per tile (none without tiles)."""
    order = torch.argsort(scale, descending=True, stable=True)
    return [float(error[part].abs().median()) / laplace_mixture_median(scale[part])
            for part in torch.tensor_split(order, min(bins, order.numel()))] if order.numel() else []


def save_stage_errors(path: str | Path, errors: dict[str, torch.Tensor], settings: dict, wall_s: float = 0.0) -> None:
    """Save :func:`collect_stage_errors`'s columns with the ``settings`` that collected them
    (model, planes, scenes, calibrated_psf, sweep_chart, register) and the collection's ``wall_s``, for
    :func:`load_stage_errors`."""
    torch.save({"settings": dict(settings), "wall_s": float(wall_s),
                "errors": {k: errors[k].contiguous() for k in ERROR_COLUMNS}}, path)


def load_stage_errors(path: str | Path, settings: dict) -> tuple[dict[str, torch.Tensor], float]:
    """The columns :func:`save_stage_errors` wrote (loaded with ``weights_only=True``) and the
    seconds their collection took.

    Raises:
        ValueError: the file lacks a column, its columns differ in length, or a setting in
            ``settings`` differs from the one the file was collected with (named)."""
    data = torch.load(path, weights_only=True)
    if not isinstance(data, dict) or not isinstance(data.get("settings"), dict) or not isinstance(
            data.get("errors"), dict):
        raise ValueError(f"{path}: not an errors file of training.fit_likelihood_stage --save-errors")
    errors, saved = data["errors"], data["settings"]
    missing = [k for k in ERROR_COLUMNS if k not in errors]
    if missing:
        raise ValueError(f"{path}: the errors file lacks the columns {missing}")
    lengths = {errors[k].numel() for k in ERROR_COLUMNS}
    if len(lengths) != 1:
        raise ValueError(f"{path}: the errors file's columns differ in length ({sorted(lengths)})")
    saved = {"register": False, **saved}  # files from before --register were collected without it
    differ = [f"{k}: file {saved.get(k)!r}, asked {v!r}" for k, v in settings.items() if saved.get(k) != v]
    if differ:
        raise ValueError(f"{path} was collected with other settings ({'; '.join(differ)})")
    return {k: errors[k] for k in ERROR_COLUMNS}, float(data.get("wall_s", 0.0))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--model", default="models/reference", help="model path stem (writes STEM.likelihood.json)")
    p.add_argument("--planes", type=int, default=128, help="textured planes, 256x256")
    p.add_argument("--scenes", type=int, default=6, help="scenes per depth-structure layout, 480x640")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--out", default="", help="the scales file to write (default: MODEL.likelihood.json)")
    p.add_argument("--shared-bias", action="store_true", help="remove the model's bias, measured against the fit, "
                                                               "before the fusion (default: the model's map as it is)")
    p.add_argument("--bias-radius", type=int, default=BIAS_RADIUS,
                   help="measure the model's bias on the fitted tiles within this many tiles (0: the whole image)")
    p.add_argument("--fused-bins", type=int, default=FUSED_BINS,
                   help="equal-count bins of the fused scale for its map (0: no map)")
    p.add_argument("--fused-slope-bins", type=int, default=FUSED_SLOPE_BINS,
                   help="equal-count bands of the tiles' slope for the map's slope part (0: none)")
    p.add_argument("--calibrated-psf", type=int, default=0, metavar="FRAMES",
                   help="tell each scene's stage its lens's PSF as a focus sweep with FRAMES frames per power "
                        "measures it (the scales of `tdfd depth --psf-model`; default 0: the PSF profiled)")
    p.add_argument("--sweep-chart", default=SWEEP_CHART, choices=SWEEP_CHARTS,
                   help=f"with --calibrated-psf, the texture family the sweeps see (default {SWEEP_CHART})")
    p.add_argument("--save-errors", default="", metavar="PATH",
                   help="also save the collected tiles' errors and sigmas (torch file), so that other options "
                        "(--shared-bias, --bias-radius, --fused-bins) can be fitted on them with --errors")
    p.add_argument("--errors", default="", metavar="PATH",
                   help="fit on errors a run with --save-errors collected instead of collecting them (the scenes, "
                        "PSF and chart are the file's; --planes, --scenes, --calibrated-psf, --sweep-chart must "
                        "match it)")
    p.add_argument("--register", action="store_true",
                   help="the stage fits each pair's focus breathing and shift first (the scales of "
                        "`tdfd depth --likelihood-register`; default: the pairs taken as registered)")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    if (args.planes < 1 or args.scenes < 0 or args.bias_radius < 0 or args.fused_bins == 1 or args.fused_bins < 0
            or args.calibrated_psf < 0 or args.fused_slope_bins == 1 or args.fused_slope_bins < 0):
        p.error("--planes must be >= 1, --scenes, --bias-radius and --calibrated-psf >= 0, --fused-bins and "
                "--fused-slope-bins 0 or >= 2")
    torch.set_num_threads(args.threads)
    model = DFDModel.load(args.model)
    t0 = time.perf_counter()
    settings = {"model": args.model, "planes": args.planes, "scenes": args.scenes,
                "calibrated_psf": args.calibrated_psf, "sweep_chart": args.sweep_chart, "register": args.register}
    if args.errors:
        errors, collection_wall = load_stage_errors(args.errors, settings)
    else:
        errors = collect_stage_errors(model, args.planes, args.scenes, args.calibrated_psf, args.sweep_chart,
                                      args.register)
        if args.save_errors:
            save_stage_errors(args.save_errors, errors, settings, time.perf_counter() - t0)
    fitted = fit_scales(errors, remove_bias=args.shared_bias, bias_radius=args.bias_radius or None)
    fused_err, fused_b = fused_errors(errors, fitted)
    bins = min(args.fused_bins, fused_err.numel() // FUSED_MIN_TILES_PER_BIN)
    if bins < args.fused_bins:
        logger.warning("%d fitted tiles: the fused scale's map gets %s (asked %d bins, at least %d tiles each)",
                       fused_err.numel(), f"{bins} bins" if bins >= 2 else "no map", args.fused_bins,
                       FUSED_MIN_TILES_PER_BIN)
    if bins >= 2:
        slope_bins = min(args.fused_slope_bins, fused_err.numel() // FUSED_MIN_TILES_PER_BIN)
        fitted = fit_fused_scale_map(fused_err, fused_b, fitted, bins, errors["slope"],
                                     slope_bins if slope_bins >= 2 else 0)
    wall = time.perf_counter() - t0
    sets = [(name, errors["set"] == k) for k, name in enumerate(("planes", "slanted", "layout", "smooth"))]
    counts = {name: int(sel.sum()) for name, sel in sets}
    stated = fitted.fused_scale(fused_b, errors["slope"])
    bands = fitted.band(errors["slope"])
    f_fit, f_model = fitted.factors(errors["slope"])
    biases = (image_biases(errors, f_fit, f_model, fitted.bias_radius) if fitted.shared_bias
              else torch.zeros_like(errors["model_error"]))
    provenance = {
        "command": f".venv/bin/python -m training.fit_likelihood_stage --model {args.model} --planes {args.planes} "
                   f"--scenes {args.scenes}" + (f" --shared-bias --bias-radius {args.bias_radius}" if args.shared_bias
                                                  else "")
                   + (f" --fused-bins {args.fused_bins}" if args.fused_bins != FUSED_BINS else "")
                   + (f" --fused-slope-bins {args.fused_slope_bins}" if args.fused_slope_bins != FUSED_SLOPE_BINS
                      else "")
                   + (f" --calibrated-psf {args.calibrated_psf}" if args.calibrated_psf else "")
                   + (f" --sweep-chart {args.sweep_chart}" if args.calibrated_psf and args.sweep_chart != SWEEP_CHART
                      else "")
                   + (" --register" if args.register else "")
                   + (f" --out {args.out}" if args.out else "")
                   + (f" --errors {args.errors}" if args.errors else ""),
        "planes": args.planes, "scenes_per_layout": args.scenes, "plane_seed": PLANE_SEED,
        "structure_seed": STRUCTURE_SEED,
        "psf": (f"each scene's lens calibrated from a focus sweep of a {args.sweep_chart} chart "
                f"({args.calibrated_psf} frame(s) per power, "
                f"seed {CALIBRATION_SWEEP_SEED} + 100000 x set + scene; training.calibrated_lens)"
                if args.calibrated_psf else "profiled over every shape"),
        "tiles": counts,
        "median_abs_error": {"fit": float(errors["fit_error"].abs().median()),
                             "model": float(errors["model_error"].abs().median()),
                             "model_without_bias": float(model_error_without_bias(errors, biases).abs().median()),
                             "fused": float(fused_err.abs().median())},
        "fused_decile_ratios_most_confident_last": {
            "before_map": [round(r, 3) for r in decile_ratios(fused_err, fused_b)],
            "after_map": [round(r, 3) for r in decile_ratios(fused_err, stated)],
            "after_map_per_set": {name: [round(r, 3) for r in decile_ratios(fused_err[sel], stated[sel])]
                                  for name, sel in sets if int(sel.sum()) >= 20},
            "note": "in sample: the map's own tiles; observed median |e| over the Laplace mixture median"},
        "tiles_per_slope_band": [int((bands == k).sum()) for k in range(len(fitted.fit))],
        "fused_bins": bins if bins >= 2 else 0,
        "wall_s": round(wall, 1),
    }
    if args.errors:
        provenance["errors_collection_wall_s"] = round(collection_wall, 1)
    path = Path(args.out or f"{args.model}.likelihood.json")
    dataclasses.replace(fitted, provenance=provenance, psf="measured" if args.calibrated_psf else "profiled",
                        registered=args.register).save(path)
    logger.info("fit sigma factors %s, model sigma factors %s (slope bands at %s, %s tiles) on %d tiles (%s); fused "
                "scale's decile ratios (most confident last) %s before its map, %s after; %.0f s; wrote %s",
                [round(x, 4) for x in fitted.fit], [round(x, 4) for x in fitted.model], fitted.slope_edges,
                provenance["tiles_per_slope_band"], sum(counts.values()), provenance["tiles"],
                provenance["fused_decile_ratios_most_confident_last"]["before_map"],
                provenance["fused_decile_ratios_most_confident_last"]["after_map"], wall, path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
