r"""The DFD forward model, in the deepinv manner: scene -> defocus -> breathing/misregistration
-> gain -> sensor.

One composable pipeline that the synthesiser (``data_synth``), the export verification
(``export/verify.py``), the benchmarks and the tests all use instead of chaining the steps
by hand. Each stage is a function plus a thin :class:`torch.nn.Module`; a frame pair is
``(B, 2, H, W)`` (channel 0 ``image_f1``, channel 1 ``image_f2``), so every stage after the
optics treats the two frames as independent channels:

1. :func:`defocus_pair` / :class:`Defocus`: sharp radiance ``(B, 1, H, W)`` and depth
   ``(B, 1, H, W)`` to the two noise-free frames at the camera's ECVFL powers (paper eqs.
   4-8). Both frames come from one layer decomposition
   (:func:`tdfd.optics.render.defocus_layered_multi`); frame 2's blur map is frame 1's plus
   the constant of eq. 6. PSFs: a shape of :mod:`tdfd.optics.psf` or any ``kernel_fn``
   (e.g. ``data_synth.psf.batch_kernel_fn``, the aberrated lens PSFs).
2. :func:`tdfd.warp.misregister` / :class:`tdfd.warp.Misregistration`: focus breathing and
   sub-pixel misregistration of frame 2 relative to frame 1.
3. :func:`frame_gain` / :class:`FrameGain`: negative render ringing removed and frame 2's
   relative brightness (flicker, exposure jitter).
4. The sensor: :class:`tdfd.sensor.SensorModel` (Poisson-Gaussian noise, saturation,
   black level, quantisation, vignetting; draws from the caller's generator), or
   :class:`IdealSensor` (noise-free linear frames).

:class:`DFDForward` composes the four. The stages hold no random state: whoever generates
samples owns the :class:`torch.Generator` and the parameters (``data_synth``'s
``SynthBatchGenerator`` returns every parameter that made a sample; :class:`PlanePairs`
does the same for textured two-plane test scenes).

Example:
    >>> import torch
    >>> from tdfd import Camera
    >>> from tdfd.sensor import SensorModel
    >>> fwd = DFDForward(Defocus(Camera.preset("reference")), SensorModel(bits=12))
    >>> x = torch.rand(1, 1, 64, 64, generator=torch.Generator().manual_seed(0))
    >>> y = fwd(x, torch.full_like(x, 0.5), breathing=0.005, generator=torch.Generator().manual_seed(1))
    >>> y.shape
    torch.Size([1, 2, 64, 64])
"""

from __future__ import annotations

from typing import Any, Sequence

import torch
from torch import nn

from .camera import Camera
from .errors import InputError, ShapeError
from .optics.psf import PSFShape
from .optics.render import KernelFn, defocus_layered_multi, frame_sigma_map, sigma_map
from .sensor import Param, SensorModel
from .warp import Misregistration, misregister

__all__ = ["defocus_pair", "Defocus", "frame_gain", "FrameGain", "IdealSensor", "DFDForward", "PlanePairs",
           "misregister", "Misregistration", "DEFOCUS_MODES"]

#: Rendering modes of :func:`defocus_pair`.
DEFOCUS_MODES = ("auto", "occlusion", "gather")


def _check_scene(radiance: torch.Tensor, depth_m: torch.Tensor) -> None:
    for name, t in (("radiance", radiance), ("depth_m", depth_m)):
        if not isinstance(t, torch.Tensor) or t.ndim != 4 or t.shape[1] != 1:
            raise ShapeError(f"{name} must be a (B, 1, H, W) tensor, got {getattr(t, 'shape', type(t).__name__)}")
    if depth_m.shape != radiance.shape:
        raise ShapeError(f"depth_m {tuple(depth_m.shape)} must match radiance {tuple(radiance.shape)}")
    if not torch.isfinite(depth_m).all() or bool((depth_m <= 0).any()):
        raise InputError("depth_m must be finite and > 0 everywhere")


def defocus_pair(camera: Camera, radiance: torch.Tensor, depth_m: torch.Tensor,
                 psf: PSFShape | KernelFn = "gaussian", mode: str = "auto", layer_spacing: float = 0.25,
                 mu: float | None = None) -> torch.Tensor:
    """Both DFD frames of a scene, noise-free: ``(B, 2, H, W)``.

    Args:
        camera: the camera (its two ECVFL powers and, unless ``mu`` is given, its ``mu``).
        radiance: sharp linear radiance ``(B, 1, H, W)``.
        depth_m: object distance in metres ``(B, 1, H, W)``, finite and > 0.
        psf: a PSF shape (``"gaussian"``, ``"pillbox"`` or a power-exponential beta) or a
            ``kernel_fn(sigma, sample)`` (see :func:`tdfd.optics.render.defocus_layered_multi`).
        mode: ``"auto"`` and ``"occlusion"``: occluding soft layers (a constant-depth sample
            takes the exact single-PSF path); ``"gather"``: the cheaper non-occluding mix, for
            depth maps without discontinuities (slanted planes, smooth surfaces).
        layer_spacing: layer spacing in px of blur (accuracy budget, ``docs/BENCHMARKS.md``).
        mu: the simulated optics' true blur constant in px/m (default ``camera.mu_px_per_m``).

    Returns:
        ``(B, 2, H, W)``: ``image_f1`` and ``image_f2`` as channels.
    """
    _check_scene(radiance, depth_m)
    if mode not in DEFOCUS_MODES:
        raise InputError(f"mode must be one of {DEFOCUS_MODES}, got {mode!r}")
    b = radiance.shape[0]
    kw: dict[str, Any] = {"kernel_fn": psf} if callable(psf) else {"shape": psf}
    multi = dict(layer_spacing=layer_spacing, exact_planes=True, occlusion=(mode != "gather"), **kw)
    if camera.sensor_distances_m is not None or camera.apertures_m is not None:
        # two sensor distances or apertures: the blur maps differ by a depth-dependent amount,
        # so each frame gets its own layer decomposition (eq. 4 per frame; frame 1's pixel grid,
        # no d_s2/d_s1 scale: see tdfd.optics.render.render_pair)
        frames = [defocus_layered_multi(radiance, frame_sigma_map(camera, depth_m, i, mu), None, **multi)[:, 0, 0]
                  for i in (0, 1)]
        return torch.stack(frames, dim=1)
    p1, p2 = camera.lens_powers_dpt
    s1 = sigma_map(camera, depth_m, p1, mu)
    # frame 2's blur map differs by the constant of paper eq. 6
    diff = camera.sigma_difference_px if mu is None else float(mu) * camera.blur_scale_m_dpt * (p1 - p2)
    offsets = torch.tensor([[0.0, diff * -1.0]], dtype=s1.dtype).expand(b, 2)
    out = defocus_layered_multi(radiance, s1, offsets, **multi)
    return out[:, :, 0]


class Defocus(nn.Module):
    """:func:`defocus_pair` as a module: ``forward(radiance, depth_m) -> (B, 2, H, W)``.

    Args:
        camera, psf, mode, layer_spacing, mu: see :func:`defocus_pair`.
    """

    def __init__(self, camera: Camera, psf: PSFShape | KernelFn = "gaussian", mode: str = "auto",
                 layer_spacing: float = 0.25, mu: float | None = None) -> None:
        super().__init__()
        if mode not in DEFOCUS_MODES:
            raise InputError(f"mode must be one of {DEFOCUS_MODES}, got {mode!r}")
        self.camera, self.psf, self.mode, self.layer_spacing, self.mu = camera, psf, mode, float(layer_spacing), mu

    def forward(self, radiance: torch.Tensor, depth_m: torch.Tensor) -> torch.Tensor:
        return defocus_pair(self.camera, radiance, depth_m, self.psf, self.mode, self.layer_spacing, self.mu)


def frame_gain(frames: torch.Tensor, gain: float = 1.0) -> torch.Tensor:
    """Irradiance pair ``(B, 2, H, W)`` with negative values (render ringing) set to 0 and
    frame 2 scaled by ``gain`` relative to frame 1 (flicker, exposure jitter)."""
    if frames.ndim != 4 or frames.shape[1] != 2:
        raise ShapeError(f"frames must be (B, 2, H, W), got {tuple(frames.shape)}")
    out = frames.clamp_min(0.0)
    if gain != 1.0:
        out[:, 1] *= gain
    return out


class FrameGain(nn.Module):
    """:func:`frame_gain` as a module: ``forward(frames, gain=1.0)``."""

    def forward(self, frames: torch.Tensor, gain: float = 1.0) -> torch.Tensor:
        return frame_gain(frames, gain)


class IdealSensor(nn.Module):
    """A noise-free linear sensor: ``clamp(x * exposure * gain, 0, 1)`` (no noise, black
    level, quantisation or vignetting). ``forward(x, generator=None)`` ignores the generator.

    Args:
        exposure, gain: float or ``(B,)``.
    """

    def __init__(self, exposure: Param = 1.0, gain: Param = 1.0) -> None:
        super().__init__()
        self.exposure, self.gain = exposure, gain

    def forward(self, x: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
        e, g = self.exposure, self.gain
        if isinstance(e, torch.Tensor) or isinstance(g, torch.Tensor):
            scale = (torch.as_tensor(e, dtype=torch.float64) * torch.as_tensor(g, dtype=torch.float64)).to(x.dtype)
            return (x * (scale.reshape(-1, 1, 1, 1) if scale.ndim else scale)).clamp(0.0, 1.0)
        return (x * (float(e) * float(g))).clamp(0.0, 1.0)


class DFDForward(nn.Module):
    """The whole forward model: ``sensor(gain(misregister(defocus(radiance, depth))))``.

    Args:
        defocus: a :class:`Defocus`.
        sensor: :class:`tdfd.sensor.SensorModel`, :class:`IdealSensor`, or ``None`` for the
            irradiance pair itself (no sensor).

    Shape:
        - radiance, depth_m: ``(B, 1, H, W)``.
        - output: ``(B, 2, H, W)`` frames (in [0, 1] with a sensor).
    """

    def __init__(self, defocus: Defocus, sensor: nn.Module | None = None) -> None:
        super().__init__()
        self.defocus, self.sensor = defocus, sensor
        self.misregistration, self.gain = Misregistration(), FrameGain()

    def forward(self, radiance: torch.Tensor, depth_m: torch.Tensor, *, breathing: float = 0.0,
                shift_y_px: float = 0.0, shift_x_px: float = 0.0, frame_gain: float = 1.0,
                generator: torch.Generator | None = None) -> torch.Tensor:
        """Frames of a scene; ``generator`` is the sensor's only random source."""
        x = self.defocus(radiance, depth_m)
        x = self.misregistration(x, breathing, shift_y_px, shift_x_px)
        x = self.gain(x, frame_gain)
        return x if self.sensor is None else self.sensor(x, generator=generator)


class PlanePairs:
    """Textured test scenes through the forward model: ``planes`` fronto-parallel planes side
    by side (random depths uniform in inverse depth over the camera's range, random column
    splits, occlusion at the steps), textures from :func:`tdfd.textures.random_texture`.

    The generator of the parameters: :meth:`sample` owns a :class:`torch.Generator` seeded
    by ``(seed, batch)`` and returns the frames with the parameters that made them.

    Args:
        camera: the camera.
        forward: the forward model (default: Gaussian PSF, a 10 000 e- / 10 e- read noise
            12-bit sensor without black level).
        families: texture families to draw from.
        planes: planes per scene (1 or more).
        albedo, contrast: ranges of :func:`tdfd.textures.random_texture` (bright, contrasty
            scenes by default: the frames span most of [0, 1]).
    """

    def __init__(self, camera: Camera, forward: DFDForward | None = None,
                 families: Sequence[str] = ("fractal", "dead_leaves"), planes: int = 2,
                 albedo: tuple[float, float] = (0.7, 0.95), contrast: tuple[float, float] = (0.6, 1.0)) -> None:
        if planes < 1:
            raise InputError(f"planes must be >= 1, got {planes}")
        self.camera, self.families, self.planes = camera, tuple(families), int(planes)
        self.albedo, self.contrast = tuple(albedo), tuple(contrast)
        self.forward = forward or DFDForward(Defocus(camera), SensorModel(full_well_e=10000.0, read_noise_e=10.0,
                                                                          bits=12, black_level_dn=0.0))

    def sample(self, batch: int, height: int, width: int, seed: int = 0) -> tuple[torch.Tensor, dict]:
        """``(frames (B, 2, H, W) float32, params)``; ``params`` holds per sample the plane
        depths (m), the split columns, the textures' parameters, and the ``depth`` map."""
        from .textures import random_texture

        g = torch.Generator().manual_seed(int(seed))
        texs, tex_params = [], []
        for _ in range(batch):
            t, p = random_texture(g, (height, width), families=self.families, albedo=self.albedo,
                                  contrast=self.contrast)
            texs.append(t)
            tex_params.append(p)
        sharp = torch.cat(texs).float()
        near, far = self.camera.depth_range_m
        q = 1.0 / far + torch.rand(batch, self.planes, generator=g, dtype=torch.float64) * (1.0 / near - 1.0 / far)
        cuts = torch.randint(width // 4, 3 * width // 4 + 1, (batch, self.planes - 1), generator=g)
        cuts = torch.sort(cuts, 1).values
        col = torch.arange(width)
        idx = (col[None, None, :] >= cuts[:, :, None]).sum(1)  # (B, W): plane of every column
        depth = (1.0 / q).gather(1, idx).float()[:, None, None, :].expand(batch, 1, height, width).contiguous()
        with torch.no_grad():
            frames = self.forward(sharp, depth, generator=g).float().contiguous()
        params = {"depth_m": (1.0 / q).tolist(), "split_columns": cuts.tolist(), "textures": tex_params,
                  "depth": depth}
        return frames, params
