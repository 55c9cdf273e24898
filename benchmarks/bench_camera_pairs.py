"""Any varying camera parameter: analytic Fourier-ratio DFD accuracy for an ECVFL pair (the
reference camera), an aperture pair (Pentland) and a sensor-distance pair (the paper's remark
after eq. 13), on noise-free Gaussian renders of textured planes in moderate blur.

Run from the repository root:

    python3 dev.py python -m benchmarks.bench_camera_pairs

Prints the tables and writes the ``camera-pairs`` section of docs/BENCHMARKS.md.
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from tdfd import Camera
from tdfd.breathing import magnify
from tdfd.dfd import FourierRatioDFD, register_sensor_pair
from tdfd.forward import defocus_pair
from tdfd.optics import camera_sigmas
from tdfd.textures import fractal

from .report import markdown_table, update_section

#: Depth grid (m); "moderate blur" keeps the depths where both |sigma| <= 2 px.
GRID = [round(0.30 + 0.02 * i, 2) for i in range(36)]
MODERATE_PX = 2.0

REF = Camera.preset("reference")
CAMERAS = {
    "ECVFL pair (reference: 1.7 / 2.7 dpt)": REF,
    "aperture pair (A = 1.0 / 0.5 mm, focus at infinity)":
        REF.replace(aperture_m=1e-3, apertures_m=(1e-3, 0.5e-3), lens_powers_dpt=(0.0, 0.0), name="aperture-pair"),
    "sensor-distance pair (d_s = 25.0 / 25.5 mm, 2.2 dpt)":
        REF.replace(lens_powers_dpt=(2.2, 2.2), sensor_distances_m=(0.025, 0.0255), name="sensor-pair"),
}


def pink_texture(n: int, batch: int, generator: torch.Generator) -> torch.Tensor:
    """1/f noise texture in [0.2, 0.8], ``(batch, 1, n, n)``."""
    return 0.2 + 0.6 * fractal(n, generator, batch, beta=2.0)


def moderate_depths(camera: Camera) -> list[float]:
    return [d for d in GRID if max(abs(float(s)) for s in camera_sigmas(camera, d)) <= MODERATE_PX]


def errors(camera: Camera, depths: list[float], scenes: int, size: int, seed: int, magnified: bool = False,
           registered: bool = True) -> dict[float, np.ndarray]:
    """Per depth, the absolute relative depth errors of all 64-px tiles (WLS estimator).

    ``magnified``: frame 2 scaled by ``d_s2/d_s1`` as a sensor-distance camera takes it
    (the renderer works on frame 1's grid); ``registered``: :func:`register_sensor_pair`
    before the estimator.
    """
    m = FourierRatioDFD(camera, tile=64, stride=64)
    out = {}
    for d in depths:
        g = torch.Generator().manual_seed(seed + int(d * 1000))
        x = pink_texture(size, scenes, g)
        pair = defocus_pair(camera, x, torch.full_like(x, d))
        i1, i2 = pair[:, 0:1].clamp(0, 1), pair[:, 1:2]
        if magnified:
            i2 = torch.from_numpy(magnify(i2.double().numpy(), camera.image_scale_ratio)).to(i1.dtype)
        if registered:
            i2 = register_sensor_pair(i2, camera)
        depth, _ = m(i1, i2.clamp(0, 1))
        out[d] = ((depth - d).abs() / d).flatten().numpy()
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--scenes", type=int, default=4, help="textures per distance")
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-write", action="store_true")
    args = ap.parse_args(argv)
    torch.set_num_threads(2)
    runs = []
    for label, cam in CAMERAS.items():
        runs.append((label, cam, {}))
        if cam.image_scale_ratio != 1.0:
            runs.append((f"{label}, frame 2 magnified {cam.image_scale_ratio:.3f}x, registered", cam,
                         {"magnified": True}))
            runs.append((f"{label}, frame 2 magnified, not registered", cam, {"magnified": True, "registered": False}))
    rows = []
    for label, cam, kw in runs:
        depths = moderate_depths(cam)
        err = errors(cam, depths, args.scenes, args.size, args.seed, **kw)
        per_depth = [float(np.median(e)) for e in err.values()]
        rows.append([label, f"{depths[0]:.2f}-{depths[-1]:.2f} ({len(depths)})",
                     f"{100 * float(np.median(np.concatenate(list(err.values())))):.2f}",
                     f"{100 * max(per_depth):.2f}"])
        print(rows[-1], flush=True)
    table = markdown_table(["camera", "moderate-blur depths, m (count)", "median abs rel err %",
                            "worst depth's median %"], rows)
    print(table)
    body = (
        "The analytic estimator for any varying camera parameter: eq. 4 with the subscript where the\n"
        "parameter varies, `sigma_i = mu (A_i/2) d_s,i (1/F_i - 1/d_o - 1/d_s,i)`, and the depth solve\n"
        "of `sigma1^2 - sigma2^2` generalised (a quadratic in 1/d_o for sensor-distance and aperture\n"
        "pairs, root on the working range's side). Noise-free renders (`tdfd.forward.defocus_pair`) of\n"
        f"1/f-textured planes with the Gaussian PSF, {args.scenes} textures of {args.size}x{args.size} px per\n"
        f"distance, depths every 2 cm over 0.30-1.00 m where both |sigma| <= {MODERATE_PX:g} px (moderate blur), 64-px\n"
        "tiles, WLS estimator; median over all tiles of all those depths (target <= 1 %).\n"
        "The renderer renders both frames on frame 1's pixel grid; a sensor-distance camera's frame 2\n"
        "is really `d_s2/d_s1` larger: the magnified rows scale it so (`tdfd.breathing.magnify`) and\n"
        "either register it back (`tdfd.dfd.register_sensor_pair`) or not.\n\n"
        f"{table}\n")
    if not args.no_write:
        update_section("camera-pairs", "Camera pairs: ECVFL, aperture and sensor-distance pairs (analytic)", body,
                       "python3 dev.py python -m benchmarks.bench_camera_pairs")


if __name__ == "__main__":
    main()
