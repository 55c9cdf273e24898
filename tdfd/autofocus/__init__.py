"""Autofocus: the DFD control loop, the contrast-detect baseline, the simulated bench and
the real-hardware loop (``tdfd autofocus``).

Layers, bottom to top; a module imports only from its own layer or the ones below:

1. Protocol and state machine

   * :mod:`~tdfd.autofocus.messages`: commands (``SetPower``, ``Capture``, ``Estimate``,
     ``Done``), observations (``LensAck``, ``Frame``, ``Estimation``, their faults,
     ``Halt``), :class:`~tdfd.autofocus.messages.State`, :class:`AFResult`.
   * :mod:`~tdfd.autofocus.interfaces`: the :class:`Estimator` and ``Plant`` protocols.
   * :mod:`~tdfd.autofocus.machine`: ``StateMachine`` (retries, counting, answer
     checks) and :func:`drive` (a controller against a plant).
   * helpers the policies share: :mod:`~tdfd.autofocus.roi` (:class:`Roi`, ROI tiles),
     :mod:`~tdfd.autofocus.aggregate` (:func:`aggregate_depth`),
     :mod:`~tdfd.autofocus.sharpness` (:func:`sharpness`, texture over noise); the in-focus
     power is :func:`tdfd.camera.in_focus_power_dpt` (the one formula, re-exported here),
     :mod:`~tdfd.autofocus.evidence` (what a declared focus rests on: the estimate's
     uncertainty, the DFD pair's own relative blur, a verification frame), measured with
     :mod:`~tdfd.autofocus.relative_blur` (two frames' relative blur, no model; its search
     range scaled to the camera's blur) and :mod:`~tdfd.autofocus.cross_blur` (the
     in-focus power and PSF family, Gaussian or disk, from all frames of a run), bounded by
     :mod:`~tdfd.autofocus.sharpness_order` (the in-focus powers that the frames' sharpness
     order allows, with no blur model).

2. Policies

   * :mod:`~tdfd.autofocus.contrast`: :class:`ContrastSearch`, :class:`ContrastController`.
   * :mod:`~tdfd.autofocus.dfd`: :class:`DFDController` (the DFD step: pair, estimate,
     move; falls back to the contrast search), with its declaration steps in
     :mod:`~tdfd.autofocus.declaration` (focus declared only on its own evidence: the
     estimate's uncertainty, a verification frame, the three-frame estimate), and its
     contrast-detect fall-back in :mod:`~tdfd.autofocus.fallback` (a peak the scan frames'
     cross-blur focus contradicts is not declared, with the PSF family known).
   * :mod:`~tdfd.autofocus.assist`: ``AssistedDFDController``, DFD that lights the pair of a
     texture-less target with an assist light (:mod:`tdfd.light`), pooling the lit tiles
     (:mod:`~tdfd.autofocus.lit_tiles`).

3. Plants and what they plug in

   * :mod:`~tdfd.autofocus.estimators`: the shipped ONNX model or the analytic stand-in
     (:mod:`~tdfd.autofocus.threads`: torch threads for it and the bench).
   * :mod:`~tdfd.autofocus.registered`: breathing registration (a calibrated camera's
     ``magnification_per_dpt``) in front of an estimator that does not register the pair.
   * :mod:`~tdfd.autofocus.lens_command`: a set-point with read-back, for both plants.
   * :mod:`tdfd.autofocus.sim`: the simulated bench (lens emulator on a pty through the
     real driver, a virtual camera on a simulated clock); its ``__init__`` lists its files.
   * :mod:`~tdfd.autofocus.hardware`: OpenCV capture + the serial driver.

4. Reporting and CLI

   * :mod:`~tdfd.autofocus.report`: the autofocus report of CONTRACT.md section 3.
   * :mod:`~tdfd.autofocus.cli`: ``tdfd autofocus``; :mod:`~tdfd.autofocus.light_cli`: its
     assist-light options; :mod:`~tdfd.autofocus.psf_family_option`: its ``--psf-family`` (the
     lens's PSF family the DFD controller is told: given, a calibrated camera file's, or
     measured on the simulated bench).

Heavy dependencies (torch, onnxruntime, OpenCV) are imported only where used.
"""

from __future__ import annotations

from .aggregate import DepthAggregate, aggregate_depth
from .contrast import ContrastController, ContrastSearch
from .dfd import DFDController
from ..camera import in_focus_power_dpt
from .interfaces import Estimator, Plant
from .machine import StateMachine, drive
from .messages import AFResult
from .roi import Roi, roi_crop_box, roi_tile_mask
from .sharpness import sharpness

__all__ = [
    "AFResult",
    "ContrastController",
    "ContrastSearch",
    "DepthAggregate",
    "DFDController",
    "Estimator",
    "Plant",
    "Roi",
    "StateMachine",
    "aggregate_depth",
    "drive",
    "in_focus_power_dpt",
    "roi_crop_box",
    "roi_tile_mask",
    "sharpness",
]
