"""Paired A/B of two depth models on the same held-out scenes, with the scenes' sampling error.

    .venv/bin/python -m benchmarks.compare_models OLD NEW [--planes 1024] [--scenes 128] [--jobs 1]

A model is a :meth:`tdfd.model.DFDModel.save` stem or an ``.onnx`` file
(:func:`benchmarks.depth_models.load_depth_model`). Both run on the refinement benchmark's
first ``--planes`` textured planes (seed 31 337 000, 256x256, full realism) and on the
structure benchmark's first ``--scenes`` scenes per layout (480x640, seed 53 000 017, the
tiles away from occlusion edges). The tiles of one scene share its texture, PSF and sensor, so
the medians scatter by scene, not by tile: every difference comes with a bootstrap over the
scenes (the same resampled scenes for both models, so the difference is paired).

The structure rows took 32 scenes per layout until 2026-11-27 (evening); a few large scenes
carried them (``models/README.md``, "How many structure scenes"), so the default is 128, and
``--jobs`` spreads those scenes over processes.

Why: the refinement benchmark's 256-plane per-tile median carries about 0.1 points of that
sampling error, as much as a retrain changes it (2026-11-26 night: 2.11 -> 2.24 % on 256
planes, 2.241 -> 2.240 % on 1024, ``models/README.md``). Prints only; writes no docs.
"""

from __future__ import annotations

import argparse
import logging
import math
import sys

import torch

from benchmarks.bench_structure import collect_layouts, merge_layouts
from benchmarks.bench_uncertainty import plane_tiles
from benchmarks.depth_models import OUTPUTS, DepthModel, load_depth_model
from benchmarks.report import markdown_table
from benchmarks.uncertainty import resample_scenes
from training.config import TEXTURED_FAMILIES
from training.data import STRUCTURE_LAYOUTS

__all__ = ["paired_tile_median", "paired_group_median", "compare"]

logger = logging.getLogger(__name__)


def _check(err_a: torch.Tensor, err_b: torch.Tensor, group: torch.Tensor) -> None:
    if not (err_a.shape == err_b.shape == group.shape) or err_a.dim() != 1:
        raise ValueError(f"err_a, err_b and group must be equal (N,) tensors, got {tuple(err_a.shape)}, "
                         f"{tuple(err_b.shape)}, {tuple(group.shape)}")
    if err_a.numel() == 0:
        raise ValueError("no tiles to compare")


def _summary(a: float, b: float, diffs: torch.Tensor) -> dict[str, float]:
    d = diffs[torch.isfinite(diffs)]
    return {"a": a, "b": b, "diff": b - a, "se": float(d.std()) if d.numel() > 1 else math.nan,
            "lo": float(d.quantile(0.025)) if d.numel() else math.nan,
            "hi": float(d.quantile(0.975)) if d.numel() else math.nan}


def paired_tile_median(err_a: torch.Tensor, err_b: torch.Tensor, group: torch.Tensor, reps: int = 200,
                       generator: torch.Generator | None = None) -> dict[str, float]:
    """Median over tiles of two models' errors on the same tiles, and the bootstrap of their
    difference over the tiles' groups (scenes).

    Args:
        err_a: ``(N,)`` model A's error per tile.
        err_b: ``(N,)`` model B's error on the same tiles.
        group: ``(N,)`` integer scene of each tile; whole scenes are resampled.
        reps: bootstrap resamples (0: no standard error).
        generator: the resampling's random source (default: seeded 0).

    Returns:
        ``a``, ``b`` (the medians), ``diff`` (``b - a``), ``se`` (bootstrap standard error of
        ``diff``) and ``lo``, ``hi`` (its 2.5 and 97.5 percentiles).

    Example:
        >>> e = torch.tensor([0.01, 0.02, 0.03, 0.04]); g = torch.tensor([0, 0, 1, 1])
        >>> r = paired_tile_median(e, e + 0.01, g, reps=50)
        >>> round(r["diff"], 6), round(r["se"], 6)
        (0.01, 0.0)
    """
    _check(err_a, err_b, group)
    gen = generator if generator is not None else torch.Generator().manual_seed(0)
    diffs = [float(err_b[idx].median()) - float(err_a[idx].median()) for idx in resample_scenes(group, reps, gen)]
    return _summary(float(err_a.median()), float(err_b.median()), torch.tensor(diffs, dtype=torch.float64))


def paired_group_median(depth_a: torch.Tensor, depth_b: torch.Tensor, true: torch.Tensor, group: torch.Tensor,
                        reps: int = 200, generator: torch.Generator | None = None) -> dict[str, float]:
    """Per-scene error (one depth per fronto-parallel plane: the median of its tiles' depths,
    against its true depth), median over scenes, for two models; bootstrap over scenes.

    Args:
        depth_a, depth_b: ``(N,)`` the models' tile depths (m).
        true: ``(N,)`` true tile depth (m), the same for every tile of a scene.
        group: ``(N,)`` integer scene of each tile.
        reps, generator: as :func:`paired_tile_median`.

    Returns:
        As :func:`paired_tile_median`, over scenes.
    """
    _check(depth_a, depth_b, group)
    if true.shape != group.shape:
        raise ValueError(f"true must match group's shape {tuple(group.shape)}, got {tuple(true.shape)}")
    ids, inverse = torch.unique(group, return_inverse=True)
    ea, eb = [], []
    for k in range(len(ids)):
        sel = inverse == k
        t = float(true[sel].median())
        ea.append(abs(float(depth_a[sel].median()) - t) / t)
        eb.append(abs(float(depth_b[sel].median()) - t) / t)
    ea_t, eb_t = torch.tensor(ea, dtype=torch.float64), torch.tensor(eb, dtype=torch.float64)
    gen = generator if generator is not None else torch.Generator().manual_seed(0)
    diffs = [float(eb_t[idx].median()) - float(ea_t[idx].median())
             for idx in resample_scenes(torch.arange(len(ids)), reps, gen)]  # one value per scene
    return _summary(float(ea_t.median()), float(eb_t.median()), torch.tensor(diffs, dtype=torch.float64))


def _rel(depth: torch.Tensor, true: torch.Tensor) -> torch.Tensor:
    return (depth.double() - true.double()).abs() / true.double()


def compare(model_a: DepthModel, model_b: DepthModel, planes: int = 1024, scenes: int = 128, reps: int = 200,
            seed: int = 0, jobs: int = 1, paths: tuple[str, str] | None = None,
            outputs: tuple[str, str] = ("map", "map")) -> list[tuple[str, dict[str, float]]]:
    """The paired comparisons: planes per tile (all tiles, then the tiles on the edge of the
    grid and those inside it, then each texture family's planes) and per plane, each structure
    layout and all layouts per tile away from edges. Rows of ``(name, result)``.

    With ``jobs > 1`` the structure scenes are spread over that many processes
    (:func:`benchmarks.bench_structure.collect_layouts`), which load the models from ``paths``
    (A's, B's) with ``outputs`` (:func:`~benchmarks.depth_models.load_depth_model`'s, as the models were loaded)."""
    if jobs > 1 and paths is None:
        raise ValueError("jobs > 1 needs the models' paths, which the worker processes load")
    if model_a.camera.depth_range_m != model_b.camera.depth_range_m:
        raise ValueError("the two models' cameras have different working ranges: not the same benchmark")
    near, far = model_a.camera.depth_range_m
    gen = torch.Generator().manual_seed(seed)
    rows: list[tuple[str, dict[str, float]]] = []
    if planes > 0:
        ta, tb = plane_tiles(model_a, planes, 256), plane_tiles(model_b, planes, 256)
        if not torch.equal(ta["true"], tb["true"]):
            raise ValueError("the two models' tile grids differ: not the same tiles")
        keep = (ta["true"] >= near) & (ta["true"] <= far)
        ea, eb = _rel(ta["refined"], ta["true"]), _rel(tb["refined"], tb["true"])
        for name, sel in (("", keep), (" on the grid's edge", keep & (ta["border"] == 0)),
                          (" inside the edge", keep & (ta["border"] > 0))):
            rows.append((f"textured planes ({planes}), per tile{name}",
                         paired_tile_median(ea[sel], eb[sel], ta["scene"][sel], reps, gen)))
        for k, family in enumerate(TEXTURED_FAMILIES):  # where a change lands: a family's planes alone
            sel = keep & (ta["family"] == k)
            if bool(sel.any()):
                count = int(ta["scene"][sel].unique().numel())
                rows.append((f"textured planes ({planes}), per tile, {family} ({count} planes)",
                             paired_tile_median(ea[sel], eb[sel], ta["scene"][sel], reps, gen)))
        plane_true = torch.zeros(planes).index_reduce_(0, ta["scene"], ta["true"], "amax", include_self=False)
        in_range = (plane_true >= near) & (plane_true <= far)
        sel = in_range[ta["scene"]]
        rows.append((f"textured planes ({planes}), per plane", paired_group_median(
            ta["refined"][sel], tb["refined"][sel], ta["true"][sel], ta["scene"][sel], reps, gen)))
    if scenes > 0:
        path_a, path_b = paths if paths is not None else ("", "")
        struct_a = collect_layouts(model_a, path_a, scenes, (480, 640), bound=False, told=False, jobs=jobs,
                                   output=outputs[0])
        struct_b = collect_layouts(model_b, path_b, scenes, (480, 640), bound=False, told=False, jobs=jobs,
                                   output=outputs[1])
        if any(not torch.equal(struct_a[lay]["true"], struct_b[lay]["true"]) for lay in STRUCTURE_LAYOUTS):
            raise ValueError("the two models' structure tiles differ: not the same tiles")
        sets = [(f"{lay} ({scenes} scenes)", struct_a[lay], struct_b[lay]) for lay in STRUCTURE_LAYOUTS]
        sets.append(("all layouts", merge_layouts(struct_a), merge_layouts(struct_b)))  # scenes kept apart
        for name, sa, sb in sets:
            keep = ~sa["edge"] & (sa["true"] >= near) & (sa["true"] <= far)
            ea, eb = _rel(sa["refined"], sa["true"])[keep], _rel(sb["refined"], sb["true"])[keep]
            rows.append((f"{name}, away from edges", paired_tile_median(ea, eb, sa["scene"][keep], reps, gen)))
    return rows


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.compare_models", description=__doc__.splitlines()[0])
    p.add_argument("model_a", help="model A (the baseline): stem or .onnx")
    p.add_argument("model_b", help="model B: stem or .onnx")
    p.add_argument("--planes", type=int, default=1024, help="textured planes (0: none)")
    p.add_argument("--scenes", type=int, default=128, help="structure scenes per layout (0: none)")
    p.add_argument("--jobs", type=int, default=1, help="worker processes for the structure scenes (same tiles as 1)")
    p.add_argument("--reps", type=int, default=200, help="bootstrap resamples of the scenes")
    p.add_argument("--seed", type=int, default=0, help="seed of the bootstrap")
    p.add_argument("--threads", type=int, default=2, help="torch / ONNX Runtime threads")
    for side in ("a", "b"):
        p.add_argument(f"--output-{side}", choices=OUTPUTS, default="map",
                       help=f"model {side.upper()}'s depth: 'map' (the structure-pooled map when the model has it) or "
                            "'tiles' (each tile's own estimate); the same model with 'tiles' and 'map' measures the pooling")
    args = p.parse_args(argv)
    if args.planes < 0 or args.scenes < 0 or args.reps < 2 or (args.planes == 0 and args.scenes == 0) or args.jobs < 1:
        p.error("--planes and --scenes must be >= 0 and not both 0; --reps >= 2; --jobs >= 1")
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    torch.set_num_threads(args.threads)
    a = load_depth_model(args.model_a, args.threads, output=args.output_a)
    b = load_depth_model(args.model_b, args.threads, output=args.output_b)
    rows = compare(a, b, args.planes, args.scenes, args.reps, args.seed, args.jobs, (args.model_a, args.model_b),
                   (args.output_a, args.output_b))
    table = [[name, f"{100 * r['a']:.3f} %", f"{100 * r['b']:.3f} %",
              f"{100 * r['diff']:+.3f} +- {100 * r['se']:.3f}", f"{100 * r['lo']:+.3f} .. {100 * r['hi']:+.3f}"]
             for name, r in rows]
    print(f"A = {args.model_a} ({'pooled map' if a.pooled else 'tiles'}), B = {args.model_b} "
          f"({'pooled map' if b.pooled else 'tiles'}); median abs. rel. depth error; bootstrap over scenes "
          f"({args.reps} resamples, seed {args.seed})\n")
    print(markdown_table(["scenes", "A", "B", "B - A (points) +- s.e.", "95 % interval"], table))
    return 0


if __name__ == "__main__":
    sys.exit(main())
