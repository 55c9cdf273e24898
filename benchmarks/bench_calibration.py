"""Camera calibration from captures on the simulated bench (issue 18), over several scenes.

::

    .venv/bin/python -m benchmarks.bench_calibration [--seeds 5] [--size 384]

A camera that is no preset (16 mm fixed lens, 3.45 um pixels, 1.6 mm aperture, ECVFL pair
1.5/2.5 dpt) whose true mu is 15 % above the datasheet value, whose ECVFL reads 0.3 dpt
low (real power = commanded + 0.3) and which breathes by 0.4 % per dioptre; the nominal
JSON knows none of that. For each seed (a new dead-leaves scene and noise):

* self-calibration: ``tdfd capture --sim`` sweep 0..3.5 dpt in 0.25 dpt steps plus one
  pair, of three planes at 0.5, 0.4 and 0.7 m (one folder each, no distance recorded),
  calibrated together (``tdfd calibrate DIR1 DIR2 DIR3``): one scene leaves a K error of
  1-2 % that shows at the range ends;
* known distances: one pair each at 0.32, 0.4, 0.5, 0.65 and 0.9 m, distances recorded
  (three pairs, at 0.35, 0.5 and 0.8 m, left a K error of 0.6-0.9 %);

then each calibrated camera (and the true one, "oracle") predicts the in-focus power from one fresh pair (analytic
estimator, breathing registered) at 0.3 ... 1.0 m; the error against the true commanded
in-focus power is reported (target: 0.03 dpt), with the errors of K (= mu A d_s / 2) and
of the breathing (target 10 %).
"""

from __future__ import annotations

import argparse
import logging
import tempfile
import time
from pathlib import Path

import numpy as np

from tdfd import Camera
from tdfd.calibration import calibrate_known_distance, calibrate_self, in_focus_power_from_pair
from tdfd.calibration.measure import PREDICTION_REGION_PX
from tdfd.camera_file import CameraFile
from tdfd.capture import capture_session, read_folder
from tdfd.capture.sim import SimulatedRig

from .report import markdown_table, update_section

__all__ = ["main", "run"]

PITCH = 3.45e-6
NOMINAL = Camera(aperture_m=1.6e-3, sensor_distance_m=16e-3, fixed_focal_length_m=16e-3, lens_powers_dpt=(1.5, 2.5),
                 pixel_pitch_m=PITCH, depth_range_m=(0.3, 1.0), mu_px_per_m=1 / (2 * PITCH), name="nominal")
TRUE = CameraFile(NOMINAL.replace(mu_px_per_m=1.15 / (2 * PITCH)), magnification_per_dpt=0.004, ecvfl_offset_dpt=0.3)
DISTANCES = (0.3, 0.35, 0.45, 0.6, 0.8, 0.95, 1.0)
#: the self-calibration's scenes (planes, distance not recorded), one capture folder each
SELF_SCENES_M = (0.5, 0.4, 0.7)
#: the known-distance route's pairs (distance recorded): five across the range
KNOWN_SCENES_M = (0.32, 0.4, 0.5, 0.65, 0.9)


#: the true camera as a calibration would ideally write it (offset folded into f0).
ORACLE = CameraFile(TRUE.camera.replace(fixed_focal_length_m=1 / (TRUE.camera.fixed_power_dpt + TRUE.ecvfl_offset_dpt)),
                    magnification_per_dpt=TRUE.magnification_per_dpt)


def _errors(cal: CameraFile, size: int, seed: int, region: int = PREDICTION_REGION_PX) -> tuple[list[float], list[float]]:
    """In-focus power error (dpt) and relative metric depth error of one fresh pair per
    distance, with camera ``cal`` (estimator regions of ``region`` px)."""
    out, depth = [], []
    for i, d in enumerate(DISTANCES):
        rig = SimulatedRig(TRUE, d, size=(size, size), seed=1000 * seed + 100 + i)
        (f1, _), (f2, _) = rig.capture(1.5), rig.capture(2.5)
        p = in_focus_power_from_pair(cal.camera, f1 / 4095, f2 / 4095, 1.5, 2.5, region=region,
                                     magnification_per_dpt=cal.magnification_per_dpt)
        out.append(p - rig.in_focus_command_dpt())
        depth.append(1.0 / (p + cal.camera.fixed_power_dpt - 1.0 / cal.camera.sensor_distance_m) / d - 1.0)
    return out, depth


def run(seeds: int, size: int) -> list[dict]:
    k_true = TRUE.camera.mu_px_per_m * TRUE.camera.blur_scale_m_dpt
    rows = []
    for seed in range(1, seeds + 1):
        errs, derr = _errors(ORACLE, size, seed)
        rows.append({"seed": seed, "route": "oracle (true camera)", "k_err": 0.0, "m": 0.004, "offset": float("nan"),
                     "errs": errs, "depth_errs": derr, "time_s": 0.0})
        print(f"seed {seed} oracle          in-focus errors {np.round(errs, 4).tolist()}", flush=True)
        errs64, derr64 = _errors(ORACLE, size, seed, region=64)
        rows.append({"seed": seed, "route": "oracle, 64-px regions", "k_err": 0.0, "m": 0.004, "offset": float("nan"),
                     "errs": errs64, "depth_errs": derr64, "time_s": 0.0})
        print(f"seed {seed} oracle (64 px)  in-focus errors {np.round(errs64, 4).tolist()}", flush=True)
        with tempfile.TemporaryDirectory() as tmp:
            root = Path(tmp)
            for i, d in enumerate(SELF_SCENES_M):  # one folder per scene, no distance recorded
                capture_session(SimulatedRig(TRUE, d, size=(size, size), seed=seed + 10 * i), root / f"self{i}",
                                sweep=list(np.arange(0.0, 3.51, 0.25)), pairs=[(1.5, 2.5)])
            for i, d in enumerate(KNOWN_SCENES_M):
                capture_session(SimulatedRig(TRUE, d, size=(size, size), seed=100 * seed + i), root / "known",
                                pairs=[(1.5, 2.5)], distance_m=d, prefix=f"d{i}_")
            routes = (("self", calibrate_self, [f"self{i}" for i in range(len(SELF_SCENES_M))]),
                      ("known-distance", calibrate_known_distance, ["known"]))
            for route, fn, folders in routes:
                t0 = time.perf_counter()
                r = fn([f for folder in folders for f in read_folder(root / folder)], CameraFile(NOMINAL))
                dt = time.perf_counter() - t0
                errs, derr = _errors(r.camera_file, size, seed)
                row = {"seed": seed, "route": route, "k_err": r.k_px_per_dpt / k_true - 1,
                       "m": r.magnification_per_dpt, "offset": r.in_focus_offset_dpt, "errs": errs,
                       "depth_errs": derr, "time_s": dt}
                rows.append(row)
                print(f"seed {seed} {route:15s} K {100 * row['k_err']:+.2f} %  m {100 * row['m']:.3f} %/dpt  "
                      f"B {row['offset']:+.4f} dpt  in-focus errors {np.round(errs, 4).tolist()}  ({dt:.1f} s)", flush=True)
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--size", type=int, default=384)
    ap.add_argument("--no-write", action="store_true", help="print only; leave docs/BENCHMARKS.md alone")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.ERROR)
    rows = run(args.seeds, args.size)
    table = []
    for route in ("oracle, 64-px regions", "oracle (true camera)", "self", "known-distance"):
        rs = [r for r in rows if r["route"] == route]
        errs = np.abs(np.array([r["errs"] for r in rs]))
        m_err = np.abs(np.array([r["m"] for r in rs]) / 0.004 - 1)
        k_err = np.abs(np.array([r["k_err"] for r in rs]))
        derr = np.abs(np.array([r["depth_errs"] for r in rs]))
        table.append([route, f"{100 * np.median(k_err):.2f} / {100 * k_err.max():.2f}",
                      f"{100 * np.median(m_err):.1f} / {100 * m_err.max():.1f}",
                      f"{np.median(errs):.4f} / {errs.max():.4f}",
                      f"{np.mean(errs <= 0.03):.0%}", f"{100 * np.median(derr):.2f} / {100 * derr.max():.2f}",
                      f"{np.median([r['time_s'] for r in rs]):.1f}"])
    body = markdown_table(["route", "K error % (abs, median / max)", "breathing error % (abs, median / max)",
                           "in-focus error dpt (abs, median / max)", "pairs within 0.03 dpt", "depth error % (abs, median / max)", "fit time s"], table)
    body += (f"\n\n{args.seeds} calibrations (seeds 1..{args.seeds}; dead-leaves planes; self-calibration from three "
             f"scene folders at {', '.join(map(str, SELF_SCENES_M))} m, known distances from pairs at {', '.join(map(str, KNOWN_SCENES_M))} m), "
             f"{args.size}x{args.size} frames, "
             f"in-focus power from one pair at {', '.join(map(str, DISTANCES))} m each. Targets (issue 18): "
             "in-focus power within 0.03 dpt, breathing within 10 %. The known-distance route also recovers "
             "the 0.3 dpt ECVFL offset (in-focus offset B); self-calibration takes B from the datasheet and says so (hence its metric depth error: the 0.3 dpt offset it cannot see). "
             "The oracle rows use the true camera: the estimator's own single-pair error, which no calibration removes; "
             f"predictions use {PREDICTION_REGION_PX}-px regions (`PREDICTION_REGION_PX`), the first row 64-px regions, "
             "whose error grows with the pair's larger blur (3.3-3.8 px at 0.8-1.0 m) and misses 0.03 dpt there.\n")
    b = np.array([r["offset"] for r in rows if r["route"] == "known-distance"])
    body += (f"\nIn-focus offset B from the known-distance route (true -0.300 dpt: the 0.3 dpt ECVFL offset): "
             f"median {np.median(b):+.4f}, worst {b[np.argmax(np.abs(b + 0.3))]:+.4f} dpt.\n")
    print(body)
    if not args.no_write:
        update_section("calibration", "Camera calibration from captures (simulated bench)", body,
                       f".venv/bin/python -m benchmarks.bench_calibration --seeds {args.seeds} --size {args.size}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
