"""How accurate can any DFD estimator be on the refinement benchmark's planes? A Cramér-Rao bound.

Run from the repository root::

    .venv/bin/python -m benchmarks.bench_bound [--samples 256] [--model models/reference]

For every held-out plane of the ``refinement`` benchmark (same seed, same options, same
64/32 tile grid) it computes the Fisher information that the two noisy frames carry about
the plane's inverse depth ``q = 1/d``, and from it the Cramér-Rao lower bound on the depth
error of an unbiased estimator. The observation model, per 64x64 tile and spatial
frequency ``u`` (rectangular tile, circular blur, so that white noise is independent
across bins):

    G_i(u) = H_i(u; q) S(u) + N_i(u),   E|N_i(u)|^2 = nu_i = 64^2 var_i,   i = 1, 2,

with ``S`` the tile of the sharp scene as the sensor sees it (exposure and gain applied),
``H_i`` the optical transfer function of the sample's **own** PSF (shape, diffraction and
aberration as drawn, at the blur ``sigma_i(q)`` of paper eq. 4), and ``var_i`` the sensor's
variance (shot, read and quantisation noise, :meth:`tdfd.sensor.SensorModel.expected_variance`)
at the tile's mean level. The texture ``S(u)`` is unknown (a nuisance amplitude per bin, as
for any estimator that assumes nothing about the scene). Projecting it out gives, per bin,

    J(u) = 2 |S(u)|^2 (H1' H2 - H2' H1)^2 / (nu_2 H1^2 + nu_1 H2^2),   H' = dH/dq,

summed over the independent half of the spectrum. The bound on the relative depth error of
a tile is ``sqrt(1 / J) / q`` (a standard deviation); for a normal error its median
absolute value is 0.674 times that. Two versions:

* **per tile**: the information of one 64x64 tile (what a tile-local estimator can use);
* **per plane**: the information of the whole 256x256 plane (16 disjoint tiles summed),
  which bounds even an estimator that pools every tile of the plane, as a CNN with a wide
  receptive field may on fronto-parallel planes.

The bound is optimistic for every real estimator: it knows the PSF shape and the frames'
noise levels, ignores clipping of over-exposed highlights, vignetting, breathing and
misregistration, and uses no tile-boundary effects. Writes the ``bound`` section of
``docs/BENCHMARKS.md`` next to the refined model's measured errors on the same planes.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch
from tqdm import tqdm

from benchmarks.bench_refinement import BENCH_SEED, bench_tiles  # the refinement benchmark's planes
from benchmarks.report import ROOT, markdown_table, update_section
from data_synth import DefocusPairDataset
from data_synth.psf import PSFModel
from tdfd import Camera
from tdfd.errors import InputError
from tdfd.model import DFDModel
from tdfd.optics.thin_lens import camera_sigmas
from tdfd.sensor import SensorModel
from training.config import EvalConfig
from training.losses import depth_relative_error

__all__ = ["plane_information", "otf", "main"]

TILE, STRIDE = 64, 32
MEDIAN_ABS = 0.6745  # median |x| of a standard normal x
BINS = ((0.30, 0.40), (0.40, 0.50), (0.50, 0.60), (0.60, 0.70), (0.70, 0.80), (0.80, 0.90), (0.90, 1.00))


def psf_model(params: dict) -> PSFModel:
    """The :class:`~data_synth.psf.PSFModel` a ``data_synth`` sample was rendered with."""
    shape = params["psf_shape"]
    shape_v: str | float = float(params["psf_beta"]) if shape == "beta" else str(shape)
    return PSFModel(shape_v, float(params["diffraction_sigma_px"]), float(params["astigmatism"]),
                    float(params["astigmatism_angle"]), float(params["spherical"]))


def otf(model: PSFModel, sigma: float, size: int = TILE) -> torch.Tensor:
    """Optical transfer function ``(size, size)`` (complex; real for symmetric PSFs) of the
    PSF of signed blur ``sigma`` px, centred so that a delta PSF gives 1 everywhere."""
    k = model.kernels(torch.tensor([sigma], dtype=torch.float64))[0]
    n = k.shape[-1]
    if n > size:
        raise InputError(f"PSF of {n} px does not fit a {size} px tile")
    pad = torch.zeros(size, size, dtype=torch.float64)
    pad[:n, :n] = k
    pad = torch.roll(pad, (-(n // 2), -(n // 2)), (0, 1))  # kernel centre at pixel (0, 0)
    return torch.fft.fft2(pad)


def plane_information(camera: Camera, sharp: torch.Tensor, depth_m: float, params: dict,
                      dq: float = 1e-3) -> torch.Tensor:
    """Fisher information about ``q = 1/d`` (1/m^-2) of each tile of a fronto-parallel plane.

    Args:
        camera: the camera (blur per depth, eq. 4).
        sharp: the sharp radiance ``(H, W)`` of the plane (before the sensor).
        depth_m: the plane's distance.
        params: the sample's ``data_synth`` parameters (PSF, sensor, exposure).
        dq: finite-difference step of ``q`` in 1/m.

    Returns:
        ``(h, w)`` information of the 64/32 grid's tiles (``J`` in the module docs).
    """
    q = 1.0 / depth_m
    model = psf_model(params)
    sensor = SensorModel(full_well_e=params["full_well_e"], read_noise_e=params["read_noise_e"], bits=params["bits"],
                         black_level_dn=params["black_level_dn"], gain=params["gain"], exposure=params["exposure"])
    # output units per unit radiance (slope of the sensor's mean response, far from clipping)
    lo, hi = sensor.expected_mean(torch.tensor([0.0, 1e-3], dtype=torch.float64))
    scale = float(hi - lo) / 1e-3

    def otfs(qq: float) -> tuple[torch.Tensor, torch.Tensor]:
        s1, s2 = camera_sigmas(camera, 1.0 / qq)
        return otf(model, float(s1)), otf(model, float(s2))

    h1, h2 = otfs(q)
    p1, p2 = otfs(q + dq)
    m1, m2 = otfs(q - dq)
    d1, d2 = (p1 - m1) / (2 * dq), (p2 - m2) / (2 * dq)
    # per bin: |H1' H2 - H2' H1|^2 and the two noise weights (complex-safe form of the formula)
    cross = (d1 * h2 - d2 * h1).abs() ** 2
    a1, a2 = h1.abs() ** 2, h2.abs() ** 2
    x = sharp.double() * scale
    tiles = x.unfold(0, TILE, STRIDE).unfold(1, TILE, STRIDE)  # (h, w, T, T)
    mean = tiles.mean((-1, -2))
    var = sensor.expected_variance(mean / scale)  # output variance at the tile's mean level
    # frame 2 has the same mean level (blur keeps the mean); the two frames' noise is alike
    spec = torch.fft.fft2(tiles - mean[..., None, None]).abs() ** 2  # |S(u)|^2, DC removed
    nu = (TILE * TILE) * var
    info_bin = 2.0 * spec * cross / (nu[..., None, None] * (a1 + a2)).clamp_min(1e-300)
    return 0.5 * info_bin.sum((-1, -2))  # the spectrum of a real tile counts each bin twice


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--samples", type=int, default=256, help="textured planes (the refinement benchmark's first N)")
    p.add_argument("--size", type=int, default=256, help="image side in px")
    p.add_argument("--model", default=str(ROOT / "models" / "reference"), help="model whose errors are compared ('' none)")
    p.add_argument("--no-write", action="store_true", help="print only; leave docs/ alone")
    args = p.parse_args(argv)
    torch.set_num_threads(2)
    camera = Camera.preset("reference")
    ev = EvalConfig(samples=args.samples, seed=BENCH_SEED, height=args.size, width=args.size)
    ds = DefocusPairDataset(size=args.size, camera=camera, seed=BENCH_SEED, tile=TILE, stride=STRIDE,
                            return_sharp=True, **ev.options)
    t0 = time.perf_counter()
    rows = []  # per plane: depth, per-tile bounds (list), plane bound
    for i in tqdm(range(args.samples), desc="bound", mininterval=5.0):
        s = ds[i]
        prm = s["params"]
        if prm["layout"] != "plane":
            continue
        d = float(s["tile_depth"].median())
        info = plane_information(camera, s["sharp"][0], d, prm)
        tile_rel = (1.0 / info.clamp_min(1e-300).sqrt()) * d  # std of q / q = relative depth std
        # disjoint 64x64 tiles (every other grid cell) add up to the whole plane's information
        plane_rel = float((1.0 / info[::2, ::2].sum().sqrt()) * d)
        rows.append({"depth": d, "tiles": (MEDIAN_ABS * tile_rel).flatten(), "plane": MEDIAN_ABS * plane_rel})
    wall = time.perf_counter() - t0
    keep = [r for r in rows if 0.3 <= r["depth"] <= 1.0]
    all_tiles = torch.cat([r["tiles"] for r in keep])
    planes = torch.tensor([r["plane"] for r in keep])

    measured = None
    if args.model:
        measured = bench_tiles(DFDModel.load(args.model), args.samples, args.size)

    def pct(x: float) -> str:
        return f"{100 * x:.2f} %"

    table = []
    for lo, hi in BINS:
        sel = [r for r in keep if lo <= r["depth"] < hi or (hi == 1.0 and r["depth"] == 1.0)]
        if not sel:
            continue
        t = torch.cat([r["tiles"] for r in sel])
        pl = torch.tensor([r["plane"] for r in sel])
        row = [f"{lo:.2f}-{hi:.2f}", len(sel), pct(float(t.median())), f"{100 * float((t <= 0.01).double().mean()):.0f} %",
               pct(float(pl.median()))]
        if measured is not None:
            tr = measured["true"]
            m = (tr >= lo) & ((tr < hi) if hi < 1.0 else (tr <= hi))
            row += [pct(float(depth_relative_error(measured[k], tr)[m].median())) for k in ("refined", "analytic")]
        table.append(row)
    summary = {"planes": len(keep), "tiles": int(all_tiles.numel()),
               "tile_bound_median": float(all_tiles.median()), "tile_bound_share_le_1pct": float((all_tiles <= 0.01).double().mean()),
               "plane_bound_median": float(planes.median()), "plane_bound_share_le_1pct": float((planes <= 0.01).double().mean()),
               "wall_s": round(wall, 1)}
    if measured is not None:
        tr = measured["true"]
        m = (tr >= 0.3) & (tr <= 1.0)
        for k in ("refined", "analytic"):
            summary[f"{k}_median"] = float(depth_relative_error(measured[k], tr)[m].median())
    print(json.dumps(summary, indent=2))
    header = ["distance (m)", "planes", "bound per tile: median", "tiles whose bound <= 1 %", "bound per plane: median"]
    if measured is not None:
        header += ["refined, measured", "analytic, measured"]
    for row in table:
        print(" | ".join(str(v) for v in row))
    if args.no_write:
        return 0
    body = (
        f"The refinement benchmark's {len(keep)} held-out planes in 0.3-1.0 m ({summary['tiles']} tiles of 64 px, "
        f"first {args.samples} samples, seed {BENCH_SEED}, full realism; see `refinement`). For each plane the Fisher "
        "information that its two noisy frames carry about the inverse depth, with the sample's own PSF (shape, "
        "diffraction, aberration), the sensor's shot, read and quantisation noise at each tile's mean level, and the "
        "texture unknown per spatial frequency. Its Cramér-Rao bound, as a median absolute relative depth error "
        "(0.674 sigma), is what an unbiased estimator cannot beat; the bound is optimistic (the PSF shape and noise "
        "levels known; no clipping, vignetting, breathing or misregistration). *Per tile*: one 64x64 tile's "
        "information; *per plane*: the whole plane's (16 disjoint tiles), which bounds even an estimator that pools "
        "every tile of a fronto-parallel plane.\n\n"
        + markdown_table(header, table) + "\n\n"
        f"- Bound per tile, median over all tiles: **{pct(summary['tile_bound_median'])}**; tiles whose bound is at "
        f"most 1 %: {100 * summary['tile_bound_share_le_1pct']:.0f} %.\n"
        f"- Bound per plane, median over planes: **{pct(summary['plane_bound_median'])}**; planes whose bound is at "
        f"most 1 %: {100 * summary['plane_bound_share_le_1pct']:.0f} %.\n"
    )
    if measured is not None:
        body += (f"- Measured on the same tiles (`{Path(args.model).name}`): refined {pct(summary['refined_median'])}, "
                 f"analytic {pct(summary['analytic_median'])}.\n")
    body += f"\nWall time: {wall:.0f} s.\n"
    update_section("bound", "Information bound on the refinement benchmark (Cramér-Rao)", body,
                   f".venv/bin/python -m benchmarks.bench_bound --samples {args.samples}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
