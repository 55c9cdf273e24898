r"""The synthesiser: random scenes and parameters through the forward model (:mod:`tdfd.forward`).

:class:`SynthBatchGenerator` makes sample ``index`` of stream ``seed`` from its own
generator (:func:`~data_synth.params.sample_generator`), so every sample is a pure function
of ``(config, camera, size, seed, index)``: the same bytes whatever the batch it is made in,
the worker that makes it, or the order of requests.

Image formation per sample (the draws in this order from the sample's generator, which
then feeds the sensor noise; :class:`tdfd.forward.DFDForward` composes steps 2-4):

1. :func:`~data_synth.scenes.make_scene`: sharp radiance and depth.
2. Both frames in one pass (:func:`tdfd.forward.defocus_pair`: the camera's
   two ECVFL powers share one layer decomposition; their blur maps differ by the constant
   of paper eq. 6) with the sample's :class:`~data_synth.psf.PSFModel`. A fronto-parallel
   plane takes the exact single-PSF path, slanted and smooth surfaces the gather mode (no
   depth discontinuities), piecewise-planar layouts the occluding layered mode.
3. Focus breathing and misregistration (:func:`tdfd.warp.misregister`): frame 2 is
   magnified by ``1 + breathing`` about the image centre and shifted by ``(shift_y,
   shift_x)`` px relative to frame 1, the warp split symmetrically between the frames.
4. A small frame-to-frame gain difference (:func:`tdfd.forward.frame_gain`), auto-exposure
   to the drawn mean level, then :class:`tdfd.sensor.SensorModel` (Poisson-Gaussian noise, black level, gain, 8-12 bit
   quantisation, vignetting, saturation), independently per frame.
5. ``tile_depth``: :func:`tdfd.grid.tile_true_depth` with the configured window.
"""

from __future__ import annotations

import json
from typing import Any, Sequence

import torch

from tdfd import Camera
from tdfd.dfd.spectra import periodic_hann
from tdfd.errors import InputError
from tdfd.grid import grid_shape, tile_true_depth
from tdfd.forward import Defocus, DFDForward, IdealSensor, misregister
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
    """Both DFD frames of a scene, noise-free: ``(B, 2, H, W)``: the forward model's defocus
    stage (:func:`tdfd.forward.defocus_pair`) with the samples' lens PSFs.

    Args:
        camera: the camera (its two ECVFL powers, ``mu``).
        radiance: ``(B, 1, H, W)`` sharp radiance.
        depth_m: ``(B, 1, H, W)`` depth in metres.
        psf: one :class:`~data_synth.psf.PSFModel` per sample (or one for all).
        mode: ``"occlusion"`` (layered, occluding), ``"gather"`` (smooth depth maps) or
            ``"auto"`` (occluding; exact single PSF for constant depth).
        layer_spacing: layer spacing in px of sigma.
    """
    return Defocus(camera, _kernel_fn(psf, radiance.shape[0]), mode, layer_spacing)(radiance, depth_m)


def _kernel_fn(psf: PSFModel | Sequence[PSFModel], b: int):
    models = [psf] * b if isinstance(psf, PSFModel) else list(psf)
    if len(models) != b:
        raise InputError(f"need one PSF model per sample ({b}), got {len(models)}")
    return batch_kernel_fn(models)


#: Focus breathing and misregistration of pairs ``(B, 2, H, W)`` (:func:`tdfd.warp.misregister`).
warp_pair = misregister


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
            # auto-exposure on the sharp radiance: mean frame level ~ target_level
            mean_rad = max(det_mean(scene.radiance), 1e-6)
            exposure = sparams["target_level"] / (mean_rad * sparams["gain"])
            if cfg.noise:
                sensor: torch.nn.Module = SensorModel(
                    full_well_e=sparams["full_well_e"], read_noise_e=sparams["read_noise_e"], bits=sparams["bits"],
                    black_level_dn=sparams["black_level_dn"], gain=sparams["gain"], exposure=exposure,
                    vignetting=sparams["vignetting"])
            else:
                sensor = IdealSensor(exposure, sparams["gain"])
            forward = DFDForward(Defocus(cam, _kernel_fn(psf, 1), mode, cfg.layer_spacing), sensor)
            images = forward(scene.radiance, scene.depth, breathing=wparams["breathing"],
                             shift_y_px=wparams["shift_y_px"], shift_x_px=wparams["shift_x_px"],
                             frame_gain=sparams["frame_gain"], generator=g)
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
