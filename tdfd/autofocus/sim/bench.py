r"""The simulated autofocus bench: emulated lens on a real pty, virtual camera, simulated clock.

:class:`SimBench` puts the pieces of :mod:`tdfd.autofocus.sim` together and runs trials.

Everything a trial touches is the real product code except the physics:

* **Lens**: the Lens Driver 4 emulator (:class:`tdfd.driver.EmulatorServer`) on a real pseudo-terminal,
  driven through the real :class:`tdfd.driver.OptotuneLens` driver. The emulator's clock is the
  bench's :class:`~tdfd.autofocus.sim.clock.SimClock`, so its first-order settling (1 % after
  ``settling_time_s``, default 15 ms) runs on simulated time. Serial traffic costs simulated time:
  10 bits per byte at 115200 baud, each way; a read timeout costs the driver's timeout. After every
  set-point the bench reads it back (``PrDA``), as ``PwDA`` has no reply: a lost command is caught there.
* **Camera** (:class:`~tdfd.autofocus.sim.camera.VirtualCamera`): renders the scene with the one renderer
  (:func:`tdfd.optics.render_at_power`) at the lens's *optical* power during the exposure (sampled
  at its start, middle and end and averaged when the lens is still moving, so settling transients
  show), adds sensor noise, and delivers the frame ``readout_s`` after the exposure ends. Timing
  (:class:`~tdfd.autofocus.sim.timing.CameraTiming`): at most one exposure start per frame period
  (60 fps); ``trigger="hardware"`` starts the exposure as soon as the lens is settled (a triggered
  machine-vision camera), ``trigger="free"`` only on the free-running frame boundaries.
* **Compute**: the depth estimator's wall time as measured on this machine
  (``compute_s="measured"``) or a fixed, documented time per estimate.
* **Scene** (:class:`~tdfd.autofocus.sim.scene.Scene`): a procedural texture on a fronto-parallel plane at the
  target distance (default), or a user's image and depth map scaled so that the ROI sits
  at the target distance.

Simulated time is charged for: serial bytes, settling waits, frame boundaries, exposure,
read-out, the estimator and the controller's evidence (each relative-blur measurement and
cross-blur search, at measured wall times); not for the rest of the controller's arithmetic
and the sharpness measure (well under 1 ms, overlapping the lens settling).

Example::

    with SimBench(estimator=AnalyticEstimator(Camera.preset("reference"))) as bench:
        record = bench.run_trial(0.5, method="dfd")
        print(record.residual_blur_px, record.frames, record.time_ms)
"""

from __future__ import annotations

import contextlib
import logging
from typing import Any, Callable, Sequence

import numpy as np

from ...camera import Camera
from ...camera_file import CameraFile
from ...errors import InputError
from ...light.guard import DEFAULT_LIMITS, LightGuard, LightLimits
from ..assist import AssistedDFDController
from ..contrast import ContrastController
from ..dfd import DFDController
from ..estimators import estimator_breathing, suggested_confidence_scale, suggested_min_confidence
from ..interfaces import Estimator
from ..machine import StateMachine, drive
from ..messages import AFResult
from ..roi import Roi
from .camera import VirtualCamera
from .charges import cross_blur_wall_s, estimator_wall_s, evidence_wall_s, pair_cross_blur_wall_s, region_fit_wall_s
from .clock import SimClock
from .lens import EmulatedLens
from .noise import SensorNoise
from .plant import BenchPlant
from .scene import Scene
from .timing import CameraTiming
from .trials import TrialRecord

__all__ = ["SimBench", "DEFAULT_READOUT_HW"]

log = logging.getLogger(__name__)

#: default sensor read-out window (AOI) of the virtual camera, ``(H, W)`` px, centred on the reference sensor
DEFAULT_READOUT_HW = (256, 320)


class SimBench:
    """The simulated autofocus bench (a context manager: it owns the emulator and its pty).

    Args:
        camera: the camera (default: the estimator's, else ``reference``).
        estimator: the depth estimator for DFD (``None``: contrast AF only).
        readout_hw: the sensor read-out window ``(H, W)`` (px).
        roi: ROI in read-out pixels (default: the centred half).
        timing: camera timing.
        noise: sensor noise.
        settle_s: settling time the controllers wait, and the emulator's 1 % settling time (s).
        compute_s: estimator time charged per estimate: ``"calibrated"`` (the median wall
            time of the estimator on this machine, measured once when the bench opens),
            ``"measured"`` (each call's own wall time: noisy on a shared machine) or a fixed
            time in seconds.
        seed: seeds the scene textures and the sensor noise.
        psf: PSF shape of the simulated optics.
        scene: a user :class:`Scene` (its depth is rescaled per trial), default a
            procedural texture plane per trial.
        faults: emulator fault injection (a :class:`~tdfd.driver.Faults`) during trials.
        driver_timeout_s: the driver's reply timeout (s).
        controller: extra keyword arguments for :class:`DFDController`.
        contrast: keyword arguments for the contrast search (strategy, step, ...).
        texture_families: texture families of the default scenes (see :meth:`Scene.texture_plane`).
        light: the bench's assist light (a :class:`~tdfd.light.simulated.SimulatedLight`),
            switched only through :attr:`light_guard` (on the simulated clock); DFD
            trials asked with ``illumination=PATTERN`` (controller option) run the
            :class:`~tdfd.autofocus.assist.AssistedDFDController`. ``None``: no light.
        light_limits: the light's on-time and duty caps.
        evidence_s: time charged per relative-blur measurement of the controller's evidence
            (``None``: calibrated on this machine when the bench opens, 0 with ``compute_s=0``);
            added to the trial's time to focus (every one lies on the path to the declaration).
        cross_blur_s: likewise per cross-blur focus search (:mod:`tdfd.autofocus.cross_blur`).
        pair_cross_blur_s: likewise per 2-frame check of a known disk PSF (a cross-blur search
            of the DFD pair, one family: about a fifth of a 3-frame search; :mod:`.charges`).
        region_fit_s: likewise per region fit of a lit pair (:class:`~tdfd.autofocus.assist.AssistedDFDController`,
            step 3; measured when a light is given, the Gaussian Fourier ratio and a disk lens's
            cross-blur each; a number given is charged for both).
        true_camera: the simulated optics when they differ from ``camera`` (a
            :class:`~tdfd.camera_file.CameraFile`: its camera, ECVFL power offset and focus
            breathing, as in :mod:`tdfd.capture.sim`). ``camera`` is then what the
            controllers believe (e.g. a calibrated camera file's), and the record's truth
            (ideal power, residual blur) is the true camera's at the lens's real power.
            ``None``: the optics are ``camera``.
    """

    def __init__(self, camera: Camera | None = None, estimator: Estimator | None = None,
                 readout_hw: tuple[int, int] = DEFAULT_READOUT_HW, roi: Roi | None = None,
                 timing: CameraTiming = CameraTiming(), noise: SensorNoise = SensorNoise(), settle_s: float = 0.015,
                 compute_s: float | str = "calibrated", seed: int = 0, psf: Any = "gaussian", scene: Scene | None = None,
                 faults: Any | None = None, driver_timeout_s: float = 0.1, controller: dict | None = None,
                 contrast: dict | None = None, texture_families: Sequence[str] | None = None,
                 light: Any | None = None, light_limits: LightLimits = DEFAULT_LIMITS,
                 evidence_s: float | None = None, true_camera: CameraFile | None = None,
                 cross_blur_s: float | None = None, pair_cross_blur_s: float | None = None,
                 region_fit_s: float | None = None) -> None:
        if camera is None:
            camera = estimator.camera if estimator is not None else Camera.preset("reference")
        self.camera, self.estimator = camera, estimator
        self.true_camera = true_camera if true_camera is not None else CameraFile(camera)
        self.readout_hw = (int(readout_hw[0]), int(readout_hw[1]))
        self.roi = (roi or Roi.centre(self.readout_hw)).clip(self.readout_hw)
        self.timing, self.noise, self.settle_s, self.compute_s = timing, noise, float(settle_s), compute_s
        self.seed, self.psf, self.user_scene, self.faults = int(seed), psf, scene, faults
        if scene is not None and scene.sharp.shape != self.readout_hw:
            raise InputError(f"the scene is {scene.sharp.shape}, the read-out window {self.readout_hw}")
        self.driver_timeout_s = float(driver_timeout_s)
        self.controller_kwargs = dict(controller or {})
        self.contrast_kwargs = dict(contrast or {})
        self.texture_families = tuple(texture_families) if texture_families else None
        self.clock = SimClock()
        self.light = light
        self.light_guard = LightGuard(light, light_limits, clock=self.clock) if light is not None else None
        self.rng = np.random.default_rng(self.seed)
        self._phase_rng = np.random.default_rng([self.seed, 1])
        self.lens: EmulatedLens | None = None
        self.last_plant: BenchPlant | None = None
        if compute_s not in ("calibrated", "measured") and not (isinstance(compute_s, (int, float)) and compute_s >= 0):
            raise InputError(f"compute_s must be 'calibrated', 'measured' or a time >= 0 (s), got {compute_s!r}")
        self.compute_charge_s: float | str = compute_s if compute_s != "calibrated" else "measured"
        self.evidence_charge_s: float | None = evidence_s
        self.cross_blur_charge_s: float | None = cross_blur_s
        self.pair_cross_blur_charge_s: float | None = pair_cross_blur_s
        self.region_fit_charge_s: float | None = region_fit_s
        self.disk_region_fit_charge_s: float | None = region_fit_s

    def calibrate_evidence(self, repeats: int = 5) -> float:
        """Median wall time (s) of one relative-blur measurement on the ROI (:func:`~.charges.evidence_wall_s`)."""
        return evidence_wall_s(self.camera, self.roi, self.readout_hw, repeats)

    def calibrate_cross_blur(self, repeats: int = 3) -> float:
        """Median wall time (s) of one cross-blur focus search on three frames (:func:`~.charges.cross_blur_wall_s`)."""
        return cross_blur_wall_s(self.camera, self.roi, self.readout_hw, repeats)

    def calibrate_compute(self, repeats: int = 7) -> float:
        """Median wall time (s) of the estimator on the crop the DFD controller sends (:func:`~.charges.estimator_wall_s`)."""
        return estimator_wall_s(self.estimator, self.roi, self.readout_hw, repeats)

    # ------------------------------------------------------------------ life cycle
    def open(self) -> "SimBench":
        """Start the emulator and connect the driver."""
        if self.lens is None:
            self.lens = EmulatedLens(self.clock, settling_time_s=self.settle_s, timeout_s=self.driver_timeout_s)
        if self.evidence_charge_s is None:
            self.evidence_charge_s = self.calibrate_evidence() if self.compute_s != 0 else 0.0
            log.info("evidence charged per relative-blur measurement: %.1f ms", self.evidence_charge_s * 1e3)
        if self.cross_blur_charge_s is None:
            self.cross_blur_charge_s = self.calibrate_cross_blur() if self.compute_s != 0 else 0.0
        if self.region_fit_charge_s is None:
            self.region_fit_charge_s = (region_fit_wall_s(self.camera, self.roi, self.readout_hw)
                                        if self.compute_s != 0 and self.light is not None else 0.0)
        if self.disk_region_fit_charge_s is None:
            self.disk_region_fit_charge_s = (region_fit_wall_s(self.camera, self.roi, self.readout_hw, disk=True)
                                             if self.compute_s != 0 and self.light is not None else 0.0)
        if self.pair_cross_blur_charge_s is None:
            self.pair_cross_blur_charge_s = (pair_cross_blur_wall_s(self.camera, self.roi, self.readout_hw)
                                             if self.compute_s != 0 else 0.0)
        if self.compute_s == "calibrated" and self.compute_charge_s == "measured" and self.estimator is not None:
            self.compute_charge_s = self.calibrate_compute()
            log.info("estimator compute time charged per estimate: %.1f ms (median on this machine)",
                     self.compute_charge_s * 1e3)
        return self

    def close(self) -> None:
        """Disconnect and stop the emulator. Idempotent."""
        if self.lens is not None:
            self.lens.close()
            self.lens = None

    def __enter__(self) -> "SimBench":
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ trials
    def scene_for(self, target_m: float, trial: int, uniform: bool = False) -> Scene:
        """The scene of one trial: the user's scene at ``target_m``, or a seeded texture plane."""
        if self.user_scene is not None and not uniform:
            return self.user_scene.at_distance(target_m, self.roi)
        return Scene.texture_plane(self.readout_hw, target_m, seed=self.seed * 100003 + trial, uniform=uniform,
                                   families=self.texture_families)

    def make_controller(self, method: str, **overrides: Any) -> StateMachine:
        """A fresh controller for ``method`` (``"dfd"`` or ``"contrast"``) with the bench's settings."""
        assert self.lens is not None
        limits = self.lens.power_limits_dpt
        if method == "dfd":
            grid = (self.estimator.tile, self.estimator.stride) if self.estimator is not None else None
            kwargs = dict(roi=self.roi, settle_s=self.settle_s, power_limits_dpt=limits, contrast=self.contrast_kwargs,
                          grid=grid, min_confidence=suggested_min_confidence(self.estimator),
                          confidence_scale=suggested_confidence_scale(self.estimator))
            kwargs.update(self.controller_kwargs)
            kwargs.update(overrides)
            if kwargs.get("illumination") is not None:
                kwargs.setdefault("region_fit", estimator_breathing(self.estimator) == 0.0)  # it does not register
                return AssistedDFDController(self.camera, **kwargs)
            kwargs.pop("illumination", None)
            return DFDController(self.camera, **kwargs)
        if method == "contrast":
            kwargs = dict(roi=self.roi, settle_s=self.settle_s, power_limits_dpt=limits, **self.contrast_kwargs)
            kwargs.update(overrides)
            return ContrastController(self.camera, **kwargs)
        raise InputError(f"method must be 'dfd' or 'contrast', got {method!r}")

    def _plant(self, scene: Scene, halt_at_s: float | None = None,
               on_time: Callable[[float], None] | None = None) -> BenchPlant:
        assert self.lens is not None
        tc = self.true_camera
        cam = VirtualCamera(tc.camera, scene, self.lens.optical_power_at, self.timing, self.noise, self.rng, psf=self.psf,
                            light=self.light, power_offset_dpt=tc.ecvfl_offset_dpt,
                            magnification_per_dpt=tc.magnification_per_dpt)
        return BenchPlant(self.clock, self.lens, cam, self.estimator, self.compute_charge_s, halt_at_s=halt_at_s,
                          on_time=on_time, light_guard=self.light_guard)

    def _light_request(self) -> contextlib.AbstractContextManager:
        """One focus request for the light guard (fresh on-time budget; the light off at its end)."""
        return self.light_guard.request() if self.light_guard is not None else contextlib.nullcontext()

    def run_trial(self, target_m: float, method: str = "dfd", trial: int = 0, uniform: bool = False,
                  idle_s: float = 0.1, **controller: Any) -> TrialRecord:
        """One autofocus trial on a target at ``target_m``; never raises for a lens fault.

        The lens starts wherever the previous trial left it; ``idle_s`` plus a random
        (seeded) fraction of a frame period passes first, so the request falls at a random
        phase of a free-running camera's frame clock.

        Returns:
            The :class:`TrialRecord`.
        """
        if self.lens is None:
            self.open()
        assert self.lens is not None
        if method == "dfd" and self.estimator is None:
            raise InputError("DFD needs a depth estimator")
        self.clock.advance(idle_s + float(self._phase_rng.uniform(0.0, self.timing.frame_period_s)))
        scene = self.scene_for(target_m, trial, uniform)
        target = scene.roi_depth_m(self.roi)
        plant = self._plant(scene)
        self.last_plant = plant
        ctrl = self.make_controller(method, **controller)
        self.lens.set_faults(self.faults)
        on_before = self.light_guard.total_on_s if self.light_guard is not None else 0.0
        try:
            with self._light_request():
                result = drive(ctrl, plant)
        finally:
            self.lens.set_faults(None)
        rec = self._record(result, target, method, plant, trial)
        rec.scene = scene.name
        if isinstance(ctrl, AssistedDFDController):
            rec.extra.update(ctrl.lit_summary())
            rec.extra["light_on_ms"] = (self.light_guard.total_on_s - on_before) * 1e3 if self.light_guard else 0.0
        return rec

    def _record(self, result: AFResult, target: float, requested: str, plant: BenchPlant, trial: int) -> TrialRecord:
        from ...optics.thin_lens import camera_blur_radii_px

        assert self.lens is not None
        true, offset = self.true_camera.camera, self.true_camera.ecvfl_offset_dpt
        ideal = true.in_focus_power_dpt(target) - offset  # the command that focuses the target
        t_end = result.t_focus_s if result.t_focus_s is not None else self.clock.now()
        # an undeclared run's lens still settles on its last command (the run ends at the command)
        final = self.lens.optical_power_at(t_end if result.t_focus_s is not None or not result.history
                                           else max(t_end, result.history[-1][0]))
        resid = abs(float(camera_blur_radii_px(true, target, final + offset)))
        t0 = result.t_start_s if result.t_start_s is not None else t_end
        reason = (result.error or result.fallback_reason) if result.status != "focused" else result.fallback_reason
        if result.status == "focused" and result.error:  # e.g. clamped to the lens range
            reason = result.error + (f"; {result.fallback_reason}" if result.fallback_reason else "")
        compute = sum(plant.compute_times_s) * 1e3 if plant.compute_times_s else None
        if compute is not None and self.compute_charge_s != "measured":
            compute = float(self.compute_charge_s) * 1e3 * len(plant.compute_times_s)
        return TrialRecord(
            target_depth_m=float(target), estimated_depth_m=result.estimated_depth_m, ideal_power_dpt=float(ideal),
            final_power_dpt=float(final), residual_blur_px=resid, frames=result.frames,
            lens_commands=result.lens_commands,
            time_ms=(t_end - t0 + result.blur_measurements * float(self.evidence_charge_s or 0.0)
                     + result.cross_blur_measurements * float(self.cross_blur_charge_s or 0.0)
                     + result.pair_cross_blur_checks * float(self.pair_cross_blur_charge_s or 0.0)
                     + (result.region_fits - result.disk_region_fits) * float(self.region_fit_charge_s or 0.0)
                     + result.disk_region_fits * float(self.disk_region_fit_charge_s or 0.0)) * 1e3,
            method=result.method,
            requested=requested, status=result.status, reason=reason, confidence=result.confidence,
            compute_ms=compute, verified=result.verified, trial=trial, evidence=result.evidence,
            uncertainty_px=result.uncertainty_px, refine_count=result.refine_count, psf=str(self.psf),
            blur_measurements=result.blur_measurements,
            dfd_blur_px=None if result.dfd_power_dpt is None else
            abs(float(camera_blur_radii_px(true, target, result.dfd_power_dpt + offset))))

    def run_trials(self, depths: Sequence[float], methods: Sequence[str] = ("dfd",), uniform: bool = False,
                   progress: Callable[[TrialRecord], None] | None = None, **controller: Any) -> list[TrialRecord]:
        """Run every method on every target distance (the same scene per trial for every method).

        Returns:
            The records, trial-major (``[t0/m0, t0/m1, t1/m0, ...]``).
        """
        out = []
        for i, d in enumerate(depths):
            for m in methods:
                rec = self.run_trial(d, m, trial=i, uniform=uniform, **controller)
                out.append(rec)
                if progress is not None:
                    progress(rec)
        return out

    def run_continuous(self, schedule: Callable[[float], float], duration_s: float = 2.0, **controller: Any
                       ) -> tuple[AFResult, list[dict[str, float]]]:
        """Continuous DFD autofocus while the target moves along ``schedule(t) -> metres``.

        Args:
            schedule: target distance over time since the start of the run (s -> m).
            duration_s: simulated duration (s).

        Returns:
            ``(result, frames)``: the controller result and, per captured frame, its time
            (s, from the start), tag, target distance (m) and residual blur (px) at the
            optical power of its exposure.
        """
        from ...optics.thin_lens import camera_blur_radii_px

        if self.lens is None:
            self.open()
        assert self.lens is not None
        self.clock.advance(0.1)
        t0 = self.clock.now()
        base = self.scene_for(schedule(0.0), 0)
        holder = {"scene": base}

        def move(t: float) -> None:
            holder["scene"] = base.at_distance(schedule(t - t0), self.roi)
            plant.camera.scene = holder["scene"]

        plant = self._plant(base, halt_at_s=t0 + duration_s, on_time=move)
        self.last_plant = plant
        ctrl = self.make_controller("dfd", continuous=True, **controller)
        self.lens.set_faults(self.faults)
        try:
            with self._light_request():
                result = drive(ctrl, plant)
        finally:
            self.lens.set_faults(None)
        rows = []
        for start, optical, tag in plant.frames:
            d = schedule(start - t0)
            rows.append({"t_s": start - t0, "tag": tag, "target_depth_m": d,
                         "residual_blur_px": abs(float(camera_blur_radii_px(
                             self.true_camera.camera, d, optical + self.true_camera.ecvfl_offset_dpt)))})
        return result, rows
