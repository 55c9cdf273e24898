"""Autofocus: the DFD control loop, the contrast-detect baseline, the simulated bench and
the real-hardware loop (``tdfd autofocus``).

* :mod:`tdfd.autofocus.controller`: :class:`DFDController`, a pure state machine
  (observation in, command out), ROI aggregation and the in-focus power.
* :mod:`tdfd.autofocus.contrast`: :class:`ContrastController`, contrast-detect AF.
* :mod:`tdfd.autofocus.bench`: the simulated bench (lens emulator on a pty through the
  real driver, a virtual camera on a simulated clock).
* :mod:`tdfd.autofocus.hardware`: OpenCV capture + the serial driver.
* :mod:`tdfd.autofocus.report`: the autofocus report of CONTRACT.md section 3.

Heavy dependencies (torch, onnxruntime) are imported only where used.
"""

from __future__ import annotations

from .contrast import ContrastController, ContrastSearch, sharpness
from .controller import (
    AFResult,
    DepthAggregate,
    DFDController,
    Estimator,
    Roi,
    aggregate_depth,
    drive,
    in_focus_power_dpt,
    roi_tile_mask,
)

__all__ = [
    "AFResult",
    "ContrastController",
    "ContrastSearch",
    "DepthAggregate",
    "DFDController",
    "Estimator",
    "Roi",
    "aggregate_depth",
    "drive",
    "in_focus_power_dpt",
    "roi_tile_mask",
    "sharpness",
]
