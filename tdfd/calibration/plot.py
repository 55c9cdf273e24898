"""The calibration fit as a picture (matplotlib PNG), so a person can judge it at a glance.

Three panels: the sharpness curves of the sweep with each region's fitted in-focus power
(self-calibration) or the pairs' blur differences against inverse distance with the
fitted line (known distances); the blur-difference model against the measurements; the
breathing fit (log magnification against power difference). :func:`plot_psf_model` draws the
PSF a sweep measured (``tdfd calibrate --psf-model``) beside the Gaussian of the same blur.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from .fit import CalibrationResult

__all__ = ["plot_calibration", "plot_psf_model", "PSF_PLOT_BLURS_PX"]

#: the camera's blurs (px) at which :func:`plot_psf_model` draws the kernels
PSF_PLOT_BLURS_PX = (-3.0, -2.0, -1.0, 1.0, 2.0, 3.0)


def plot_calibration(result: CalibrationResult, path: str | os.PathLike) -> Path:
    """Write the fit plot PNG to ``path`` and return it."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    d = result.plot_data
    fig, ax = plt.subplots(1, 3, figsize=(15, 4.6))
    if result.route == "self":
        powers, logf, _ = d["sweeps"][0]
        fitted = d["fitted_peaks"][0]
        rows, cols = logf.shape[1:]
        for i in range(rows):
            for j in range(cols):
                if np.isfinite(fitted[i, j]):
                    line, = ax[0].plot(powers, logf[:, i, j] - logf[:, i, j].max(), ".-", lw=0.8, ms=3)
                    ax[0].axvline(fitted[i, j], color=line.get_color(), lw=0.6, ls=":")
        ax[0].set_xlabel("ECVFL power (dpt)")
        ax[0].set_ylabel("log sharpness (relative to peak)")
        ax[0].set_title(f"focus sweep ({d['labels'][0]}): regions and fitted peaks")
        x, y = d["x_def"], d["d_over_dp"]
        xs = np.linspace(min(x.min(), 0), max(x.max(), 0), 50)
        ax[1].plot(x, y, ".", ms=4, label="pairs (per region)")
        ax[1].plot(xs, 2 * d["a2"] * xs, "k-", lw=1, label=f"fit: K = {result.k_px_per_dpt:.4g} px/dpt")
        ax[1].set_xlabel("pair midpoint - in-focus power (dpt)")
        ax[1].set_ylabel("D / (P_a - P_b)  (px^2/dpt)")
    else:
        x, y = d["inv_d"], d["y"]
        mid = (d["pa"] + d["pb"]) / 2
        ax[0].plot(x, y, "o", label="pairs (median over regions)")
        xs = np.linspace(x.min() * 0.9, x.max() * 1.1, 50)
        ax[0].plot(xs, d["a2"] * (2 * np.mean(mid) - 2 * (xs + d["b"])), "k-", lw=1,
                   label=f"fit: K = {result.k_px_per_dpt:.4g} px/dpt, B = {d['b']:+.4f} dpt")
        ax[0].set_xlabel("1 / distance (1/m)")
        ax[0].set_ylabel("D / (P_a - P_b)  (px^2/dpt)")
        ax[0].set_title("known distances")
        ax[0].legend(fontsize=8)
        r = result.residuals_dpt["pairs"]
        ax[1].bar(range(len(r)), r)
        ax[1].set_xlabel("pair")
    res = result.residuals_dpt["pairs"]
    ax[1].set_title(f"blur-difference fit: residual RMS {np.sqrt(np.mean(res ** 2)):.4f} dpt")
    if result.route == "known-distance":
        ax[1].set_ylabel("residual (dpt)")
    else:
        ax[1].legend(fontsize=8)
    b = d["breathing"]
    if len(b["dp"]):
        ax[2].plot(b["dp"], 100 * b["log_rho"], ".", ms=5, label="registered frames")
        xs = np.linspace(min(b["dp"].min(), 0), max(b["dp"].max(), 0), 20)
        ax[2].plot(xs, 100 * result.magnification_per_dpt * xs, "k-", lw=1,
                   label=f"fit: {100 * result.magnification_per_dpt:.3f} % per dpt")
        ax[2].legend(fontsize=8)
    else:
        ax[2].text(0.5, 0.5, "breathing not measured", ha="center", transform=ax[2].transAxes)
    ax[2].set_xlabel("power difference (dpt)")
    ax[2].set_ylabel("magnification (%)")
    ax[2].set_title("focus breathing")
    for a in ax:
        a.grid(alpha=0.3)
    cam = result.camera_file.camera
    fig.suptitle(f"tdfd calibrate ({result.route}): mu = {cam.mu_px_per_m:.4g} px/m, "
                 f"f0 = {1000 * cam.fixed_focal_length_m:.4f} mm; in-focus offset B: {result.offset_source}",
                 fontsize=9)
    fig.tight_layout()
    p = Path(path)
    fig.savefig(p, dpi=90)
    plt.close(fig)
    return p


def plot_psf_model(fit: Any, path: str | os.PathLike) -> Path:
    """Write the measured PSF (a :class:`~tdfd.calibration.psf_model.PsfModelFit`) as a PNG: its
    kernels at :data:`PSF_PLOT_BLURS_PX` of the camera's blur (top row) over the plain Gaussian of
    the same blur (bottom row), one colour scale per column; returns the path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import torch

    from ..dfd.psf_hypotheses import PsfHypothesis

    h = fit.hypothesis
    sigma = torch.tensor(PSF_PLOT_BLURS_PX, dtype=torch.float64)
    size = max(h.kernel_size(max(abs(v) for v in PSF_PLOT_BLURS_PX)), 9)
    rows = (h.kernels(sigma, size).numpy(), PsfHypothesis("gaussian").kernels(sigma, size).numpy())
    fig, ax = plt.subplots(2, len(PSF_PLOT_BLURS_PX), figsize=(2.2 * len(PSF_PLOT_BLURS_PX), 5.4))
    for j, s in enumerate(PSF_PLOT_BLURS_PX):
        top = max(rows[0][j].max(), rows[1][j].max())
        for i, label in enumerate(("measured", "Gaussian")):
            ax[i, j].imshow(rows[i][j], cmap="magma", vmin=0.0, vmax=top, interpolation="nearest")
            ax[i, j].set_xticks([])
            ax[i, j].set_yticks([])
            ax[i, j].set_title(f"{label}, {s:+.0f} px", fontsize=8)
    shape = h.shape if isinstance(h.shape, str) else f"beta {h.shape:.2f}"
    fig.suptitle(f"PSF from the sweep: {shape}, astigmatism {h.astigmatism:.3f} at {h.astigmatism_angle:.2f} rad, "
                 f"spherical {h.spherical:+.3f}, blur scale {h.sigma_scale:.3f}; the best plain family fits "
                 f"{fit.family_cost_ratio:.2f}x worse ({fit.regions} regions)", fontsize=9)
    fig.tight_layout()
    p = Path(path)
    fig.savefig(p, dpi=90)
    plt.close(fig)
    return p
