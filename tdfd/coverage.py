"""Which cameras a model covers: the ``tdfd.coverage`` metadata and the load-time check.

A model reads depth from blur in pixels: its analytic layer maps the measured
``sigma1^2 - sigma2^2`` to depth through its own camera's eq. 4 (per frame,
:meth:`tdfd.camera.Camera.sigma_lines_px`), and its CNN was trained on the blur that camera
produces over its working range. Another camera is served by the same model exactly when

1. it blurs like the model's camera (in pixels, frame by frame) at every depth of its
   working range, within ``tolerance_px``: then the model's depth is this camera's depth
   (a camera with another focal length, aperture or pixel pitch can qualify); and
2. its blur over its working range lies inside the blur the model covers (``sigma1_px``,
   ``sigma2_px``: both frames' blur over the trained working range).

Condition 1 holds up to a constant shift of inverse depth as well: a camera whose fixed
lens (or ECVFL offset) is stronger by ``delta`` dioptres than the model's blurs at inverse
depth ``q`` as the model's camera does at ``q - delta`` (eq. 4: the blur depends on
``1/F - 1/d_o`` only), for both frames alike. The model reads the blur, so its inverse
depth is the camera's minus ``delta``: :func:`check_coverage` returns that
``inverse_depth_offset_dpt`` (``q_model - q_camera``, 1/m; 0 for a camera that blurs like
the model's at the same depth) and :class:`tdfd.runtime.DepthRuntime` adds it back. This is
what lets one model serve both calibrations of one camera (the self-calibration route fixes
``f0`` from the datasheet, the known-distance route measures it: docs/CALIBRATION.md).

Anything else needs its own model (``python -m training --set model.camera=CAM.json``).

The metadata (JSON), written by ``python -m export``::

    {"sigma1_px": [lo, hi], "sigma2_px": [lo, hi], "depth_range_m": [near, far],
     "tolerance_px": 0.02}

Torch-free (numpy), like :mod:`tdfd.runtime`.

Example:
    >>> from tdfd import Camera
    >>> ref = Camera.preset("reference")
    >>> cov = camera_coverage(ref)
    >>> [round(v, 2) for v in cov["sigma1_px"]]
    [-3.85, 1.65]
    >>> check_coverage(ref, cov, ref.replace(depth_range_m=(0.4, 0.8)))  # a narrower range: covered
    0.0
    >>> stronger_f0 = ref.replace(fixed_focal_length_m=0.0249, depth_range_m=(0.34, 0.7))  # 0.16 dpt stronger
    >>> round(check_coverage(ref, cov, stronger_f0), 4)  # its inverse depth is the model's + 0.1606
    -0.1606
    >>> check_coverage(ref, cov, ref.replace(depth_range_m=(0.2, 0.8)))
    Traceback (most recent call last):
    ...
    tdfd.errors.ModelError: ...
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .camera import Camera
from .errors import ModelError

__all__ = ["COVERAGE_TOLERANCE_PX", "camera_coverage", "check_coverage", "frame_blur_px", "inverse_depth_offset_dpt"]

#: Largest blur mismatch (px, either frame) between a camera and the model's camera at the
#: same depth (after the inverse-depth shift) for the model to count as serving it: about
#: 0.8 % of depth for the reference camera, a third of the model's per-tile error, and twice
#: the 0.011 px by which two calibrations of one camera differ (bench_calibration, seed 1:
#: the self-calibration and known-distance routes, K within 0.3 % of each other).
COVERAGE_TOLERANCE_PX = 0.02
_SAMPLES = 129


def frame_blur_px(camera: Camera, inverse_depth: np.ndarray) -> np.ndarray:
    """Both frames' signed blur ``sigma_i = alpha_i - a_i q`` (px) at inverse depths ``q``:
    shape ``(2, N)``."""
    q = np.asarray(inverse_depth, dtype=np.float64)
    return np.stack([alpha - a * q for alpha, a in camera.sigma_lines_px()])


def _inverse_depths(camera: Camera) -> np.ndarray:
    near, far = camera.depth_range_m
    return np.linspace(1.0 / far, 1.0 / near, _SAMPLES)


def camera_coverage(camera: Camera) -> dict[str, Any]:
    """The ``tdfd.coverage`` object of a model built for ``camera``: both frames' blur range
    (px) over its working range, that range, and the matching tolerance."""
    s = frame_blur_px(camera, _inverse_depths(camera))
    return {"sigma1_px": [float(s[0].min()), float(s[0].max())], "sigma2_px": [float(s[1].min()), float(s[1].max())],
            "depth_range_m": list(camera.depth_range_m), "tolerance_px": COVERAGE_TOLERANCE_PX}


def inverse_depth_offset_dpt(model_camera: Camera, camera: Camera) -> tuple[float, float]:
    """The shift ``delta = q_model - q_camera`` (1/m) under which ``camera`` blurs most like
    ``model_camera`` over ``camera``'s working range (least squares over both frames), and the
    largest blur mismatch (px) left after it.

    A camera that differs from the model's only in its fixed-lens power (or a common ECVFL
    offset) is matched exactly: ``delta`` is the model's total power minus the camera's.
    """
    q = _inverse_depths(camera)
    return _best_shift(model_camera, frame_blur_px(camera, q), frame_blur_px(model_camera, q))


def _best_shift(model_camera: Camera, mine: np.ndarray, theirs: np.ndarray) -> tuple[float, float]:
    """:func:`inverse_depth_offset_dpt` from both frames' blur ``(2, N)`` of the camera
    (``mine``) and of the model's camera (``theirs``) at the same inverse depths."""
    slopes = np.broadcast_to(np.array([a for _, a in model_camera.sigma_lines_px()], dtype=np.float64)[:, None],
                             mine.shape)
    # theirs(q + delta) = theirs(q) - a delta (sigma = alpha - a q): minimise |mine - theirs + a delta|^2
    denom = float((slopes * slopes).sum())
    delta = float((slopes * (theirs - mine)).sum() / denom) if denom > 0 else 0.0
    miss = float(np.abs(mine - (theirs - slopes * delta)).max())
    return delta, miss


def _parse(coverage: Any, source: str) -> tuple[np.ndarray, float]:
    try:
        ranges = np.array([coverage["sigma1_px"], coverage["sigma2_px"]], dtype=np.float64)
        tol = float(coverage["tolerance_px"])
    except (KeyError, TypeError, ValueError) as exc:
        raise ModelError(f"{source}: invalid 'tdfd.coverage' metadata {coverage!r}") from exc
    if ranges.shape != (2, 2) or not np.all(np.isfinite(ranges)) or not np.all(ranges[:, 0] <= ranges[:, 1]) \
            or not np.isfinite(tol) or tol < 0:
        raise ModelError(f"{source}: invalid 'tdfd.coverage' metadata {coverage!r}")
    return ranges, tol


def check_coverage(model_camera: Camera, coverage: Any, camera: Camera, source: str = "the model",
                   camera_file: str | None = None) -> float:
    """Refuse a camera the model does not serve (module docstring: same blur at every depth
    of its range, up to a constant shift of inverse depth, and that blur inside the covered
    range).

    Args:
        model_camera: the model's camera (``tdfd.camera`` metadata).
        coverage: the ``tdfd.coverage`` object.
        camera: the camera the user means to use the model with.
        source: the model's name for messages (its path).
        camera_file: the camera's file, if it came from one (named in the hint).

    Returns:
        ``inverse_depth_offset_dpt``: ``q_model - q_camera`` (1/m); exactly 0.0 when the
        camera blurs like the model's at the same depth (within the tolerance). The camera's
        inverse depth is the model's minus this.

    Raises:
        ModelError: naming the camera, the first depth or blur range that is not covered,
            and the command that trains a model for it.
    """
    ranges, tol = _parse(coverage, source)
    name = camera.name
    hint = f"train a model for it: python -m training --set model.camera={camera_file or 'CAM.json'}, then python -m export"
    q = _inverse_depths(camera)
    mine, theirs = frame_blur_px(camera, q), frame_blur_px(model_camera, q)
    miss = np.abs(mine - theirs).max(0)
    offset = 0.0
    if float(miss.max()) > tol:
        delta, shifted_miss = _best_shift(model_camera, mine, theirs)
        if shifted_miss > tol:
            k = int(np.argmax(miss))
            raise ModelError(
                f"{source} does not cover camera {name!r}: at {1.0 / q[k]:.3g} m it blurs "
                f"({mine[0, k]:+.3f}, {mine[1, k]:+.3f}) px, the model's camera ({theirs[0, k]:+.3f}, {theirs[1, k]:+.3f}) px "
                f"(tolerance {tol:g} px; {shifted_miss:.3f} px at best under a shift of inverse depth), "
                f"so the model's depths would be wrong; {hint}")
        offset = delta
    for i in (0, 1):
        lo, hi = float(mine[i].min()), float(mine[i].max())
        if lo < ranges[i, 0] - tol or hi > ranges[i, 1] + tol:
            near, far = camera.depth_range_m
            raise ModelError(
                f"{source} does not cover camera {name!r}: over its working range {near:g}-{far:g} m frame {i + 1} "
                f"blurs {lo:+.2f}..{hi:+.2f} px, the model covers {ranges[i, 0]:+.2f}..{ranges[i, 1]:+.2f} px "
                f"(tdfd.coverage); {hint}")
    return offset
