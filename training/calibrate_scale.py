"""The training pipeline's last stage: calibrate a trained model's predicted error scale.

A training run does it itself when its config enables it (``[calibration] enabled = true``,
as ``training/configs/reference.toml`` does: :class:`training.config.CalibrationConfig`);
for a model trained without it, run from the repository root (the shipped model's commands
are in ``models/README.md``)::

    .venv/bin/python -m training.calibrate_scale --model models/reference

The CNN's Laplace scale ``b`` of the relative inverse-depth error is trained by the Laplace
NLL, whose optimum is the *mean* absolute error; the errors are heavier-tailed than a
Laplace and the held-out scenes differ from the training mix, so the median error per band
of ``b`` is off by up to half, and at the same ``b`` the error depends on the tile's depth
and on its distance to the frame's edge by up to 1.4x (issue 19). This stage runs the model
on scenes that no training run or benchmark uses, fits the map
``log b' = log b + s(log b) + g(q) + h(n)`` (:mod:`tdfd.model.scale_calibration`;
:func:`tdfd.model.scale_calibration_fit.fit_tile_calibration`: in each of ``--bins``
equal-count bands of ``b``, ``--depth-bins`` bands of the refined inverse depth ``q`` and
``--border-levels`` distances ``n`` to the grid's edge the median ``|e|`` becomes
``b' ln 2``; ``--depth-bins 0 --border-levels 0`` fits ``s`` alone; ``--min-factor 1``
would only ever widen the CNN's scale in ``s``) and writes it into the model's JSON
description (the weights are unchanged). The scenes, all tiles in the working range, the
model told the family it is saved with:

- textured fronto-parallel planes, 256x256, the training evaluation's textures, no assist
  light (seed :data:`PLANE_SEED`, ``--planes``);
- the depth-structure layouts (slanted, piecewise-planar with occlusion edges, smooth),
  480x640 (seed :data:`STRUCTURE_SEED`, ``--scenes`` per layout).

A model that already has a calibration is refitted from its uncalibrated scale.

A model with the structure pooling (:mod:`tdfd.model.structure_pooling`, ``--structure-pooling``)
gets a second map of the same form, fitted the same way on the same scenes: from the calibrated
scale of the CNN's depth (the pooling's weights) to the pooled depth's errors
(``pooled_scale_calibration``). ``--pooled-only`` keeps the tiles' map and fits only that one.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
import time
from pathlib import Path

import torch
from tqdm import tqdm

from data_synth import DefocusPairDataset
from tdfd.model import DFDModel
from tdfd.errors import InputError
from tdfd.model.scale_calibration import ScaleCalibration, calibrate_log_scale, tile_border_distance
from tdfd.model.scale_calibration_fit import fit_tile_calibration

from .data import STRUCTURE_LAYOUTS, textured_scenes

__all__ = ["PLANE_SEED", "STRUCTURE_SEED", "calibration_scene_sets", "collect_scale_errors", "calibrate_model",
           "plot_scale_calibration", "main"]

logger = logging.getLogger("training.calibrate_scale")

#: seeds of the calibration scenes (no training run or benchmark uses them)
PLANE_SEED = 91_000_001
STRUCTURE_SEED = 92_000_003


def calibration_scene_sets(model: DFDModel, planes: int, scenes: int, plane_size: int = 256,
                           structure_size: tuple[int, int] = (480, 640)
                           ) -> list[tuple[str, DefocusPairDataset, int, int]]:
    """The calibration's scene sets: ``(name, dataset, count, batch)`` for the planes (seed
    :data:`PLANE_SEED`) and each depth-structure layout (seed :data:`STRUCTURE_SEED`)."""
    grid = (model.camera, model.tile, model.stride)
    sets = [("planes", textured_scenes(*grid, "plane", (plane_size, plane_size), PLANE_SEED), planes, 16)]
    for layout in STRUCTURE_LAYOUTS:
        sets.append((layout, textured_scenes(*grid, layout, structure_size, STRUCTURE_SEED), scenes, 4))
    return sets


@torch.no_grad()
def collect_scale_errors(model: DFDModel, planes: int = 2048, scenes: int = 64, plane_size: int = 256,
                         structure_size: tuple[int, int] = (480, 640), pooled: bool = False) -> dict[str, torch.Tensor]:
    """The model's uncalibrated scale and observed error on the calibration scenes.

    Args:
        pooled: ``False``: the CNN's depth and its own scale (no pooling, no calibration);
            ``True``: the structure-pooled depth and the CNN's *calibrated* scale (the model's
            ``scale_calibration`` applied, its ``pooled_scale_calibration`` not).

    Returns:
        ``scale`` (``b``, as ``pooled`` says), ``error`` (signed relative inverse-depth error),
        ``inverse_depth`` (the refined ``q``, 1/m), ``border`` (tiles to the grid's edge) and
        ``set`` (0 planes, 1.. the structure layouts), ``(N,)`` float64 each, over the tiles
        whose true depth is in the working range.

    Raises:
        InputError: ``pooled`` for a model without the structure pooling.
    """
    if pooled and model.structure_pooling is None:
        raise InputError("the model has no structure pooling whose errors could be collected")
    saved = model.scale_calibration, model.structure_pooling, model.pooled_scale_calibration
    if pooled:
        model.pooled_scale_calibration = ScaleCalibration()
    else:
        model.scale_calibration, model.structure_pooling = ScaleCalibration(), None  # the CNN's own scale
    model.eval()
    near, far = model.camera.depth_range_m
    out: dict[str, list[torch.Tensor]] = {"scale": [], "error": [], "inverse_depth": [], "border": [], "set": []}
    try:
        sets = calibration_scene_sets(model, planes, scenes, plane_size, structure_size)
        for k, (name, ds, count, chunk) in enumerate(sets):
            for start in tqdm(range(0, count, chunk), desc=name, mininterval=10.0):
                batch = ds.batch(list(range(start, min(count, start + chunk))))
                r = model.analyse(batch["image_f1"].float(), batch["image_f2"].float())
                true = batch["tile_depth"].double()
                keep = (true >= near) & (true <= far)
                q_r, log_r = (r.inverse_depth_pooled, r.log_scale_pooled) if pooled else (r.inverse_depth, r.log_scale)
                q, q_true = q_r.double()[keep], 1.0 / true[keep]
                out["scale"].append(log_r.double()[keep].exp())
                out["error"].append((q - q_true) / q_true)
                out["inverse_depth"].append(q)
                out["border"].append(tile_border_distance(true).expand_as(true)[keep])
                out["set"].append(torch.full((int(keep.sum()),), float(k), dtype=torch.float64))
    finally:
        model.scale_calibration, model.structure_pooling, model.pooled_scale_calibration = saved
    return {key: torch.cat(v) for key, v in out.items()}


def calibrate_model(model: DFDModel, planes: int = 2048, scenes: int = 64, bins: int = 40, smooth: int = 3,
                    min_factor: float | None = None, depth_bins: int = 20, border_levels: int = 5,
                    pooled_only: bool = False, pooled_planes: int | None = None,
                    pooled_scenes: int | None = None) -> dict[str, object]:
    """Fit and set ``model.scale_calibration`` (:func:`collect_scale_errors`, then
    :func:`~tdfd.model.scale_calibration_fit.fit_tile_calibration`; ``depth_bins`` or
    ``border_levels`` 0: without that part), and for a model with the structure pooling its
    ``pooled_scale_calibration`` after it (the same fit on the pooled errors).

    Args:
        pooled_only: keep the model's ``scale_calibration`` (the tiles' map, which the autofocus
            reads) and fit only the pooled map on top of it.
        pooled_planes, pooled_scenes: the pooled map's planes and scenes per layout (``None``:
            ``planes``, ``scenes``); the first ones of the same seeds.

    Returns:
        What the fit used and found: seeds, counts, and per knot the factor ``b' / b`` of each
        part; the pooled map's under ``"pooled"`` (with ``pooled_only``, only that).

    Raises:
        InputError: ``pooled_only`` for a model without the structure pooling.
    """
    t0 = time.perf_counter()
    fit = dict(bins=bins, smooth=smooth, depth_bins=depth_bins, border_levels=border_levels, min_factor=min_factor)
    if pooled_only:
        if model.structure_pooling is None:
            raise InputError("pooled_only needs a model with the structure pooling")
        info: dict[str, object] = {}
    else:
        data = collect_scale_errors(model, planes, scenes)
        model.scale_calibration = ScaleCalibration.from_config(_fit(data, fit))
        info = _describe(model.scale_calibration.to_config(), data, planes, scenes, fit)
    if model.structure_pooling is not None:
        p_planes, p_scenes = pooled_planes or planes, pooled_scenes or scenes
        model.pooled_scale_calibration = ScaleCalibration()
        pooled = collect_scale_errors(model, p_planes, p_scenes, pooled=True)
        model.pooled_scale_calibration = ScaleCalibration.from_config(_fit(pooled, fit))
        logger.info("the structure-pooled depth's scale:")
        info["pooled"] = _describe(model.pooled_scale_calibration.to_config(), pooled, p_planes, p_scenes, fit)
        info["pooled"]["structure_pooling"] = model.structure_pooling.to_config()
    info["seconds"] = round(time.perf_counter() - t0, 1)
    logger.info("fitted in %.0f s", info["seconds"])
    return info


def _fit(data: dict[str, torch.Tensor], fit: dict[str, object]) -> dict[str, list[float]]:
    depth_bins, border_levels = fit["depth_bins"], fit["border_levels"]
    return fit_tile_calibration(data["scale"], data["error"], data["inverse_depth"] if depth_bins else None,
                                data["border"] if border_levels else None, **fit)


def _describe(cfg: dict[str, list[float]], data: dict[str, torch.Tensor], planes: int, scenes: int,
              fit: dict[str, object]) -> dict[str, object]:
    """The fit's record (seeds, counts, knots as factors), logged as it is built."""
    bins, smooth, min_factor = fit["bins"], fit["smooth"], fit["min_factor"]
    depth_bins, border_levels = fit["depth_bins"], fit["border_levels"]
    factors = [round(math.exp(c - b), 4) for b, c in zip(cfg["log_b"], cfg["log_b_calibrated"])]
    info: dict[str, object] = {
        "plane_seed": PLANE_SEED, "structure_seed": STRUCTURE_SEED, "planes": planes, "scenes_per_layout": scenes,
        "layouts": list(STRUCTURE_LAYOUTS), "tiles": int(data["scale"].numel()),
        "plane_tiles": int((data["set"] == 0).sum()), "bins": bins, "smooth": smooth, "min_factor": min_factor,
        "depth_bins": depth_bins, "border_levels": border_levels,
        "knot_scales": [round(math.exp(v), 6) for v in cfg["log_b"]], "knot_factors": factors}
    logger.info("scale calibration on %d tiles (%d planes, %d scenes per layout): factor b'/b %.2f .. %.2f at the "
                "scale knots", info["tiles"], planes, scenes, min(factors), max(factors))
    if "depth_log_shift" in cfg:
        info["depth_knots_m"] = [round(1.0 / v, 4) for v in cfg["inverse_depth_per_m"]]
        info["depth_factors"] = [round(math.exp(v), 4) for v in cfg["depth_log_shift"]]
        logger.info("  depth factors %s at %s m", info["depth_factors"], info["depth_knots_m"])
    if "border_log_shift" in cfg:
        info["border_factors"] = [round(math.exp(v), 4) for v in cfg["border_log_shift"]]
        logger.info("  factors 0, 1, .. tiles from the edge %s", info["border_factors"])
    return info


def plot_scale_calibration(calibration: ScaleCalibration, path: Path, title: str = "") -> None:
    """The calibration's parts as factors on ``b``: ``exp(s)`` against the CNN's ``b``, ``exp(g)``
    against the depth (m) and ``exp(h)`` per distance to the grid's edge; a part the map lacks
    is left out. Written to ``path`` (PNG).

    Raises:
        InputError: the calibration is the identity (nothing to plot).
    """
    cfg = calibration.to_config()
    if cfg is None:
        raise InputError("the model has no scale calibration to plot")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(13, 4))
    if "log_b" in cfg:
        x = torch.linspace(min(cfg["log_b"]) - 0.5, max(cfg["log_b"]) + 0.5, 400, dtype=torch.float64)
        f = (calibrate_log_scale(x, torch.tensor(cfg["log_b"], dtype=torch.float64),
                                 torch.tensor(cfg["log_b_calibrated"], dtype=torch.float64)) - x).exp()
        axes[0].plot((100 * x.exp()).numpy(), f.numpy(), "-")
        axes[0].plot([100 * math.exp(v) for v in cfg["log_b"]],
                     [math.exp(c - b) for b, c in zip(cfg["log_b"], cfg["log_b_calibrated"])], "o", ms=3)
    axes[0].set(xscale="log", xlabel="the CNN's predicted scale b (% relative error)", ylabel="factor b' / b",
                title="scale part exp(s)")
    if "inverse_depth_per_m" in cfg:
        q = torch.tensor(cfg["inverse_depth_per_m"], dtype=torch.float64)
        axes[1].plot((1.0 / q).numpy(), [math.exp(v) for v in cfg["depth_log_shift"]], "o-", ms=3)
    axes[1].set(xlabel="refined depth (m)", ylabel="factor", title="depth part exp(g)")
    if "border_log_shift" in cfg:
        shifts = cfg["border_log_shift"]
        axes[2].bar([str(k) if k < len(shifts) - 1 else f">={k}" for k in range(len(shifts))],
                    [math.exp(v) for v in shifts])
    axes[2].set(xlabel="tiles to the grid's edge", ylabel="factor", title="edge part exp(h)")
    for ax in axes:
        ax.axhline(1.0, color="k", lw=0.8)
        ax.grid(alpha=0.3)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m training.calibrate_scale", description=__doc__.splitlines()[0])
    p.add_argument("--model", required=True, help="model stem written by python -m training (e.g. models/reference)")
    p.add_argument("--out", help="stem to write (default: the model's own files; the weights are copied unchanged)")
    p.add_argument("--planes", type=int, default=2048, help="textured planes (256x256)")
    p.add_argument("--scenes", type=int, default=64, help="scenes per depth-structure layout (480x640)")
    p.add_argument("--bins", type=int, default=40, help="equal-count bands of the predicted scale (knots)")
    p.add_argument("--smooth", type=int, default=3, help="odd moving-average width over the bands' factors")
    p.add_argument("--depth-bins", type=int, default=20, help="bands of the refined inverse depth (0: no depth part)")
    p.add_argument("--border-levels", type=int, default=5,
                   help="distances to the grid's edge with their own factor, the last held beyond (0: no edge part)")
    p.add_argument("--min-factor", default="none",
                   help="smallest factor b'/b at a knot (1: only widen the CNN's scale); default 'none': no bound")
    p.add_argument("--threads", type=int, default=2, help="torch threads")
    p.add_argument("--plot", help="also write the fitted parts as a figure (PNG) to this path (the pooled map's "
                   "beside it, <name>_pooled.png)")
    p.add_argument("--structure-pooling", default="keep",
                   help="'keep' (the model's own), 'none', 'default' (StructurePooling's defaults) or a JSON object "
                        "of its options: the last stage whose scale is calibrated second")
    p.add_argument("--pooled-planes", type=int, default=0, help="the pooled map's planes (0: --planes)")
    p.add_argument("--pooled-scenes", type=int, default=0, help="the pooled map's scenes per layout (0: --scenes)")
    p.add_argument("--pooled-only", action="store_true",
                   help="keep the model's own map of the tiles' scale (what the autofocus reads) and fit only the "
                        "structure-pooled depth's map on top of it")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s", stream=sys.stdout)
    if args.planes < 1 or args.scenes < 1 or args.pooled_planes < 0 or args.pooled_scenes < 0:
        p.error("--planes and --scenes must be >= 1, --pooled-planes and --pooled-scenes >= 0")
    if min(args.depth_bins, args.border_levels) < 0 or 1 in (args.depth_bins, args.border_levels):
        p.error("--depth-bins and --border-levels must be 0 (without that part) or >= 2")
    try:
        min_factor = None if args.min_factor.lower() == "none" else float(args.min_factor)
    except ValueError:
        p.error(f"--min-factor must be a number or 'none', got {args.min_factor!r}")
    torch.set_num_threads(args.threads)
    model = DFDModel.load(args.model)
    if args.structure_pooling != "keep":
        try:
            options = {"none": None, "default": {}}.get(args.structure_pooling)
            if args.structure_pooling not in ("none", "default"):
                options = json.loads(args.structure_pooling)
            model.set_structure_pooling(options)
        except (json.JSONDecodeError, InputError, TypeError) as exc:
            p.error(f"--structure-pooling: {exc}")
    if args.pooled_only and model.structure_pooling is None:
        p.error("--pooled-only needs a model with the structure pooling (--structure-pooling)")
    meta = DFDModel.read_description(args.model)
    info = calibrate_model(model, args.planes, args.scenes, args.bins, args.smooth, min_factor, args.depth_bins,
                           args.border_levels, pooled_only=args.pooled_only, pooled_planes=args.pooled_planes or None,
                           pooled_scenes=args.pooled_scenes or None)
    extra = dict(meta.get("extra") or {})
    if args.pooled_only:  # the tiles' fit as it was, the pooled one beside it
        info = {**dict(extra.get("scale_calibration_fit") or {}), "pooled": info["pooled"],
                "pooled_seconds": info["seconds"]}
    extra["scale_calibration_fit"] = info
    out = Path(args.out or args.model)
    weights, desc = model.save(out, extra=extra)
    logger.info("wrote %s and %s", weights, desc)
    if args.plot:
        if not args.pooled_only:
            plot_scale_calibration(model.scale_calibration, Path(args.plot), f"Scale calibration of {out.name}")
            logger.info("wrote %s", args.plot)
        if model.structure_pooling is not None:
            pooled_plot = Path(args.plot).with_name(Path(args.plot).stem + "_pooled.png")
            plot_scale_calibration(model.pooled_scale_calibration, pooled_plot,
                                   f"Scale calibration of {out.name}'s structure-pooled depth")
            logger.info("wrote %s", pooled_plot)
    return 0


if __name__ == "__main__":
    sys.exit(main())
