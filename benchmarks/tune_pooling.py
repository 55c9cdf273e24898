"""Choose the structure pooling's options on the calibration scenes, not the benchmarks'.

The pooling (:mod:`tdfd.model.structure_pooling`) is a stage after training with a few options
(window, degree, robust kernel, ridge, curvature test). Choosing them on the benchmarks' own
scenes would tune the benchmark. This tool runs a trained model once on the scale calibration's
held-out scenes (:func:`training.calibrate_scale.calibration_scene_sets`:
textured planes and the three depth-structure layouts), keeps each tile's refined inverse depth,
calibrated scale, true depth and whether it lies near an occlusion edge, and scores every option
set given: the median relative depth error per tile away from edges, per scene set, against no
pooling. The chosen options are then checked once on the benchmarks' scenes
(``python -m benchmarks.compare_models``)::

    .venv/bin/python -m benchmarks.tune_pooling --model models/reference \\
        --options '[{}, {"curvature_test": 1.0}, {"degree": 1}]'

Each option set is a JSON object over :class:`~tdfd.model.structure_pooling.StructurePooling`'s
defaults.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from typing import Any

import torch
from tqdm import tqdm

from benchmarks.depth_edges import edge_tiles
from tdfd.errors import InputError
from tdfd.model import DFDModel
from tdfd.model.structure_pooling import StructurePooling

from training.calibrate_scale import PLANE_SEED, STRUCTURE_SEED, calibration_scene_sets

__all__ = ["collect_tiles", "score_pooling", "main"]

logger = logging.getLogger("benchmarks.tune_pooling")


@torch.no_grad()
def collect_tiles(model: DFDModel, planes: int, scenes: int) -> dict[str, dict[str, torch.Tensor]]:
    """The model's tiles on the calibration scenes, per set (``planes``, then each layout):
    ``q`` (refined inverse depth, 1/m), ``log_b`` (its calibrated log scale), ``true`` (tile
    depth, m) and ``edge`` (within one tile of an occlusion edge), each ``(N, 1, h, w)``."""
    model = model.eval()
    out: dict[str, dict[str, torch.Tensor]] = {}
    for name, ds, count, chunk in calibration_scene_sets(model, planes, scenes):
        parts: dict[str, list[torch.Tensor]] = {"q": [], "log_b": [], "true": [], "edge": []}
        for start in tqdm(range(0, count, chunk), desc=name, mininterval=10.0):
            batch = ds.batch(list(range(start, min(count, start + chunk))))
            # the tiles' stage only: a model's own pooling, if it has one, is not needed here
            feats, r = model.features(batch["image_f1"].float(), batch["image_f2"].float())
            q, log_b, _, _ = model.head(feats, r.inverse_depth, r.rel_error)
            parts["q"].append(q)
            parts["log_b"].append(log_b)
            parts["true"].append(batch["tile_depth"].float())
            parts["edge"].append(torch.stack([edge_tiles(d[0].float(), model.tile, model.stride)
                                              for d in batch["depth"]])[:, None])
        out[name] = {k: torch.cat(v) for k, v in parts.items()}
    return out


def score_pooling(tiles: dict[str, dict[str, torch.Tensor]], options: dict[str, Any] | None,
                  inv_depth_limits: tuple[float, float], depth_range: tuple[float, float]) -> dict[str, float]:
    """Median ``|d - d_true| / d_true`` per set over the tiles away from edges in ``depth_range``,
    after the pooling with ``options`` over the defaults (``None``: no pooling), and
    ``structure``, the mean of the layouts' medians.

    Raises:
        InputError: unknown or out-of-range options.
    """
    pool = None if options is None else StructurePooling.from_config(dict(options))
    near, far = depth_range
    res: dict[str, float] = {}
    for name, t in tiles.items():
        q = t["q"].double()
        if pool is not None:
            q = pool(q, t["log_b"].double().exp()).clamp(*inv_depth_limits)
        true = t["true"].double()
        keep = (true >= near) & (true <= far) & ~t["edge"]
        res[name] = float(((1.0 / q - true).abs() / true)[keep].median())
    layouts = [k for k in res if k != "planes"]
    res["structure"] = sum(res[k] for k in layouts) / max(len(layouts), 1)
    return res


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.tune_pooling", description=__doc__.splitlines()[0])
    p.add_argument("--model", required=True, help="model stem (its own pooling, if any, is not used)")
    p.add_argument("--options", default="[{}]", help="JSON list of option objects over the stage's defaults")
    p.add_argument("--planes", type=int, default=1024, help="calibration planes (256x256)")
    p.add_argument("--scenes", type=int, default=64, help="calibration scenes per layout (480x640)")
    p.add_argument("--threads", type=int, default=2, help="torch threads")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s", stream=sys.stdout)
    try:
        grid = json.loads(args.options)
    except json.JSONDecodeError as exc:
        p.error(f"--options is not JSON: {exc}")
    if not isinstance(grid, list) or not all(isinstance(o, dict) for o in grid):
        p.error("--options must be a JSON list of objects")
    if args.planes < 1 or args.scenes < 1:
        p.error("--planes and --scenes must be >= 1")
    for options in grid:  # typed errors before the long run
        try:
            StructurePooling.from_config(dict(options))
        except (InputError, TypeError) as exc:
            p.error(f"--options {json.dumps(options)}: {exc}")
    torch.set_num_threads(args.threads)
    model = DFDModel.load(args.model)
    t0 = time.perf_counter()
    tiles = collect_tiles(model, args.planes, args.scenes)
    limits, rng = model.analytic.inv_depth_limits, model.camera.depth_range_m
    base = score_pooling(tiles, None, limits, rng)
    names = list(base)
    print(f"calibration scenes: {args.planes} planes (seed {PLANE_SEED}), {args.scenes} scenes per layout (seed "
          f"{STRUCTURE_SEED}); median abs. rel. error per tile away from edges, in points against no pooling\n")
    print("| options | " + " | ".join(names) + " |")
    print("|---|" + "---|" * len(names))
    print("| no pooling | " + " | ".join(f"{100 * base[n]:.3f} %" for n in names) + " |")
    for options in grid:
        r = score_pooling(tiles, options, limits, rng)
        print(f"| `{json.dumps(options)}` | " + " | ".join(f"{100 * (r[n] - base[n]):+.3f}" for n in names) + " |")
    logger.info("%.0f s", time.perf_counter() - t0)
    return 0


if __name__ == "__main__":
    sys.exit(main())
