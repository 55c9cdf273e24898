"""The README's picture: one synthetic scene, its DFD pair, and the depth tdfd recovers.

    python3 dev.py python -m benchmarks.overview_figure

Writes ``docs/overview.png``: the two frames at the reference camera's ECVFL powers, the
true depth, the analytic Fourier-ratio depth, the refined depth of the shipped ONNX model
(if ``models/reference.onnx`` exists) and its confidence, all on the contract's tile grid.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from data_synth import DefocusPairDataset
from tdfd import Camera
from tdfd.dfd import FourierRatioDFD

from .report import ROOT

FIGURE = ROOT / "docs" / "overview.png"


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--index", type=int, default=5)
    ap.add_argument("--model", type=Path, default=ROOT / "models" / "reference.onnx")
    args = ap.parse_args(argv)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cam = Camera.preset("reference")
    ds = DefocusPairDataset(size=(384, 512), camera=cam, seed=args.seed, layouts={"layout": 1.0},
                            illumination_prob=0.0, psf_shapes=["pillbox"],
                            families=["fractal", "voronoi", "bandlimited"])
    item = ds[args.index]
    i1, i2 = item["image_f1"][None], item["image_f2"][None]
    analytic, _ = FourierRatioDFD(cam, tile=64, stride=32)(i1, i2)
    true = item["depth"][0].numpy()
    rng = (0.95 * float(true.min()), 1.05 * float(true.max()))  # colour scale of every depth panel
    panels = [("image_f1 (P_e = +1.7 dpt)", i1[0, 0].numpy(), "gray", None),
              ("image_f2 (P_e = +2.7 dpt)", i2[0, 0].numpy(), "gray", None),
              ("true depth (m)", true, "viridis", rng),
              ("analytic depth (m)", analytic[0, 0].numpy(), "viridis", rng)]
    if args.model.exists():
        from tdfd.runtime import DepthRuntime

        r = DepthRuntime(str(args.model))(i1[0, 0].numpy(), i2[0, 0].numpy())
        panels += [("refined depth, ONNX (m)", np.asarray(r.depth).squeeze(), "viridis", rng),
                   ("confidence", np.asarray(r.confidence).squeeze(), "magma", (0, 1))]
    fig, axes = plt.subplots(2, 3, figsize=(13, 7.2))
    for ax, (title, img, cmap, rng) in zip(axes.flat, panels):
        im = ax.imshow(img, cmap=cmap, vmin=None if rng is None else rng[0], vmax=None if rng is None else rng[1])
        ax.set_title(title)
        ax.axis("off")
        if rng is not None:
            fig.colorbar(im, ax=ax, fraction=0.035)
    for ax in list(axes.flat)[len(panels):]:
        ax.axis("off")
    fig.suptitle("tdfd: depth from two frames at two lens powers (reference camera, synthetic scene, pillbox optics, sensor noise)")
    fig.tight_layout()
    FIGURE.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(FIGURE, dpi=90)
    print(f"wrote {FIGURE}")


if __name__ == "__main__":
    main()
