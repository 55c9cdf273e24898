"""Regenerate docs/BENCHMARKS.md and its figures: every benchmark, one after the other.

    python3 dev.py python -m benchmarks            # all
    python3 dev.py python -m benchmarks analytic   # some, by short name

Each benchmark prints its figures and rewrites only its own section of docs/BENCHMARKS.md.
Run on an otherwise idle machine: the timings are medians of repeated runs, but other load
still shifts them.
"""

from __future__ import annotations

import importlib
import logging
import sys
import time

BENCHMARKS = {
    "analytic": "benchmarks.bench_analytic",
    "synthesis": "benchmarks.bench_synthesis",
    "refinement": "benchmarks.bench_refinement",
    "bound": "benchmarks.bench_bound",
    "family_ablation": "benchmarks.bench_family_ablation",
    "structure": "benchmarks.bench_structure",
    "uncertainty": "benchmarks.bench_uncertainty",
    "onnx": "benchmarks.bench_onnx",
    "autofocus": "benchmarks.bench_autofocus",
    "assist_light": "benchmarks.bench_assist_light",
    "reliability": "benchmarks.bench_reliability",
    "paper": "benchmarks.paper_experiment",
    "overview": "benchmarks.overview_figure",
    "calibration": "benchmarks.bench_calibration",
    "camera_pairs": "benchmarks.bench_camera_pairs",
    "breathing": "benchmarks.bench_breathing",
    "calibrated_af": "benchmarks.bench_calibrated_af",
    "psf_family": "benchmarks.bench_psf_family",
}


def main(argv: list[str]) -> int:
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    names = argv or list(BENCHMARKS)
    unknown = [n for n in names if n not in BENCHMARKS]
    if unknown:
        print(f"unknown benchmark(s) {unknown}; known: {list(BENCHMARKS)}", file=sys.stderr)
        return 2
    for name in names:
        t0 = time.perf_counter()
        print(f"\n=== {name} ({BENCHMARKS[name]}) ===", flush=True)
        importlib.import_module(BENCHMARKS[name]).main([])
        print(f"=== {name} done in {time.perf_counter() - t0:.0f} s", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
