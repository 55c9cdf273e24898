r"""A synthetic sample's lens calibrated as a user calibrates theirs: a focus sweep through it.

Every ``data_synth`` sample has its own lens (:func:`data_synth.psf.sample_psf_model`: a shape
between Gaussian and disk, diffraction, astigmatism, spherical aberration). A user measures their
lens's PSF from a focus sweep (``tdfd calibrate --psf-model``,
:func:`tdfd.calibration.psf_model.psf_model_from_frames`); this is that sweep on the simulated
rig (:class:`tdfd.capture.sim.SimulatedRig`): a band-limited chart at :data:`SWEEP_DISTANCE_M`
through the sample's lens, :data:`SWEEP_SIZE`, 12-bit, shot and read noise, :data:`SWEEP_POWERS`
powers over +-:data:`SWEEP_HALF_SPAN_PX` px of blur around focus, ``frames_per_power`` frames at
each averaged, fitted on :data:`SWEEP_REGIONS` central 128-px regions.

The likelihood stage's scales fitted on such lenses (``training/fit_likelihood_stage.py
--calibrated-psf``) and the benchmark of the stage told them (``benchmarks/bench_psf_model.py``)
both calibrate here, with seeds of their own.

Example:
    >>> from tdfd.camera import Camera
    >>> from tdfd.optics.aberrated_psf import PSFModel
    >>> fit = sweep_fit(Camera.preset("reference"), PSFModel(2.0), seed=1, frames_per_power=1)  # doctest: +SKIP
"""

from __future__ import annotations

import numpy as np

from tdfd.autofocus.evidence import sigma_px_per_dpt
from tdfd.calibration.psf_model import PsfModelFit, psf_model_from_frames
from tdfd.camera import Camera
from tdfd.camera_file import CameraFile
from tdfd.capture.sim import SimulatedRig
from tdfd.errors import InputError
from tdfd.optics.aberrated_psf import PSFModel

__all__ = ["SWEEP_POWERS", "SWEEP_HALF_SPAN_PX", "SWEEP_DISTANCE_M", "SWEEP_SIZE", "SWEEP_REGIONS", "sweep_fit"]

#: the sweep: powers, half-span in px of blur, chart distance (m), frame size (px), 128-px regions fitted
SWEEP_POWERS = 7
SWEEP_HALF_SPAN_PX = 3.0
SWEEP_DISTANCE_M = 0.5
SWEEP_SIZE = (256, 256)
SWEEP_REGIONS = 2


def sweep_fit(camera: Camera, lens: PSFModel, seed: int, frames_per_power: int) -> PsfModelFit:
    """The PSF a focus sweep of a band-limited chart through ``lens`` gives (module docstring).

    Args:
        camera: the camera (its optics give the blur per dioptre).
        lens: the lens's true PSF, which renders the sweep.
        seed: the rig's seed (chart and noise).
        frames_per_power: frames averaged at each power, >= 1.

    Raises:
        InputError: ``frames_per_power`` below 1.
    """
    if int(frames_per_power) < 1:
        raise InputError(f"frames_per_power must be >= 1, got {frames_per_power}")
    rig = SimulatedRig(CameraFile(camera), SWEEP_DISTANCE_M, size=SWEEP_SIZE, seed=seed, texture="bandlimited",
                       psf=lens)
    centre, half = rig.in_focus_command_dpt(), SWEEP_HALF_SPAN_PX / sigma_px_per_dpt(camera)
    frames = [(rig.capture(p)[0].astype(np.float64), float(p))
              for p in np.linspace(centre - half, centre + half, SWEEP_POWERS) for _ in range(int(frames_per_power))]
    return psf_model_from_frames([frames], camera, region=128, max_regions=SWEEP_REGIONS, max_evaluations=250)
