"""The training pipeline's last stage: calibrate a trained model's predicted error scale.

A training run does it itself when its config enables it (``[calibration] enabled = true``,
as ``training/configs/reference.toml`` does: :class:`training.config.CalibrationConfig`);
for a model trained without it, run from the repository root (the shipped model's commands
are in ``models/README.md``)::

    .venv/bin/python -m training.calibrate_scale --model models/reference

The CNN's Laplace scale ``b`` of the relative inverse-depth error is trained by the Laplace
NLL, whose optimum is the *mean* absolute error; the errors are heavier-tailed than a
Laplace and the held-out scenes differ from the training mix, so the median error per band
of ``b`` is off by up to half (issue 19). This stage runs the model on scenes that no
training run or benchmark uses, fits a monotone map of ``log b``
(:func:`tdfd.model.scale_calibration.fit_scale_calibration`: in each of ``--bins``
equal-count bands of ``b`` the median ``|e|`` becomes ``b' ln 2``; ``--min-factor 1`` would
only ever widen the CNN's scale) and writes it into the
model's JSON description (the weights are unchanged). The scenes, all tiles in the working
range, the model told the family it is saved with:

- textured fronto-parallel planes, 256x256, the training evaluation's textures, no assist
  light (seed :data:`PLANE_SEED`, ``--planes``);
- the depth-structure layouts (slanted, piecewise-planar with occlusion edges, smooth),
  480x640 (seed :data:`STRUCTURE_SEED`, ``--scenes`` per layout).

A model that already has a calibration is refitted from its uncalibrated scale.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

import torch
from tqdm import tqdm

from data_synth import DefocusPairDataset
from tdfd.model import DFDModel
from tdfd.model.scale_calibration import ScaleCalibration, fit_scale_calibration

from .data import STRUCTURE_LAYOUTS, textured_scenes

__all__ = ["PLANE_SEED", "STRUCTURE_SEED", "collect_scale_errors", "calibrate_model", "main"]

logger = logging.getLogger("training.calibrate_scale")

#: seeds of the calibration scenes (no training run or benchmark uses them)
PLANE_SEED = 91_000_001
STRUCTURE_SEED = 92_000_003


def _scene_sets(model: DFDModel, planes: int, scenes: int, plane_size: int, structure_size: tuple[int, int]
                ) -> list[tuple[str, DefocusPairDataset, int, int]]:
    grid = (model.camera, model.tile, model.stride)
    sets = [("planes", textured_scenes(*grid, "plane", (plane_size, plane_size), PLANE_SEED), planes, 16)]
    for layout in STRUCTURE_LAYOUTS:
        sets.append((layout, textured_scenes(*grid, layout, structure_size, STRUCTURE_SEED), scenes, 4))
    return sets


@torch.no_grad()
def collect_scale_errors(model: DFDModel, planes: int = 2048, scenes: int = 64, plane_size: int = 256,
                         structure_size: tuple[int, int] = (480, 640)) -> dict[str, torch.Tensor]:
    """The model's uncalibrated scale and observed error on the calibration scenes.

    Returns:
        ``scale`` (``b``, the CNN's before any calibration), ``error`` (signed relative
        inverse-depth error) and ``set`` (0 planes, 1.. the structure layouts), ``(N,)``
        float64 each, over the tiles whose true depth is in the working range.
    """
    saved = model.scale_calibration
    model.scale_calibration = ScaleCalibration()  # the CNN's own scale
    model.eval()
    near, far = model.camera.depth_range_m
    out: dict[str, list[torch.Tensor]] = {"scale": [], "error": [], "set": []}
    try:
        for k, (name, ds, count, chunk) in enumerate(_scene_sets(model, planes, scenes, plane_size, structure_size)):
            for start in tqdm(range(0, count, chunk), desc=name, mininterval=10.0):
                batch = ds.batch(list(range(start, min(count, start + chunk))))
                r = model.analyse(batch["image_f1"].float(), batch["image_f2"].float())
                true = batch["tile_depth"].double()
                keep = (true >= near) & (true <= far)
                q, q_true = r.inverse_depth.double()[keep], 1.0 / true[keep]
                out["scale"].append(r.log_scale.double()[keep].exp())
                out["error"].append((q - q_true) / q_true)
                out["set"].append(torch.full((int(keep.sum()),), float(k), dtype=torch.float64))
    finally:
        model.scale_calibration = saved
    return {key: torch.cat(v) for key, v in out.items()}


def calibrate_model(model: DFDModel, planes: int = 2048, scenes: int = 64, bins: int = 40, smooth: int = 3,
                    min_factor: float | None = None) -> dict[str, object]:
    """Fit and set ``model.scale_calibration`` (:func:`collect_scale_errors`, then
    :func:`~tdfd.model.scale_calibration.fit_scale_calibration`).

    Returns:
        What the fit used and found: seeds, counts, knots, and per knot the factor ``b' / b``.
    """
    t0 = time.perf_counter()
    data = collect_scale_errors(model, planes, scenes)
    knots_b, knots_c = fit_scale_calibration(data["scale"], data["error"], bins=bins, smooth=smooth,
                                             min_factor=min_factor)
    model.scale_calibration = ScaleCalibration(knots_b.tolist(), knots_c.tolist())
    factors = (knots_c - knots_b).exp()
    info = {"plane_seed": PLANE_SEED, "structure_seed": STRUCTURE_SEED, "planes": planes, "scenes_per_layout": scenes,
            "layouts": list(STRUCTURE_LAYOUTS), "tiles": int(data["scale"].numel()),
            "plane_tiles": int((data["set"] == 0).sum()), "bins": bins, "smooth": smooth, "min_factor": min_factor,
            "knot_scales": [round(float(v), 6) for v in knots_b.exp()],
            "knot_factors": [round(float(v), 4) for v in factors], "seconds": round(time.perf_counter() - t0, 1)}
    logger.info("scale calibration on %d tiles (%d planes, %d scenes per layout): factor b'/b %.2f .. %.2f at the "
                "knots, %.0f s", info["tiles"], planes, scenes, float(factors.min()), float(factors.max()),
                info["seconds"])
    for b, f in zip(info["knot_scales"], info["knot_factors"]):  # type: ignore[call-overload]
        logger.info("  b %.5f -> x %.3f", b, f)
    return info


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m training.calibrate_scale", description=__doc__.splitlines()[0])
    p.add_argument("--model", required=True, help="model stem written by python -m training (e.g. models/reference)")
    p.add_argument("--out", help="stem to write (default: the model's own files; the weights are copied unchanged)")
    p.add_argument("--planes", type=int, default=2048, help="textured planes (256x256)")
    p.add_argument("--scenes", type=int, default=64, help="scenes per depth-structure layout (480x640)")
    p.add_argument("--bins", type=int, default=40, help="equal-count bands of the predicted scale (knots)")
    p.add_argument("--smooth", type=int, default=3, help="odd moving-average width over the bands' factors")
    p.add_argument("--min-factor", default="none",
                   help="smallest factor b'/b at a knot (1: only widen the CNN's scale); default 'none': no bound")
    p.add_argument("--threads", type=int, default=2, help="torch threads")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s", stream=sys.stdout)
    if args.planes < 1 or args.scenes < 1:
        p.error("--planes and --scenes must be >= 1")
    try:
        min_factor = None if args.min_factor.lower() == "none" else float(args.min_factor)
    except ValueError:
        p.error(f"--min-factor must be a number or 'none', got {args.min_factor!r}")
    torch.set_num_threads(args.threads)
    model = DFDModel.load(args.model)
    meta = DFDModel.read_description(args.model)
    info = calibrate_model(model, args.planes, args.scenes, args.bins, args.smooth, min_factor)
    extra = dict(meta.get("extra") or {})
    extra["scale_calibration_fit"] = info
    out = Path(args.out or args.model)
    weights, desc = model.save(out, extra=extra)
    logger.info("wrote %s and %s", weights, desc)
    return 0


if __name__ == "__main__":
    sys.exit(main())
