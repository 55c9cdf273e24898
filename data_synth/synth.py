r"""The synthesiser: scene -> defocus pair -> breathing/misregistration -> sensor.

:class:`SynthBatchGenerator` makes sample ``index`` of stream ``seed`` from its own
generator (:func:`~data_synth.params.sample_generator`), so every sample is a pure function
of ``(config, camera, size, seed, index)``: the same bytes whatever the batch it is made in,
the worker that makes it, or the order of requests.

Image formation per sample:

1. :func:`~data_synth.scenes.make_scene`: sharp radiance and depth.
2. Both frames in one pass of :func:`tdfd.optics.render.defocus_layered_multi` (the camera's
   two ECVFL powers share one layer decomposition; their blur maps differ by the constant
   of paper eq. 6) with the sample's :class:`~data_synth.psf.PSFModel`. A fronto-parallel
   plane takes the exact single-PSF path, slanted and smooth surfaces the gather mode (no
   depth discontinuities), piecewise-planar layouts the occluding layered mode.
3. Focus breathing and misregistration: frame 2 is magnified by ``1 + breathing`` about
   the image centre and shifted by ``(shift_y, shift_x)`` px relative to frame 1; the warp is
   split symmetrically (frame 1 by the inverse half, frame 2 by the half; separable Keys
   cubic resampling), so both frames are resampled alike and the depth map stays aligned
   with their mean.
4. Auto-exposure to the drawn mean level, a small frame-to-frame gain difference, then
   :class:`tdfd.sensor.SensorModel` (Poisson-Gaussian noise, black level, gain, 8-12 bit
   quantisation, vignetting, saturation), independently per frame.
5. ``tile_depth``: :func:`tdfd.grid.tile_true_depth` with the configured window.
"""

from __future__ import annotations

import json
import math
from typing import Any, Sequence

import torch

from tdfd import Camera
from tdfd.dfd.spectra import periodic_hann
from tdfd.errors import InputError
from tdfd.grid import grid_shape, tile_true_depth
from tdfd.optics.render import defocus_layered_multi, sigma_map
from tdfd.sensor import SensorModel

from .params import SynthConfig, draw_psf, draw_sensor, draw_warp, sample_generator, sample_seed
from .psf import PSFModel, batch_kernel_fn
from .scenes import Scene, det_mean, make_scene

__all__ = ["SynthBatchGenerator", "render_frames", "warp_pair", "tile_window", "PARAM_KEYS"]

#: Keys of the flat ``params`` dict of every sample (all present in every sample, plain
#: ``int``/``float``/``str``, so ``default_collate`` batches them); ``details`` is a JSON
#: string with everything else (textures, objects, illumination mask, ...).
PARAM_KEYS = ("seed", "index", "sample_seed", "layout", "illumination", "textureless", "n_objects",
              "texture_families", "depth_min_m", "depth_max_m", "psf_shape", "psf_beta", "wavelength_m",
              "diffraction_sigma_px", "astigmatism", "astigmatism_angle", "spherical", "speckle_contrast",
              "ambient", "bits", "full_well_e", "read_noise_e", "gain", "black_level_dn", "vignetting",
              "exposure", "target_level", "overexposed", "frame_gain", "breathing", "shift_y_px", "shift_x_px",
              "noise", "details")


def tile_window(kind: str, tile: int) -> torch.Tensor | None:
    """The ``(tile, tile)`` weight of ``tile_depth``: ``"hann2"``, ``"hann"`` or ``"box"`` (None)."""
    if kind == "box":
        return None
    w1 = periodic_hann(tile, torch.float64)
    w = w1[:, None] * w1[None, :]
    return (w * w if kind == "hann2" else w).to(torch.float32)


def render_frames(camera: Camera, radiance: torch.Tensor, depth_m: torch.Tensor, psf: PSFModel | Sequence[PSFModel],
                  mode: str = "auto", layer_spacing: float = 0.5) -> torch.Tensor:
    """Both DFD frames of a scene, noise-free: ``(B, 2, H, W)``.

    Args:
        camera: the camera (its two ECVFL powers, ``mu``).
        radiance: ``(B, 1, H, W)`` sharp radiance.
        depth_m: ``(B, 1, H, W)`` depth in metres.
        psf: one :class:`~data_synth.psf.PSFModel` per sample (or one for all).
        mode: ``"occlusion"`` (layered, occluding), ``"gather"`` (smooth depth maps) or
            ``"auto"`` (occluding; exact single PSF for constant depth).
        layer_spacing: layer spacing in px of sigma.
    """
    b = radiance.shape[0]
    models = [psf] * b if isinstance(psf, PSFModel) else list(psf)
    if len(models) != b:
        raise InputError(f"need one PSF model per sample ({b}), got {len(models)}")
    p1, p2 = camera.lens_powers_dpt
    s1 = sigma_map(camera, depth_m, p1)
    # frame 2's blur map differs by the constant of paper eq. 6
    offsets = torch.tensor([[0.0, camera.sigma_difference_px * -1.0]], dtype=s1.dtype).expand(b, 2)
    out = defocus_layered_multi(radiance, s1, offsets, layer_spacing=layer_spacing, kernel_fn=batch_kernel_fn(models),
                                exact_planes=True, occlusion=(mode != "gather"))
    return out[:, :, 0]


def _keys_weights(t: torch.Tensor) -> torch.Tensor:
    """Keys cubic-convolution weights (``a = -1/2``) of the taps at offsets -1, 0, 1, 2 for a
    fractional position ``t`` in [0, 1): ``(n, 4)``. This kernel reproduces polynomials up
    to degree 2, so a resampled image keeps its centroid exactly (PyTorch's bicubic uses
    ``a = -3/4``, which shifts centroids of fractionally moved content by up to ~30 %)."""
    t2, t3 = t * t, t * t * t
    return torch.stack([(-t3 + 2 * t2 - t) / 2, (3 * t3 - 5 * t2 + 2) / 2, (-3 * t3 + 4 * t2 + t) / 2,
                        (t3 - t2) / 2], dim=-1)


def _resample_axis(x: torch.Tensor, pos: torch.Tensor, dim: int) -> torch.Tensor:
    """Values of ``x`` at fractional source positions ``pos`` (px) along ``dim`` (Keys cubic,
    reflected borders)."""
    n = x.shape[dim]
    i0 = torch.floor(pos)
    w = _keys_weights((pos - i0).to(x.dtype))  # (m, 4)
    out = None
    for k in range(4):
        idx = (i0.long() + (k - 1)).abs()  # reflect at 0 ...
        idx = torch.where(idx > n - 1, 2 * (n - 1) - idx, idx).clamp(0, n - 1)  # ... and at n - 1
        shape = [1] * x.ndim
        shape[dim] = -1
        term = x.index_select(dim, idx) * w[:, k].reshape(shape)
        out = term if out is None else out + term
    return out


def _magnify_shift(img: torch.Tensor, scale: float, shift_y: float, shift_x: float) -> torch.Tensor:
    """Content of ``img`` ``(..., H, W)`` magnified by ``scale`` about the centre and moved by
    ``(shift_y, shift_x)`` px: output ``p`` samples the input at ``c + (p - c - shift) / scale``."""
    h, w = img.shape[-2:]
    cy, cx = (h - 1) / 2.0, (w - 1) / 2.0
    py = cy + (torch.arange(h, dtype=torch.float64) - cy - shift_y) / scale
    px = cx + (torch.arange(w, dtype=torch.float64) - cx - shift_x) / scale
    return _resample_axis(_resample_axis(img, py, img.ndim - 2), px, img.ndim - 1)


def warp_pair(frames: torch.Tensor, breathing: float, shift_y_px: float, shift_x_px: float) -> torch.Tensor:
    """Apply focus breathing and misregistration to pairs ``(B, 2, H, W)``: frame 2 ends
    magnified by ``1 + breathing`` and shifted by ``(shift_y_px, shift_x_px)`` relative to
    frame 1, the warp split half and half between the frames (separable Keys cubic
    resampling, reflected borders). Zero parameters return the input unchanged."""
    if breathing == 0 and shift_y_px == 0 and shift_x_px == 0:
        return frames
    half = math.sqrt(1.0 + breathing)
    m = 1.0 + breathing  # frame 2 = c + m (frame-1 position - c) + shift, exactly
    f1 = _magnify_shift(frames[:, 0], 1.0 / half, -0.5 * shift_y_px / m, -0.5 * shift_x_px / m)
    f2 = _magnify_shift(frames[:, 1], half, 0.5 * shift_y_px, 0.5 * shift_x_px)
    return torch.stack([f1, f2], dim=1)


class SynthBatchGenerator:
    """Procedural DFD pairs, deterministic per ``(seed, index)``.

    Args:
        size: image size ``(H, W)`` or a side length (px).
        camera: the camera (default the ``reference`` preset).
        seed: the stream seed.
        config: a :class:`~data_synth.params.SynthConfig` (default the training mix);
            keyword ``overrides`` replace its fields.
        return_sharp: also return the sharp radiance (``sharp``) of each sample.

    Example:
        >>> gen = SynthBatchGenerator(size=64, seed=3, config=SynthConfig(tile=32, stride=16))
        >>> s = gen.sample(0)
        >>> s["image_f1"].shape, s["tile_depth"].shape, s["params"]["index"]
        (torch.Size([1, 64, 64]), torch.Size([1, 3, 3]), 0)
    """

    def __init__(self, size: int | Sequence[int] = 256, camera: Camera | None = None, seed: int = 0,
                 config: SynthConfig | None = None, return_sharp: bool = False, **overrides: Any) -> None:
        self.size = _size(size)
        self.camera = Camera.preset("reference") if camera is None else camera
        self.seed = int(seed)
        cfg = SynthConfig() if config is None else config
        if overrides:
            cfg = SynthConfig.from_dict({**cfg.to_dict(), **overrides})
        self.config = cfg
        grid_shape(*self.size, cfg.tile, cfg.stride)  # validates the grid against the size
        self.window = tile_window(cfg.tile_window, cfg.tile)
        self.return_sharp = bool(return_sharp)

    # ------------------------------------------------------------------ one sample
    def sample(self, index: int) -> dict[str, Any]:
        """Sample ``index``: ``image_f1``, ``image_f2`` ``(1, H, W)`` float32 in [0, 1],
        ``depth`` ``(1, H, W)`` m, ``tile_depth`` ``(1, h, w)`` m and ``params`` (see
        :data:`PARAM_KEYS`)."""
        cfg, cam = self.config, self.camera
        g = sample_generator(self.seed, index)
        with torch.no_grad():
            scene: Scene = make_scene(g, cfg, cam, self.size)
            psf, pparams = draw_psf(g, cfg, cam)
            sparams = draw_sensor(g, cfg)
            wparams = draw_warp(g, cfg)
            mode = {"plane": "auto", "slanted": "gather", "smooth": "gather"}.get(scene.layout, "occlusion")
            frames = render_frames(cam, scene.radiance, scene.depth, psf, mode, cfg.layer_spacing)
            frames = warp_pair(frames, wparams["breathing"], wparams["shift_y_px"], wparams["shift_x_px"])
            frames = frames.clamp_min(0.0)
            frames[:, 1] *= sparams["frame_gain"]
            # auto-exposure on the sharp radiance: mean frame level ~ target_level
            mean_rad = max(det_mean(scene.radiance), 1e-6)
            exposure = sparams["target_level"] / (mean_rad * sparams["gain"])
            if cfg.noise:
                sensor = SensorModel(full_well_e=sparams["full_well_e"], read_noise_e=sparams["read_noise_e"],
                                     bits=sparams["bits"], black_level_dn=sparams["black_level_dn"],
                                     gain=sparams["gain"], exposure=exposure, vignetting=sparams["vignetting"])
                images = sensor(frames, generator=g)
            else:
                images = (frames * (exposure * sparams["gain"])).clamp(0.0, 1.0)
            depth = scene.depth
            tdepth = tile_true_depth(depth, cfg.tile, cfg.stride, self.window)
        params = self._params(index, scene, pparams, sparams, wparams, exposure)
        out = {"image_f1": images[0, 0:1].float().contiguous(), "image_f2": images[0, 1:2].float().contiguous(),
               "depth": depth[0].float(), "tile_depth": tdepth[0].float(), "params": params}
        if self.return_sharp:
            out["sharp"] = scene.radiance[0].float()
        return out

    def _params(self, index: int, scene: Scene, pparams: dict, sparams: dict, wparams: dict, exposure: float) -> dict:
        sp = scene.params
        ill = sp["illumination"]
        fams = sorted({t["family"] for t in sp["textures"]})
        d = scene.depth
        flat = {
            "seed": self.seed, "index": int(index), "sample_seed": sample_seed(self.seed, index),
            "layout": scene.layout, "illumination": ill["illumination"], "textureless": bool(sp["textureless"]),
            "n_objects": len(sp["objects"]), "texture_families": ",".join(fams),
            "depth_min_m": float(d.min()), "depth_max_m": float(d.max()),
            **{k: pparams[k] for k in ("psf_shape", "psf_beta", "wavelength_m", "diffraction_sigma_px", "astigmatism",
                                       "astigmatism_angle", "spherical")},
            "speckle_contrast": float(ill.get("speckle_contrast", 0.0)), "ambient": float(sp["ambient"]),
            **{k: sparams[k] for k in ("bits", "full_well_e", "read_noise_e", "gain", "black_level_dn", "vignetting",
                                       "target_level", "overexposed", "frame_gain")},
            "exposure": float(exposure), **wparams, "noise": bool(self.config.noise),
        }
        flat["details"] = json.dumps({"illumination": ill, "textures": sp["textures"], "objects": sp["objects"],
                                      "inverse_depth_range": sp["inverse_depth_range"]}, sort_keys=True)
        return {k: flat[k] for k in PARAM_KEYS}

    # ------------------------------------------------------------------ batches
    def batch(self, indices: Sequence[int]) -> dict[str, Any]:
        """Samples ``indices`` stacked: tensors ``(N, 1, ., .)`` and ``params`` as a list of
        dicts. Each sample is the same as :meth:`sample` (same bytes)."""
        items = [self.sample(int(i)) for i in indices]
        if not items:
            raise InputError("batch needs at least one index")
        out: dict[str, Any] = {k: torch.stack([it[k] for it in items]) for k in items[0] if k != "params"}
        out["params"] = [it["params"] for it in items]
        return out

    __call__ = batch


def _size(size: int | Sequence[int]) -> tuple[int, int]:
    if isinstance(size, int):
        h = w = size
    else:
        try:
            h, w = (int(v) for v in size)
        except (TypeError, ValueError) as exc:
            raise InputError(f"size must be an int or (H, W), got {size!r}") from exc
    if h < 8 or w < 8:
        raise InputError(f"size must be at least 8 x 8 px, got {(h, w)}")
    return h, w
