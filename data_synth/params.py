"""Configuration and random parameter draws of the synthesiser.

:class:`SynthConfig` holds every knob (ranges and probabilities); the ``draw_*`` functions
turn a :class:`torch.Generator` into concrete parameters (plain Python values). Every
sample owns its generator, seeded from ``(seed, index)`` by :func:`sample_seed`, so a sample
is a pure function of ``(config, camera, seed, index)``.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np
import torch

from tdfd import Camera
from tdfd.errors import InputError
from tdfd.textures import TEXTURE_FAMILIES, family_weights

from .psf import PSFModel, diffraction_sigma_px

__all__ = ["SynthConfig", "LAYOUTS", "PSF_SHAPES", "sample_seed", "sample_generator", "uniform", "log_uniform",
           "randint", "choice", "bernoulli", "inverse_depth_range", "draw_psf", "draw_sensor", "draw_warp"]

#: Depth layouts: fronto-parallel plane, slanted plane, piecewise-planar with occlusions, smooth surface.
LAYOUTS = ("plane", "slanted", "layout", "smooth")
#: PSF shape options: the two ends and the power-exponential family between them.
PSF_SHAPES = ("gaussian", "pillbox", "beta")


def sample_seed(seed: int, index: int) -> int:
    """A 63-bit seed for sample ``index`` of stream ``seed`` (numpy ``SeedSequence`` mixing,
    so neighbouring seeds and indices give unrelated streams)."""
    if int(index) != index or index < 0:
        raise InputError(f"sample index must be a non-negative integer, got {index!r}")
    state = np.random.SeedSequence([int(seed) & 0xFFFFFFFFFFFFFFFF, int(index)]).generate_state(2, np.uint32)
    return int((int(state[0]) << 31) ^ int(state[1])) & 0x7FFFFFFFFFFFFFFF


def sample_generator(seed: int, index: int) -> torch.Generator:
    """The :class:`torch.Generator` of sample ``index`` (see :func:`sample_seed`)."""
    return torch.Generator().manual_seed(sample_seed(seed, index))


def uniform(g: torch.Generator, lo: float, hi: float) -> float:
    """A uniform float in [lo, hi)."""
    return lo + (hi - lo) * float(torch.rand((), generator=g, dtype=torch.float64))


def log_uniform(g: torch.Generator, lo: float, hi: float) -> float:
    """A log-uniform float in [lo, hi)."""
    return math.exp(uniform(g, math.log(lo), math.log(hi)))


def randint(g: torch.Generator, lo: int, hi: int) -> int:
    """An integer in [lo, hi]."""
    return int(torch.randint(int(lo), int(hi) + 1, (), generator=g))


def bernoulli(g: torch.Generator, p: float) -> bool:
    """True with probability ``p``."""
    return uniform(g, 0.0, 1.0) < p


def choice(g: torch.Generator, options: Sequence[Any], weights: Sequence[float] | None = None) -> Any:
    """One of ``options`` (uniform, or with relative ``weights``)."""
    if not options:
        raise InputError("nothing to choose from")
    if weights is None:
        return options[randint(g, 0, len(options) - 1)]
    w = np.asarray(weights, dtype=np.float64)
    u = uniform(g, 0.0, float(w.sum()))
    return options[int(min(np.searchsorted(np.cumsum(w), u, side="right"), len(options) - 1))]


@dataclass
class SynthConfig:
    """Every knob of the synthesiser. Defaults give the training mix.

    Scene:
        layouts: relative frequency of each depth layout (:data:`LAYOUTS`).
        families: texture families to draw from (default: all registered), uniformly; or a
            mapping ``{family: relative weight}`` (a family it leaves out is never drawn), which
            shifts the mix towards families an estimator finds hard without leaving any out.
        depth_margin: the depth range sampled is ``camera.depth_range_m`` widened by this
            fraction on both sides (``near / (1 + m)`` to ``far * (1 + m)``), uniformly in
            inverse depth.
        max_objects: most foreground objects of a ``layout`` scene.
        slant_spread: largest inverse-depth spread of a slanted plane, as a fraction of the
            sampled inverse-depth range.
        spectral_tilt: largest tilt of a texture's amplitude spectrum
            (:func:`tdfd.textures.spectral_tilt`): every textured surface's spectrum is tilted
            by ``(f / 0.1 cycles/px)^a``, ``a`` uniform in ``[-spectral_tilt, spectral_tilt]``,
            so that a frame's spectral shape stops telling its blur (0: off, the default; no
            draw is made, the same scenes as before).
    Illumination:
        illumination_prob: probability of an active source (else ambient light only).
        coherent_fraction: fraction of active sources that are the coherent module (the
            rest are the incoherent projector).
        speckle_prob: probability of laser speckle on a coherent pattern.
        textureless_prob: probability that an actively lit scene is a texture-less target.
        mask_feature_px: range of the pattern's feature size (bar width, period / 2, ...) in
            pixels at the pattern's reference distance, drawn log-uniformly. The paper's
            two-bar mask seen by the reference camera has bars about 30 px wide.
    Optics:
        psf_shapes: shapes drawn uniformly from (:data:`PSF_SHAPES`; ``"beta"`` draws a
            power-exponential exponent from ``beta_range`` log-uniformly).
        diffraction_prob, wavelength_range_m: diffraction softening and its wavelength.
        aberration_prob, astigmatism_max, spherical_max: mild aberration.
        layer_spacing: layer spacing of the renderer in px of sigma (accuracy budget, see
            ``docs/BENCHMARKS.md``).
    Sensor:
        noise: apply the sensor model (``False``: ideal linear frames, no noise, no black
            level, no quantisation, no vignetting).
        bits: ADC depths to draw from; full_well_range_e, read_noise_range_e, gain_range,
            black_level_max (fraction of white), vignetting_max, level_range (mean frame
            level the auto-exposure aims at, log-uniform), overexpose_prob (aim at
            ``overexpose_level`` instead: saturated highlights), frame_gain_jitter (relative
            brightness difference between the frames: flicker, exposure jitter).
    Geometry:
        breathing_prob, breathing_max: focus breathing (relative magnification between the
            frames, uniform in ``[-max, max]``).
        shift_prob, shift_max_px: sub-pixel misregistration between the frames.
    Output:
        tile, stride: the tile grid of ``tile_depth``.
        tile_window: ``"hann2"`` (squared periodic Hann, the power weighting of the windowed
            tile spectra the DFD estimators fit; default), ``"hann"`` or ``"box"``.
    """

    layouts: dict = field(default_factory=lambda: {"plane": 0.15, "slanted": 0.25, "layout": 0.4, "smooth": 0.2})
    families: tuple | dict | None = None
    depth_margin: float = 0.1
    max_objects: int = 4
    slant_spread: float = 0.6
    spectral_tilt: float = 0.0
    illumination_prob: float = 0.3
    coherent_fraction: float = 0.6
    speckle_prob: float = 0.5
    textureless_prob: float = 0.5
    mask_feature_px: tuple = (3.0, 24.0)
    psf_shapes: tuple = PSF_SHAPES
    beta_range: tuple = (2.5, 16.0)
    diffraction_prob: float = 0.7
    wavelength_range_m: tuple = (450e-9, 850e-9)
    aberration_prob: float = 0.4
    astigmatism_max: float = 0.15
    spherical_max: float = 0.3
    layer_spacing: float = 0.5
    noise: bool = True
    bits: tuple = (8, 10, 12)
    full_well_range_e: tuple = (3000.0, 40000.0)
    read_noise_range_e: tuple = (1.0, 8.0)
    gain_range: tuple = (1.0, 4.0)
    black_level_max: float = 0.06
    vignetting_prob: float = 0.5
    vignetting_max: float = 0.3
    level_range: tuple = (0.08, 0.6)
    overexpose_prob: float = 0.08
    overexpose_level: tuple = (0.6, 1.0)
    frame_gain_jitter: float = 0.02
    breathing_prob: float = 0.5
    breathing_max: float = 0.01
    shift_prob: float = 0.5
    shift_max_px: float = 0.5
    tile: int = 64
    stride: int = 32
    tile_window: str = "hann2"

    def __post_init__(self) -> None:
        if isinstance(self.layouts, (list, tuple)):
            self.layouts = {k: 1.0 for k in self.layouts}
        self.layouts = {str(k): float(v) for k, v in dict(self.layouts).items()}
        bad = sorted(set(self.layouts) - set(LAYOUTS))
        if bad or not self.layouts or any(v < 0 for v in self.layouts.values()) or sum(self.layouts.values()) <= 0:
            raise InputError(f"layouts must weight some of {LAYOUTS}, got {self.layouts}")
        if isinstance(self.families, dict):
            self.families = family_weights(self.families)
        elif self.families is not None:
            self.families = tuple(self.families)
        if self.families is not None:
            unknown = sorted(set(self.families) - set(TEXTURE_FAMILIES))
            if unknown or not self.families:
                raise InputError(f"unknown texture families {unknown}; known: {sorted(TEXTURE_FAMILIES)}")
        self.psf_shapes = tuple(self.psf_shapes)
        for s in self.psf_shapes:
            if s not in PSF_SHAPES:
                try:
                    if float(s) < 1:
                        raise ValueError
                except (TypeError, ValueError):
                    raise InputError(f"psf_shapes must be among {PSF_SHAPES} or betas >= 1, got {s!r}") from None
        if not self.psf_shapes:
            raise InputError("psf_shapes is empty")
        self.bits = tuple(int(b) for b in self.bits)
        if not self.bits or any(not 8 <= b <= 16 for b in self.bits):
            raise InputError(f"bits must lie in [8, 16], got {self.bits}")
        if self.tile_window not in ("hann2", "hann", "box"):
            raise InputError(f"tile_window must be 'hann2', 'hann' or 'box', got {self.tile_window!r}")
        self.mask_feature_px = tuple(float(v) for v in self.mask_feature_px)
        if len(self.mask_feature_px) != 2 or not 1.0 <= self.mask_feature_px[0] <= self.mask_feature_px[1]:
            raise InputError(f"mask_feature_px must be (low, high) px with 1 <= low <= high, got {self.mask_feature_px}")
        if isinstance(self.spectral_tilt, bool) or not isinstance(self.spectral_tilt, (int, float)) \
                or not 0.0 <= self.spectral_tilt <= 2.0:
            raise InputError(f"spectral_tilt must be a number in [0, 2], got {self.spectral_tilt!r}")
        self.spectral_tilt = float(self.spectral_tilt)
        if not 0 <= self.breathing_max <= 0.05 or self.shift_max_px < 0 or self.layer_spacing <= 0:
            raise InputError("need 0 <= breathing_max <= 0.05, shift_max_px >= 0 and layer_spacing > 0")
        if self.depth_margin < 0 or self.max_objects < 1:
            raise InputError("need depth_margin >= 0 and max_objects >= 1")
        for name in ("illumination_prob", "coherent_fraction", "speckle_prob", "textureless_prob", "diffraction_prob",
                     "aberration_prob", "vignetting_prob", "overexpose_prob", "breathing_prob", "shift_prob"):
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                raise InputError(f"{name} must lie in [0, 1], got {v}")

    def to_dict(self) -> dict:
        """Plain JSON-able dict (for manifests)."""
        d = dataclasses.asdict(self)
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in d.items()}

    @classmethod
    def from_dict(cls, data: dict) -> "SynthConfig":
        """Inverse of :meth:`to_dict` (unknown keys raise :class:`~tdfd.errors.InputError`)."""
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - names)
        if unknown:
            raise InputError(f"unknown synthesis options {unknown}")
        return cls(**{k: (tuple(v) if isinstance(v, list) else v) for k, v in data.items()})


def inverse_depth_range(camera: Camera, margin: float) -> tuple[float, float]:
    """``(q_min, q_max)`` in 1/m: the camera's range widened by ``margin`` on both sides."""
    near, far = camera.depth_range_m
    return 1.0 / (far * (1.0 + margin)), (1.0 + margin) / near


def draw_psf(g: torch.Generator, cfg: SynthConfig, camera: Camera) -> tuple[PSFModel, dict]:
    """A random :class:`~data_synth.psf.PSFModel` and its parameters."""
    shape = choice(g, cfg.psf_shapes)
    if shape == "beta":
        beta = log_uniform(g, *cfg.beta_range)
        shape_v: str | float = beta
    elif shape in ("gaussian", "pillbox"):
        beta = 2.0 if shape == "gaussian" else math.inf
        shape_v = shape
    else:
        beta = float(shape)
        shape_v = beta
    diff = 0.0
    wavelength = 0.0
    if bernoulli(g, cfg.diffraction_prob):
        wavelength = uniform(g, *cfg.wavelength_range_m)
        f_number = camera.focal_lengths_m[0] / camera.aperture_m
        diff = diffraction_sigma_px(f_number, wavelength, camera.pixel_pitch_m)
    astig = angle = sph = 0.0
    if bernoulli(g, cfg.aberration_prob):
        astig = uniform(g, 0.0, cfg.astigmatism_max)
        angle = uniform(g, 0.0, math.pi)
        sph = uniform(g, -cfg.spherical_max, cfg.spherical_max)
    model = PSFModel(shape_v, diff, astig, angle, sph)
    params = {"psf_shape": "beta" if not isinstance(shape_v, str) else shape_v,
              "psf_beta": beta if math.isfinite(beta) else -1.0, "wavelength_m": wavelength,
              "diffraction_sigma_px": diff, "astigmatism": astig, "astigmatism_angle": angle, "spherical": sph}
    return model, params


def draw_sensor(g: torch.Generator, cfg: SynthConfig) -> dict:
    """Random sensor parameters (see :class:`tdfd.sensor.SensorModel`) and the exposure target."""
    bits = int(choice(g, cfg.bits))
    white = 2**bits - 1
    over = bernoulli(g, cfg.overexpose_prob)
    return {
        "bits": bits,
        "full_well_e": log_uniform(g, *cfg.full_well_range_e),
        "read_noise_e": uniform(g, *cfg.read_noise_range_e),
        "gain": log_uniform(g, *cfg.gain_range),
        "black_level_dn": float(round(uniform(g, 0.0, cfg.black_level_max) * white)),
        "vignetting": uniform(g, 0.0, cfg.vignetting_max) if bernoulli(g, cfg.vignetting_prob) else 0.0,
        "target_level": uniform(g, *cfg.overexpose_level) if over else log_uniform(g, *cfg.level_range),
        "overexposed": bool(over),
        "frame_gain": 1.0 + uniform(g, -cfg.frame_gain_jitter, cfg.frame_gain_jitter),
    }


def draw_warp(g: torch.Generator, cfg: SynthConfig) -> dict:
    """Focus breathing (relative magnification - 1) and misregistration (px) of frame 2 vs 1."""
    b = uniform(g, -cfg.breathing_max, cfg.breathing_max) if bernoulli(g, cfg.breathing_prob) else 0.0
    if bernoulli(g, cfg.shift_prob):
        sy, sx = uniform(g, -cfg.shift_max_px, cfg.shift_max_px), uniform(g, -cfg.shift_max_px, cfg.shift_max_px)
    else:
        sy = sx = 0.0
    return {"breathing": b, "shift_y_px": sy, "shift_x_px": sx}
