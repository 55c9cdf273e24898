r"""The virtual camera: renders a :class:`~tdfd.autofocus.sim.scene.Scene` at the lens's optical power
during each exposure, adds sensor noise, and keeps the frame timing."""

from __future__ import annotations

from typing import Any, Callable, Sequence

import numpy as np

from ...breathing import magnify
from ...camera import Camera
from ..threads import torch_threads
from .noise import SensorNoise
from .scene import Scene
from .timing import CameraTiming

__all__ = ["VirtualCamera"]


class VirtualCamera:
    """Renders frames of a :class:`Scene` at the lens's optical power during the exposure.

    Args:
        camera: optics (aperture, sensor distance, fixed lens, pixel pitch, ``mu``).
        scene: what is seen.
        power_at: the optical ECVFL power at a simulated time, ``t -> dpt``.
        timing: frame timing.
        noise: sensor noise.
        rng: noise generator (seeded by the bench).
        psf: PSF shape of the simulated optics (``"gaussian"``, ``"pillbox"`` or a
            power-exponential ``beta``).
        mu: true blur constant in px/m (default ``camera.mu_px_per_m``).
        threads: torch threads while rendering (restored afterwards; ``None``: unchanged).
        light: a :class:`~tdfd.light.simulated.SimulatedLight` lighting the scene while it
            is on (the scene image is then the albedo, :meth:`SimulatedLight.radiance`);
            ``None``: the scene as it is.
        power_offset_dpt: the ECVFL's real power minus the power ``power_at`` reports (a
            lens whose power differs from its datasheet, :mod:`tdfd.capture.sim`); the
            frame is rendered at the real power.
        magnification_per_dpt: focus breathing: each render is magnified by ``1 + m P``
            (``P`` the real power) about the frame centre (:func:`tdfd.breathing.magnify`).
    """

    def __init__(self, camera: Camera, scene: Scene, power_at: Callable[[float], float],
                 timing: CameraTiming = CameraTiming(), noise: SensorNoise = SensorNoise(),
                 rng: np.random.Generator | None = None, psf: Any = "gaussian", mu: float | None = None,
                 threads: int | None = 1, light: Any | None = None, power_offset_dpt: float = 0.0,
                 magnification_per_dpt: float = 0.0) -> None:
        self.camera, self.scene, self.power_at = camera, scene, power_at
        self.power_offset_dpt, self.magnification_per_dpt = float(power_offset_dpt), float(magnification_per_dpt)
        self.timing, self.noise = timing, noise
        self.rng = rng if rng is not None else np.random.default_rng(0)
        self.psf, self.mu, self.threads = psf, mu, threads
        self.last_start_s: float | None = None
        self.light = light
        self._cache: tuple[Any, Any, Any] | None = None

    def _tensors(self):
        import torch

        pattern = self.light.pattern if self.light is not None else None
        key = (self.scene, pattern)
        if self._cache is None or self._cache[0][0] is not self.scene or self._cache[0][1] != pattern:
            radiance = self.scene.sharp if self.light is None else self.light.radiance(self.scene.sharp, self.scene.depth_m)
            # numpy does the dtype conversion: no torch thread pool involved
            sharp = torch.from_numpy(np.ascontiguousarray(radiance, dtype=np.float32))[None, None]
            depth = torch.from_numpy(np.ascontiguousarray(self.scene.depth_m, dtype=np.float32))[None, None]
            self._cache = (key, sharp, depth)
        return self._cache[1], self._cache[2]

    def render(self, powers_dpt: Sequence[float]) -> np.ndarray:
        """Noise-free frame: the mean of the renders at ``powers_dpt`` (the exposure's samples)."""
        import torch

        from ...optics.render import render_at_power

        sharp, depth = self._tensors()
        real = [float(v) + self.power_offset_dpt for v in powers_dpt]
        p = torch.tensor(real, dtype=torch.float32)
        with torch.no_grad(), torch_threads(self.threads):
            out = render_at_power(self.camera, sharp.expand(len(p), -1, -1, -1), depth.expand(len(p), -1, -1, -1),
                                  p, shape=self.psf, mu=self.mu)
            if not self.magnification_per_dpt:
                out = out[0, 0] if len(p) == 1 else out.mean(0)[0]
                return out.numpy().astype(np.float64)
        frames = [magnify(o.numpy().astype(np.float64), 1.0 + self.magnification_per_dpt * q) for o, q in zip(out[:, 0], real)]
        return frames[0] if len(frames) == 1 else np.mean(frames, axis=0)

    def expose(self, t_start_s: float) -> tuple[np.ndarray, float]:
        """Expose from ``t_start_s`` for ``timing.exposure_s``.

        Returns:
            ``(frame (H, W) float32 in [0, 1], mean optical power during the exposure in dpt)``.
        """
        e = self.timing.exposure_s
        samples = [self.power_at(t_start_s + f * e) for f in (0.0, 0.5, 1.0)]
        powers = [samples[1]] if max(samples) - min(samples) < 2e-3 else samples
        self.last_start_s = t_start_s
        return self.noise.apply(self.render(powers), self.rng), float(np.mean(samples))
