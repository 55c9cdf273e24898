"""The camera description: an ECVFL in contact with a fixed lens, in SI units.

Optics are two thin lenses in contact: total power ``1/F = 1/f0 + P_e`` (dioptres, 1/m),
with ``f0`` the fixed lens focal length and ``P_e`` the electronically set ECVFL power.
The DFD pair is captured at two ECVFL powers ``(P_e1, P_e2)``, i.e. two focal lengths
``(F1, F2)`` (paper sec. 3, "focal length as the varying parameter").

Other varying parameters (paper sec. 3, the remark after eq. 13; Pentland's aperture DFD):
a camera may also give each frame its own sensor distance (``sensor_distances_m``) or
aperture (``apertures_m``), with or without two different ECVFL powers. Frame ``i`` then
blurs by eq. 4 with the subscript where the parameter varies,
``sigma_i = mu (A_i/2) d_s,i (1/F_i - 1/d_o - 1/d_s,i)``. The scalar ``sensor_distance_m``
and ``aperture_m`` are frame 1's (``image_f1``); in-focus powers and image scale refer to
frame 1.

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
        sensor_distances_m: optional per-frame sensor distances ``(d_s1, d_s2)`` in metres
            (JSON key ``sensor_distances_m``); ``d_s1`` must equal ``sensor_distance_m``.
            ``None`` (or two equal values): both frames at ``sensor_distance_m``.
        apertures_m: optional per-frame aperture diameters ``(A1, A2)`` in metres (JSON key
            ``apertures_m``); ``A1`` must equal ``aperture_m``. ``None``: both at ``aperture_m``.
        name: a label (not part of the contract JSON).

    Raises:
        CameraError: for non-finite or non-positive quantities, two frames that do not
            differ (same power, sensor distance and aperture), an inverted depth range, or a
            working range that straddles the depth where ``sigma1^2 - sigma2^2`` turns
            (two depths in range would give the same blur pair).
    """

    aperture_m: float
    sensor_distance_m: float
    fixed_focal_length_m: float
    lens_powers_dpt: tuple[float, float]
    pixel_pitch_m: float
    depth_range_m: tuple[float, float]
    mu_px_per_m: float
    sensor_size_px: tuple[int, int] = (1200, 1600)
    sensor_distances_m: tuple[float, float] | None = None
    apertures_m: tuple[float, float] | None = None
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
        set_(self, "sensor_distances_m", self._per_frame("sensor_distances_m", self.sensor_distances_m,
                                                         "sensor_distance_m", self.sensor_distance_m))
        set_(self, "apertures_m", self._per_frame("apertures_m", self.apertures_m, "aperture_m", self.aperture_m))
        if p1 == p2 and self.sensor_distances_m is None and self.apertures_m is None:
            raise CameraError("the two frames must differ for depth from defocus: give two ECVFL powers, "
                              "two sensor distances (sensor_distances_m) or two apertures (apertures_m)")
        near, far = _positive("depth_range_m[0]", near), _positive("depth_range_m[1]", far)
        if not near < far:
            raise CameraError(f"depth_range_m must be (near, far) with near < far, got {(near, far)}")
        set_(self, "lens_powers_dpt", (p1, p2))
        set_(self, "depth_range_m", (near, far))
        set_(self, "sensor_size_px", (int(_positive("sensor height", h)), int(_positive("sensor width", w))))
        for p in (p1, p2):
            if self.total_power_dpt(p) <= 0:
                raise CameraError(f"total power 1/f0 + P_e must be positive, got {self.total_power_dpt(p)} dpt")
        turn = self.turning_inverse_depth
        if turn is not None and 1.0 / far <= turn <= 1.0 / near:
            raise CameraError(
                f"the working range {near:g}-{far:g} m straddles {1.0 / turn if turn > 0 else math.inf:g} m, where "
                "sigma1^2 - sigma2^2 turns: depths either side give the same blur pair (for an aperture pair, "
                "focus outside the range)")

    @staticmethod
    def _per_frame(key: str, pair: Any, scalar_key: str, scalar: float) -> tuple[float, float] | None:
        if pair is None:
            return None
        try:
            a, b = pair
        except (TypeError, ValueError) as exc:
            raise CameraError(f"camera {key} must be a pair [frame 1, frame 2], got {pair!r}") from exc
        a, b = _positive(f"{key}[0]", a), _positive(f"{key}[1]", b)
        if not math.isclose(a, scalar, rel_tol=1e-9):
            raise CameraError(f"camera {key}[0] = {a!r} must equal {scalar_key} = {scalar!r} (frame 1's value)")
        return None if a == b else (scalar, b)

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
    def frame_sensor_distances_m(self) -> tuple[float, float]:
        """``(d_s1, d_s2)`` in metres (both ``sensor_distance_m`` unless they vary)."""
        return self.sensor_distances_m or (self.sensor_distance_m, self.sensor_distance_m)

    @property
    def frame_apertures_m(self) -> tuple[float, float]:
        """``(A1, A2)`` in metres (both ``aperture_m`` unless they vary)."""
        return self.apertures_m or (self.aperture_m, self.aperture_m)

    @property
    def varying(self) -> tuple[str, ...]:
        """Which parameters differ between the frames: a subset of
        ``("lens_power", "sensor_distance", "aperture")``."""
        out = ("lens_power",) if self.lens_powers_dpt[0] != self.lens_powers_dpt[1] else ()
        return out + (("sensor_distance",) if self.sensor_distances_m else ()) + (("aperture",) if self.apertures_m else ())

    @property
    def image_scale_ratio(self) -> float:
        """Image scale of frame 2 relative to frame 1, ``d_s2 / d_s1`` (chief rays through
        the lens centre); 1 unless the sensor distance varies."""
        d1, d2 = self.frame_sensor_distances_m
        return d2 / d1

    def sigma_lines_px(self, mu: float | None = None) -> tuple[tuple[float, float], tuple[float, float]]:
        """Each frame's blur parameter as a line in inverse depth ``q = 1/d_o``:
        ``sigma_i = alpha_i - a_i q`` (pixels), from eq. 4 with per-frame ``F_i, d_s,i, A_i``:
        ``a_i = mu A_i d_s,i / 2`` and ``alpha_i = a_i (1/F_i - 1/d_s,i)``.

        Returns:
            ``((alpha_1, a_1), (alpha_2, a_2))``.
        """
        mu = self.mu_px_per_m if mu is None else float(mu)
        out = []
        for p, ds, a in zip(self.lens_powers_dpt, self.frame_sensor_distances_m, self.frame_apertures_m):
            slope = 0.5 * mu * a * ds
            out.append((slope * (self.total_power_dpt(p) - 1.0 / ds), slope))
        return tuple(out)  # type: ignore[return-value]

    @property
    def turning_inverse_depth(self) -> float | None:
        """Inverse depth (1/m) where ``sigma1^2 - sigma2^2`` has its extremum (a quadratic in
        ``1/d_o`` when the frames' blur slopes differ); ``None`` when it is linear (one
        sensor distance and one aperture: the ECVFL pair of eq. 6)."""
        (al1, a1), (al2, a2) = self.sigma_lines_px(1.0)
        quad = a1 * a1 - a2 * a2
        if self.sensor_distances_m is None and self.apertures_m is None or quad == 0.0:
            return None
        return (al1 * a1 - al2 * a2) / quad

    @property
    def equal_blur_inverse_depth(self) -> float | None:
        """Inverse depth (1/m) at which the pair blurs both frames equally, ``sigma1 = -sigma2``
        (between the two frames' focus distances): ``(alpha_1 + alpha_2) / (a_1 + a_2)`` of
        :meth:`sigma_lines_px`; ``None`` when it is not positive. There ``D = 0`` whatever
        ``mu`` and the PSF's shape: a pair measures the distance, not ``mu``
        (:mod:`tdfd.dfd.calibrate`, *Conditioning*).

        Example:
            >>> round(Camera.preset("reference").equal_blur_inverse_depth, 6)   # (1.7 + 2.7) / 2
            2.2
        """
        (al1, a1), (al2, a2) = self.sigma_lines_px(1.0)
        q = (al1 + al2) / (a1 + a2)
        return q if q > 0 else None

    @property
    def sigma_difference_px(self) -> float:
        """``sigma1 - sigma2 = mu A d_s / 2 (1/F1 - 1/F2)`` in pixels (paper eq. 6).

        Raises:
            CameraError: the sensor distance or the aperture varies, so the difference
                depends on depth (use :meth:`sigma_lines_px`).
        """
        if self.sensor_distances_m is not None or self.apertures_m is not None:
            raise CameraError("sigma1 - sigma2 depends on depth when the sensor distance or aperture varies")
        p1, p2 = self.lens_powers_dpt
        return self.mu_px_per_m * self.blur_scale_m_dpt * (p1 - p2)

    # ------------------------------------------------------------ serialisation
    def to_dict(self) -> dict[str, Any]:
        """The ``tdfd.camera`` JSON object of the ONNX contract (SI units), plus
        ``sensor_distances_m`` / ``apertures_m`` only when they vary."""
        out: dict[str, Any] = {
            "aperture_m": self.aperture_m,
            "sensor_distance_m": self.sensor_distance_m,
            "focal_lengths_m": list(self.focal_lengths_m),
            "pixel_pitch_m": self.pixel_pitch_m,
            "depth_range_m": list(self.depth_range_m),
            "mu_px_per_m": self.mu_px_per_m,
            "fixed_focal_length_m": self.fixed_focal_length_m,
            "lens_powers_dpt": list(self.lens_powers_dpt),
        }
        if self.sensor_distances_m is not None:
            out["sensor_distances_m"] = list(self.sensor_distances_m)
        if self.apertures_m is not None:
            out["apertures_m"] = list(self.apertures_m)
        return out

    def to_json(self) -> str:
        """:meth:`to_dict` as a JSON string."""
        return json.dumps(self.to_dict(), sort_keys=True)

    @classmethod
    def from_dict(cls, data: dict[str, Any], **extra: Any) -> "Camera":
        """Rebuild a camera from :meth:`to_dict` output (``focal_lengths_m`` is checked).

        ``sensor_distances_m`` / ``apertures_m`` (optional, per frame) may stand in for a
        missing ``sensor_distance_m`` / ``aperture_m`` (frame 1's value is taken).

        Raises:
            CameraError: on missing keys or focal lengths inconsistent with the powers.
        """
        data = dict(data)
        for scalar, pair in (("sensor_distance_m", "sensor_distances_m"), ("aperture_m", "apertures_m")):
            if scalar not in data and isinstance(data.get(pair), list) and data[pair]:
                data[scalar] = data[pair][0]
        keys = ("aperture_m", "sensor_distance_m", "fixed_focal_length_m", "lens_powers_dpt",
                "pixel_pitch_m", "depth_range_m", "mu_px_per_m")
        missing = [k for k in keys if k not in data]
        if missing:
            raise CameraError(f"camera description lacks {missing}")
        optional = {k: tuple(data[k]) if isinstance(data[k], list) else data[k]
                    for k in ("sensor_distances_m", "apertures_m") if data.get(k) is not None}
        cam = cls(**{k: (tuple(data[k]) if isinstance(data[k], list) else data[k]) for k in keys}, **optional, **extra)
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
