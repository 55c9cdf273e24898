"""``tdfd autofocus --psf-family``: what the DFD controller is told of the lens's PSF family.

``--psf-family`` takes ``gaussian`` or ``pillbox`` (given), ``unknown`` (the default: the
controller's cross-blur searches fit both), a camera JSON file written by ``tdfd calibrate``
(its measured ``psf_family``, :mod:`tdfd.calibration.psf_family`; unknown when the file has
none), or on the simulated bench ``calibrate`` (a focus sweep through the simulated optics
measures it, :mod:`tdfd.autofocus.sim.psf_calibration`: the controller is told what the
measurement says, not the simulator's ``--psf``).

A family given or measured also reaches the depth model when its CNN takes the family
(:func:`tell_estimator`); unknown leaves the model with the family it was exported with.
The same camera JSON's ``calibration.mu_relative_uncertainty`` (a known-distance calibration
records it: docs/CALIBRATION.md) is what the assist light's region fit counts for ``mu``
(:func:`calibrated_mu_uncertainty`).
"""

from __future__ import annotations

import argparse
import logging
import math
from pathlib import Path
from typing import Any

from ..camera import Camera
from ..camera_file import PSF_FAMILY_VALUES, load_camera_file
from ..errors import CameraError, InputError

__all__ = ["add_psf_family_argument", "resolve_psf_family", "calibrated_mu_uncertainty", "tell_estimator"]

log = logging.getLogger(__name__)


def add_psf_family_argument(parser: argparse.ArgumentParser) -> None:
    """Add ``--psf-family`` to the ``autofocus`` parser."""
    parser.add_argument("--psf-family", default="unknown", metavar="FAMILY",
                        help="the lens's PSF family the DFD controller fits: gaussian, pillbox, unknown (default: both "
                             "are tried), a camera JSON from 'tdfd calibrate' (its measured psf_family, and its mu uncertainty "
                             "for the assist light's region fit), or with --sim "
                             "'calibrate' (measured by a focus sweep through the simulated optics)")


def resolve_psf_family(text: str, *, sim_camera: Camera | None = None, sim_psf: Any = None
                       ) -> tuple[str | None, float]:
    """The PSF family ``--psf-family text`` names (``None``: unknown) and its blur scale
    (``psf_sigma_scale``: measured, from the camera file, else 1).

    Args:
        text: the option's value (module docstring).
        sim_camera, sim_psf: the simulated bench's camera and PSF (``calibrate`` only: ``None``
            on hardware).

    Raises:
        InputError: ``calibrate`` off the simulated bench, or a value that is neither a family,
            ``unknown``, ``calibrate`` nor a ``.json`` path.
        CameraError: a camera JSON file that cannot be read or holds an invalid camera (the
            message names the file).
    """
    if text in PSF_FAMILY_VALUES:
        return text, 1.0
    if text == "unknown":
        return None, 1.0
    if text == "calibrate":
        if sim_camera is None:
            raise InputError("--psf-family calibrate measures the simulated optics (--sim); on hardware run "
                             "'tdfd calibrate' on a focus sweep and give its camera JSON")
        from .sim.psf_calibration import measure_sim_psf_family  # renders with torch: loaded only here

        fit = measure_sim_psf_family(sim_camera, sim_psf)
        log.info("--psf-family calibrate: %s (the other family %.2fx the cost)", fit.family or "undecided",
                 fit.cost_ratio)
        return fit.family, fit.family_sigma_scale
    path = Path(text)
    if path.suffix.lower() != ".json":
        raise InputError(f"--psf-family must be one of {PSF_FAMILY_VALUES}, 'unknown', 'calibrate' (--sim) or a "
                         f"camera JSON file, got {text!r}")
    cf = load_camera_file(path)  # a CameraError names the file
    if cf.psf_family is None:
        log.warning("%s has no psf_family (the calibration did not decide it): the PSF family stays unknown", path)
        return None, 1.0
    return cf.psf_family, cf.psf_sigma_scale


def calibrated_mu_uncertainty(text: str) -> float | None:
    """``calibration.mu_relative_uncertainty`` of the camera JSON ``--psf-family text`` names
    (:func:`tdfd.dfd.calibrate.mu_relative_uncertainty`, written by ``tdfd calibrate``'s
    known-distance route); ``None`` for a family name, or a file that records none.

    Raises:
        CameraError: the file cannot be read, or records a value that is not a number in
            [0, 1) (the message names the file).
    """
    path = Path(text)
    if path.suffix.lower() != ".json":
        return None
    cal = load_camera_file(path).calibration or {}
    if "mu_relative_uncertainty" not in cal:
        return None
    u = cal["mu_relative_uncertainty"]
    if isinstance(u, bool) or not isinstance(u, (int, float)) or not (math.isfinite(u) and 0 <= u < 1):
        raise CameraError(f"{path}: calibration.mu_relative_uncertainty must be a number in [0, 1), got {u!r}")
    return float(u)


def tell_estimator(estimator: Any, family: str | None) -> None:
    """Tell ``estimator``'s model the ``family`` that ``--psf-family`` resolved to.

    A model whose CNN takes the family (``estimator.takes_psf_family``, an ONNX file with the
    ``tdfd.psf_family`` metadata) is told a known family; ``None`` (unknown) leaves it with the
    family it was exported with (``python -m export --camera FILE`` bakes in the file's). A
    model without the input is left as it is, with an info line when a family was known.
    """
    if family is None or estimator is None:
        return
    if getattr(estimator, "takes_psf_family", False):
        estimator.set_psf_family(family)
        log.info("the depth model is told the PSF family %s", family)
    else:
        log.info("the depth model (%s) takes no PSF family: only the controller's cross-blur fits use %s",
                 type(estimator).__name__, family)
