r"""Randomised lens PSFs for training: the renderer's per-sample kernel function.

The PSF model (shape between Gaussian and pillbox, diffraction, astigmatism, spherical
aberration) is :class:`tdfd.optics.aberrated_psf.PSFModel`, re-exported here;
``data_synth.params.draw_psf`` draws one per sample.

Example:
    >>> import torch
    >>> fn = batch_kernel_fn([PSFModel("pillbox"), PSFModel(astigmatism=0.1)])
    >>> k = fn(torch.tensor([2.0, 1.0]), torch.tensor([0, 1]))
    >>> k.shape[0], [round(float(v), 5) for v in k.sum((-1, -2))]
    (2, [1.0, 1.0])
"""

from __future__ import annotations

from typing import Sequence

import torch

from tdfd.optics.aberrated_psf import PSFModel
from tdfd.optics.psf import diffraction_sigma_px

__all__ = ["PSFModel", "diffraction_sigma_px", "sample_psf_model", "batch_kernel_fn"]


def sample_psf_model(params: dict) -> PSFModel:
    """The :class:`PSFModel` a ``data_synth`` sample was rendered with, from its ``params``."""
    shape = params["psf_shape"]
    shape_v: str | float = float(params["psf_beta"]) if shape == "beta" else str(shape)
    return PSFModel(shape_v, float(params["diffraction_sigma_px"]), float(params["astigmatism"]),
                    float(params["astigmatism_angle"]), float(params["spherical"]))


def batch_kernel_fn(models: Sequence[PSFModel]):
    """A ``kernel_fn`` for :func:`tdfd.optics.render.defocus_layered_multi`: the PSFs of
    entry ``i`` come from ``models[sample[i]]``; all kernels share one size."""

    def kernel_fn(sigma: torch.Tensor, sample: torch.Tensor):
        if sigma.numel() == 0:
            return torch.zeros(0, 1, 1, dtype=sigma.dtype)
        used = sorted(set(int(i) for i in sample.tolist()))
        size = max(models[i].kernel_size(float(sigma[sample == i].detach().abs().max())) for i in used)
        if len(used) == 1:
            m = models[used[0]]
            if m.plain and m.shape == "gaussian":
                return m.separable_gaussian(sigma, size)
            return m.kernels(sigma, size)
        out = torch.empty(sigma.numel(), size, size, dtype=sigma.dtype)
        for i in used:
            sel = sample == i
            out[sel] = models[i].kernels(sigma[sel], size)
        return out

    return kernel_fn
