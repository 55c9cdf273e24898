r"""The simulated lens's PSF family, measured as a user measures a real one: a focus sweep.

A camera file's ``psf_family`` comes from ``tdfd calibrate`` on a focus sweep of a textured
target (:mod:`tdfd.calibration.psf_family`). On the simulated bench the same measurement
runs on the same kind of captures: :class:`tdfd.capture.sim.SimulatedRig` renders a
band-limited noise target (a printed random-noise chart) at ``distance_m`` through the bench's optics (its PSF shape, sensor noise
and 12-bit ADC), at powers spanning its in-focus power, and the cross-blur costs decide the
family. The controller is then told what was measured, never the simulator's setting:
``tdfd autofocus --sim --psf pillbox --psf-family calibrate`` and the reliability
benchmark's ``--psf-family calibrate`` configuration.

Example:
    >>> from tdfd import Camera
    >>> fit = measure_sim_psf_family(Camera.preset("reference"), "pillbox", seed=0, size=(128, 128))
    >>> fit.family
    'pillbox'
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

from ...calibration.psf_family import PsfFamilyFit, psf_family_from_frames
from ...camera import Camera
from ...camera_file import CameraFile
from ...capture.sim import SimulatedRig
from ...errors import InputError
from ..evidence import sigma_px_per_dpt

__all__ = ["measure_sim_psf_family", "SWEEP_HALF_SPAN_PX", "SWEEP_FRAMES"]

log = logging.getLogger(__name__)

#: the sweep spans the target's in-focus power +- the power that blurs by this Gaussian sigma (px)
SWEEP_HALF_SPAN_PX = 3.0
#: frames of the sweep
SWEEP_FRAMES = 9


def measure_sim_psf_family(camera: Camera, psf: Any, *, seed: int = 0, distance_m: float = 0.5,
                           size: tuple[int, int] = (256, 256), texture: str = "bandlimited") -> PsfFamilyFit:
    """The PSF family a focus sweep through the simulated optics gives (module docstring).

    Args:
        camera: the bench's camera (optics and thin-lens constants; no ECVFL offset).
        psf: the simulated optics' PSF shape (``"gaussian"``, ``"pillbox"`` or a beta).
        seed: seeds the target's texture and the sensor noise.
        distance_m: the calibration target's distance (m), within the camera's range.
        size: frame size ``(H, W)`` (px).
        texture: the target's texture family (:mod:`tdfd.textures`).

    Raises:
        InputError: a distance outside the camera's depth range.
    """
    near, far = camera.depth_range_m
    if not near <= distance_m <= far:
        raise InputError(f"the calibration target's distance {distance_m} m is outside the camera's range {near}..{far} m")
    rig = SimulatedRig(CameraFile(camera), distance_m, size=size, seed=seed, texture=texture, psf=psf)
    centre = rig.in_focus_command_dpt()
    frames = []
    half = SWEEP_HALF_SPAN_PX / sigma_px_per_dpt(camera)
    for p in np.linspace(centre - half, centre + half, SWEEP_FRAMES):
        raw, meta = rig.capture(float(p))
        frames.append((raw.astype(np.float64) / meta["white_level"], float(p)))
    fit = psf_family_from_frames([frames], camera, region=min(128, min(size) // 32 * 32))
    log.info("simulated optics (%s PSF): the sweep measures %s (the other family %.2fx the cost)", psf, fit.family,
             fit.cost_ratio)
    return fit
