r"""Is the per-plane Cramér-Rao bound reachable on rendered frames? An estimator that knows the physics.

Run from the repository root::

    .venv/bin/python -m benchmarks.bench_plane_oracle [--samples 48] [--psf known,shape] [--band 0.25]

Section ``bound`` (:mod:`benchmarks.bench_bound`) puts the refined model's error per plane
(the median tile depth) at about 4x the per-plane bound. This benchmark asks whether a real
estimator on the rendered frames can do better, or whether the bound is out of reach of
anything that sees pixels: it fits every plane of the refinement benchmark with an *oracle*,
an estimator told what no deployed one knows (the plane is one fronto-parallel plane, the
sample's own PSF, the sensor's noise levels), and scores it beside the bound and the shipped
model on the same frames.

The oracle is the whole-frame cross-residual likelihood of
:mod:`tdfd.dfd.cross_residual` (``k2(q) * f1 - k1(q) * f2`` on the valid region, Tukey
taper modelled; the mean per-bin NLL of the frames' noise alone was 1.03-1.16 at the truth on
four planes without that model, its minimum up to 2 m^-1 away). The fit evaluates a grid of
``q`` (0.01 m^-1 steps, parabolic refinement); with ``--psf shape`` the PSF's shape ``kappa``
(pillbox to Gaussian) is unknown and profiled over a grid, its other parameters (diffraction,
aberrations) still given.

The world (``--world clean``) is the benchmark's planes without the nuisances that an oracle
would also have to be told (breathing, misregistration, vignetting, frame gain jitter); noise,
quantisation, PSF draws and textures are the benchmark's. ``--world full`` keeps the nuisances
and does not tell the oracle: it only matches the frames' means (section
``plane_oracle_full``). The shipped model is scored on the same frames.

Measured 2026-11-28 (section ``plane_oracle``): see docs/BENCHMARKS.md.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Sequence

import torch
from tqdm import tqdm

from benchmarks.bench_bound import (MEDIAN_ABS, depth_variances, plane_fisher, psf_model, psf_prior_variance,
                                    sample_sensor)
from benchmarks.bench_refinement import BENCH_SEED, bench_tiles
from benchmarks.report import ROOT, comma_choices, machine, markdown_table, update_section
from tdfd.dfd.cross_residual import argmin_parabolic, cross_residual_nll
from data_synth import DefocusPairDataset
from data_synth.params import SynthConfig
from data_synth.psf import PSFModel
from tdfd import Camera
from tdfd.errors import InputError
from tdfd.model import DFDModel
from tdfd.optics.thin_lens import camera_sigmas
from training.config import EvalConfig

__all__ = ["CLEAN_WORLD", "SHAPE_GRID", "Q_GRID", "fit_plane", "plane_frames", "main"]

#: data_synth options that remove the nuisances an oracle would also have to be told.
CLEAN_WORLD = {"breathing_prob": 0.0, "shift_prob": 0.0, "vignetting_prob": 0.0, "frame_gain_jitter": 0.0}
#: The PSF shapes over which ``--psf shape`` profiles (``kappa = 1/beta``: 0 pillbox .. 0.5 Gaussian).
SHAPE_GRID: tuple[str | float, ...] = ("pillbox", 20.0, 10.0, 1 / 0.15, 5.0, 4.0, 1 / 0.3, 1 / 0.35, 2.5, 1 / 0.45,
                                       "gaussian")
Q_GRID = torch.arange(0.8, 3.6001, 0.01, dtype=torch.float64)  # 0.28-1.25 m
GROSS = 0.05  # a plane off by more than 5 % counts as a gross error


def fit_plane(y1: torch.Tensor, y2: torch.Tensor, camera: Camera, psfs: Sequence[PSFModel], nu1: float, nu2: float,
              band: float = 0.25, grid: torch.Tensor = Q_GRID, model_taper: bool = True) -> tuple[float, int]:
    """The oracle's inverse depth ``q`` (1/m) of a fronto-parallel plane and the index of the
    best of the candidate ``psfs`` (profiled: the lowest NLL over every ``(q, psf)``)."""
    if not psfs:
        raise InputError("fit_plane needs at least one candidate PSF")
    sig = torch.tensor([[float(s) for s in camera_sigmas(camera, 1.0 / float(q))] for q in grid],
                       dtype=torch.float64)
    best = (math.inf, 0.0, -1)
    for j, psf in enumerate(psfs):
        size = min(psf.kernel_size(float(sig.abs().max())), 2 * (min(y1.shape) // 6) + 1) | 1
        ks = psf.kernels(sig.reshape(-1), size=size).reshape(len(grid), 2, size, size)
        nll = cross_residual_nll(y1, y2, ks[:, 0], ks[:, 1], nu1, nu2, band, model_taper)
        q, value = argmin_parabolic(nll, grid)
        if value < best[0]:
            best = (value, q, j)
    return best[1], best[2]


def plane_frames(sample: dict, match_gain: bool = False) -> tuple[torch.Tensor, torch.Tensor, float, float]:
    """A ``data_synth`` sample's frames with the black level removed, and each frame's noise
    variance at its mean level (:meth:`tdfd.sensor.SensorModel.expected_variance`).

    With ``match_gain`` frame 2 is scaled to frame 1's mean (blur keeps the mean, so a
    frame-to-frame gain difference is all that separates the two; its noise variance scales
    with it): what an estimator not told the frames' gains does."""
    p = sample["params"]
    black = p["black_level_dn"] / (2.0 ** p["bits"] - 1.0)
    sensor, slope = sample_sensor(p)
    frames = [sample[k][0].to(torch.float64) - black for k in ("image_f1", "image_f2")]
    nus = [float(sensor.expected_variance(torch.tensor([float(y.mean()) / slope], dtype=torch.float64)))
           for y in frames]
    if match_gain:
        ratio = float(frames[0].mean() / frames[1].mean())
        return frames[0], frames[1] * ratio, nus[0], nus[1] * ratio ** 2
    return frames[0], frames[1], nus[0], nus[1]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--samples", type=int, default=48, help="the refinement benchmark's first N samples")
    p.add_argument("--size", type=int, default=256, help="image side in px")
    p.add_argument("--psf", default="known,shape", help="comma list of: known, shape")
    p.add_argument("--band", type=float, default=0.25, help="the likelihood's band, cycles/px")
    p.add_argument("--world", choices=("clean", "full"), default="clean",
                   help="clean: the nuisances off (section plane_oracle); full: the benchmark's whole world, the "
                        "oracle not told them, frame gains matched by the frames' means (section plane_oracle_full)")
    p.add_argument("--model", default=str(ROOT / "models" / "reference"), help="model scored on the same frames")
    p.add_argument("--no-write", action="store_true", help="print only; leave docs/ alone")
    p.add_argument("--rows", default="", help="also write every plane's errors and bounds to this JSON file")
    args = p.parse_args(argv)
    modes = comma_choices(p, args.psf, ("known", "shape"), "--psf")
    torch.set_num_threads(2)
    camera = Camera.preset("reference")
    ev = EvalConfig(samples=args.samples, seed=BENCH_SEED, height=args.size, width=args.size)
    overrides = CLEAN_WORLD if args.world == "clean" else {}
    options = {**ev.options, **overrides}
    ds = DefocusPairDataset(size=args.size, camera=camera, seed=BENCH_SEED, tile=64, stride=32, return_sharp=True,
                            **options)
    prior = psf_prior_variance(SynthConfig(), camera)
    t0 = time.perf_counter()
    rows = []
    for i in tqdm(range(args.samples), desc="oracle", mininterval=5.0):
        s = ds[i]
        prm = s["params"]
        d = float(s["tile_depth"].median())
        if prm["layout"] != "plane" or not 0.3 <= d <= 1.0:
            continue
        y1, y2, nu1, nu2 = plane_frames(s, match_gain=args.world == "full")
        base = psf_model(prm)
        row = {"index": i, "depth": d, "family": json.loads(prm["details"])["textures"][0]["family"]}
        for mode in modes:
            cands = [base] if mode == "known" else [replace(base, shape=sh) for sh in SHAPE_GRID]
            q, _ = fit_plane(y1, y2, camera, cands, nu1, nu2, args.band)
            row[mode] = 1.0 / (q * d) - 1.0  # relative depth error, as the models'
        var = depth_variances(plane_fisher(camera, s["sharp"][0], d, prm), prior)
        row["bound_known"] = float(var["plane_known"].sqrt()) * d
        row["bound_unknown"] = float(var["plane_unknown"].sqrt()) * d
        rows.append(row)
    wall = time.perf_counter() - t0
    if not rows:
        raise SystemExit("no plane in 0.3-1.0 m among the samples")
    if args.model:
        tiles = bench_tiles(DFDModel.load(args.model), args.samples, args.size, overrides)
        true = tiles["true"].reshape(args.samples, -1)
        for key in ("refined", "analytic"):
            plane = tiles[key].reshape(args.samples, -1).median(1).values
            for row in rows:
                row[key] = float(plane[row["index"]] / true[row["index"]].median() - 1.0)
    body = report(rows, modes, args, wall)
    print(body)
    if args.rows:
        Path(args.rows).write_text(json.dumps(rows, indent=1))
    if not args.no_write:
        name = "plane_oracle" if args.world == "clean" else "plane_oracle_full"
        plot(rows, [k for k in modes + ["refined"] if k in rows[0]], ROOT / "docs" / f"{name}.png", args.world)
        body += f"\n\n![per-plane error against the per-plane bound]({name}.png)"
        cmd = f".venv/bin/python -m benchmarks.bench_plane_oracle --samples {args.samples} --psf {args.psf}"
        if args.world == "full":
            cmd += " --world full"
            title = "The per-plane oracle in the benchmark's whole world, not told its nuisances (issue 19)"
        else:
            title = "The per-plane bound against an estimator that knows the physics (issue 19)"
        update_section(name, title, body, cmd)
    return 0


def world_text(world: str) -> str:
    """How the section's frames were made."""
    if world == "clean":
        return ("the nuisances an oracle would also need told switched off ("
                + ", ".join(f"{k} = {v}" for k, v in CLEAN_WORLD.items()) + ")")
    return ("the benchmark's whole world (breathing, misregistration, vignetting and frame gain jitter as drawn), "
            "the oracle not told them: it matches frame 2's mean to frame 1's and models nothing else")


def report(rows: list[dict], modes: list[str], args: argparse.Namespace, wall: float) -> str:
    """The section's Markdown."""
    med = statistics.median
    pct = lambda x: f"{100 * x:.2f} %"  # noqa: E731
    labels = {"known": "oracle, PSF known", "shape": "oracle, PSF shape profiled", "refined": "shipped model (refined)",
              "analytic": "analytic estimator"}
    estimators = modes + [k for k in ("refined", "analytic") if k in rows[0]]
    bk, bu = [r["bound_known"] for r in rows], [r["bound_unknown"] for r in rows]
    table = []
    for k in estimators:
        e = [abs(r[k]) for r in rows]
        table.append([labels[k], pct(med(e)), f"{med(a / b for a, b in zip(e, bk)):.2f}",
                      f"{med(a / b for a, b in zip(e, bu)):.2f}", f"{100 * sum(x <= 0.01 for x in e) / len(e):.0f} %",
                      sum(x > GROSS for x in e)])
    fams = sorted({r["family"] for r in rows})
    ftable = [[f, sum(r["family"] == f for r in rows),
               pct(MEDIAN_ABS * med(r["bound_unknown"] for r in rows if r["family"] == f))]
              + [pct(med(abs(r[k]) for r in rows if r["family"] == f)) for k in estimators] for f in fams]
    dtable = []
    for lo, hi in ((0.3, 0.4), (0.4, 0.5), (0.5, 0.6), (0.6, 0.75), (0.75, 1.0)):
        sel = [r for r in rows if lo <= r["depth"] < hi or (hi == 1.0 and r["depth"] == 1.0)]
        if sel:
            dtable.append([f"{lo:.2f}-{hi:.2f}", len(sel), pct(MEDIAN_ABS * med(r["bound_known"] for r in sel)),
                           pct(MEDIAN_ABS * med(r["bound_unknown"] for r in sel))]
                          + [pct(med(abs(r[k]) for r in sel)) for k in estimators])
    return "\n".join([
        f"Machine: {machine()}; {len(rows)} planes in 0.3-1.0 m of the refinement benchmark's first {args.samples} "
        f"samples (seed {BENCH_SEED}, {args.size} px), {world_text(args.world)}; noise, quantisation, PSFs and "
        f"textures as drawn. Band {args.band} cycles/px; wall time {wall:.0f} s for the fits and bounds.",
        "",
        f"The per-plane bound (0.674 sigma, the median |error| of an unbiased estimator at the bound), median over "
        f"these planes: PSF known {pct(MEDIAN_ABS * med(bk))}, PSF unknown {pct(MEDIAN_ABS * med(bu))}. Per plane "
        f"error = |median tile depth (the models) or the fit (the oracle) / true depth - 1|; at the bound the "
        f"median of |e| / sigma is 0.674; gross: |e| > {100 * GROSS:.0f} %.",
        "",
        markdown_table(["estimator", "median per plane", "median abs(e) / sigma, PSF known",
                        "median abs(e) / sigma, PSF unknown", "share <= 1 %", "gross errors"], table),
        "",
        "Per texture family (the plane's first texture), median per plane:",
        "",
        markdown_table(["family", "planes", "bound, PSF unknown"] + [labels[k] for k in estimators], ftable),
        "",
        "Per distance, median per plane:",
        "",
        markdown_table(["distance (m)", "planes", "bound, PSF known", "bound, PSF unknown"]
                       + [labels[k] for k in estimators], dtable),
    ])


def plot(rows: list[dict], keys: list[str], path: Path, world: str = "clean") -> None:
    """Each plane's |error| against its per-plane bound (PSF unknown, 0.674 sigma), log-log, one
    series per estimator, with the lines at the bound and at twice it; written to ``path`` (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 5.5))
    bound = [100 * MEDIAN_ABS * r["bound_unknown"] for r in rows]
    for key, marker in zip(keys, "osx^"):
        ax.scatter(bound, [max(100 * abs(r[key]), 1e-3) for r in rows], marker=marker, s=18, alpha=0.7, label=key)
    lo, hi = min(bound) / 2, max(bound) * 2
    for factor, style in ((1.0, "k-"), (2.0, "k--")):
        ax.plot([lo, hi], [factor * lo, factor * hi], style, lw=0.8, label=f"{factor:g}x the bound")
    ax.set_xscale("log"), ax.set_yscale("log")
    ax.set_xlabel("per-plane bound, PSF unknown (0.674 sigma, %)")
    ax.set_ylabel("|error| per plane (%)")
    ax.set_title("Refinement benchmark planes, " + ("nuisances off" if world == "clean" else
                                                    "nuisances on, not told"))
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
