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

* :func:`defocus_layered_multi`: the same layered render for several focus settings at once
  (the two DFD frames differ by a constant blur offset, paper eq. 6, so they share the layer
  decomposition and its forward FFTs), with custom PSF kernels, an exact single-PSF path
  for constant maps and a cheaper non-occluding "gather" mode for smooth depth maps.
  :func:`defocus_layered` and :func:`render_pair` run on it. Layers no pixel falls into are
  skipped and the layers are streamed near to far, so a render costs about one forward FFT
  per used layer and one inverse FFT per used layer and frame and channel.

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
from typing import Callable, Union

import torch
import torch.nn.functional as F

from ..camera import Camera
from ..errors import InputError, NonFiniteError, ShapeError
from .psf import PSFShape, gaussian_psf_1d, kernel_size_for, psf_kernel
from .thin_lens import blur_radius_from_power

#: Kernels returned by a custom PSF function: ``(N, k, k)``, or separable ``((N, k), (N, k))``.
KernelOut = Union[torch.Tensor, tuple[torch.Tensor, torch.Tensor]]
#: ``kernel_fn(sigma (N,), sample (N,) long) -> KernelOut``: custom PSFs for the renderer.
KernelFn = Callable[[torch.Tensor, torch.Tensor], KernelOut]

__all__ = [
    "defocus_uniform",
    "defocus_layered",
    "defocus_layered_multi",
    "sigma_map",
    "frame_sigma_map",
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
    c = k // 2
    hp, wp = padded_hw
    # the kernel's centre tap goes to (0, 0), the rest wraps around (circular shift)
    full = kernels.new_zeros(*kernels.shape[:-2], hp, wp)
    full[..., : k - c, : k - c] = kernels[..., c:, c:]
    full[..., : k - c, wp - c :] = kernels[..., c:, :c]
    full[..., hp - c :, : k - c] = kernels[..., :c, c:]
    full[..., hp - c :, wp - c :] = kernels[..., :c, :c]
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


def frame_sigma_map(camera: Camera, depth_m: torch.Tensor, frame: int, mu: float | torch.Tensor | None = None
                    ) -> torch.Tensor:
    """Signed blur parameter in pixels of DFD frame ``frame`` (0: ``image_f1``, 1: ``image_f2``)
    for every depth: eq. 4 with that frame's ECVFL power, sensor distance and aperture
    (:meth:`tdfd.camera.Camera.sigma_lines_px`). ``mu`` defaults to ``camera.mu_px_per_m``."""
    if frame not in (0, 1):
        raise InputError(f"frame must be 0 or 1, got {frame!r}")
    if camera.sensor_distances_m is None and camera.apertures_m is None:
        return sigma_map(camera, depth_m, camera.lens_powers_dpt[frame], mu)
    mu = camera.mu_px_per_m if mu is None else mu
    f, ds, a = camera.focal_lengths_m[frame], camera.frame_sensor_distances_m[frame], camera.frame_apertures_m[frame]
    return mu * 0.5 * a * ds * (1.0 / f - 1.0 / depth_m - 1.0 / ds)


def _default_kernel_fn(shape: PSFShape) -> KernelFn:
    def kernel_fn(sigma: torch.Tensor, sample: torch.Tensor) -> KernelOut:
        size = kernel_size_for(float(sigma.detach().abs().max()) if sigma.numel() else 0.0, shape)
        if shape == "gaussian" or (not isinstance(shape, str) and float(shape) == 2.0):
            k1 = gaussian_psf_1d(sigma, size)  # separable: cheaper OTFs, same kernel
            return k1, k1
        return psf_kernel(sigma, shape, size)
    return kernel_fn


def _kernel_otfs(kernels: KernelOut, padded_hw: tuple[int, int]) -> tuple[torch.Tensor, int]:
    """OTFs ``(N, hp, wp//2+1)`` of centred kernels (2-D, or separable ``(k_y, k_x)``) and
    the kernel half-size."""
    hp, wp = padded_hw
    if isinstance(kernels, tuple):
        ky, kx = kernels
        k = ky.shape[-1]
        c = k // 2
        py, px = ky.new_zeros(*ky.shape[:-1], hp), kx.new_zeros(*kx.shape[:-1], wp)
        py[..., : k - c], py[..., hp - c :] = ky[..., c:], ky[..., :c]
        px[..., : k - c], px[..., wp - c :] = kx[..., c:], kx[..., :c]
        fy, fx = torch.fft.fft(py), torch.fft.rfft(px)
        return fy[..., :, None] * fx[..., None, :], k // 2
    return _otf_of_kernels(kernels, padded_hw), kernels.shape[-1] // 2


def _kernel_half(kernels: KernelOut) -> int:
    k = kernels[0].shape[-1] if isinstance(kernels, tuple) else kernels.shape[-1]
    if k % 2 == 0:
        raise ShapeError(f"PSF kernels must have an odd size, got {k}")
    return k // 2


def _layer_grid(lo: float, hi: float, layer_spacing: float, max_layers: int) -> tuple[float, int, int]:
    """Spacing and first/last index of the fixed layer grid ``k * spacing`` covering [lo, hi]."""
    spacing = float(layer_spacing)
    first, last = math.floor(lo / spacing), math.ceil(hi / spacing)
    if last - first + 1 > max_layers:
        spacing *= math.ceil((last - first) / (max_layers - 1))
        first, last = math.floor(lo / spacing), math.ceil(hi / spacing)
    return spacing, first, max(last, first + 1)


def _entry_otfs(kernel_fn: KernelFn, psf_sigma: torch.Tensor, owner: torch.Tensor, hw: tuple[int, int]
                ) -> tuple[torch.Tensor, int, tuple[int, int]]:
    """OTFs ``(N, F, hp, wp//2+1)`` of the PSFs ``psf_sigma`` ``(N, F)``, the padding and FFT size."""
    n, n_frames = psf_sigma.shape
    kernels = kernel_fn(psf_sigma.reshape(-1), owner[:, None].expand(-1, n_frames).reshape(-1))
    pad = _kernel_half(kernels)
    hp, wp = _fft_size(hw[0] + 2 * pad), _fft_size(hw[1] + 2 * pad)
    otf, _ = _kernel_otfs(kernels, (hp, wp))
    return otf.reshape(n, n_frames, hp, wp // 2 + 1), pad, (hp, wp)


def _irfft2_crop(spec: torch.Tensor, hp: int, wp: int, pad: int, h: int, w: int) -> torch.Tensor:
    """``irfft2(spec, s=(hp, wp))[..., pad:pad+h, pad:pad+w]`` without computing the rows
    that are cropped away."""
    x = torch.fft.ifft(spec, n=hp, dim=-2)[..., pad : pad + h, :]
    return torch.fft.irfft(x, n=wp, dim=-1)[..., pad : pad + w]


def defocus_layered_multi(image: torch.Tensor, sigma: torch.Tensor, offsets: torch.Tensor | None = None,
                          shape: PSFShape = "gaussian", layer_spacing: float = 0.25, max_layers: int = 48,
                          kernel_fn: KernelFn | None = None, exact_planes: bool = False,
                          occlusion: bool = True) -> torch.Tensor:
    """Layered defocus of one scene at several focus settings in one pass.

    Frame ``f`` has the blur map ``sigma + offsets[:, f]``: for the focal-length-varying
    camera the two DFD frames differ by a constant (paper eq. 6), so they share one soft
    layer decomposition (the fixed grid ``k * layer_spacing`` of ``sigma``, see
    :func:`defocus_layered`) and its forward FFTs; only the PSFs differ (frame ``f``'s
    layer ``k`` is blurred by ``k * layer_spacing + offsets[:, f]``). With zero offsets a
    frame equals :func:`defocus_layered`; otherwise each frame differs from
    :func:`defocus_layered` of its own map only by where the layer interpolation falls
    (both are within the layering accuracy), and the interpolation error is the same in
    every frame.

    Layers no pixel of a sample falls into are skipped (per sample), so a piecewise-planar
    scene costs only the layers its planes occupy.

    Args:
        image: sharp image ``(B, C, H, W)``.
        sigma: signed blur map of the first frame in pixels ``(B, 1, H, W)``.
        offsets: per-frame constant added to ``sigma``, ``(F,)`` or ``(B, F)``; default one
            frame with offset 0.
        shape: PSF shape (ignored when ``kernel_fn`` is given).
        layer_spacing: spacing of the layer centres in pixels of ``sigma``.
        max_layers: upper bound on the layer count (the spacing grows if needed).
        kernel_fn: optional custom PSFs: called as ``kernel_fn(sigma, sample)`` with the
            signed blur of every needed PSF ``(N,)`` and the index of its sample in the
            batch ``(N,)`` (long); returns centred unit-sum kernels ``(N, k, k)`` of odd
            size, or a separable pair ``((N, k), (N, k))`` whose outer products are the kernels.
        exact_planes: render samples whose blur map is constant with one PSF of exactly
            that blur (the :func:`defocus_uniform` result) instead of interpolating two
            grid layers. Faster and exact for fronto-parallel planes, but the switch is not
            differentiable-consistent (leave off for gradient checks).
        occlusion: ``True`` (default) composites the layers front to back (scatter: each
            scene point spreads light with its own PSF, near layers hide far ones). ``False``
            blurs the *whole* image with each layer's PSF and mixes the results per pixel
            with the layer weights (gather: each output pixel takes its own PSF): no
            occlusion, about three times cheaper (one forward FFT per sample, one inverse per
            layer and frame). The two agree to first order where the blur map is smooth; use
            ``False`` only for depth maps without discontinuities (planes, smooth surfaces)
            and for illumination patterns projected from the camera's viewpoint.

    Returns:
        ``(B, F, C, H, W)``: the defocused image of every frame.

    Example:
        >>> import torch
        >>> x = torch.rand(2, 1, 32, 32)
        >>> s = torch.linspace(-2, 2, 32).expand(2, 1, 32, 32)
        >>> defocus_layered_multi(x, s, torch.tensor([0.0, -1.5])).shape
        torch.Size([2, 2, 1, 32, 32])
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
    if offsets is None:
        offsets = torch.zeros(b, 1, dtype=sigma.dtype, device=sigma.device)
    offsets = torch.as_tensor(offsets, dtype=sigma.dtype, device=sigma.device)
    if offsets.ndim == 1:
        offsets = offsets[None, :].expand(b, -1)
    if offsets.ndim != 2 or offsets.shape[0] != b or offsets.shape[1] < 1:
        raise ShapeError(f"offsets must have shape (F,) or ({b}, F), got {tuple(offsets.shape)}")
    if not torch.isfinite(offsets).all():
        raise NonFiniteError("offsets contain NaN or inf")
    n_frames = offsets.shape[1]
    kernel_fn = _default_kernel_fn(shape) if kernel_fn is None else kernel_fn
    out = image.new_zeros(b, n_frames, c, h, w)

    flat = sigma.detach().reshape(b, -1)
    lo_b, hi_b = flat.amin(1), flat.amax(1)
    planar = (lo_b == hi_b) if exact_planes else torch.zeros(b, dtype=torch.bool, device=sigma.device)
    if bool(planar.any()):  # one PSF of exactly the plane's blur
        ip = planar.nonzero(as_tuple=True)[0]
        psf_sigma = sigma.reshape(b, -1)[ip, :1] + offsets[ip]
        otf, pad, (hp, wp) = _entry_otfs(kernel_fn, psf_sigma, ip, (h, w))
        spec = torch.fft.rfft2(_pad(image[ip], pad), s=(hp, wp))
        out = out.index_put((ip,), _irfft2_crop(spec[:, None] * otf[:, :, None], hp, wp, pad, h, w))
    if bool(planar.all()):
        return out
    layered = (~planar).nonzero(as_tuple=True)[0]

    # ---- soft layers on the fixed grid k * spacing (hat weights between neighbours)
    spacing, first, last = _layer_grid(float(lo_b[layered].min()), float(hi_b[layered].max()), layer_spacing, max_layers)
    n_layers = last - first + 1
    centres = torch.arange(first, last + 1, dtype=sigma.dtype, device=sigma.device) * spacing  # (L,) near to far
    # which layers each sample touches: a pixel at u = sigma / spacing - first lies between
    # layers floor(u) and floor(u) + 1 (weights 1 - frac and frac)
    u = sigma.detach().reshape(b, -1) / spacing - first
    k = torch.floor(u).clamp(0, n_layers - 1)
    k = k.long()
    rows = torch.arange(b, device=sigma.device)[:, None] * n_layers
    flags = torch.zeros(b * n_layers, dtype=torch.bool, device=sigma.device)
    flags[(rows + k).reshape(-1)] = True
    # the upper neighbour (weight frac; a pixel exactly on a centre adds a weight-0 layer)
    flags[(rows + (k + 1).clamp_max(n_layers - 1)).reshape(-1)] = True
    if torch.is_grad_enabled() and sigma.requires_grad:
        # the layers a pixel touches at weight 0 (the hat's kink) matter for gradients
        flags[(rows + (k - 1).clamp_min(0)).reshape(-1)] = True
    sel = torch.zeros(b, dtype=torch.bool, device=sigma.device)
    sel[layered] = True
    touched = flags.reshape(b, n_layers) & sel[:, None]
    idx_b, idx_l = touched.nonzero(as_tuple=True)  # layers some pixel falls into
    scaled = sigma / spacing - first  # layer weight of layer l: max(0, 1 - |scaled - l|)
    psf_sigma = centres[idx_l][:, None] + offsets[idx_b]  # (N, F)
    otf, pad, (hp, wp) = _entry_otfs(kernel_fn, psf_sigma, idx_b, (h, w))
    num = image.new_zeros(b, n_frames, c, h, w)
    if not occlusion:  # gather: per-pixel mix of whole-image blurs, one forward FFT per sample
        spec_img = torch.fft.rfft2(_pad(image, pad), s=(hp, wp))  # (B, C, hp, wq)
    else:
        den = image.new_zeros(b, n_frames, 1, h, w)
        clear_1 = image.new_ones(b, n_frames, 1, h, w)  # prod_{k <= l-1} (1 - A_k)
        clear_2 = clear_1  # prod_{k <= l-2} (1 - A_k): transmittance of layer l
    # stream the layers near to far (small working set; front-to-back compositing)
    order = torch.argsort(idx_l, stable=True)
    idx_b, idx_l, otf = idx_b[order], idx_l[order], otf[order]
    counts = torch.bincount(idx_l, minlength=n_layers).tolist()
    start = 0
    for layer in range(n_layers):
        stop = start + counts[layer]
        if stop == start:  # no sample uses this layer: nothing is added, coverage 0
            if occlusion:
                clear_2 = clear_1
            continue
        sb = idx_b[start:stop]
        every = stop - start == b  # all samples use this layer: plain tensors, no gathers
        pick = (lambda x: x) if every else (lambda x: x[sb])
        a = (1.0 - (pick(scaled) - layer).abs()).clamp_min(0.0)  # (n, 1, H, W) hat weights
        if not occlusion:
            blurred = _irfft2_crop(pick(spec_img)[:, None] * otf[start:stop, :, None], hp, wp, pad, h, w)
            num = num + blurred * a[:, None] if every else num.index_add(0, sb, blurred * a[:, None])
        else:
            stack = torch.cat([a * pick(image), a], dim=1)  # (n, C+1, H, W)
            spec = torch.fft.rfft2(_pad(stack, pad), s=(hp, wp))
            blurred = _irfft2_crop(spec[:, None] * otf[start:stop, :, None], hp, wp, pad, h, w)  # (n, F, C+1, H, W)
            colour, cover = blurred[:, :, :c], blurred[:, :, c:].clamp(0.0, 1.0)
            t = pick(clear_2)
            clear = 1.0 - cover.clamp(max=1.0 - 1e-6)
            if every:
                num, den = num + colour * t, den + cover * t
                new_clear = clear_1 * clear
            else:
                num, den = num.index_add(0, sb, colour * t), den.index_add(0, sb, cover * t)
                new_clear = clear_1.index_copy(0, sb, clear_1[sb] * clear)
            clear_2, clear_1 = clear_1, new_clear
        start = stop
    res = num if not occlusion else num / den.clamp_min(1e-6)
    return torch.where(planar[:, None, None, None, None], out, res)


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
    return defocus_layered_multi(image, sigma, None, shape, layer_spacing, max_layers)[:, 0]


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
    return _render_sigma(sharp, sigma_map(camera, depth_m, ecvfl_power_dpt, mu), shape, layer_spacing)


def _render_sigma(sharp: torch.Tensor, s: torch.Tensor, shape: PSFShape, layer_spacing: float) -> torch.Tensor:
    """Defocus by a blur map: exact uniform path for samples of one ``sigma``, else layered."""
    flat = s.reshape(s.shape[0], -1)
    if bool((flat.detach().amax(1) == flat.detach().amin(1)).all()):
        return defocus_uniform(sharp, flat[:, 0], shape)
    return defocus_layered(sharp, s, shape, layer_spacing=layer_spacing)


def render_pair(camera: Camera, sharp: torch.Tensor, depth_m: torch.Tensor, shape: PSFShape = "gaussian",
                mu: float | torch.Tensor | None = None, layer_spacing: float = 0.25) -> tuple[torch.Tensor, torch.Tensor]:
    """The DFD pair ``(image_f1, image_f2)`` at the camera's two ECVFL powers (noise-free).

    Each frame blurs by eq. 4 with its own power, sensor distance and aperture
    (:func:`frame_sigma_map`). Both frames are rendered on frame 1's pixel grid: a camera
    whose sensor distance varies also scales frame 2 by ``d_s2/d_s1``, which this renderer
    does **not** apply (the pair comes out registered; :func:`tdfd.breathing.magnify` adds
    the scale, :func:`tdfd.dfd.register_sensor_pair` removes it from real captures).

    Both frames share one layer decomposition (their blur maps differ by a constant,
    paper eq. 6), rendered in one pass by :func:`defocus_layered_multi`: ``image_f1`` equals
    :func:`render_at_power` at the first power; ``image_f2`` differs from it at the second
    power only by where the layer interpolation falls (within the layering accuracy, and the
    same interpolation error in both frames). Constant-depth samples take the exact uniform
    path for both frames.
    """
    _check_image(sharp, "sharp")
    _check_image(depth_m, "depth_m")
    if depth_m.shape[0] != sharp.shape[0] or depth_m.shape[1] != 1 or depth_m.shape[-2:] != sharp.shape[-2:]:
        raise ShapeError(f"depth_m must have shape (B, 1, H, W) matching sharp {tuple(sharp.shape)}, got {tuple(depth_m.shape)}")
    if not torch.isfinite(depth_m).all() or bool((depth_m <= 0).any()):
        raise InputError("depth_m must be finite and > 0 everywhere")
    s1, s2 = frame_sigma_map(camera, depth_m, 0, mu), frame_sigma_map(camera, depth_m, 1, mu)
    flat = s1.reshape(s1.shape[0], -1).detach()
    diff = (s2 - s1).reshape(s1.shape[0], -1)
    tol = 1e-4 * (1.0 + float(flat.abs().max()))
    if bool((flat.amax(1) == flat.amin(1)).all()) or float((diff.detach().amax(1) - diff.detach().amin(1)).max()) > tol:
        return _render_sigma(sharp, s1, shape, layer_spacing), _render_sigma(sharp, s2, shape, layer_spacing)
    offsets = torch.stack([torch.zeros_like(diff[:, 0]), diff[:, 0]], dim=1)  # constant within `tol`
    out = defocus_layered_multi(sharp, s1, offsets, shape, layer_spacing)
    return out[:, 0], out[:, 1]
