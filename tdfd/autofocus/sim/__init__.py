r"""The simulated autofocus bench: the real driver, controllers and estimator against simulated physics and time.

What lives where (imports point down this list, and into :mod:`tdfd.autofocus`'s lower layers):

* :mod:`~tdfd.autofocus.sim.bench`: :class:`SimBench`, the bench as a context manager
  (owns the emulator), builds the controllers and runs trials, single-shot or continuous.
* :mod:`~tdfd.autofocus.sim.plant`: :class:`BenchPlant`, executes controller commands
  on the parts below and charges simulated time for each.
* :mod:`~tdfd.autofocus.sim.charges`: the computation the bench charges (median wall times of
  the estimator, the relative-blur measurements and cross-blur searches on this machine).
* :mod:`~tdfd.autofocus.sim.psf_calibration`: the simulated optics' PSF family, measured by a
  focus sweep of a noise chart (:mod:`tdfd.capture.sim`, :mod:`tdfd.calibration.psf_family`)
  as ``tdfd calibrate`` measures a real lens's.
* :mod:`~tdfd.autofocus.sim.trials`: :class:`TrialRecord` (one trial, the report's raw
  material) and :func:`trial_depths` (seeded target distances).
* :mod:`~tdfd.autofocus.sim.lens`: :class:`EmulatedLens`, the Lens Driver 4 emulator on a
  pty, through the real :class:`~tdfd.driver.OptotuneLens`.
* :mod:`~tdfd.autofocus.sim.port`: :class:`TimedPort`, the serial port that charges the
  wire time of every byte.
* :mod:`~tdfd.autofocus.sim.camera`: :class:`VirtualCamera`, renders the scene at the
  lens's optical power during the exposure.
* :mod:`~tdfd.autofocus.sim.scene`: :class:`Scene`, a textured plane or a user's image and
  depth map; :data:`BENCH_TEXTURE_FAMILIES`.
* :mod:`~tdfd.autofocus.sim.noise`: :class:`SensorNoise`.
* :mod:`~tdfd.autofocus.sim.timing`: :class:`CameraTiming`.
* :mod:`~tdfd.autofocus.sim.clock`: :class:`SimClock`.

torch (renderer, sensor model, textures) is imported only when a frame is rendered.
"""

from __future__ import annotations

from .bench import DEFAULT_READOUT_HW, SimBench
from .camera import VirtualCamera
from .clock import SimClock
from .lens import BENCH_TEMPERATURE_LIMITS_C, EmulatedLens
from .noise import SensorNoise
from .plant import BenchPlant
from .port import TimedPort
from .scene import BENCH_TEXTURE_FAMILIES, Scene
from .timing import CameraTiming
from .trials import TrialRecord, trial_depths

__all__ = [
    "BENCH_TEMPERATURE_LIMITS_C",
    "BENCH_TEXTURE_FAMILIES",
    "BenchPlant",
    "CameraTiming",
    "DEFAULT_READOUT_HW",
    "EmulatedLens",
    "Scene",
    "SensorNoise",
    "SimBench",
    "SimClock",
    "TimedPort",
    "TrialRecord",
    "VirtualCamera",
    "trial_depths",
]
