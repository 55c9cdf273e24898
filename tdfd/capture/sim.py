r"""The simulated capture rig: a textured plane seen by a *true* camera that differs from
its datasheet.

The true camera (a :class:`~tdfd.camera_file.CameraFile`) adds to the contract camera:

* an ECVFL power offset: the lens's real power is ``P_cmd + ecvfl_offset_dpt``;
* focus breathing: the frame is magnified by ``1 + m (P_cmd + offset)`` about the optical
  centre (:mod:`tdfd.breathing`).

Each frame is rendered with the library's renderer and sensor model, in this order
(``sensor(noise(breathing(blur(x))))``): blur of a fronto-parallel plane with
``sigma = mu r_b`` (paper eqs. 3-4, exact uniform path of
:func:`tdfd.optics.render.defocus_uniform`), magnification, then
:class:`tdfd.sensor.SensorModel` (Poisson-Gaussian noise, black level, 12-bit ADC). The
rig reports the *commanded* power as the read-back power, as a perfect lens driver would
(the offset is what calibration has to find).

Example:
    >>> from tdfd import Camera
    >>> from tdfd.camera_file import CameraFile
    >>> rig = SimulatedRig(CameraFile(Camera.preset("reference"), 0.004, 0.3), distance_m=0.5, size=(64, 64))
    >>> raw, meta = rig.capture(1.7)
    >>> raw.shape, raw.dtype.name, meta["lens_power_dpt"], meta["white_level"]
    ((64, 64), 'uint16', 1.7, 4095)
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from ..breathing import magnify
from ..camera_file import CameraFile
from ..errors import InputError
from ..optics.aberrated_psf import PSFModel
from ..optics.psf import PSFShape
from ..optics.render import defocus_uniform
from ..optics.thin_lens import blur_radius_from_power
from ..sensor import SensorModel, white_level
from ..textures import random_texture

__all__ = ["SimulatedRig"]


class SimulatedRig:
    """A simulated camera + lens looking at a textured plane.

    Args:
        true_camera: the simulated optics, breathing and ECVFL offset.
        distance_m: plane distance in metres.
        size: frame ``(H, W)`` in pixels.
        seed: seed of the texture and of the sensor noise (frame ``k`` uses ``seed + 1 + k``).
        texture: texture family of :mod:`tdfd.textures` (a rich one by default).
        psf: PSF shape of the simulated lens (the analytic estimator assumes ``"gaussian"``), or a
            whole :class:`~tdfd.optics.aberrated_psf.PSFModel` (diffraction and aberrations).
        bits: ADC bit depth; frames are written as 16-bit PNGs with this white level.
        full_well_e, read_noise_e, black_level_dn, exposure: see :class:`~tdfd.sensor.SensorModel`.
        noise: draw sensor noise.
        margin: pixels rendered beyond the frame on each side (blur and magnification).
    """

    def __init__(self, true_camera: CameraFile, distance_m: float, size: tuple[int, int] = (256, 256),
                 seed: int = 0, texture: str = "dead_leaves", psf: PSFShape | PSFModel = "gaussian", bits: int = 12,
                 full_well_e: float = 20000.0, read_noise_e: float = 3.0, black_level_dn: float = 64.0,
                 exposure: float = 0.8, noise: bool = True, margin: int = 32) -> None:
        if not np.isfinite(distance_m) or distance_m <= 0:
            raise InputError(f"distance_m must be finite and > 0, got {distance_m}")
        h, w = (int(v) for v in size)
        if h < 16 or w < 16:
            raise InputError(f"frame size must be at least 16x16, got {h}x{w}")
        self.true_camera, self.distance_m, self.size = true_camera, float(distance_m), (h, w)
        self.seed, self.psf, self.margin, self.bits = int(seed), psf, int(margin), int(bits)
        g = torch.Generator().manual_seed(self.seed)
        tex, self.texture_params = random_texture(g, (h + 2 * margin, w + 2 * margin), family=texture,
                                                  albedo=(0.75, 0.85), contrast=(0.7, 1.0))
        self.sharp = tex.to(torch.float64)
        self.sensor = SensorModel(full_well_e=full_well_e, read_noise_e=read_noise_e, bits=bits,
                                  black_level_dn=black_level_dn, exposure=exposure, noise=noise)
        self.frames = 0

    def actual_power_dpt(self, commanded_dpt: float) -> float:
        """The real ECVFL power for a command."""
        return float(commanded_dpt) + self.true_camera.ecvfl_offset_dpt

    def sigma_px(self, commanded_dpt: float) -> float:
        """Signed blur parameter of the plane at a commanded power (eq. 4 at the real power)."""
        cam = self.true_camera.camera
        r = float(blur_radius_from_power(cam, self.distance_m, self.actual_power_dpt(commanded_dpt)))
        return cam.mu_px_per_m * r

    def in_focus_command_dpt(self) -> float:
        """The commanded power that focuses the plane (the truth calibration should recover)."""
        return self.true_camera.camera.in_focus_power_dpt(self.distance_m) - self.true_camera.ecvfl_offset_dpt

    def capture(self, commanded_dpt: float) -> tuple[np.ndarray, dict[str, Any]]:
        """One frame at a commanded ECVFL power.

        Returns:
            ``(raw (H, W) uint16, sidecar dict)`` with ``lens_power_dpt`` (the command) and
            ``white_level``.
        """
        sigma = torch.tensor([self.sigma_px(commanded_dpt)], dtype=torch.float64)
        if isinstance(self.psf, PSFModel):  # point-symmetric kernels: correlation is convolution
            k = self.psf.kernels(sigma)
            blurred = torch.nn.functional.conv2d(self.sharp, k[None], padding=k.shape[-1] // 2)[0, 0].numpy()
        else:
            blurred = defocus_uniform(self.sharp, sigma, self.psf)[0, 0].numpy()
        scale = self.true_camera.scale_at(self.actual_power_dpt(commanded_dpt))
        frame = magnify(blurred, scale, out_shape=self.size)
        g = torch.Generator().manual_seed(self.seed + 1 + self.frames)
        self.frames += 1
        y = self.sensor(torch.from_numpy(frame)[None, None], generator=g)[0, 0].numpy()
        wl = white_level(self.bits)
        raw = np.clip(np.round(y * wl), 0, wl).astype(np.uint16)
        return raw, {"lens_power_dpt": float(commanded_dpt), "white_level": wl, "time_s": float(self.frames)}

    def close(self) -> None:
        """Nothing to release (symmetry with the hardware rig)."""
