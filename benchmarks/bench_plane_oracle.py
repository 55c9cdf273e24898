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

The oracle is the profile likelihood of the texture-unknown model, free of any window. Both
frames are the same sharp texture ``s`` blurred by their own PSFs, ``f_i = k_i * s + n_i``,
so the *cross residual*

.. math::

    r(q) = k_2(q) * f_1 - k_1(q) * f_2

is texture-free at the true inverse depth ``q`` wherever both linear convolutions are valid
(the image less a kernel's half-width on every side: no tile boundary, no assumption on the
texture outside the frame). Its noise is stationary with spectrum
``P(u; q) = nu_1 |K_2(u)|^2 + nu_2 |K_1(u)|^2``, and with ``nu_i`` the frames' noise variances,

.. math::

    \mathrm{NLL}(q) = \frac{1}{B} \sum_{u \in \mathrm{band}} \frac{|R(u; q)|^2}{\tilde P(u; q)}

over the band's ``B`` bins (the circular-case profile likelihood; its expectation is 1 at the
truth and larger elsewhere). ``R`` is the spectrum of the residual times a Tukey taper (10 % of
each side), and ``P~`` is the *tapered* residual's expected periodogram, ``P`` convolved with
the taper's spectrum (the product of the residual's autocovariance and the taper's
autocorrelation in the lag domain): without it the taper's leakage from low into
high frequencies, where ``P`` is small, makes even pure noise prefer some depths (the mean
per-bin NLL of the frames' noise alone was 1.03-1.16 at the truth on four planes, and its
minimum up to 2 m^-1 away). The fit evaluates a grid of ``q`` (0.01 m^-1 steps, parabolic
refinement); with ``--psf shape`` the PSF's shape ``kappa`` (pillbox to Gaussian) is unknown
and profiled over a grid, its other parameters (diffraction, aberrations) still given.

The world is the benchmark's planes without the nuisances that an oracle would also have to be
told (breathing, misregistration, vignetting, frame gain jitter); noise, quantisation, PSF
draws and textures are the benchmark's. The shipped model is scored on the same frames.

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
from benchmarks.report import ROOT, machine, markdown_table, update_section
from data_synth import DefocusPairDataset
from data_synth.params import SynthConfig
from data_synth.psf import PSFModel
from tdfd import Camera
from tdfd.errors import InputError, ShapeError
from tdfd.model import DFDModel
from tdfd.optics.thin_lens import camera_sigmas
from training.config import EvalConfig

__all__ = ["CLEAN_WORLD", "tukey_window", "cross_residual_nll", "fit_plane", "plane_frames", "main"]

#: data_synth options that remove the nuisances an oracle would also have to be told.
CLEAN_WORLD = {"breathing_prob": 0.0, "shift_prob": 0.0, "vignetting_prob": 0.0, "frame_gain_jitter": 0.0}
#: The PSF shapes over which ``--psf shape`` profiles (``kappa = 1/beta``: 0 pillbox .. 0.5 Gaussian).
SHAPE_GRID: tuple[str | float, ...] = ("pillbox", 20.0, 10.0, 1 / 0.15, 5.0, 4.0, 1 / 0.3, 1 / 0.35, 2.5, 1 / 0.45,
                                       "gaussian")
Q_GRID = torch.arange(0.8, 3.6001, 0.01, dtype=torch.float64)  # 0.28-1.25 m
TAPER_FRACTION = 0.1
GROSS = 0.05  # a plane off by more than 5 % counts as a gross error


def tukey_window(height: int, width: int | None = None, fraction: float = TAPER_FRACTION,
                 dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """Separable Tukey taper ``(height, width)``: flat, with raised-cosine edges over
    ``fraction / 2`` of each side.

    Example:
        >>> w = tukey_window(40, 30, fraction=0.2)
        >>> tuple(w.shape), float(w[20, 15]), float(w[0, 15])
        ((40, 30), 1.0, 0.0)
    """
    if not 0.0 <= fraction <= 1.0:
        raise InputError(f"taper fraction must lie in [0, 1], got {fraction}")

    def one(size: int) -> torch.Tensor:
        w1 = torch.ones(size, dtype=dtype)
        edge = int(fraction * size / 2)
        if edge:
            n = torch.arange(edge, dtype=dtype)
            w1[:edge] = 0.5 * (1.0 - torch.cos(math.pi * n / edge))
            w1[size - edge:] = w1[:edge].flip(0)
        return w1

    return one(height)[:, None] * one(height if width is None else width)[None, :]


def _check_frames(y1: torch.Tensor, y2: torch.Tensor) -> None:
    if y1.ndim != 2 or y1.shape != y2.shape:
        raise ShapeError(f"frames must be two (H, W) of one shape, got {tuple(y1.shape)} and {tuple(y2.shape)}")


def cross_residual_nll(y1: torch.Tensor, y2: torch.Tensor, k1: torch.Tensor, k2: torch.Tensor, nu1: float,
                       nu2: float, band: float = 0.25, model_taper: bool = True) -> torch.Tensor:
    """Mean per-bin negative log-likelihood of each hypothesis (see the module docs).

    Args:
        y1, y2: ``(H, W)`` frames, linear in irradiance, black level removed (any gain).
        k1, k2: ``(Q, n, n)`` each hypothesis's PSFs of frame 1 and 2 (odd ``n``, unit sum).
        nu1, nu2: the frames' noise variances per pixel (units of ``y`` squared).
        band: upper edge of the band in cycles/px, in ``(0, 0.5]`` (the lowest bins, below
            1.5 cycles per residual, are left out).
        model_taper: divide by the tapered residual's expected periodogram (True) or by ``P``
            itself (a plain Whittle likelihood, biased by the taper's leakage).

    Returns:
        ``(Q,)`` float64; about 1 at the true hypothesis.
    """
    _check_frames(y1, y2)
    if k1.ndim != 3 or k1.shape != k2.shape or k1.shape[-1] != k1.shape[-2] or k1.shape[-1] % 2 == 0:
        raise ShapeError(f"kernels must be two (Q, n, n) stacks of odd n, got {tuple(k1.shape)} and {tuple(k2.shape)}")
    if not (0.0 < band <= 0.5):
        raise InputError(f"band must lie in (0, 0.5] cycles/px, got {band}")
    if not (nu1 > 0 and nu2 > 0 and math.isfinite(nu1) and math.isfinite(nu2)):
        raise InputError(f"noise variances must be finite and > 0, got {nu1}, {nu2}")
    h, w = y1.shape
    n = k1.shape[-1]
    if min(h, w) < 2 * n + 8:
        raise ShapeError(f"frames of {h}x{w} px are too small for {n}-px kernels")
    y1, y2, k1, k2 = (t.to(torch.float64) for t in (y1, y2, k1, k2))
    F1, F2 = torch.fft.rfft2(y1), torch.fft.rfft2(y2)

    def spectra(k: torch.Tensor, shape: tuple[int, int]) -> torch.Tensor:
        pad = torch.zeros(k.shape[0], *shape, dtype=torch.float64)
        pad[:, :n, :n] = k
        return torch.fft.rfft2(torch.roll(pad, (-(n // 2), -(n // 2)), (1, 2)))

    K1, K2 = spectra(k1, (h, w)), spectra(k2, (h, w))
    r = torch.fft.irfft2(K2 * F1[None] - K1 * F2[None], s=(h, w))  # circular; the valid part is linear
    half = n // 2
    v = r[:, half: h - half, half: w - half]
    mh, mw = v.shape[-2:]
    taper = tukey_window(mh, mw)
    taper = taper / float((taper ** 2).mean().sqrt())
    R = torch.fft.rfft2(v * taper)
    A1, A2 = (spectra(k, (mh, mw)).abs() ** 2 for k in (k1, k2))
    P = nu1 * A2 + nu2 * A1
    if model_taper:
        big = torch.fft.fft2(taper, s=(2 * mh, 2 * mw))
        acw = torch.fft.ifft2(big.abs() ** 2).real / (mh * mw)  # the taper's autocorrelation, 1 at lag 0
        ly, lx = (torch.fft.fftfreq(m, 1.0 / m).long() % (2 * m) for m in (mh, mw))
        cov = torch.fft.irfft2(P, s=(mh, mw))  # the residual's autocovariance: a kernel's support
        P = torch.fft.rfft2(cov * acw[ly][:, lx]).real
    fy = torch.fft.fftfreq(mh, dtype=torch.float64)[:, None]
    fx = torch.fft.rfftfreq(mw, dtype=torch.float64)[None, :]
    f = torch.sqrt(fy ** 2 + fx ** 2)
    inside = ((f > 1.5 / min(mh, mw)) & (f <= band)).to(torch.float64)
    weight = torch.full_like(f, 2.0)  # the half spectrum stands for both halves ...
    weight[:, 0] = 1.0  # ... but for its self-conjugate columns
    if mw % 2 == 0:
        weight[:, -1] = 1.0
    weight = weight * inside
    terms = R.abs() ** 2 / (mh * mw) / P.clamp_min(1e-300)
    return (terms * weight).sum((-1, -2)) / weight.sum()


def _argmin_parabolic(nll: torch.Tensor, grid: torch.Tensor) -> tuple[float, float]:
    i = int(nll.argmin().clamp(1, len(grid) - 2))
    a, b, c = (float(nll[j]) for j in (i - 1, i, i + 1))
    den = a - 2 * b + c
    off = max(-1.0, min(1.0, 0.5 * (a - c) / den)) if den > 0 else 0.0
    return float(grid[i]) + off * float(grid[1] - grid[0]), b


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
        q, value = _argmin_parabolic(nll, grid)
        if value < best[0]:
            best = (value, q, j)
    return best[1], best[2]


def plane_frames(sample: dict) -> tuple[torch.Tensor, torch.Tensor, float, float]:
    """A ``data_synth`` sample's frames with the black level removed, and each frame's noise
    variance at its mean level (:meth:`tdfd.sensor.SensorModel.expected_variance`)."""
    p = sample["params"]
    black = p["black_level_dn"] / (2.0 ** p["bits"] - 1.0)
    sensor, slope = sample_sensor(p)
    frames = [sample[k][0].to(torch.float64) - black for k in ("image_f1", "image_f2")]
    nus = [float(sensor.expected_variance(torch.tensor([float(y.mean()) / slope], dtype=torch.float64)))
           for y in frames]
    return frames[0], frames[1], nus[0], nus[1]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--samples", type=int, default=48, help="the refinement benchmark's first N samples")
    p.add_argument("--size", type=int, default=256, help="image side in px")
    p.add_argument("--psf", default="known,shape", help="comma list of: known, shape")
    p.add_argument("--band", type=float, default=0.25, help="the likelihood's band, cycles/px")
    p.add_argument("--model", default=str(ROOT / "models" / "reference"), help="model scored on the same frames")
    p.add_argument("--no-write", action="store_true", help="print only; leave docs/ alone")
    p.add_argument("--rows", default="", help="also write every plane's errors and bounds to this JSON file")
    args = p.parse_args(argv)
    modes = [m.strip() for m in args.psf.split(",") if m.strip()]
    if not modes or any(m not in ("known", "shape") for m in modes):
        p.error(f"--psf takes known and/or shape, got {args.psf!r}")
    torch.set_num_threads(2)
    camera = Camera.preset("reference")
    ev = EvalConfig(samples=args.samples, seed=BENCH_SEED, height=args.size, width=args.size)
    options = {**ev.options, **CLEAN_WORLD}
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
        y1, y2, nu1, nu2 = plane_frames(s)
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
        tiles = bench_tiles(DFDModel.load(args.model), args.samples, args.size, CLEAN_WORLD)
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
        plot(rows, [k for k in modes + ["refined"] if k in rows[0]], ROOT / "docs" / "plane_oracle.png")
        body += "\n\n![per-plane error against the per-plane bound](plane_oracle.png)"
        cmd = f".venv/bin/python -m benchmarks.bench_plane_oracle --samples {args.samples} --psf {args.psf}"
        update_section("plane_oracle", "The per-plane bound against an estimator that knows the physics (issue 19)",
                       body, cmd)
    return 0


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
        f"samples (seed {BENCH_SEED}, {args.size} px), the nuisances an oracle would also need told switched off "
        f"({', '.join(f'{k} = {v}' for k, v in CLEAN_WORLD.items())}); noise, quantisation, PSFs and textures as "
        f"drawn. Band {args.band} cycles/px; wall time {wall:.0f} s for the fits and bounds.",
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


def plot(rows: list[dict], keys: list[str], path: Path) -> None:
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
    ax.set_title("Planes of the refinement benchmark (nuisances off)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
