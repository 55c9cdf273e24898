r"""Fitting a camera to a capture folder: the known-distance route and self-calibration.

Model (paper eqs. 3-4 with a commanded ECVFL power ``P``): a region focused at commanded
power ``P*`` has ``sigma(P) = K (P - P*)`` px, with ``K = mu (A/2) d_s`` px/dpt, so a pair
at ``(P_a, P_b)`` measures

.. math:: D = \sigma_a^2 - \sigma_b^2 = K^2 (P_a - P_b)(P_a + P_b - 2 P^*).

``P*`` of a target at distance ``d`` is ``1/d + B`` with ``B = 1/d_s - 1/f0 - delta``
(``delta`` the ECVFL's power offset, which no measurement separates from the fixed lens).

* **Known distances** (:func:`calibrate_known_distance`, the paper's route): pairs at known
  ``d``; ``D/(P_a - P_b) = K^2 (P_a + P_b - 2/d) - 2 K^2 B`` is linear in ``(K^2, K^2 B)``,
  fitted over all pairs when they span two or more distances; from one distance ``B``
  comes from the datasheet and only ``K`` is fitted (the paper's single-pair mu).
* **Self-calibration** (:func:`calibrate_self`): a focus sweep gives each region's ``P*``
  (sharpness peak, :mod:`.focus`); pairs of the same scene (tagged pairs, and sweep frames
  one pair-separation apart, within moderate blur) give ``D`` at known defocus; one joint
  Gauss-Newton fit over ``K^2`` and every region's ``P*`` uses both, residuals in
  dioptres. ``B`` (metric depth only) comes from a scene with a known distance when there
  is one, else from the datasheet, and the result says which.

Both routes measure the breathing ``m`` by registration (:mod:`.registration`) first and
register every pair before measuring ``D``. The fitted camera keeps the nominal aperture,
sensor distance and pixel pitch and stores ``mu = K / ((A/2) d_s)`` and
``1/f0 = 1/d_s - B`` (the ECVFL offset folded into the fixed lens), so that
``Camera.in_focus_power_dpt`` returns commanded powers.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from .. import __version__
from ..camera_file import CameraFile
from ..capture.folder import CaptureFolderError, CaptureFrame
from ..dfd.calibrate import MAX_MU_UNCERTAINTY, PAIR_POWER_SD_DPT
from ..errors import InputError
from .focus import focus_measure, region_grid, symmetric_peak
from .measure import PREDICTION_REGION_PX, PairMeasurement, measure_pair
from .registration import fit_magnification_per_dpt, relative_magnification

__all__ = ["CalibrationError", "Scene", "CalibrationResult", "group_scenes", "estimate_breathing",
           "sweep_peaks", "calibrate_known_distance", "calibrate_self", "k_relative_uncertainty", "MIN_SWEEP_FRAMES",
           "MAX_BLUR_PX"]

log = logging.getLogger(__name__)

#: fewest sweep frames a self-calibration accepts.
MIN_SWEEP_FRAMES = 5
#: sweep-frame pairs are used only where the nominal camera predicts at most this blur (px).
MAX_BLUR_PX = 3.0
#: sweep frames this many times the camera's pair separation apart serve as pairs too.
SWEEP_PAIR_SEPARATIONS = (0.5, 1.0)
#: a region whose log focus measure varies less than this over the sweep has no texture.
MIN_FOCUS_CONTRAST = 0.3


class CalibrationError(InputError):
    """Captures that cannot calibrate a camera (too few, never in focus, inconsistent)."""


@dataclass
class Scene:
    """The frames of one scene: a sweep (sorted by power) and tagged pairs.

    ``folder`` is set when the frames came from several capture folders (one scene per
    folder and distance); ``None`` for a single folder.
    """

    distance_m: float | None
    sweep: list[CaptureFrame] = field(default_factory=list)
    pairs: list[tuple[CaptureFrame, CaptureFrame]] = field(default_factory=list)
    folder: Path | None = None

    @property
    def label(self) -> str:
        base = "unknown distance" if self.distance_m is None else f"distance {self.distance_m:g} m"
        return base if self.folder is None else f"{base} in {self.folder}"


def group_scenes(frames: Sequence[CaptureFrame]) -> list[Scene]:
    """Group frames into scenes by capture folder and ``distance_m`` (in one folder, the frames
    without a distance form one scene; several folders give one scene each, so that sweeps of
    several scenes with no distance known can calibrate together)."""
    several = len({f.path.parent for f in frames}) > 1
    scenes: dict[tuple[Path | None, float | None], Scene] = {}
    tagged: dict[tuple[Path, str], list[CaptureFrame]] = {}
    for f in frames:
        key = (f.path.parent if several else None, f.metadata.distance_m)
        scenes.setdefault(key, Scene(key[1], folder=key[0]))
        if f.metadata.pair is None:
            scenes[key].sweep.append(f)
        else:
            tagged.setdefault((f.path.parent, f.metadata.pair), []).append(f)
    for (folder, tag), (a, b) in tagged.items():
        if a.metadata.distance_m != b.metadata.distance_m:
            raise CaptureFolderError(f"{b.path}: the frames of pair {tag!r} record different distances")
        scenes[(folder if several else None, a.metadata.distance_m)].pairs.append((a, b))
    for s in scenes.values():
        s.sweep.sort(key=lambda f: f.power_dpt)
        powers = [f.power_dpt for f in s.sweep]
        for k in range(1, len(powers)):
            if powers[k] == powers[k - 1]:
                raise CaptureFolderError(f"{s.sweep[k].path}: two sweep frames of one scene ({s.label}) at "
                                         f"{powers[k]:g} dpt ({s.sweep[k - 1].name})")
    return [scenes[k] for k in sorted(scenes, key=lambda k: (str(k[0]), k[1] is None, k[1] or 0.0))]


@dataclass
class CalibrationResult:
    """A fitted camera and everything needed to judge the fit.

    Attributes:
        camera_file: the fitted camera (with breathing and provenance).
        route: ``"known-distance"`` or ``"self"``.
        k_px_per_dpt: ``K = mu (A/2) d_s``, blur in px per dioptre of defocus.
        in_focus_offset_dpt: ``B``: commanded in-focus power minus ``1/d``.
        offset_source: where ``B`` came from (a known distance, or the datasheet).
        magnification_per_dpt: the fitted breathing.
        residuals_dpt: per measurement kind, residuals in dioptres.
        plot_data: what :mod:`.plot` draws.
    """

    camera_file: CameraFile
    route: str
    k_px_per_dpt: float
    in_focus_offset_dpt: float
    offset_source: str
    magnification_per_dpt: float
    residuals_dpt: dict[str, np.ndarray]
    plot_data: dict[str, Any]

    def summary(self) -> dict[str, Any]:
        """Numbers for logs and the camera file's provenance."""
        rms = {k: (float(np.sqrt(np.mean(v ** 2))) if len(v) else None) for k, v in self.residuals_dpt.items()}
        return {"route": self.route, "k_px_per_dpt": self.k_px_per_dpt,
                "mu_px_per_m": self.camera_file.camera.mu_px_per_m,
                "in_focus_offset_dpt": self.in_focus_offset_dpt, "in_focus_offset_source": self.offset_source,
                "magnification_per_dpt": self.magnification_per_dpt,
                "residual_rms_dpt": rms, "counts": {k: int(len(v)) for k, v in self.residuals_dpt.items()}}


def _where(frames: Sequence[CaptureFrame]) -> str:
    """The capture folder(s) of ``frames``, for messages."""
    folders = sorted({str(f.path.parent) for f in frames})
    return ", ".join(folders) if folders else "no frames"


# ---------------------------------------------------------------------------- breathing
def _register(camera, a: CaptureFrame, b: CaptureFrame, region: int) -> tuple[float, int]:
    pm = measure_pair(camera, a.image, b.image, a.power_dpt, b.power_dpt, region)
    # one blur difference for the frame (median over regions): per-region values are too
    # noisy to match blur with, and calibration targets are planar
    dsq = np.full_like(pm.square_difference, float(np.median(pm.square_difference)))
    return relative_magnification(a.image, b.image, region, dsq)


def estimate_breathing(scenes: Sequence[Scene], region: int, camera) -> tuple[float, dict[str, Any]]:
    """Breathing ``m`` from registered frame pairs of each scene: its DFD pairs, and sweep
    frames mirrored about the sharpest sweep frame (equal blur on both sides of focus),
    within :data:`MAX_BLUR_PX` of focus by the nominal camera. Returns ``(m, plot data)``; ``m = 0`` with a warning when nothing registers.
    """
    pa, pb, rho, w = [], [], [], []
    for s in scenes:
        todo = list(s.pairs)
        if len(s.sweep) >= 2:
            # sweep frames mirrored about the sharpest one: equal blur, large power difference
            ref = max(s.sweep, key=lambda f: float(np.sum(np.log(focus_measure(f.image, region) + 1e-12))))
            step = float(np.median(np.diff([f.power_dpt for f in s.sweep])))
            reach = MAX_BLUR_PX / (camera.mu_px_per_m * camera.blur_scale_m_dpt)
            for a in s.sweep:
                if a.power_dpt >= ref.power_dpt or ref.power_dpt - a.power_dpt > reach:
                    continue
                b = min(s.sweep, key=lambda f: abs(f.power_dpt + a.power_dpt - 2 * ref.power_dpt))
                if b.power_dpt > ref.power_dpt and abs(b.power_dpt + a.power_dpt - 2 * ref.power_dpt) <= 0.6 * step:
                    todo.append((a, b))
        for a, b in todo:
            r, n = _register(camera, a, b, region)
            pa.append(a.power_dpt), pb.append(b.power_dpt), rho.append(r), w.append(n)
    try:
        m, res = fit_magnification_per_dpt(pa, pb, rho, w)
    except InputError as exc:
        log.warning("breathing not measured (%s); assuming none", exc)
        return 0.0, {"dp": np.zeros(0), "log_rho": np.zeros(0), "m": 0.0}
    dp = np.asarray(pb) - np.asarray(pa)
    ok = np.isfinite(rho)
    return m, {"dp": dp[ok], "log_rho": np.log(np.asarray(rho)[ok]), "m": m, "residuals": res}


# ---------------------------------------------------------------------------- sweeps
def sweep_peaks(scene: Scene, region: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """In-focus power per region from the scene's sweep.

    Returns:
        ``(peaks (rows, cols) dpt, NaN where untextured; powers (N,); log focus (N, rows, cols))``.

    Raises:
        CalibrationError: fewer than :data:`MIN_SWEEP_FRAMES` frames, a textured region
            whose sharpness peaks at the first or last frame (the sweep never reaches its
            focus), or no textured region at all.
    """
    if len(scene.sweep) < MIN_SWEEP_FRAMES:
        names = ", ".join(f.name for f in scene.sweep) or "none"
        raise CalibrationError(f"the focus sweep of the scene at {scene.label} has {len(scene.sweep)} frames ({names}); "
                               f"self-calibration needs at least {MIN_SWEEP_FRAMES}")
    powers = np.array([f.power_dpt for f in scene.sweep])
    logf = np.log(np.stack([focus_measure(f.image, region) for f in scene.sweep]) + 1e-12)
    rows, cols = logf.shape[1:]
    peaks = np.full((rows, cols), np.nan)
    half = max(2.5 * float(np.median(np.diff(powers))), 0.3)
    for i in range(rows):
        for j in range(cols):
            v = logf[:, i, j]
            if v.max() - v.min() < MIN_FOCUS_CONTRAST:
                log.warning("region (%d, %d) of the sweep at %s has no texture (sharpness varies by %.2f); not used",
                            i, j, scene.label, float(v.max() - v.min()))
                continue
            k = int(np.argmax(v))
            if k in (0, len(v) - 1):
                end = scene.sweep[k]
                raise CalibrationError(
                    f"the focus sweep {powers[0]:g}..{powers[-1]:g} dpt never reaches focus in region (row {i}, col {j}) "
                    f"of the scene at {scene.label}: sharpness is highest at its end frame {end.path}; extend the sweep")
            peaks[i, j] = symmetric_peak(powers, v, half)
    if not np.isfinite(peaks).any():
        raise CalibrationError(f"no region of the sweep at {scene.label} ({scene.sweep[0].path.parent}) has texture")
    return peaks, powers, logf


def _sweep_pairs(scene: Scene, separation: float, centre: float, half_range: float) -> list[tuple[CaptureFrame, CaptureFrame]]:
    """Sweep frames about ``separation`` apart, both within ``half_range`` of ``centre``."""
    fr = [f for f in scene.sweep if abs(f.power_dpt - centre) <= half_range]
    out = []
    for a in fr:
        best = min((b for b in fr if b.power_dpt > a.power_dpt), default=None,
                   key=lambda b: abs((b.power_dpt - a.power_dpt) - separation))
        if best is not None and abs((best.power_dpt - a.power_dpt) - separation) <= 0.26 * separation:
            out.append((a, best))
    return out


# ---------------------------------------------------------------------------- fitted camera
def _fitted_file(nominal: CameraFile, k: float, b: float, m: float, provenance: dict[str, Any]) -> CameraFile:
    cam = nominal.camera
    mu = k / cam.blur_scale_m_dpt
    inv_f0 = 1.0 / cam.sensor_distance_m - b
    if not (math.isfinite(mu) and mu > 0 and inv_f0 > 0):
        raise CalibrationError(f"the fit gives an impossible camera (mu {mu:.4g} px/m, 1/f0 {inv_f0:.4g} dpt)")
    fitted = cam.replace(mu_px_per_m=mu, fixed_focal_length_m=1.0 / inv_f0, name=f"{cam.name}-calibrated")
    return CameraFile(fitted, magnification_per_dpt=m, calibration=provenance)


def _datasheet_offset(nominal: CameraFile) -> float:
    cam = nominal.camera
    return 1.0 / cam.sensor_distance_m - cam.fixed_power_dpt - nominal.ecvfl_offset_dpt


def _provenance(route: str, source: str, nominal_path: str | None, frames: int, k: float, b: float,
                nominal: CameraFile, m: float, residuals: dict[str, np.ndarray]) -> dict[str, Any]:
    rms = {key: (float(np.sqrt(np.mean(v ** 2))) if len(v) else None) for key, v in residuals.items()}
    return {"route": route, "tdfd_version": __version__, "nominal_camera": nominal_path, "frames": frames,
            "k_px_per_dpt": k, "in_focus_offset_dpt": b, "in_focus_offset_source": source,
            "power_offset_vs_datasheet_dpt": _datasheet_offset(nominal) - b, "magnification_per_dpt": m,
            "residual_rms_dpt": rms, "residual_counts": {key: int(len(v)) for key, v in residuals.items()}}


# ---------------------------------------------------------------------------- known distance
def k_relative_uncertainty(design: np.ndarray, power_sd_dpt: float) -> float:
    r"""Relative standard uncertainty of ``K`` (and of ``mu``) from a known-distance fit's design.

    The fit is ``y = D / (P_a - P_b) = X theta`` with ``theta[0] = K^2`` and ``design`` ``X``
    (one column ``P_a + P_b - 2 P*`` for one distance; two, ``(P_a + P_b - 2/d, -2)``, for
    several). An error ``dP`` of a pair's in-focus power moves ``y`` by ``2 K^2 dP``, so
    ``sd(K^2) / K^2 = 2 power_sd sqrt((X^T X)^-1_00)`` and ``K`` has half that. Pairs centred
    on the target's focus (``P_a + P_b = 2 P*``: both frames equally blurred) measure no
    ``K``: :mod:`tdfd.dfd.calibrate`, *Conditioning*.
    """
    x = np.asarray(design, dtype=np.float64).reshape(len(design), -1)
    try:
        cov = np.linalg.inv(x.T @ x)
    except np.linalg.LinAlgError:
        return math.inf
    c00 = float(cov[0, 0])
    return power_sd_dpt * math.sqrt(c00) if c00 >= 0 and math.isfinite(c00) else math.inf


def _check_conditioning(frames: Sequence[CaptureFrame], distances: Sequence[float], pa: np.ndarray, pb: np.ndarray,
                        u: float, sd_power: float, max_mu_uncertainty: float | None) -> None:
    """Raise :class:`CalibrationError` when the known-distance pairs leave ``mu`` more uncertain than allowed."""
    if max_mu_uncertainty is None or u <= max_mu_uncertainty:
        return
    mids = ", ".join(f"{v:g}" for v in sorted({float(v) for v in (pa + pb) / 2}))
    raise CalibrationError(
        f"{_where(frames)}: the pairs at {', '.join(f'{v:g}' for v in distances)} m leave mu uncertain by {u:.1%} "
        f"(over {max_mu_uncertainty:.1%}) for a {sd_power:.3g} dpt error of a pair's in-focus power: a target whose "
        f"in-focus power is near the pair's midpoint ({mids} dpt) blurs both frames equally and measures no mu; "
        "add a pair at a distance farther from it (or --max-mu-uncertainty)")


def calibrate_known_distance(frames: Sequence[CaptureFrame], nominal: CameraFile, region: int = 64,
                             nominal_path: str | None = None, min_confidence: float = 0.5,
                             max_mu_uncertainty: float | None = MAX_MU_UNCERTAINTY,
                             power_sd_dpt: float = PAIR_POWER_SD_DPT) -> CalibrationResult:
    """The paper's route: pairs of a planar target at known distances.

    ``max_mu_uncertainty``: the largest relative standard uncertainty of ``mu`` the pairs may
    leave (:func:`k_relative_uncertainty`, with each pair's in-focus power uncertain by
    ``power_sd_dpt`` or the fit's residual RMS, whichever is larger); ``None`` accepts any.
    The uncertainty is recorded in the camera file's ``calibration.mu_relative_uncertainty``.

    Raises:
        CalibrationError: no pair with a known distance, measurements that give
            ``K^2 <= 0``, or pairs too near the distance their frames blur equally.
    """
    scenes = [s for s in group_scenes(frames) if s.distance_m is not None and s.pairs]
    if not scenes:
        raise CalibrationError(f"{_where(frames)}: the known-distance route needs at least one DFD pair (frames with "
                               "a 'pair' tag) whose sidecars give distance_m; none found")
    m, breath = estimate_breathing(scenes, region, nominal.camera)
    rows = []  # (pa, pb, d, D, name)
    meas: list[PairMeasurement] = []
    for s in scenes:
        for a, b in s.pairs:
            # a planar target: large regions (PREDICTION_REGION_PX), whose D the larger blur does not bias
            big = PREDICTION_REGION_PX if min(a.shape) >= PREDICTION_REGION_PX else region
            pm = measure_pair(nominal.camera, a.image, b.image, a.power_dpt, b.power_dpt, max(region, big), m,
                              (a.name, b.name))
            c = pm.confidence
            sel = c >= min_confidence * c.max()
            rows.append((a.power_dpt, b.power_dpt, s.distance_m, float(np.median(pm.square_difference[sel])), a.name))
            meas.append(pm)
    pa, pb, d, dsq = (np.array([r[i] for r in rows], dtype=np.float64) for i in range(4))
    y = dsq / (pa - pb)
    distances = sorted({float(v) for v in d})
    several = len(distances) >= 2
    # conditioning first (it needs the design only): a pair centred on its target's focus measures no K
    pre_design = (np.stack([pa + pb - 2 / d, -2 * np.ones_like(d)], 1) if several
                  else (pa + pb - 2 * (1 / d + _datasheet_offset(nominal)))[:, None])
    _check_conditioning(frames, distances, pa, pb, k_relative_uncertainty(pre_design, power_sd_dpt), power_sd_dpt,
                        max_mu_uncertainty)
    if several:
        design = np.stack([pa + pb - 2 / d, -2 * np.ones_like(d)], 1)
        (a2, a2b), *_ = np.linalg.lstsq(design, y, rcond=None)
        if a2 <= 0:
            raise CalibrationError(f"{_where(frames)}: the pairs give K^2 = {a2:.4g} <= 0: measurements disagree with the thin-lens model")
        b_fit = float(a2b / a2)
        source = f"fitted from known distances {', '.join(f'{v:g}' for v in distances)} m"
    else:
        b_fit = _datasheet_offset(nominal)
        x = pa + pb - 2 * (1 / d + b_fit)
        a2 = float(np.sum(x * y) / np.sum(x * x))
        if not a2 > 0:
            raise CalibrationError(f"{_where(frames)}: the pairs give K^2 = {a2:.4g} <= 0 (pair centred on focus?)")
        source = f"datasheet (nominal camera): one known distance ({distances[0]:g} m) fits mu only"
    k = math.sqrt(a2)
    model = a2 * (pa + pb - 2 * (1 / d + b_fit))
    res = (y - model) / (2 * a2)  # dpt: error of the pair's in-focus power
    residuals = {"pairs": res}
    n_par = 2 if len(distances) >= 2 else 1
    rms = float(np.sqrt(np.sum(res ** 2) / (len(res) - n_par))) if len(res) > n_par else 0.0
    sd_power = max(power_sd_dpt, rms)
    u = k_relative_uncertainty(design if several else x[:, None], sd_power)
    _check_conditioning(frames, distances, pa, pb, u, sd_power, max_mu_uncertainty)
    for (p1, p2, dd, _, name), r in zip(rows, res):
        log.info("pair %s (%.3f/%.3f dpt) at %.3f m: residual %+.4f dpt", name, p1, p2, dd, r)
    prov = _provenance("known-distance", source, nominal_path, len(frames), k, b_fit, nominal, m, residuals)
    prov["mu_relative_uncertainty"] = u
    prov["pair_power_sd_dpt"] = sd_power
    plot = {"route": "known-distance", "inv_d": 1 / d, "y": y, "pa": pa, "pb": pb, "a2": a2, "b": b_fit,
            "breathing": breath}
    return CalibrationResult(_fitted_file(nominal, k, b_fit, m, prov), "known-distance", k, b_fit, source, m,
                             residuals, plot)


# ---------------------------------------------------------------------------- self-calibration
def calibrate_self(frames: Sequence[CaptureFrame], nominal: CameraFile, region: int = 64,
                   nominal_path: str | None = None, min_confidence: float = 0.2, iterations: int = 20
                   ) -> CalibrationResult:
    """Self-calibration from focus sweeps (and pairs) of textured scenes, no distance needed.

    Raises:
        CalibrationError: no scene with a sweep, a sweep too short or never in focus,
            no usable pair measurement, or a fit giving ``K^2 <= 0``.
    """
    scenes = [s for s in group_scenes(frames) if s.sweep]
    if not scenes:
        raise CalibrationError(f"{_where(frames)}: self-calibration needs a focus sweep (frames without a 'pair' tag); "
                               "none found")
    m, breath = estimate_breathing(scenes, region, nominal.camera)
    cam = nominal.camera
    k_nom = cam.mu_px_per_m * cam.blur_scale_m_dpt
    separation = abs(cam.lens_powers_dpt[0] - cam.lens_powers_dpt[1])
    peak_list, eqs, sweeps = [], [], []  # eqs: (scene index, pa, pb, D (rows, cols), conf)
    for si, s in enumerate(scenes):
        peaks, powers, logf = sweep_peaks(s, region)
        peak_list.append(peaks)
        sweeps.append((powers, logf, peaks))
        centre = float(np.nanmedian(peaks))
        pairs = list(s.pairs)
        for sep in SWEEP_PAIR_SEPARATIONS:
            pairs += _sweep_pairs(s, sep * separation, centre, MAX_BLUR_PX / k_nom)
        for a, b in pairs:
            pm = measure_pair(cam, a.image, b.image, a.power_dpt, b.power_dpt, region, m, (a.name, b.name))
            eqs.append((si, a.power_dpt, b.power_dpt, pm.square_difference, pm.confidence))
    shape = peak_list[0].shape
    # unknowns: a = K^2, then one P* per (scene, textured region)
    index: dict[tuple[int, int, int], int] = {}
    init = []
    for si, pk in enumerate(peak_list):
        for i, j in zip(*np.nonzero(np.isfinite(pk))):
            index[(si, int(i), int(j))] = 1 + len(init)
            init.append(pk[i, j])
    obs = []  # (param index, pa, pb, D)
    for si, pa, pb, dsq, conf in eqs:
        for (s2, i, j), col in index.items():
            if s2 == si and conf[i, j] >= min_confidence * conf.max() and np.isfinite(dsq[i, j]):
                obs.append((col, pa, pb, float(dsq[i, j])))
    if not obs:
        raise CalibrationError(f"{_where(frames)}: no DFD pair of the swept scenes gives a usable blur measurement: "
                               "capture pairs of the same scene (--pair) or a finer sweep")
    col = np.array([o[0] for o in obs])
    pa, pb, dsq = (np.array([o[i] for o in obs], dtype=np.float64) for i in (1, 2, 3))
    theta = np.concatenate([[0.0], init])
    x = (pa - pb) * (pa + pb - 2 * theta[col])
    if np.sum(x * x) <= 0:
        raise CalibrationError(f"{_where(frames)}: the pairs are all centred on focus: no blur difference to fit")
    theta[0] = float(np.sum(x * dsq) / np.sum(x * x))
    if not theta[0] > 0:
        raise CalibrationError(f"{_where(frames)}: the pairs give K^2 = {theta[0]:.4g} <= 0: the measurements disagree with the sweep")
    n_p = len(init)
    peaks0 = np.array(init)
    keep = np.ones(len(obs), bool)
    for _ in range(3):  # Gauss-Newton, then drop pair measurements beyond 3 robust sigmas and refit
        for _ in range(iterations):  # residuals in dioptres (weights frozen per step)
            a = theta[0]
            scale = 1.0 / (2 * a * np.abs(pa - pb))
            r_pairs = (dsq - a * (pa - pb) * (pa + pb - 2 * theta[col])) * scale
            j_pairs = np.zeros((len(obs), 1 + n_p))
            j_pairs[:, 0] = -(pa - pb) * (pa + pb - 2 * theta[col]) * scale
            j_pairs[np.arange(len(obs)), col] = 2 * a * (pa - pb) * scale
            r_peaks = theta[1:] - peaks0
            j_peaks = np.hstack([np.zeros((n_p, 1)), np.eye(n_p)])
            jac = np.vstack([j_pairs[keep], j_peaks])
            res = np.concatenate([r_pairs[keep], r_peaks])
            step, *_ = np.linalg.lstsq(jac, -res, rcond=None)
            theta += step
            if abs(step[0]) < 1e-10 * abs(theta[0]) and np.max(np.abs(step[1:])) < 1e-9:
                break
        r_all = (dsq - theta[0] * (pa - pb) * (pa + pb - 2 * theta[col])) / (2 * theta[0] * np.abs(pa - pb))
        spread = max(1.4826 * float(np.median(np.abs(r_all[keep]))), 0.005)
        new = np.abs(r_all) <= 3 * spread
        if np.array_equal(new, keep) or new.sum() < 2:
            break
        keep = new
    if (~keep).any():
        log.info("self-calibration: %d of %d pair measurements dropped as outliers", int((~keep).sum()), len(keep))
    a2 = theta[0]
    if not a2 > 0:
        raise CalibrationError(f"{_where(frames)}: the joint fit gives K^2 = {a2:.4g} <= 0")
    k = math.sqrt(a2)
    r_pairs = ((dsq - a2 * (pa - pb) * (pa + pb - 2 * theta[col])) / (2 * a2 * np.abs(pa - pb)))[keep]
    r_peaks = theta[1:] - peaks0
    fitted_peaks = [np.full(shape, np.nan) for _ in scenes]
    for (si, i, j), c in index.items():
        fitted_peaks[si][i, j] = theta[c]
    known = [(s, fp) for s, fp in zip(scenes, fitted_peaks) if s.distance_m is not None]
    if known:
        offs = [float(np.nanmedian(fp)) - 1.0 / s.distance_m for s, fp in known]
        b_fit = float(np.mean(offs))
        source = "known distance " + ", ".join(f"{s.distance_m:g} m" for s, _ in known) + " (sweep peak)"
    else:
        b_fit = _datasheet_offset(nominal)
        source = "datasheet (nominal camera): no known distance; in-focus powers from pairs need only K"
    residuals = {"pairs": r_pairs, "peaks": r_peaks}
    prov = _provenance("self", source, nominal_path, len(frames), k, b_fit, nominal, m, residuals)
    prov["scenes"] = [{"label": s.label, "sweep_frames": len(s.sweep), "pairs": len(s.pairs),
                       "in_focus_power_dpt_median": float(np.nanmedian(fp))} for s, fp in zip(scenes, fitted_peaks)]
    x_def = ((pa + pb) / 2 - theta[col])[keep]  # pair midpoint minus fitted in-focus power
    plot = {"route": "self", "sweeps": sweeps, "fitted_peaks": fitted_peaks, "x_def": x_def,
            "d_over_dp": (dsq / (pa - pb))[keep], "a2": a2, "dropped": int((~keep).sum()), "breathing": breath, "labels": [s.label for s in scenes]}
    return CalibrationResult(_fitted_file(nominal, k, b_fit, m, prov), "self", k, b_fit, source, m, residuals, plot)
