r"""The simulated assist light of the autofocus bench: the paper's two illuminators.

``on("coherent")`` lights the scene with :class:`tdfd.illumination.CoherentIllumination`
(the sharpness-retaining laser pattern, paper sec. 2.1: the same physical size and sharp
edges at every distance), ``on("projector")`` with
:class:`tdfd.illumination.ProjectorIllumination` (focused at 56.8 cm with the paper's
depth of field, 44.3-73.3 cm, blurred outside it). Both default to the paper's mask (two
6.2 mm x 18.9 mm bars 6.2 mm apart).

Scene radiance (Lambertian target, :func:`tdfd.illumination.illuminate`):

.. math:: L = \rho \, (E_\mathrm{amb} + P \, E_\mathrm{pattern})

with ``rho`` the scene's albedo (the bench's :class:`~tdfd.autofocus.bench.Scene` image is
its radiance under unit ambient irradiance, i.e. its albedo), ``E_amb`` the ambient
irradiance (``ambient``), ``E_pattern`` the pattern's relative irradiance and ``P`` the
source's power. The camera then blurs ``L`` and adds sensor noise (the bench's virtual
camera does that).

Power: the coherent pattern's peak irradiance is ``power`` at every distance (a
collimated beam). The projector's falls as ``(focus / d)^2``; it is scaled so that its
peak equals ``power`` at ``projector_peak_at_m`` (default 0.3 m, the near end of the
working range: one fixed exposure that never saturates on the pattern, as a camera
without auto-exposure would be set up). With the defaults (``ambient = 1``,
``power = 0.8``) a mid-grey target (albedo 0.5) reads 0.5 in the dark and 0.9 on the
coherent bars.

Example:
    >>> import numpy as np
    >>> from tdfd import Camera
    >>> light = SimulatedLight(Camera.preset("reference"))
    >>> albedo, depth = np.full((64, 96), 0.5), np.full((64, 96), 0.5)
    >>> float(light.radiance(albedo, depth).max())          # off: ambient only
    0.5
    >>> light.on("coherent"); round(float(light.radiance(albedo, depth).max()), 3)
    0.9
"""

from __future__ import annotations

import logging
from typing import Any, Mapping

import numpy as np

from ..camera import Camera
from ..errors import InputError, ShapeError
from ..illumination import CoherentIllumination, ProjectorIllumination, illuminate
from .base import AssistLight

__all__ = ["SimulatedLight", "SIMULATED_PATTERNS"]

log = logging.getLogger(__name__)

#: the patterns of the simulated light.
SIMULATED_PATTERNS = ("coherent", "projector")


class SimulatedLight(AssistLight):
    """The bench's assist light: the coherent module or the projector, with ambient light.

    Args:
        camera: the imaging camera (pixel geometry of the pattern).
        coherent: the coherent module (default: the paper's mask, no speckle).
        projector: the projector (default: focused at 0.568 m, paper's depth of field).
        ambient: ambient irradiance (relative; 1 = the scene as the bench renders it unlit).
        power: the source's peak irradiance relative to ``ambient = 1`` (module docs).
        projector_peak_at_m: distance at which the projector's peak equals ``power`` (m).
        seed: seeds the laser speckle (used only if the coherent module has speckle).
        patterns: restrict the patterns offered (default both); the first is the default.

    Raises:
        InputError: negative ambient, power <= 0, or an unknown pattern name.
    """

    def __init__(self, camera: Camera, coherent: CoherentIllumination | None = None,
                 projector: ProjectorIllumination | None = None, ambient: float = 1.0, power: float = 0.8,
                 projector_peak_at_m: float = 0.3, seed: int = 0,
                 patterns: tuple[str, ...] = SIMULATED_PATTERNS) -> None:
        super().__init__()
        if not (ambient >= 0 and power > 0 and projector_peak_at_m > 0):
            raise InputError(f"need ambient >= 0, power > 0 and projector_peak_at_m > 0, got {ambient}, {power}, "
                             f"{projector_peak_at_m}")
        bad = [p for p in patterns if p not in SIMULATED_PATTERNS]
        if bad or not patterns:
            raise InputError(f"simulated light patterns must be among {SIMULATED_PATTERNS}, got {patterns}")
        self.camera = camera
        self.modules: Mapping[str, Any] = {"coherent": coherent or CoherentIllumination(),
                                           "projector": projector or ProjectorIllumination()}
        self.ambient, self.power = float(ambient), float(power)
        self.projector_peak_at_m, self.seed = float(projector_peak_at_m), int(seed)
        self.patterns = tuple(patterns)
        self.name = "simulated:" + "|".join(self.patterns)
        self.switch_count = 0
        self._cache: dict[tuple[str, int], tuple[np.ndarray, np.ndarray]] = {}

    # ------------------------------------------------------------------ AssistLight
    def _switch_on(self, pattern: str) -> None:
        self.switch_count += 1

    def _switch_off(self) -> None:
        pass

    # ------------------------------------------------------------------ rendering
    def source_power(self, pattern: str) -> float:
        """Scale of :meth:`pattern_irradiance` for ``pattern`` (module docs)."""
        if pattern == "projector":
            proj = self.modules["projector"]
            return self.power * (self.projector_peak_at_m / proj.focus_m) ** 2
        return self.power

    def pattern_irradiance(self, pattern: str, depth_m: np.ndarray) -> np.ndarray:
        """The pattern's relative irradiance on a scene, ``(H, W)``, from its depth map (m).

        The image centre is the optical axis (the bench's read-out window is centred on
        the sensor). Cached for the last depth maps seen (the bench renders each scene
        many times).
        """
        import torch

        depth_m = np.asarray(depth_m, dtype=np.float64)
        if depth_m.ndim != 2:
            raise ShapeError(f"depth map must be (H, W), got {depth_m.shape}")
        key = (self.resolve_pattern(pattern), id(depth_m))
        hit = self._cache.get(key)
        if hit is not None and hit[0] is depth_m:
            return hit[1]
        d = torch.from_numpy(np.ascontiguousarray(depth_m, dtype=np.float32))[None, None]
        gen = torch.Generator().manual_seed(self.seed)
        with torch.no_grad():
            irr = self.modules[key[0]].render(self.camera, d, generator=gen)[0, 0].double().numpy()
        if len(self._cache) >= 8:
            self._cache.clear()
        self._cache[key] = (depth_m, irr)  # keep the array alive: its id stays unique
        return irr

    def radiance(self, albedo: np.ndarray, depth_m: np.ndarray, pattern: str | None = None) -> np.ndarray:
        """Scene radiance ``albedo * (ambient + power * pattern)``, ``(H, W)``.

        Args:
            albedo: ``(H, W)`` reflectance (the bench scene's image).
            depth_m: ``(H, W)`` distance (m).
            pattern: the pattern to light with; default: the one shown now (``None`` when
                the light is off, which leaves ambient light only).
        """
        import torch

        albedo = np.asarray(albedo, dtype=np.float64)
        if albedo.shape != np.shape(depth_m):
            raise ShapeError(f"albedo {albedo.shape} and depth {np.shape(depth_m)} differ")
        p = pattern if pattern is not None else self.pattern
        a = torch.from_numpy(albedo)[None, None]
        if p is None:
            return illuminate(a, None, self.ambient)[0, 0].numpy()
        irr = torch.from_numpy(self.pattern_irradiance(p, depth_m))[None, None]
        return illuminate(a, irr, self.ambient, self.source_power(p))[0, 0].numpy()
