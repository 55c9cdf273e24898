"""Where the refined paper-experiment estimate loses to the analytic one: tile by tile.

The paper experiment (:mod:`benchmarks.paper_experiment`, reference camera) compares the
one-region analytic estimate with the model's lit tiles pooled as the autofocus pools them.
This diagnosis looks inside the pooling: over the tiles that it uses (a cue in the lit pair,
``pair_cue_mask``, and confidence >= ``CONFIDENT_TILE``), the median signed error of the
model's refined depth and of the same model's analytic depth (the ``depth_analytic``
output: the Fourier-ratio fit of the same 64-px tile, before the CNN). A refined median
farther from zero than the analytic one is a bias that the CNN adds.

Run from the repository root::

    .venv/bin/python -m benchmarks.paper_tiles [--model models/reference.onnx] [--repeats 3] [--optics pillbox]
        [--psf-family optics|gaussian|pillbox|unknown|exported]

It prints a table (ad-hoc diagnosis; it writes nothing to docs/BENCHMARKS.md).
"""

from __future__ import annotations

import argparse
import statistics

import numpy as np
import torch

from tdfd import Camera
from tdfd.autofocus.lit_tiles import CONFIDENT_TILE
from tdfd.runtime import DepthRuntime

from .paper_experiment import (DISTANCES_CM, PSF_FAMILY_CHOICES, REFERENCE_FIELD, capture, lit_tile_depths, paper_sensor,
                               paper_sources, told_family)
from .report import ROOT, machine, markdown_table


def tile_errors(rt: DepthRuntime, i1: torch.Tensor, i2: torch.Tensor, depth_m: float) -> tuple[float, float, float, int]:
    """``(pooled, median refined, median analytic, tiles)``: signed errors in % over the pooled tiles."""
    lit = lit_tile_depths(rt, i1, i2)
    used = lit.used & (lit.confidence >= CONFIDENT_TILE)
    if not used.any():
        return float("nan"), float("nan"), float("nan"), 0
    err = lambda d: 100.0 * (d - depth_m) / depth_m  # noqa: E731
    return (err(lit.pooled.depth_m), float(np.median(err(lit.depth[used]))), float(np.median(err(lit.analytic[used]))),
            int(used.sum()))


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(prog="python -m benchmarks.paper_tiles", description=__doc__.split("\n\n")[0])
    p.add_argument("--model", default=str(ROOT / "models" / "reference.onnx"), help="ONNX model")
    p.add_argument("--repeats", type=int, default=3, help="noisy captures per distance (median)")
    p.add_argument("--seed", type=int, default=5)
    p.add_argument("--optics", choices=("gaussian", "pillbox"), default="gaussian",
                   help="simulated PSF shape (as benchmarks.paper_experiment; default gaussian)")
    p.add_argument("--psf-family", choices=PSF_FAMILY_CHOICES, default="optics",
                   help="the PSF family the model's CNN is told (as benchmarks.paper_experiment; default: the optics')")
    args = p.parse_args(argv)
    camera = Camera.preset("reference")
    sensor = paper_sensor()
    told = told_family(args.psf_family, args.optics)
    rt = DepthRuntime(args.model, psf_family=told)
    g = torch.Generator().manual_seed(args.seed)
    rows = []
    for name, source in paper_sources().items():
        for dcm in DISTANCES_CM:
            runs = [tile_errors(rt, *capture(camera, source, dcm / 100, REFERENCE_FIELD, g, sensor, args.optics),
                                dcm / 100)
                    for _ in range(args.repeats)]
            kept = [r for r in runs if r[3] > 0]
            if not kept:
                rows.append([name, f"{dcm:g}", "-", "-", "-", 0])
                continue
            med = [statistics.median(r[k] for r in kept) for k in range(3)]
            rows.append([name, f"{dcm:g}", f"{med[0]:+.2f}", f"{med[1]:+.2f}", f"{med[2]:+.2f}",
                         int(statistics.median(r[3] for r in kept))])
    table = markdown_table(["light", "distance (cm)", "pooled refined %", "tiles: median refined %",
                            "tiles: median analytic (same tiles) %", "tiles used"], rows)
    print(f"{machine()}\nmodel {args.model} told {rt.psf_family or 'unknown'}, {args.optics} optics, median of "
          f"{args.repeats} captures\n\n{table}")


if __name__ == "__main__":
    main()
