r"""A synthetic sample's lens calibrated as a user calibrates theirs: a focus sweep through it.

Every ``data_synth`` sample has its own lens (:func:`data_synth.psf.sample_psf_model`: a shape
between Gaussian and disk, diffraction, astigmatism, spherical aberration). A user measures their
lens's PSF from a focus sweep (``tdfd calibrate --psf-model``,
:func:`tdfd.calibration.psf_model.psf_model_from_frames`); this is that sweep on the simulated
rig (:class:`tdfd.capture.sim.SimulatedRig`): a chart (:data:`SWEEP_CHART`, a texture family of
:mod:`tdfd.textures`) at :data:`SWEEP_DISTANCE_M`
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
from tdfd.textures import TEXTURE_FAMILIES

__all__ = ["SWEEP_POWERS", "SWEEP_HALF_SPAN_PX", "SWEEP_DISTANCE_M", "SWEEP_SIZE", "SWEEP_REGIONS", "SWEEP_CHART",
           "SWEEP_CHARTS", "sweep_fit"]

#: the sweep: powers, half-span in px of blur, chart distance (m), frame size (px), 128-px regions fitted
SWEEP_POWERS = 7
SWEEP_HALF_SPAN_PX = 3.0
SWEEP_DISTANCE_M = 0.5
SWEEP_SIZE = (256, 256)
SWEEP_REGIONS = 2
#: the chart swept: a texture with detail at every scale. A band-limited chart (until 2026-11-29) leaves
#: the blur scale and the profile's tails nearly unseen: on the 229 lenses of ``bench_psf_model`` 63
#: fits were over 2 % off in their kernels, up to 70 % (a scale of 1.9 for a plain Gaussian), where
#: dead-leaves sweeps of the same lenses gave them back to about 1 % (docs/CALIBRATION.md)
SWEEP_CHART = "dead_leaves"
#: the charts a sweep can see: the textured families
SWEEP_CHARTS = tuple(f for f in TEXTURE_FAMILIES if f != "flat")


def sweep_fit(camera: Camera, lens: PSFModel, seed: int, frames_per_power: int, chart: str = SWEEP_CHART
              ) -> PsfModelFit:
    """The PSF a focus sweep of a ``chart`` (a texture family) through ``lens`` gives (module docstring).

    Args:
        camera: the camera (its optics give the blur per dioptre).
        lens: the lens's true PSF, which renders the sweep.
        seed: the rig's seed (chart and noise).
        frames_per_power: frames averaged at each power, >= 1.
        chart: the texture family swept (:data:`tdfd.textures.TEXTURE_FAMILIES`).

    Raises:
        InputError: ``frames_per_power`` below 1, an unknown chart.
    """
    if int(frames_per_power) < 1:
        raise InputError(f"frames_per_power must be >= 1, got {frames_per_power}")
    if chart not in SWEEP_CHARTS:
        raise InputError(f"the sweep's chart must be a textured family of tdfd.textures, got {chart!r}")
    rig = SimulatedRig(CameraFile(camera), SWEEP_DISTANCE_M, size=SWEEP_SIZE, seed=seed, texture=chart,
                       psf=lens)
    centre, half = rig.in_focus_command_dpt(), SWEEP_HALF_SPAN_PX / sigma_px_per_dpt(camera)
    frames = [(rig.capture(p)[0].astype(np.float64), float(p))
              for p in np.linspace(centre - half, centre + half, SWEEP_POWERS) for _ in range(int(frames_per_power))]
    return psf_model_from_frames([frames], camera, region=128, max_regions=SWEEP_REGIONS, max_evaluations=250)
