r"""A likelihood stage after the CNN: each tile's cross-residual fit, seeded by the model and fused with it.

Run from the repository root::

    .venv/bin/python -m benchmarks.bench_likelihood_stage [--samples 256] [--world clean,full]

What a model-based stage in the product would add to the shipped model, measured on the
refinement benchmark's planes (0.3-1.0 m; section ``likelihood_stage``). For each interior tile
of the 64/32 grid (:func:`benchmarks.bench_tile_oracle.interior_origins`):

1. **Seeded fit**: the per-tile cross-residual likelihood
   (:func:`benchmarks.residual_likelihood.tile_cross_residual_nll`) searched only within
   :data:`~benchmarks.bench_tile_oracle.SEED_WINDOW` of the model's inverse depth, the PSF's
   shape shared by the image and profiled over
   :data:`~benchmarks.bench_plane_oracle.SHAPE_GRID` (its diffraction and aberrations told:
   the oracle part), or the PSF known (``known``). Frame 2's mean is matched to frame 1's.
2. **Its variance** from the curvature at the minimum: ``var(q) = 1 / L''(q)`` with ``L`` the
   summed NLL over the band's independent bins (half the half-plane count).
3. **The model's variance** from its confidence ``conf = 1 / (1 + (b / b0)^2)``: the Laplace
   scale ``b`` of the relative error, variance ``2 b^2`` (:mod:`tdfd.model.combined`).
4. **Fusion**: the inverse-variance mean of the two inverse depths, each variance times a scale
   factor fitted on the *other* half of the planes (even / odd sample index) so that the
   median of ``|e| / sigma`` there is 0.674 (both raw variances are off: the taper's correlated
   bins make the curvature too sharp, the model's scale is conservative). The border ring
   keeps the model's estimate.

Scores: the median relative error over the interior tiles, per plane the median tile's, and
the fused-minus-model difference with a paired bootstrap over planes (95 % interval). The
nuisances: ``clean`` switches off breathing, misregistration, vignetting and gain jitter,
``full`` keeps them (the stage models none of them).
"""

from __future__ import annotations

import argparse
import math
import random
import statistics
import sys
import time
from dataclasses import replace

import torch
from tqdm import tqdm

from benchmarks.bench_bound import MEDIAN_ABS, STRIDE, TILE, psf_model
from benchmarks.bench_plane_oracle import CLEAN_WORLD, Q_GRID, SHAPE_GRID, plane_frames
from benchmarks.bench_refinement import BENCH_SEED, bench_tiles
from benchmarks.bench_tile_oracle import (SEED_WINDOW, interior_origins, profile_tiles, seed_mask, tile_nll_stack,
                                          tile_noise)
from benchmarks.report import ROOT, comma_choices, machine, markdown_table, update_section
from benchmarks.residual_likelihood import _band_weight
from data_synth import DefocusPairDataset
from tdfd.errors import InputError
from tdfd.model import DFDModel
from training.config import EvalConfig

__all__ = ["seeded_fit", "model_sigma", "sigma_factor", "fuse", "paired_bootstrap", "main"]


def seeded_fit(nll: torch.Tensor, grid: torch.Tensor, seed_q: torch.Tensor, bins: float,
               window: float = SEED_WINDOW) -> tuple[torch.Tensor, torch.Tensor, int]:
    """Each tile's seeded minimum and its standard deviation in ``q``.

    Args:
        nll: ``(C, Q, T)`` mean per-bin NLL of ``C`` candidate PSFs (``inf`` where not computed).
        grid: ``(Q,)`` uniform grid of ``q`` (1/m).
        seed_q: ``(T,)`` each tile's seed.
        bins: independent bins per tile (the NLL's sum is ``bins`` times its mean).
        window: relative half-width of each tile's search.

    Returns:
        ``q`` ``(T,)`` (parabolic refinement, at most one step), ``sigma_q`` ``(T,)`` (``inf`` where
        the minimum lies on the window's edge or the curvature is not positive), and the index
        of the candidate shared by the image (:func:`benchmarks.bench_tile_oracle.profile_tiles`).
    """
    if nll.ndim != 3 or nll.shape[1] != grid.shape[0] or seed_q.shape != (nll.shape[2],):
        raise InputError(f"need nll (C, Q, T), grid (Q,), seed_q (T,); got {tuple(nll.shape)}, "
                         f"{tuple(grid.shape)}, {tuple(seed_q.shape)}")
    if not bins > 0:
        raise InputError(f"bins must be > 0, got {bins}")
    q, j, curvature = profile_tiles(nll, grid, seed_mask(grid, seed_q, window))
    ok = torch.isfinite(curvature)  # finite only where positive
    sigma = torch.where(ok, 1.0 / (bins * torch.where(ok, curvature, torch.ones_like(curvature))).sqrt(),
                        torch.full_like(curvature, math.inf))
    return q, sigma, j


def model_sigma(confidence: torch.Tensor, confidence_scale: float) -> torch.Tensor:
    """The model's standard deviation of the relative error from its confidence:
    ``sqrt(2) b0 sqrt(1/conf - 1)`` (a Laplace scale ``b``; :mod:`tdfd.model.combined`).

    Example:
        >>> round(float(model_sigma(torch.tensor([0.5]), 0.01)[0]), 5)
        0.01414
    """
    if not bool(((confidence > 0) & (confidence <= 1)).all()):
        raise InputError("confidences must lie in (0, 1]")
    return math.sqrt(2.0) * confidence_scale * (1.0 / confidence - 1.0).clamp_min(0).sqrt()


def sigma_factor(errors: torch.Tensor, sigmas: torch.Tensor) -> float:
    """The factor on ``sigmas`` that makes the median of ``|errors| / sigma`` 0.674 (a normal's),
    over the finite, positive sigmas."""
    ok = torch.isfinite(sigmas) & (sigmas > 0)
    if not bool(ok.any()):
        raise InputError("no finite positive sigma to calibrate")
    return float((errors[ok].abs() / sigmas[ok]).median()) / MEDIAN_ABS


def fuse(q_a: torch.Tensor, sigma_a: torch.Tensor, q_b: torch.Tensor, sigma_b: torch.Tensor) -> torch.Tensor:
    """Inverse-variance mean of two estimates; an infinite sigma gives its estimate no weight.

    Example:
        >>> fuse(torch.tensor([1.0, 1.0]), torch.tensor([1.0, float("inf")]),
        ...      torch.tensor([2.0, 2.0]), torch.tensor([1.0, 1.0])).tolist()
        [1.5, 2.0]
    """
    wa = torch.where(torch.isfinite(sigma_a), 1.0 / sigma_a.clamp_min(1e-300) ** 2, torch.zeros_like(sigma_a))
    wb = torch.where(torch.isfinite(sigma_b), 1.0 / sigma_b.clamp_min(1e-300) ** 2, torch.zeros_like(sigma_b))
    if not bool((wa + wb > 0).all()):
        raise InputError("every pair needs at least one finite sigma")
    return (wa * q_a + wb * q_b) / (wa + wb)


def paired_bootstrap(a: list[list[float]], b: list[list[float]], resamples: int = 1000, seed: int = 0
                     ) -> tuple[float, float, float]:
    """Mean and 95 % interval of ``median |a| - median |b|`` over tiles pooled from planes drawn
    with replacement (``a``, ``b``: per plane, the tiles' errors of two estimators)."""
    rng = random.Random(seed)
    n = len(a)
    diffs = []
    for _ in range(resamples):
        pick = [rng.randrange(n) for _ in range(n)]
        diffs.append(statistics.median(abs(x) for i in pick for x in a[i])
                     - statistics.median(abs(x) for i in pick for x in b[i]))
    diffs.sort()
    return statistics.mean(diffs), diffs[int(0.025 * resamples)], diffs[int(0.975 * resamples) - 1]


def run_world(world: str, samples: int, model: DFDModel) -> list[dict]:
    """Every plane's interior tiles: true ``q``, the model's ``q`` and sigma, and per mode the
    seeded fit's ``q`` and sigma (relative)."""
    over = CLEAN_WORLD if world == "clean" else {}
    camera = model.camera
    n = (256 - TILE) // STRIDE + 1
    tiles = bench_tiles(model, samples, 256, over)
    true, ref, conf = (tiles[k].reshape(samples, n, n).double() for k in ("true", "refined", "confidence"))
    ev = EvalConfig(samples=samples, seed=BENCH_SEED, height=256, width=256)
    ds = DefocusPairDataset(size=256, camera=camera, seed=BENCH_SEED, tile=TILE, stride=STRIDE, **{**ev.options, **over})
    origins, inner = interior_origins(256)
    bins = float(_band_weight(TILE, TILE, 0.25).sum()) / 2.0
    rows = []
    for i in tqdm(range(samples), desc=f"likelihood stage ({world})", mininterval=10.0):
        s = ds[i]
        p = s["params"]
        if p["layout"] != "plane" or not 0.3 <= float(true[i].median()) <= 1.0:
            continue
        y1, y2, _, _ = plane_frames(s, match_gain=True)
        nu1, nu2 = tile_noise(p, y1, origins), tile_noise(p, y2, origins)
        seed = 1.0 / ref[i][inner, inner].flatten()
        needed = seed_mask(Q_GRID, seed).any(1)  # only the hypotheses some tile searches
        row = {"index": i, "true_q": (1.0 / true[i][inner, inner].flatten()).tolist(), "model_q": seed.tolist(),
               "model_sigma": model_sigma(conf[i][inner, inner].flatten().clamp(1e-9, 1.0),
                                          model.confidence_scale).tolist()}
        base = psf_model(p)
        for mode in ("known", "shape"):
            cands = [base] if mode == "known" else [replace(base, shape=sh) for sh in SHAPE_GRID]
            stack = tile_nll_stack(y1, y2, camera, cands, nu1, nu2, origins, only=needed)
            q, sq, _ = seeded_fit(stack, Q_GRID, seed, bins)
            row[f"{mode}_q"], row[f"{mode}_sigma"] = q.tolist(), (sq / q).tolist()
        rows.append(row)
    return rows


def score(rows: list[dict], mode: str) -> dict[str, list[list[float]]]:
    """Per plane, the relative depth errors of the model, the seeded fit and the fusion (raw and
    with each sigma's scale fitted on the other half of the planes)."""
    def err(q: torch.Tensor, qt: torch.Tensor) -> list[float]:
        return (qt / q - 1.0).tolist()  # depth / true depth - 1

    t = {k: [torch.tensor(r[k], dtype=torch.float64) for r in rows]
         for k in ("true_q", "model_q", "model_sigma", f"{mode}_q", f"{mode}_sigma")}
    out: dict[str, list[list[float]]] = {"model": [], "seeded": [], "raw": [], "fused": []}
    factors = {}
    for half in (0, 1):
        cal = [j for j, r in enumerate(rows) if r["index"] % 2 != half]
        e_l = torch.cat([t["true_q"][j] / t[f"{mode}_q"][j] - 1 for j in cal])
        e_c = torch.cat([t["true_q"][j] / t["model_q"][j] - 1 for j in cal])
        factors[half] = (sigma_factor(e_l, torch.cat([t[f"{mode}_sigma"][j] for j in cal])),
                         sigma_factor(e_c, torch.cat([t["model_sigma"][j] for j in cal])))
    for j, r in enumerate(rows):
        ql, qc, qt = t[f"{mode}_q"][j], t["model_q"][j], t["true_q"][j]
        sl, sc = t[f"{mode}_sigma"][j] * ql, t["model_sigma"][j] * qc
        fl, fc = factors[r["index"] % 2]
        out["model"].append(err(qc, qt))
        out["seeded"].append(err(ql, qt))
        out["raw"].append(err(fuse(ql, sl, qc, sc), qt))
        out["fused"].append(err(fuse(ql, fl * sl, qc, fc * sc), qt))
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--samples", type=int, default=256, help="the refinement benchmark's first N samples")
    p.add_argument("--world", default="clean,full", help="comma list of: clean, full")
    p.add_argument("--model", default=str(ROOT / "models" / "reference"))
    p.add_argument("--no-write", action="store_true", help="print only; leave docs/ alone")
    args = p.parse_args(argv)
    worlds = comma_choices(p, args.world, ("clean", "full"), "--world")
    torch.set_num_threads(2)
    model = DFDModel.load(args.model)
    med = statistics.median
    pct = lambda x: f"{100 * x:.2f} %"  # noqa: E731
    table, lines = [], []
    t0 = time.perf_counter()
    for world in worlds:
        rows = run_world(world, args.samples, model)
        for mode, label in (("shape", "PSF shape profiled"), ("known", "PSF known")):
            sc = score(rows, mode)
            tile = {k: med(abs(x) for pl in v for x in pl) for k, v in sc.items()}
            plane = {k: med(abs(med(pl)) for pl in v) for k, v in sc.items()}
            table.append([world, label, len(rows)] + [f"{pct(tile[k])} / {pct(plane[k])}"
                                                      for k in ("model", "seeded", "raw", "fused")])
            mt, lo, hi = paired_bootstrap(sc["fused"], sc["model"])
            mp, plo, phi = paired_bootstrap([[med(pl)] for pl in sc["fused"]], [[med(pl)] for pl in sc["model"]])
            lines.append(f"- {world}, {label}: fused - model per tile {100 * mt:+.2f} points (95 %: {100 * lo:+.2f} .. "
                         f"{100 * hi:+.2f}), per plane {100 * mp:+.2f} ({100 * plo:+.2f} .. {100 * phi:+.2f})")
    wall = time.perf_counter() - t0
    body = "\n".join([
        f"Machine: {machine()}; the refinement benchmark's first {args.samples} samples (seed {BENCH_SEED}, 256 px), "
        f"its planes in 0.3-1.0 m, the 25 interior tiles of each (the ring keeps the model's estimate and is not "
        f"scored); wall time {wall:.0f} s. Each cell: median over tiles / median over planes of the median tile. "
        f"`seeded`: the cross-residual fit within {100 * SEED_WINDOW:.0f} % of the model's estimate; `fused, raw`: "
        f"inverse-variance mean with the curvature's and the confidence's sigmas as they are; `fused`: each sigma's "
        f"scale fitted on the other half of the planes (even / odd sample index). The PSF's diffraction and "
        f"aberrations are told in both modes.",
        "",
        markdown_table(["world", "PSF", "planes", "model", "seeded", "fused, raw", "fused"], table),
        "",
        "Paired bootstrap over planes (1000 resamples, seed 0):",
        "",
        *lines,
    ])
    print(body)
    if not args.no_write:
        cmd = f".venv/bin/python -m benchmarks.bench_likelihood_stage --samples {args.samples} --world {args.world}"
        update_section("likelihood_stage", "A likelihood stage after the CNN, fused by inverse variance (issue 19)",
                       body, cmd)
    return 0


if __name__ == "__main__":
    sys.exit(main())
