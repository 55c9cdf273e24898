"""The lens's PSF family measured from a focus sweep (issue 20), on the simulated bench.

::

    .venv/bin/python -m benchmarks.bench_psf_family [--seeds 4] [--no-doc]

For each seed (a new chart and sensor noise) and each simulated optics (Gaussian, pillbox),
a 9-frame focus sweep of a target at 0.5 m spanning +-3 px of blur, reference camera, 256x320
frames (``tdfd.capture.sim.SimulatedRig``: 12-bit sensor, noise on), measured by
``tdfd.calibration.psf_family.psf_family_from_frames`` as ``tdfd calibrate`` measures it:

* on a band-limited random-noise chart (what ``--psf-family calibrate`` sweeps) and on a
  dead-leaves scene;
* as shipped: the Gaussian family's scale 1 (the calibrated ``mu`` is the Gaussian relative
  blur's), the disk's fitted and refined on the frames at least 1 px from focus;
* with the Gaussian's scale fitted too (``fixed_gaussian_scale=False``);
* with both scales fitted on all frames only (the pixel grid's own blur near focus biases them).

Prints per configuration the family named (right / wrong / undecided), the other family's
cost ratio and the true family's scale (truth 1), and writes section ``psf_family`` of
docs/BENCHMARKS.md.
"""

from __future__ import annotations

import argparse
import contextlib
import sys
import time
from unittest import mock

import numpy as np

from tdfd import Camera
from tdfd.autofocus.evidence import sigma_px_per_dpt
from tdfd.autofocus.sim import DEFAULT_READOUT_HW
from tdfd.autofocus.sim.psf_calibration import SWEEP_FRAMES, SWEEP_HALF_SPAN_PX
from tdfd.calibration import psf_family as pf
from tdfd.camera_file import CameraFile
from tdfd.capture.sim import SimulatedRig

from .report import markdown_table, update_section

__all__ = ["main"]

CAM = Camera.preset("reference")
FAMILIES = ("gaussian", "pillbox")
#: (label, fixed_gaussian_scale, a replacement scale fit or None)
VARIANTS = (("shipped (Gaussian scale 1, disk's refined far from focus)", True, None),
            ("Gaussian scale fitted too", False, None),
            ("scales fitted on all frames only", False, "all"))
HEADER = ["chart", "optics", "scale fit", "named right / wrong / undecided", "other family's cost ratio min / max",
          "true family's scale min / max"]


def _sweep(psf: str, seed: int, texture: str) -> list:
    rig = SimulatedRig(CameraFile(CAM), 0.5, size=DEFAULT_READOUT_HW, seed=seed, texture=texture, psf=psf)
    centre, half = rig.in_focus_command_dpt(), SWEEP_HALF_SPAN_PX / sigma_px_per_dpt(CAM)
    frames = []
    for p in np.linspace(centre - half, centre + half, SWEEP_FRAMES):
        raw, meta = rig.capture(float(p))
        frames.append((raw.astype(np.float64) / meta["white_level"], float(p)))
    return frames


def _all_frames_scale(search, roi, family, frames, m):  # the scale fit without its far-frame refinement
    coarse = min(pf.SCALE_GRID, key=lambda c: search(roi, family, c).cost)
    return float(min(coarse * pf.SCALE_GRID ** 0.125, key=lambda c: search(roi, family, c).cost))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, default=4, help="charts (seeds 0..N-1) per configuration (default 4)")
    ap.add_argument("--no-doc", action="store_true", help="do not write docs/BENCHMARKS.md")
    args = ap.parse_args(argv)
    if args.seeds < 1:
        ap.error(f"--seeds must be at least 1, got {args.seeds}")
    t0 = time.perf_counter()
    rows = []
    for texture in ("bandlimited", "dead_leaves"):
        for psf in FAMILIES:
            sweeps = [_sweep(psf, seed, texture) for seed in range(args.seeds)]
            for label, fixed, patch in VARIANTS:
                fits = []
                for frames in sweeps:
                    with mock.patch.object(pf, "_fit_scale", _all_frames_scale) if patch else contextlib.nullcontext():
                        fits.append(pf.psf_family_from_frames([frames], CAM, region=128, fixed_gaussian_scale=fixed))
                right = sum(f.family == psf for f in fits)
                wrong = sum(f.family not in (None, psf) for f in fits)
                ratios = [f.cost_ratio for f in fits if np.isfinite(f.cost_ratio)]
                scales = [f.sigma_scale[psf] for f in fits if f.sigma_scale]
                rows.append([texture, psf, label, f"{right} / {wrong} / {len(fits) - right - wrong}",
                             f"{min(ratios):.2f} / {max(ratios):.2f}" if ratios else "-",
                             f"{min(scales):.3f} / {max(scales):.3f}" if scales else "-"])
                print(" | ".join(rows[-1]), flush=True)
    table = markdown_table(HEADER, rows)
    wall = time.perf_counter() - t0
    body = f"""
Reference camera, 256x320 frames, a target at 0.5 m; per row {args.seeds} charts (seeds 0-{args.seeds - 1}, each
with its own sensor noise), a {SWEEP_FRAMES}-frame focus sweep over +-{SWEEP_HALF_SPAN_PX:g} px of blur
(`tdfd.capture.sim.SimulatedRig`, 12-bit, noise on), measured by
`tdfd.calibration.psf_family.psf_family_from_frames` (128-px regions, a family named at
{pf.MIN_FAMILY_RATIO:g}x and a majority of regions). "Scale fit": as shipped (the Gaussian's scale 1, the
disk's refined on the frames at least {pf.SCALE_MIN_BLUR_PX:g} px from focus), with the Gaussian's fitted
too, or both fitted on all frames only (ablations). The true scale is 1.

{table}

Wall time: {wall:.0f} s.
"""
    print(f"wall {wall:.0f} s")
    if not args.no_doc:
        update_section("psf_family", "The lens's PSF family from a focus sweep (simulated bench)", body,
                       ".venv/bin/python -m benchmarks.bench_psf_family")
        print("wrote the psf_family section of docs/BENCHMARKS.md")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
