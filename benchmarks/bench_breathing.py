"""Benchmark of focus-breathing registration: refined depth error with and without breathing.

Run from the repository root::

    nice -n 5 .venv/bin/python -m benchmarks.bench_breathing [--model models/reference] [--planes 16] [--size 960 1280]

Scenes: held-out fronto-parallel textured planes through the forward model
(:class:`tdfd.forward.DFDForward`): every textured family of :mod:`tdfd.textures`, depth
uniform in inverse depth over the camera's working range, Gaussian or pillbox PSF
(alternating), Poisson-Gaussian 12-bit sensor; seeds from :data:`BENCH_SEED`, which no
training run uses. Each plane is rendered twice with the same scene and the same sensor
noise: without breathing, and with frame 2 magnified by ``1 + breathing`` (default 0.5 %)
relative to frame 1 about the image centre (:func:`tdfd.warp.misregister`). Three
conditions on the same model weights:

1. no breathing, the model without registration;
2. breathing, the model without registration (what a camera file's breathing cost before);
3. breathing, the model registering the camera's ``magnification_per_dpt`` (the ``m`` with
   ``(1 + m P2) / (1 + m P1) = 1 + breathing``; what ``python -m export --camera FILE`` ships).

Errors are medians of ``|d - d_true| / d_true`` over all 64-px tiles (stride 32). Writes the
``breathing`` section of ``docs/BENCHMARKS.md``.
"""

from __future__ import annotations

import argparse
import sys
import time

import torch

from benchmarks.report import ROOT, markdown_table, update_section
from tdfd.forward import Defocus, DFDForward
from tdfd.model import DFDModel
from tdfd.sensor import SensorModel
from tdfd.textures import TEXTURE_FAMILIES, random_texture

#: first seed of the benchmark's planes (no training run uses seeds near it)
BENCH_SEED = 18_180_000
#: texture families with detail (``flat`` and ``gradient`` give no defocus cue)
FAMILIES = tuple(f for f in TEXTURE_FAMILIES if f not in ("flat", "gradient"))


def magnification_per_dpt(breathing: float, powers: tuple[float, float]) -> float:
    """``m`` such that ``(1 + m P2) / (1 + m P1) = 1 + breathing``."""
    p1, p2 = powers
    return breathing / (p2 - (1.0 + breathing) * p1)


def render(camera, index: int, height: int, width: int, breathing: float) -> tuple[torch.Tensor, float]:
    """Plane ``index``: frames ``(1, 2, H, W)`` float32 and its depth (m)."""
    g = torch.Generator().manual_seed(BENCH_SEED + index)
    tex, _ = random_texture(g, (height, width), families=FAMILIES, albedo=(0.4, 0.95), contrast=(0.2, 1.0))
    near, far = camera.depth_range_m
    q = 1.0 / far + float(torch.rand(1, generator=g, dtype=torch.float64)) * (1.0 / near - 1.0 / far)
    depth = 1.0 / q
    psf = ("gaussian", "pillbox")[index % 2]
    sensor = SensorModel(full_well_e=10000.0, read_noise_e=5.0, bits=12, black_level_dn=0.0)
    fwd = DFDForward(Defocus(camera, psf=psf), sensor)
    noise = torch.Generator().manual_seed(BENCH_SEED + 500_000 + index)  # the same noise in every condition
    with torch.no_grad():
        frames = fwd(tex.double(), torch.full((1, 1, height, width), depth, dtype=torch.float64),
                     breathing=breathing, generator=noise)
    return frames.float(), depth


def errors(model: DFDModel, frames: list[torch.Tensor], depths: list[float]) -> dict[str, float]:
    """Median relative errors (refined, analytic) over all tiles of all planes."""
    ref, ana = [], []
    with torch.no_grad():
        for f, d in zip(frames, depths):
            depth, _, depth_a = model(f[:, 0:1], f[:, 1:2])[:3]
            ref.append(((depth - d).abs() / d).flatten())
            ana.append(((depth_a - d).abs() / d).flatten())
    return {"refined": float(torch.cat(ref).median()), "analytic": float(torch.cat(ana).median())}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--model", default=str(ROOT / "models" / "reference"), help="model path stem")
    p.add_argument("--planes", type=int, default=16, help="textured planes")
    p.add_argument("--size", type=int, nargs=2, default=(960, 1280), metavar=("H", "W"), help="frame size in px")
    p.add_argument("--breathing", type=float, default=0.005, help="relative magnification of frame 2 (0.005: 0.5 %%)")
    p.add_argument("--no-write", action="store_true", help="print only; leave docs/ alone")
    args = p.parse_args(argv)
    torch.set_num_threads(1)  # small tensors; immune to other load on the 2 cores
    t0 = time.perf_counter()
    model = DFDModel.load(args.model).eval().set_validate(False)
    cam = model.camera
    m = magnification_per_dpt(args.breathing, cam.lens_powers_dpt)
    h, w = args.size
    clean, breathed, depths = [], [], []
    for i in range(args.planes):
        f0, d = render(cam, i, h, w, 0.0)
        f1, _ = render(cam, i, h, w, args.breathing)
        clean.append(f0)
        breathed.append(f1)
        depths.append(d)
    model.set_breathing(0.0)
    base = errors(model, clean, depths)
    raw = errors(model, breathed, depths)
    model.set_breathing(m)
    reg = errors(model, breathed, depths)
    wall = time.perf_counter() - t0
    pct = lambda v: f"{100 * v:.2f} %"  # noqa: E731
    rows = [["no breathing", "none", pct(base["analytic"]), pct(base["refined"]), "1.00x"],
            [f"{100 * args.breathing:g} % breathing", "none", pct(raw["analytic"]), pct(raw["refined"]),
             f"{raw['refined'] / base['refined']:.2f}x"],
            [f"{100 * args.breathing:g} % breathing", f"m = {m:.5f} /dpt", pct(reg["analytic"]), pct(reg["refined"]),
             f"{reg['refined'] / base['refined']:.2f}x"]]
    table = markdown_table(["frames", "registration in the model", "analytic median error", "refined median error",
                            "refined vs no breathing"], rows)
    ratio = reg["refined"] / base["refined"]
    print(table)
    print(f"target: refined error with registered breathing within 1.2x of no breathing: {ratio:.2f}x "
          f"({'met' if ratio <= 1.2 else 'NOT met'}); {wall:.0f} s")
    if not args.no_write:
        model_name = args.model.replace(str(ROOT) + "/", "")
        body = (f"Model `{model_name}`, {args.planes} held-out fronto-parallel textured planes of {h}x{w} px "
                f"(forward model, seeds from {BENCH_SEED}; families {', '.join(FAMILIES)}; depth uniform in inverse "
                f"depth over {cam.depth_range_m[0]}-{cam.depth_range_m[1]} m; Gaussian and pillbox PSFs alternating; "
                "10 000 e- / 5 e- read noise, 12-bit sensor). Each plane rendered with the same scene and sensor "
                f"noise without breathing and with frame 2 magnified by {100 * args.breathing:g} % relative to frame 1 "
                "about the image centre. Registration: the model's breathing stage (`tdfd/registration.py`, "
                "both frames brought to their common scale by moving whole pixels before the analytic "
                "features), with the camera's magnification per dioptre as `python -m export --camera FILE` ships "
                "it. Errors: medians of |d - d_true| / d_true over all 64-px tiles (stride 32).\n\n"
                f"{table}\n\n"
                f"Target (issue 18): refined error with 0.5 % breathing within 1.2x of the error without: "
                f"**{ratio:.2f}x** ({'met' if ratio <= 1.2 else 'not met'}). Run time {wall:.0f} s.\n\n"
                "Notes (2026-11-24, reference model of that day): registering by separable Lanczos-6 interpolation "
                "instead of whole pixels made it worse, 1.45x at 480x640 (32 planes; unregistered 1.05x): any "
                "interpolator lowers the sensor noise near Nyquist by a position-dependent amount, and the "
                "estimator's noise model assumes white noise (on noise-free frames Lanczos registration did restore "
                "the analytic error, 2.44 % -> 1.80 % vs 1.78 % without breathing). Whole pixels at 480x640: 1.04x. "
                "On these planes the shipped model, trained with up to 1 % random breathing, loses little to "
                "unregistered breathing (1.06x); the issue's 'about 1.6x' was not reproduced here.")
        cmd = "nice -n 5 .venv/bin/python -m benchmarks.bench_breathing" + (
            f" --planes {args.planes}" if args.planes != 16 else "")
        update_section("breathing", "Focus-breathing registration (issue 18)", body, cmd)
    return 0


if __name__ == "__main__":
    sys.exit(main())
