"""Fit the likelihood stage's two sigma factors for a trained model, on held-out training scenes.

Run from the repository root (the shipped model's command and log: ``models/README.md``)::

    .venv/bin/python -m training.fit_likelihood_stage --model models/reference [--planes 128] [--scenes 6]

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

Writes ``<model>.likelihood.json`` (:class:`tdfd.dfd.inverse_variance.LikelihoodScales`, with the
command, the scene counts, the tile counts and the medians as provenance).
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

import torch
from tqdm import tqdm

from tdfd.dfd.inverse_variance import LikelihoodScales, model_sigma, sigma_factor
from tdfd.dfd.likelihood_stage import LikelihoodStage
from tdfd.model import DFDModel

from .calibrate_scale import PLANE_SEED, STRUCTURE_SEED, calibration_scene_sets

__all__ = ["SLOPE_EDGES", "MIN_BAND_TILES", "black_levels", "collect_stage_errors", "fit_scales", "main"]

#: the inner edges of the slope bands (:func:`tdfd.dfd.inverse_variance.tile_slope`)
SLOPE_EDGES = (0.01, 0.03)
#: the fewest tiles a band's own factors are fitted on
MIN_BAND_TILES = 100

logger = logging.getLogger("training.fit_likelihood_stage")


def black_levels(params: list[dict]) -> list[float]:
    """Each sample's black level as a fraction of full scale (the frames' units)."""
    return [float(p["black_level_dn"]) / (2.0 ** int(p["bits"]) - 1.0) for p in params]


@torch.no_grad()
def collect_stage_errors(model: DFDModel, planes: int, scenes: int) -> dict[str, torch.Tensor]:
    """The fit's and the model's relative errors (``q_true / q - 1``, the depth's) and raw
    sigmas on every fitted tile in the working range of the calibration scenes; ``set``: 0
    planes, 1.. the structure layouts."""
    model.eval()
    near, far = model.camera.depth_range_m
    out: dict[str, list[torch.Tensor]] = {k: [] for k in ("fit_error", "fit_sigma", "model_error", "model_sigma",
                                                          "slope", "set")}
    stage = LikelihoodStage.for_model(model)  # raw sigmas: the factors are what this fits
    for k, (name, ds, count, _) in enumerate(calibration_scene_sets(model, planes, scenes)):
        for i in tqdm(range(count), desc=f"likelihood stage: {name}", mininterval=10.0):
            s = ds.batch([i])
            i1, i2 = s["image_f1"].float(), s["image_f2"].float()
            depth, conf = model.analyse(i1, i2).depth_map
            r = stage(i1, i2, depth, conf, black_level=black_levels(s["params"])[0])
            true = s["tile_depth"].double()
            keep = r.fitted & (true >= near) & (true <= far) & torch.isfinite(r.sigma_fit)
            out["fit_error"].append(r.depth_fit.double()[keep] / true[keep] - 1.0)
            out["fit_sigma"].append(r.sigma_fit.double()[keep])
            out["model_error"].append(depth.double()[keep] / true[keep] - 1.0)
            out["model_sigma"].append(model_sigma(conf.double(), model.confidence_scale)[keep])
            out["slope"].append(r.slope.double()[keep])
            out["set"].append(torch.full((int(keep.sum()),), float(k), dtype=torch.float64))
    return {key: torch.cat(v) for key, v in out.items()}


def fit_scales(errors: dict[str, torch.Tensor], slope_edges: tuple[float, ...] = SLOPE_EDGES,
               min_tiles: int = MIN_BAND_TILES) -> LikelihoodScales:
    """The factors of :func:`collect_stage_errors`'s tiles, one pair per band of the tiles' slope
    (a band with fewer than ``min_tiles`` tiles takes the factors of all tiles)."""
    pooled = (sigma_factor(errors["fit_error"], errors["fit_sigma"]),
              sigma_factor(errors["model_error"], errors["model_sigma"]))
    band = LikelihoodScales(slope_edges=slope_edges, fit=(1.0,) * (len(slope_edges) + 1),
                            model=(1.0,) * (len(slope_edges) + 1)).band(errors["slope"])
    fit, mod = [], []
    for k in range(len(slope_edges) + 1):
        sel = band == k
        if int(sel.sum()) < min_tiles:
            logger.warning("slope band %d has %d tiles (< %d): it takes the factors of all tiles", k, int(sel.sum()),
                           min_tiles)
            fit.append(pooled[0])
            mod.append(pooled[1])
            continue
        fit.append(sigma_factor(errors["fit_error"][sel], errors["fit_sigma"][sel]))
        mod.append(sigma_factor(errors["model_error"][sel], errors["model_sigma"][sel]))
    return LikelihoodScales(fit=tuple(fit), model=tuple(mod), slope_edges=slope_edges)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--model", default="models/reference", help="model path stem (writes STEM.likelihood.json)")
    p.add_argument("--planes", type=int, default=128, help="textured planes, 256x256")
    p.add_argument("--scenes", type=int, default=6, help="scenes per depth-structure layout, 480x640")
    p.add_argument("--threads", type=int, default=2)
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    if args.planes < 1 or args.scenes < 0:
        p.error("--planes must be >= 1 and --scenes >= 0")
    torch.set_num_threads(args.threads)
    model = DFDModel.load(args.model)
    t0 = time.perf_counter()
    errors = collect_stage_errors(model, args.planes, args.scenes)
    fitted = fit_scales(errors)
    wall = time.perf_counter() - t0
    counts = [int((errors["set"] == k).sum()) for k in range(4)]
    bands = fitted.band(errors["slope"])
    provenance = {
        "command": f".venv/bin/python -m training.fit_likelihood_stage --model {args.model} --planes {args.planes} "
                   f"--scenes {args.scenes}",
        "planes": args.planes, "scenes_per_layout": args.scenes, "plane_seed": PLANE_SEED,
        "structure_seed": STRUCTURE_SEED, "tiles": {"planes": counts[0], "slanted": counts[1], "layout": counts[2],
                                                    "smooth": counts[3]},
        "median_abs_error": {"fit": float(errors["fit_error"].abs().median()),
                             "model": float(errors["model_error"].abs().median())},
        "tiles_per_slope_band": [int((bands == k).sum()) for k in range(len(fitted.fit))],
        "wall_s": round(wall, 1),
    }
    path = Path(f"{args.model}.likelihood.json")
    LikelihoodScales(fit=fitted.fit, model=fitted.model, slope_edges=fitted.slope_edges,
                     provenance=provenance).save(path)
    logger.info("fit sigma factors %s, model sigma factors %s (slope bands at %s, %s tiles) on %d tiles (%s); %.0f s; "
                "wrote %s", [round(x, 4) for x in fitted.fit], [round(x, 4) for x in fitted.model], fitted.slope_edges,
                provenance["tiles_per_slope_band"], sum(counts), provenance["tiles"], wall, path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
