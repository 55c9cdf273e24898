"""The camera description: an ECVFL in contact with a fixed lens, in SI units.

Optics are two thin lenses in contact: total power ``1/F = 1/f0 + P_e`` (dioptres, 1/m),
with ``f0`` the fixed lens focal length and ``P_e`` the electronically set ECVFL power.
The DFD pair is captured at two ECVFL powers ``(P_e1, P_e2)``, i.e. two focal lengths
``(F1, F2)`` (paper sec. 3, "focal length as the varying parameter").

The blur-parameter constant ``mu`` (paper eq. 4, ``sigma = mu * r_b``) is stored in pixels
per metre of blur-circle radius, so ``sigma`` is in pixels. For the ``reference`` preset it
is ``1 / (2 * pixel_pitch)``: the Gaussian whose per-axis variance equals that of a uniform
disk of radius ``r_b`` (``sigma = r_b / 2``). Real cameras calibrate it
(:mod:`tdfd.dfd.calibrate`).

Example:
    >>> cam = Camera.preset("reference")
    >>> [round(f * 1000, 4) for f in cam.focal_lengths_m]
    [23.9808, 23.4192]
    >>> round(cam.in_focus_power_dpt(0.5), 3)
    2.0
    >>> sorted(cam.to_dict())[:3]
    ['aperture_m', 'depth_range_m', 'fixed_focal_length_m']
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .errors import CameraError, RangeError

__all__ = ["Camera", "PRESETS", "in_focus_power_dpt"]


def _positive(name: str, value: float) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError) as exc:
        raise CameraError(f"camera {name} must be a number, got {value!r}") from exc
    if not math.isfinite(v) or v <= 0:
        raise CameraError(f"camera {name} must be finite and > 0, got {value!r}")
    return v


def _finite(name: str, value: float) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError) as exc:
        raise CameraError(f"camera {name} must be a number, got {value!r}") from exc
    if not math.isfinite(v):
        raise CameraError(f"camera {name} must be finite, got {value!r}")
    return v


@dataclass(frozen=True)
class Camera:
    """A DFD camera with an electronically controlled variable-focus lens.

    Args:
        aperture_m: entrance-pupil diameter ``A`` in metres.
        sensor_distance_m: lens-to-sensor distance ``d_s`` in metres.
        fixed_focal_length_m: focal length ``f0`` of the fixed lens in metres.
        lens_powers_dpt: ECVFL powers ``(P_e1, P_e2)`` in dioptres for ``image_f1`` and
            ``image_f2``.
        pixel_pitch_m: sensor pixel pitch in metres.
        depth_range_m: working range ``(near, far)`` in metres.
        mu_px_per_m: blur-parameter constant ``mu`` (``sigma[px] = mu * r_b[m]``).
        sensor_size_px: sensor ``(height, width)`` in pixels (not part of the contract JSON).
        name: a label (not part of the contract JSON).

    Raises:
        CameraError: for non-finite or non-positive quantities, equal lens powers, or an
            inverted depth range.
    """

    aperture_m: float
    sensor_distance_m: float
    fixed_focal_length_m: float
    lens_powers_dpt: tuple[float, float]
    pixel_pitch_m: float
    depth_range_m: tuple[float, float]
    mu_px_per_m: float
    sensor_size_px: tuple[int, int] = (1200, 1600)
    name: str = field(default="custom", compare=False)

    def __post_init__(self) -> None:
        set_ = object.__setattr__
        set_(self, "aperture_m", _positive("aperture_m", self.aperture_m))
        set_(self, "sensor_distance_m", _positive("sensor_distance_m", self.sensor_distance_m))
        set_(self, "fixed_focal_length_m", _positive("fixed_focal_length_m", self.fixed_focal_length_m))
        set_(self, "pixel_pitch_m", _positive("pixel_pitch_m", self.pixel_pitch_m))
        set_(self, "mu_px_per_m", _positive("mu_px_per_m", self.mu_px_per_m))
        try:
            p1, p2 = self.lens_powers_dpt
            near, far = self.depth_range_m
            h, w = self.sensor_size_px
        except (TypeError, ValueError) as exc:
            raise CameraError("lens_powers_dpt, depth_range_m and sensor_size_px must be pairs") from exc
        p1, p2 = _finite("lens_powers_dpt[0]", p1), _finite("lens_powers_dpt[1]", p2)
        if p1 == p2:
            raise CameraError("the two ECVFL powers must differ for depth from defocus")
        near, far = _positive("depth_range_m[0]", near), _positive("depth_range_m[1]", far)
        if not near < far:
            raise CameraError(f"depth_range_m must be (near, far) with near < far, got {(near, far)}")
        set_(self, "lens_powers_dpt", (p1, p2))
        set_(self, "depth_range_m", (near, far))
        set_(self, "sensor_size_px", (int(_positive("sensor height", h)), int(_positive("sensor width", w))))
        for p in (p1, p2):
            if self.total_power_dpt(p) <= 0:
                raise CameraError(f"total power 1/f0 + P_e must be positive, got {self.total_power_dpt(p)} dpt")

    # ------------------------------------------------------------------ presets
    @classmethod
    def preset(cls, name: str) -> "Camera":
        """Return a preset camera (``reference`` or ``paper``, see ``CONTRACT.md``)."""
        try:
            factory = PRESETS[name]
        except KeyError:
            raise CameraError(f"unknown camera preset {name!r}; known: {sorted(PRESETS)}") from None
        return factory()

    # -------------------------------------------------------------- conversions
    @property
    def fixed_power_dpt(self) -> float:
        """Power of the fixed lens, ``1/f0``, in dioptres."""
        return 1.0 / self.fixed_focal_length_m

    def total_power_dpt(self, ecvfl_power_dpt: float) -> float:
        """Total power ``1/F = 1/f0 + P_e`` in dioptres."""
        return self.fixed_power_dpt + float(ecvfl_power_dpt)

    def focal_length_m(self, ecvfl_power_dpt: float) -> float:
        """Focal length ``F`` in metres of the lens pair at ECVFL power ``P_e``."""
        return 1.0 / self.total_power_dpt(ecvfl_power_dpt)

    def ecvfl_power_dpt(self, focal_length_m: float) -> float:
        """ECVFL power in dioptres that gives the total focal length ``F``."""
        return 1.0 / _positive("focal_length_m", focal_length_m) - self.fixed_power_dpt

    @property
    def focal_lengths_m(self) -> tuple[float, float]:
        """``(F1, F2)`` in metres at the two capture powers."""
        return tuple(self.focal_length_m(p) for p in self.lens_powers_dpt)  # type: ignore[return-value]

    def in_focus_power_dpt(self, depth_m: float | np.ndarray) -> float | np.ndarray:
        """ECVFL power that focuses an object at ``depth_m``: see :func:`in_focus_power_dpt`."""
        return in_focus_power_dpt(self, depth_m)

    def focus_distance_m(self, ecvfl_power_dpt: float) -> float:
        """Object distance in focus at ECVFL power ``P_e`` (``inf`` if none)."""
        q = self.total_power_dpt(ecvfl_power_dpt) - 1.0 / self.sensor_distance_m
        return math.inf if q <= 0 else 1.0 / q

    @property
    def blur_scale_m_dpt(self) -> float:
        """``(A/2) d_s``: blur radius in metres per dioptre of defocus (paper eq. 3)."""
        return 0.5 * self.aperture_m * self.sensor_distance_m

    @property
    def sigma_difference_px(self) -> float:
        """``sigma1 - sigma2 = mu A d_s / 2 (1/F1 - 1/F2)`` in pixels (paper eq. 6)."""
        p1, p2 = self.lens_powers_dpt
        return self.mu_px_per_m * self.blur_scale_m_dpt * (p1 - p2)

    # ------------------------------------------------------------ serialisation
    def to_dict(self) -> dict[str, Any]:
        """The ``tdfd.camera`` JSON object of the ONNX contract (SI units)."""
        return {
            "aperture_m": self.aperture_m,
            "sensor_distance_m": self.sensor_distance_m,
            "focal_lengths_m": list(self.focal_lengths_m),
            "pixel_pitch_m": self.pixel_pitch_m,
            "depth_range_m": list(self.depth_range_m),
            "mu_px_per_m": self.mu_px_per_m,
            "fixed_focal_length_m": self.fixed_focal_length_m,
            "lens_powers_dpt": list(self.lens_powers_dpt),
        }

    def to_json(self) -> str:
        """:meth:`to_dict` as a JSON string."""
        return json.dumps(self.to_dict(), sort_keys=True)

    @classmethod
    def from_dict(cls, data: dict[str, Any], **extra: Any) -> "Camera":
        """Rebuild a camera from :meth:`to_dict` output (``focal_lengths_m`` is checked).

        Raises:
            CameraError: on missing keys or focal lengths inconsistent with the powers.
        """
        keys = ("aperture_m", "sensor_distance_m", "fixed_focal_length_m", "lens_powers_dpt",
                "pixel_pitch_m", "depth_range_m", "mu_px_per_m")
        missing = [k for k in keys if k not in data]
        if missing:
            raise CameraError(f"camera description lacks {missing}")
        cam = cls(**{k: (tuple(data[k]) if isinstance(data[k], list) else data[k]) for k in keys}, **extra)
        if "focal_lengths_m" in data:
            got = [float(f) for f in data["focal_lengths_m"]]
            if len(got) != 2 or any(not math.isclose(a, b, rel_tol=1e-6) for a, b in zip(got, cam.focal_lengths_m)):
                raise CameraError(f"focal_lengths_m {got} disagree with the lens powers ({cam.focal_lengths_m})")
        return cam

    @classmethod
    def from_json(cls, text: str, **extra: Any) -> "Camera":
        """Rebuild a camera from :meth:`to_json` output."""
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise CameraError(f"camera JSON is invalid: {exc}") from exc
        if not isinstance(data, dict):
            raise CameraError("camera JSON must be an object")
        return cls.from_dict(data, **extra)

    def replace(self, **changes: Any) -> "Camera":
        """A copy with some fields changed (validated again)."""
        return dataclasses.replace(self, **changes)


def in_focus_power_dpt(camera: Camera, depth_m: float | np.ndarray) -> float | np.ndarray:
    """ECVFL power (dioptres) that focuses an object at ``depth_m`` metres (the one formula).

    ``P_e = 1/d_o + 1/d_s - 1/f0`` (``CONTRACT.md`` section 1), element-wise for arrays.
    Defined behaviour at the edges, the same for every caller (runtime, autofocus, bench):

    * ``depth_m = +inf`` gives the power that focuses at infinity, ``1/d_s - 1/f0`` (an
      aggregate of inverse depths may legitimately be 0);
    * a depth outside the camera's working range is allowed (the formula holds there; the
      lens's own power limits are the driver's business);
    * ``depth_m <= 0``, NaN or ``-inf`` raise :class:`~tdfd.errors.RangeError`.

    Returns:
        A float for a scalar, else a float64 array of the input's shape.

    Raises:
        RangeError: a depth that is not ``> 0`` (NaN, ``-inf``, zero or negative).
    """
    try:
        d = np.asarray(depth_m, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise RangeError(f"depth must be a number of metres, got {depth_m!r}") from exc
    if np.any(np.isnan(d)) or np.any(d <= 0):
        raise RangeError(f"depth must be > 0 metres (or +inf for focus at infinity), got {depth_m!r}")
    p = 1.0 / d + 1.0 / camera.sensor_distance_m - camera.fixed_power_dpt
    return float(p) if p.ndim == 0 else p


def _reference() -> Camera:
    pitch = 5.3e-6
    return Camera(
        aperture_m=2.0e-3,
        sensor_distance_m=25.0e-3,
        fixed_focal_length_m=25.0e-3,
        lens_powers_dpt=(1.7, 2.7),
        pixel_pitch_m=pitch,
        depth_range_m=(0.3, 1.0),
        mu_px_per_m=1.0 / (2.0 * pitch),
        sensor_size_px=(1200, 1600),
        name="reference",
    )


def _paper() -> Camera:
    # Paper sec. 4 / Fig. 9: A = 1 cm, d_s = 9.8 cm, F1 = 9.30 cm, F2 = 8.63 cm,
    # mu = 2.74e5 calibrated at 46 cm. The paper gives no split of F into fixed lens +
    # ECVFL; we take f0 = d_s (ECVFL at 0 dpt focuses at infinity, like `reference`).
    d_s = 0.098
    return Camera(
        aperture_m=0.01,
        sensor_distance_m=d_s,
        fixed_focal_length_m=d_s,
        lens_powers_dpt=(1.0 / 0.0930 - 1.0 / d_s, 1.0 / 0.0863 - 1.0 / d_s),
        pixel_pitch_m=5.3e-6,
        depth_range_m=(0.3, 1.0),
        mu_px_per_m=2.74e5,
        sensor_size_px=(1200, 1600),
        name="paper",
    )


PRESETS = {"reference": _reference, "paper": _paper}
