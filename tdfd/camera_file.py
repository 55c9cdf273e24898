"""Camera JSON files: the ``tdfd.camera`` contract object plus documented extra keys.

A camera file holds the ``tdfd.camera`` object of CONTRACT.md section 2 (SI units), read by
:meth:`tdfd.camera.Camera.from_dict`, and may add:

* ``sensor_distances_m`` ([m, m]): per-frame sensor distances ``[d_s1, d_s2]`` for a camera
  whose sensor moves between the two frames (paper, remark after eq. 13); ``d_s1`` equals
  ``sensor_distance_m`` (which may then be left out). Frame 2's image is ``d_s2/d_s1`` times
  frame 1's; :func:`tdfd.dfd.register_sensor_pair` rescales it before the estimator.
* ``apertures_m`` ([m, m]): per-frame aperture diameters ``[A1, A2]`` (Pentland's aperture
  DFD); ``A1`` equals ``aperture_m``. Either key may come with equal or with different
  ``lens_powers_dpt``; a key whose two values are equal means no variation. Read and
  written by :class:`~tdfd.camera.Camera` itself (``to_dict``/``from_dict``).

* ``magnification_per_dpt`` (1/dpt): focus breathing. The image scale at ECVFL power ``P``
  is ``1 + m P`` (relative), so two frames at ``P1`` and ``P2`` differ in magnification by
  about ``m (P1 - P2)``; positive when the image grows with power. Written by
  ``tdfd calibrate``; 0 when absent. The model registers it before its estimator
  (:class:`tdfd.registration.BreathingRegistration`) once it knows it:
  ``python -m export --weights ... --camera FILE`` stores it in the ONNX graph and in the
  ``tdfd.breathing`` metadata.
* ``ecvfl_offset_dpt`` (dpt): only in files describing a *simulated* true camera
  (``tdfd capture --sim``): the lens's real power is the commanded one plus this offset.
  A calibrated camera absorbs the offset into ``fixed_focal_length_m`` instead.
* ``psf_family``: the lens's defocus PSF family, ``"gaussian"`` or ``"pillbox"`` (a uniform
  disk), measured by ``tdfd calibrate`` from a focus sweep (:mod:`tdfd.calibration.psf_family`)
  when the captures decide it; absent when unknown. ``tdfd autofocus --psf-family CAM.json``
  hands it to the DFD controller, which then fits that family only.
* ``psf_sigma_scale``: that family's RMS blur per dioptre over the one ``mu_px_per_m`` gives
  (measured with the family; 1 when absent): the calibrated ``mu`` is what the Gaussian
  relative blur measures, which for a disk lens is about 0.8x its disk's RMS radius.
* ``psf_model``: the lens's whole defocus PSF, measured by ``tdfd calibrate --psf-model`` from a
  focus sweep (:mod:`tdfd.calibration.psf_model`): ``shape`` (a family or a power-exponential
  ``beta``), ``diffraction_px``, ``astigmatism``, ``astigmatism_angle_rad``, ``spherical``,
  ``sigma_scale`` (its RMS blur over the camera's, as ``psf_sigma_scale`` for the family);
  ``tdfd depth --likelihood-stage ... --psf-model CAM.json`` hands it to the likelihood stage.
* ``calibration``: provenance written by ``tdfd calibrate`` (route, inputs, residuals).

Other keys are kept in :attr:`CameraFile.extra` and ignored.

Example:
    >>> from tdfd import Camera
    >>> cf = CameraFile.from_dict({**Camera.preset("reference").to_dict(), "magnification_per_dpt": 0.004})
    >>> cf.magnification_per_dpt, cf.ecvfl_offset_dpt
    (0.004, 0.0)
"""

from __future__ import annotations

import json
import logging
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .camera import PRESETS, Camera
from .errors import CameraError

logger = logging.getLogger(__name__)
_WARNED: set = set()  # camera files already warned about (resolve_camera), once per process

__all__ = ["CameraFile", "load_camera_file", "resolve_camera", "resolve_camera_file", "EXTRA_KEYS", "PSF_FAMILY_VALUES",
           "PSF_MODEL_KEYS", "check_psf_model"]

#: keys a camera file may add to the ``tdfd.camera`` object.
EXTRA_KEYS = ("magnification_per_dpt", "ecvfl_offset_dpt", "calibration", "psf_family", "psf_sigma_scale", "psf_model")
#: the values ``psf_family`` may take
PSF_FAMILY_VALUES = ("gaussian", "pillbox")
#: the keys of a measured ``psf_model`` (:mod:`tdfd.calibration.psf_model`)
PSF_MODEL_KEYS = ("shape", "diffraction_px", "astigmatism", "astigmatism_angle_rad", "spherical", "sigma_scale")


def check_psf_model(data: Any) -> dict[str, Any]:
    """A measured ``psf_model`` as plain values, checked: ``shape`` (``"gaussian"``, ``"pillbox"``
    or a power-exponential ``beta >= 1``), ``diffraction_px >= 0``, ``0 <= astigmatism < 0.5``, a
    finite ``astigmatism_angle_rad``, ``|spherical| < 0.5``, ``sigma_scale`` in [0.2, 5] (the PSF's
    RMS blur over the camera's).

    Raises:
        CameraError: not a mapping of exactly those keys, or a value out of its range.

    Example:
        >>> check_psf_model({"shape": 4, "diffraction_px": 0, "astigmatism": 0.1, "astigmatism_angle_rad": 1,
        ...                  "spherical": -0.2, "sigma_scale": 1.0})["shape"]
        4.0
    """
    if not isinstance(data, dict) or set(data) != set(PSF_MODEL_KEYS):
        raise CameraError(f"psf_model must be a mapping with exactly the keys {list(PSF_MODEL_KEYS)}, got {data!r}")
    out: dict[str, Any] = {}
    for k in PSF_MODEL_KEYS:
        v = data[k]
        if k == "shape" and v in PSF_FAMILY_VALUES:
            out[k] = v
            continue
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(float(v)):
            raise CameraError(f"psf_model {k!r} must be a finite number{' or a family' if k == 'shape' else ''}, "
                              f"got {v!r}")
        out[k] = float(v)
    ok = (out["shape"] in PSF_FAMILY_VALUES or out["shape"] >= 1.0) and out["diffraction_px"] >= 0.0 \
        and 0.0 <= out["astigmatism"] < 0.5 and abs(out["spherical"]) < 0.5 and 0.2 <= out["sigma_scale"] <= 5.0
    if not ok:
        raise CameraError(f"psf_model out of range (shape a family or beta >= 1, diffraction_px >= 0, "
                          f"0 <= astigmatism < 0.5, |spherical| < 0.5, 0.2 <= sigma_scale <= 5): {data!r}")
    return out


def _number(data: dict, key: str, source: str) -> float:
    v = data.get(key, 0.0)
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(float(v)):
        raise CameraError(f"{source}: {key!r} must be a finite number, got {v!r}")
    return float(v)


@dataclass(frozen=True)
class CameraFile:
    """A camera description with focus breathing (and, for simulation, an ECVFL offset).

    Attributes:
        camera: the :class:`~tdfd.camera.Camera`.
        magnification_per_dpt: relative image scale per dioptre of ECVFL power (1/dpt).
        ecvfl_offset_dpt: real minus commanded ECVFL power (simulated true cameras only).
        calibration: provenance dictionary, or ``None``.
        extra: other keys, kept and unused.
        psf_family: the lens's PSF family (``"gaussian"``, ``"pillbox"``), or ``None`` when unknown.
        psf_sigma_scale: the family's RMS blur per dioptre over the camera's (``mu``'s).
        psf_model: the lens's whole PSF measured from a focus sweep (:func:`check_psf_model`'s
            keys; ``tdfd calibrate --psf-model``), which the likelihood stage takes as its one
            hypothesis; ``None`` when not measured.
    """

    camera: Camera
    magnification_per_dpt: float = 0.0
    ecvfl_offset_dpt: float = 0.0
    calibration: dict[str, Any] | None = None
    extra: dict[str, Any] = field(default_factory=dict)
    psf_family: str | None = None
    psf_sigma_scale: float = 1.0
    psf_model: dict[str, Any] | None = None

    def __post_init__(self) -> None:
        if self.psf_model is not None:
            object.__setattr__(self, "psf_model", check_psf_model(self.psf_model))
        if self.psf_family not in (None, *PSF_FAMILY_VALUES):
            raise CameraError(f"psf_family must be one of {PSF_FAMILY_VALUES} (or absent), got {self.psf_family!r}")
        if not 0.2 <= self.psf_sigma_scale <= 5.0:
            raise CameraError(f"psf_sigma_scale {self.psf_sigma_scale} is implausible (0.2 to 5 expected)")

    def scale_at(self, power_dpt: float) -> float:
        """Relative image scale ``1 + m P`` at ECVFL power ``P``."""
        return 1.0 + self.magnification_per_dpt * float(power_dpt)

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = dict(self.extra)
        out.update(self.camera.to_dict())
        out["magnification_per_dpt"] = self.magnification_per_dpt
        if self.ecvfl_offset_dpt:
            out["ecvfl_offset_dpt"] = self.ecvfl_offset_dpt
        if self.psf_family is not None:
            out["psf_family"] = self.psf_family
            out["psf_sigma_scale"] = self.psf_sigma_scale
        if self.psf_model is not None:
            out["psf_model"] = dict(self.psf_model)
        if self.calibration is not None:
            out["calibration"] = self.calibration
        return out

    def write(self, path: str | os.PathLike) -> Path:
        """Write as indented JSON; returns the path."""
        p = Path(path)
        p.write_text(json.dumps(self.to_dict(), indent=1, sort_keys=True) + "\n")
        return p

    @classmethod
    def from_dict(cls, data: Any, source: str = "camera file") -> "CameraFile":
        """Parse a camera object (raises :class:`~tdfd.errors.CameraError`, naming ``source``)."""
        if not isinstance(data, dict):
            raise CameraError(f"{source}: a camera file holds one JSON object")
        try:
            cam = Camera.from_dict(data, name=str(data.get("name", Path(source).stem)))
        except CameraError as exc:
            raise CameraError(f"{source}: {exc}") from exc
        m = _number(data, "magnification_per_dpt", source)
        if abs(m) >= 0.1:
            raise CameraError(f"{source}: magnification_per_dpt {m} is implausible (|m| < 0.1 per dioptre expected)")
        cal = data.get("calibration")
        family = data.get("psf_family")
        if family not in (None, *PSF_FAMILY_VALUES):
            raise CameraError(f"{source}: psf_family must be one of {PSF_FAMILY_VALUES} (or absent), got {family!r}")
        known = set(EXTRA_KEYS) | set(cam.to_dict()) | {"name", "sensor_distances_m", "apertures_m"}
        try:
            return cls._checked(data, source, cam, m, cal, family, known)
        except CameraError as exc:
            raise CameraError(f"{source}: {exc}") from exc

    @classmethod
    def _checked(cls, data: dict, source: str, cam: Camera, m: float, cal: Any, family: Any, known: set) -> "CameraFile":
        return cls(camera=cam, magnification_per_dpt=m, ecvfl_offset_dpt=_number(data, "ecvfl_offset_dpt", source),
                   calibration=cal if isinstance(cal, dict) else None,
                   extra={k: v for k, v in data.items() if k not in known}, psf_family=family,
                   psf_sigma_scale=_number(data, "psf_sigma_scale", source) if "psf_sigma_scale" in data else 1.0,
                   psf_model=data.get("psf_model"))


def load_camera_file(path: str | os.PathLike) -> CameraFile:
    """Read a camera JSON file.

    Raises:
        CameraError: missing or unreadable file, invalid JSON, or an invalid camera.
    """
    p = Path(path)
    try:
        text = p.read_text()
    except OSError as exc:
        raise CameraError(f"{p}: cannot read the camera file: {exc.strerror or exc}") from exc
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise CameraError(f"{p}: invalid JSON: {exc}") from exc
    return CameraFile.from_dict(data, str(p))


def resolve_camera_file(spec: str | os.PathLike) -> CameraFile:
    """A :class:`CameraFile` from a preset name (``reference``, ``paper``: no breathing) or a
    camera JSON file.

    What ``python -m export --camera ...`` accepts (the file's ``magnification_per_dpt`` goes
    into the exported model). An ``ecvfl_offset_dpt`` is logged as ignored (it describes a
    simulated true camera, not a calibrated one).

    Raises:
        CameraError: neither a preset nor a readable, valid camera file (the message names
            the file, or lists the presets).
    """
    text = os.fspath(spec)
    if text in PRESETS:
        return CameraFile(Camera.preset(text))
    path = Path(text)
    if path.suffix.lower() != ".json" and not path.exists():
        raise CameraError(f"camera {text!r} is neither a preset ({sorted(PRESETS)}) nor a camera JSON file")
    cf = load_camera_file(path)
    key = (str(path.resolve()), cf.ecvfl_offset_dpt)
    if cf.ecvfl_offset_dpt and key not in _WARNED:
        _WARNED.add(key)
        logger.warning("%s: ecvfl_offset_dpt %g is ignored: it describes a simulated true camera, not a calibrated one",
                       path, cf.ecvfl_offset_dpt)
    return cf


def resolve_camera(spec: str | os.PathLike) -> Camera:
    """The :class:`~tdfd.camera.Camera` of :func:`resolve_camera_file` (the optics alone).

    What ``python -m training --set model.camera=...`` accepts: the weights depend on the
    optics only; the camera's focus breathing is registered before the estimator, so it
    reaches the model at export (``python -m export --camera FILE``), not in training.

    Raises:
        CameraError: as :func:`resolve_camera_file`.
    """
    return resolve_camera_file(spec).camera
