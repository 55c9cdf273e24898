"""Camera calibration from a capture folder: sweeps, pairs, breathing; ``tdfd calibrate``.

:mod:`.fit` (the known-distance and self-calibration routes), :mod:`.measure` (one pair's
blur difference), :mod:`.focus` (sweep sharpness peaks), :mod:`.registration` (breathing),
:mod:`.psf_family` (the lens's PSF family, Gaussian or disk, from a sweep's cross-blur: it
uses :mod:`tdfd.autofocus.cross_blur`, a numpy helper below the autofocus policies),
:mod:`.psf_model` (the lens's whole PSF, shape, astigmatism, spherical aberration and blur
scale, from a sweep's cross residuals, minimised by :mod:`.nelder_mead`), :mod:`.plot` (the fit
plot), :mod:`.cli`.

The names below load on first use (PEP 562), so that building the ``tdfd`` command line
(which imports :mod:`tdfd.calibration.cli`) does not import torch: ``tdfd depth`` runs
without it.
"""

from __future__ import annotations

import importlib
from typing import Any

__all__ = ["CalibrationError", "CalibrationResult", "PsfFamilyFit", "calibrate_known_distance", "calibrate_self",
           "in_focus_power_from_pair", "measure_pair", "psf_family_from_captures", "psf_family_from_frames",
           "PsfModelFit", "psf_model_from_captures", "psf_model_from_frames"]

_WHERE = {"CalibrationError": "fit", "CalibrationResult": "fit", "calibrate_known_distance": "fit",
          "calibrate_self": "fit", "in_focus_power_from_pair": "measure", "measure_pair": "measure",
          "PsfFamilyFit": "psf_family", "psf_family_from_captures": "psf_family",
          "psf_family_from_frames": "psf_family",
          "PsfModelFit": "psf_model", "psf_model_from_captures": "psf_model", "psf_model_from_frames": "psf_model"}


def __getattr__(name: str) -> Any:
    if name in _WHERE:
        return getattr(importlib.import_module(f".{_WHERE[name]}", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
