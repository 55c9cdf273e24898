r"""Differentiable defocus rendering: one renderer for data synthesis, tests and the bench.

Two operations, both batched and differentiable with respect to the image, the blur sizes
(and through :mod:`tdfd.optics.thin_lens`, depth and camera parameters):

* :func:`defocus_uniform`: a fronto-parallel plane, one blur per sample (paper eq. 8,
  ``g = h * f``).
* :func:`defocus_layered`: a depth map with spatially varying blur. The scene is split into
  soft layers in signed blur ``sigma`` (which is linear in inverse depth, eq. 4), centred on
  a fixed grid of multiples of the layer spacing; each layer's
  colour and coverage are blurred with that layer's PSF and composited front to back, so a
  near object's blurred edge covers the background behind it (occlusion), and the result is
  normalised by the composited coverage. Layers whose centres are within one spacing of each
  other do not occlude one another, so a plane between two layer centres is rendered as an
  interpolation of the two blurs without self-occlusion.

Convolutions run in the Fourier domain on a reflect-padded image (linear, not circular,
convolution inside the output), so large blurs cost no more than small ones.

Example:
    >>> import torch
    >>> from tdfd import Camera
    >>> cam = Camera.preset("reference")
    >>> x = torch.rand(1, 1, 64, 64, generator=torch.Generator().manual_seed(0))
    >>> g1, g2 = render_pair(cam, x, torch.full((1, 1, 64, 64), 0.5))
    >>> g1.shape, bool(g1.std() < x.std())
    (torch.Size([1, 1, 64, 64]), True)
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from ..camera import Camera
from ..errors import InputError, NonFiniteError, ShapeError
from .psf import PSFShape, kernel_size_for, psf_kernel
from .thin_lens import blur_radius_from_power

__all__ = [
    "defocus_uniform",
    "defocus_layered",
    "sigma_map",
    "render_at_power",
    "render_pair",
]


def _check_image(image: torch.Tensor, name: str = "image") -> None:
    if not isinstance(image, torch.Tensor):
        raise InputError(f"{name} must be a torch.Tensor, got {type(image).__name__}")
    if image.ndim != 4:
        raise ShapeError(f"{name} must have shape (B, C, H, W), got {tuple(image.shape)}")
    if not image.is_floating_point():
        raise InputError(f"{name} must be floating point, got {image.dtype}")


def _otf_of_kernels(kernels: torch.Tensor, padded_hw: tuple[int, int]) -> torch.Tensor:
    """rfft2 of centred kernels ``(*, k, k)`` embedded in a ``padded_hw`` array."""
    k = kernels.shape[-1]
    hp, wp = padded_hw
    full = F.pad(kernels, (0, wp - k, 0, hp - k))
    full = torch.roll(full, shifts=(-(k // 2), -(k // 2)), dims=(-2, -1))
    return torch.fft.rfft2(full)


def _pad(x: torch.Tensor, pad: int) -> torch.Tensor:
    if pad == 0:
        return x
    h, w = x.shape[-2:]
    mode = "reflect" if pad < min(h, w) else "replicate"
    lead = x.shape[:-2]
    y = F.pad(x.reshape(-1, 1, h, w), (pad, pad, pad, pad), mode=mode)
    return y.reshape(*lead, h + 2 * pad, w + 2 * pad)


def _fft_size(n: int) -> int:
    # next size whose only prime factors are 2, 3, 5 (fast FFT)
    m = n
    while True:
        r = m
        for p in (2, 3, 5):
            while r % p == 0:
                r //= p
        if r == 1:
            return m
        m += 1


def defocus_uniform(image: torch.Tensor, sigma: torch.Tensor, shape: PSFShape = "gaussian") -> torch.Tensor:
    """Blur each sample of a batch with one PSF (a fronto-parallel plane).

    Args:
        image: sharp image ``(B, C, H, W)``, linear intensity.
        sigma: signed RMS blur radius in pixels, shape ``(B,)`` (or a scalar).
        shape: PSF shape (see :mod:`tdfd.optics.psf`).

    Returns:
        Blurred image ``(B, C, H, W)``; a zero ``sigma`` returns the image unchanged.
    """
    _check_image(image)
    b, c, h, w = image.shape
    sigma = torch.as_tensor(sigma, dtype=image.dtype, device=image.device).reshape(-1)
    if sigma.numel() == 1:
        sigma = sigma.expand(b)
    if sigma.numel() != b:
        raise ShapeError(f"sigma must have one value per sample ({b}), got {sigma.numel()}")
    if not torch.isfinite(sigma).all():
        raise NonFiniteError("sigma contains NaN or inf")
    size = kernel_size_for(float(sigma.detach().abs().max()), shape)
    pad = size // 2
    xp = _pad(image, pad)
    hp, wp = _fft_size(xp.shape[-2]), _fft_size(xp.shape[-1])
    otf = _otf_of_kernels(psf_kernel(sigma, shape, size), (hp, wp))  # (B, hp, wp//2+1)
    spec = torch.fft.rfft2(xp, s=(hp, wp)) * otf[:, None]
    out = torch.fft.irfft2(spec, s=(hp, wp))
    return out[..., pad : pad + h, pad : pad + w]


def sigma_map(camera: Camera, depth_m: torch.Tensor, ecvfl_power_dpt: float | torch.Tensor,
              mu: float | torch.Tensor | None = None) -> torch.Tensor:
    """Signed blur parameter ``sigma = mu r_b`` in pixels for every depth (paper eq. 4).

    ``ecvfl_power_dpt`` is a float or a ``(B,)`` tensor (broadcast over ``(B, 1, H, W)``).
    ``mu`` defaults to ``camera.mu_px_per_m``.
    """
    mu = camera.mu_px_per_m if mu is None else mu
    p = torch.as_tensor(ecvfl_power_dpt, dtype=depth_m.dtype, device=depth_m.device)
    if p.ndim == 1 and depth_m.ndim == 4:
        p = p[:, None, None, None]
    return mu * blur_radius_from_power(camera, depth_m, p)


def defocus_layered(image: torch.Tensor, sigma: torch.Tensor, shape: PSFShape = "gaussian",
                    layer_spacing: float = 0.25, max_layers: int = 48) -> torch.Tensor:
    """Render spatially varying defocus with occlusion by soft-layer compositing.

    Layers are ordered by signed ``sigma``, which grows monotonically with depth for the
    focal-length-varying camera (eq. 4 with ``mu > 0``): lower ``sigma`` is nearer and
    occludes higher ``sigma``.

    Args:
        image: sharp (all-in-focus) image ``(B, C, H, W)``.
        sigma: signed blur parameter per pixel in pixels ``(B, 1, H, W)``.
        shape: PSF shape.
        layer_spacing: spacing of the layer centres in pixels of ``sigma``; smaller is more
            accurate and slower.
        max_layers: upper bound on the layer count (the spacing grows if needed).

    Returns:
        The defocused image ``(B, C, H, W)``.
    """
    _check_image(image)
    _check_image(sigma, "sigma")
    b, c, h, w = image.shape
    if sigma.shape != (b, 1, h, w):
        raise ShapeError(f"sigma must have shape {(b, 1, h, w)}, got {tuple(sigma.shape)}")
    if not torch.isfinite(sigma).all():
        raise NonFiniteError("sigma contains NaN or inf")
    if layer_spacing <= 0 or max_layers < 2:
        raise InputError("layer_spacing must be > 0 and max_layers >= 2")
    # layer centres on a fixed grid k * spacing (independent of the data, so small changes of
    # sigma move weight between layers smoothly and derivatives are consistent)
    flat = sigma.detach().reshape(b, -1)
    lo_all, hi_all = float(flat.min()), float(flat.max())
    spacing = float(layer_spacing)
    first, last = math.floor(lo_all / spacing), math.ceil(hi_all / spacing)
    if last - first + 1 > max_layers:
        spacing *= math.ceil((last - first) / (max_layers - 1))
        first, last = math.floor(lo_all / spacing), math.ceil(hi_all / spacing)
    last = max(last, first + 1)
    n_layers = last - first + 1
    grid = torch.arange(first, last + 1, dtype=sigma.dtype, device=sigma.device) * spacing
    centres = grid[None, :].expand(b, n_layers)  # (B, L), ascending = near to far
    lo, hi = centres[:, 0], centres[:, -1]
    # hat-function weights: each pixel split between its two neighbouring layer centres
    t = (sigma - centres[:, :, None, None]) / spacing  # (B, L, H, W)
    alpha = (1.0 - t.abs()).clamp_min(0.0)
    size = kernel_size_for(float(torch.maximum(lo.abs(), hi.abs()).max()), shape)
    pad = size // 2
    hp, wp = _fft_size(h + 2 * pad), _fft_size(w + 2 * pad)
    otf = _otf_of_kernels(psf_kernel(centres, shape, size), (hp, wp))  # (B, L, hp, wq)
    stack = torch.cat([alpha[:, :, None] * image[:, None], alpha[:, :, None]], dim=2)  # (B, L, C+1, H, W)
    spec = torch.fft.rfft2(_pad(stack, pad), s=(hp, wp)) * otf[:, :, None]
    blurred = torch.fft.irfft2(spec, s=(hp, wp))[..., pad : pad + h, pad : pad + w]
    colour, cover = blurred[:, :, :c], blurred[:, :, c:].clamp(0.0, 1.0)
    # transmittance through layers nearer by more than one spacing: T_l = prod_{k <= l-2} (1 - A_k)
    log_clear = torch.log1p(-cover.clamp(max=1.0 - 1e-6))
    cum = torch.cumsum(log_clear, dim=1)
    trans = torch.exp(F.pad(cum, (0, 0, 0, 0, 0, 0, 2, 0))[:, :n_layers])
    num = (colour * trans).sum(1)
    den = (cover * trans).sum(1).clamp_min(1e-6)
    return num / den


def render_at_power(camera: Camera, sharp: torch.Tensor, depth_m: torch.Tensor,
                    ecvfl_power_dpt: float | torch.Tensor, shape: PSFShape = "gaussian",
                    mu: float | torch.Tensor | None = None, layer_spacing: float = 0.25) -> torch.Tensor:
    """Defocused image of a scene (sharp radiance + depth map) at one ECVFL power.

    A depth map that is constant per sample takes the exact uniform path; otherwise the
    layered renderer. ``mu`` is the *true* blur constant of the simulated optics (defaults
    to ``camera.mu_px_per_m``).

    Args:
        camera: the camera description.
        sharp: all-in-focus radiance ``(B, C, H, W)``.
        depth_m: object distance in metres ``(B, 1, H, W)``, all > 0.
        ecvfl_power_dpt: ECVFL power (float or ``(B,)``).
        shape: PSF shape.
        mu: true blur constant in px/m.
        layer_spacing: see :func:`defocus_layered`.
    """
    _check_image(sharp, "sharp")
    _check_image(depth_m, "depth_m")
    if depth_m.shape[0] != sharp.shape[0] or depth_m.shape[1] != 1 or depth_m.shape[-2:] != sharp.shape[-2:]:
        raise ShapeError(f"depth_m must have shape (B, 1, H, W) matching sharp {tuple(sharp.shape)}, got {tuple(depth_m.shape)}")
    if not torch.isfinite(depth_m).all() or bool((depth_m <= 0).any()):
        raise InputError("depth_m must be finite and > 0 everywhere")
    s = sigma_map(camera, depth_m, ecvfl_power_dpt, mu)
    flat = s.reshape(s.shape[0], -1)
    if bool((flat.detach().amax(1) == flat.detach().amin(1)).all()):
        return defocus_uniform(sharp, flat[:, 0], shape)
    return defocus_layered(sharp, s, shape, layer_spacing=layer_spacing)


def render_pair(camera: Camera, sharp: torch.Tensor, depth_m: torch.Tensor, shape: PSFShape = "gaussian",
                mu: float | torch.Tensor | None = None, layer_spacing: float = 0.25) -> tuple[torch.Tensor, torch.Tensor]:
    """The DFD pair ``(image_f1, image_f2)`` at the camera's two ECVFL powers (noise-free)."""
    p1, p2 = camera.lens_powers_dpt
    return (render_at_power(camera, sharp, depth_m, p1, shape, mu, layer_spacing),
            render_at_power(camera, sharp, depth_m, p2, shape, mu, layer_spacing))
