r"""The simulated autofocus bench: emulated lens on a real pty, virtual camera, simulated clock.

Everything a trial touches is the real product code except the physics:

* **Lens**: the Lens Driver 4 emulator (:class:`tdfd.driver.EmulatorServer`) on a real
  pseudo-terminal, driven through the real :class:`tdfd.driver.OptotuneLens` driver. The
  emulator's clock is the bench's :class:`SimClock`, so its first-order settling
  (1 % after ``settling_time_s``, default 15 ms) runs on simulated time. Serial traffic
  costs simulated time: 10 bits per byte at 115200 baud, each way; a read timeout costs
  the driver's timeout. After every set-point the bench reads the set-point back
  (``PrDA``), because ``PwDA`` has no reply of its own: a lost command is caught there.
* **Camera** (:class:`VirtualCamera`): renders the scene with the one renderer
  (:func:`tdfd.optics.render_at_power`) at the lens's *optical* power during the
  exposure (sampled at its start, middle and end and averaged when the lens is still
  moving, so settling transients show), adds sensor noise, and delivers the frame
  ``readout_s`` after the exposure ends. Timing (:class:`CameraTiming`): at most one
  exposure start per frame period (60 fps); ``trigger="hardware"`` starts the exposure
  as soon as the lens is settled (a triggered machine-vision camera),
  ``trigger="free"`` only on the free-running frame boundaries.
* **Compute**: the depth estimator's wall time as measured on this machine
  (``compute_s="measured"``) or a fixed, documented time per estimate.
* **Scene** (:class:`Scene`): a procedural texture on a fronto-parallel plane at the
  target distance (default), or a user's image and depth map scaled so that the ROI sits
  at the target distance.

Simulated time is charged for: serial bytes, settling waits, frame boundaries, exposure,
read-out and the estimator. It is not charged for the controller's own arithmetic and
the sharpness measure (well under 1 ms, overlapping the lens settling).

Example::

    with SimBench(estimator=AnalyticEstimator(Camera.preset("reference"))) as bench:
        record = bench.run_trial(0.5, method="dfd")
        print(record.residual_blur_px, record.frames, record.time_ms)
"""

from __future__ import annotations

import contextlib
import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterator, Sequence

import numpy as np

from ..camera import Camera
from ..errors import DriverError, InputError, TdfdError
from .controller import (
    AFResult,
    Capture,
    CaptureFault,
    DFDController,
    Estimate,
    EstimateFault,
    Estimation,
    Estimator,
    Frame,
    LensAck,
    LensFault,
    Roi,
    SetPower,
    StateMachine,
    drive,
)
from .contrast import ContrastController

__all__ = [
    "SimClock",
    "CameraTiming",
    "SensorNoise",
    "Scene",
    "VirtualCamera",
    "EmulatedLens",
    "BenchPlant",
    "TrialRecord",
    "SimBench",
    "trial_depths",
    "command_lens",
    "DEFAULT_READOUT_HW",
    "BENCH_TEXTURE_FAMILIES",
    "BENCH_TEMPERATURE_LIMITS_C",
    "torch_threads",
]

log = logging.getLogger(__name__)

#: default sensor read-out window (AOI) of the virtual camera, ``(H, W)`` pixels, centred
#: on the 1200 x 1600 sensor of the reference camera.
DEFAULT_READOUT_HW = (256, 320)
#: temperature limits (°C) sent before focal-power mode on the bench: the emulated
#: EL-10-30-C reaches +3.55 dpt at 25 °C, enough for 0.3 m (3.33 dpt).
BENCH_TEMPERATURE_LIMITS_C = (15.0, 25.0)
_BAUD = 115200
_BITS_PER_BYTE = 10


@contextlib.contextmanager
def torch_threads(n: int | None) -> Iterator[None]:
    """Run the block with ``n`` torch intra-op threads (``None``: unchanged), then restore.

    The bench's frames are small: one thread is as fast as two, and on a busy machine two
    threads can be many times slower (the pool waits on a preempted worker).
    """
    import torch

    before = torch.get_num_threads()
    if n is None or n == before:
        yield
        return
    torch.set_num_threads(int(n))
    try:
        yield
    finally:
        torch.set_num_threads(before)


# ------------------------------------------------------------------------------ clock
class SimClock:
    """Simulated time in seconds; only the bench advances it.

    Example:
        >>> c = SimClock(); _ = c.advance(0.5); _ = c.advance_to(0.25); c()
        0.5
    """

    def __init__(self, t0: float = 0.0) -> None:
        self._t = float(t0)

    def __call__(self) -> float:
        return self._t

    def now(self) -> float:
        """The present simulated time (s)."""
        return self._t

    def advance(self, dt: float) -> float:
        """Move ``dt >= 0`` seconds forward; return the new time."""
        if dt < 0:
            raise InputError(f"simulated time cannot go backwards ({dt} s)")
        self._t += float(dt)
        return self._t

    def advance_to(self, t: float) -> float:
        """Move forward to ``t`` if it is later; return the new time."""
        self._t = max(self._t, float(t))
        return self._t


# ---------------------------------------------------------------------------- camera
@dataclass(frozen=True)
class CameraTiming:
    """Frame timing of the virtual camera.

    Attributes:
        frame_period_s: shortest time between exposure starts (1/60 s: 60 fps).
        exposure_s: exposure time (s).
        readout_s: from the end of the exposure until the frame is on the host (s).
        trigger: ``"hardware"`` (exposure starts when the controller asks, at most one
            per frame period) or ``"free"`` (exposures start only on the free-running
            frame boundaries ``phase_s + k * frame_period_s``).
        phase_s: phase of the free-running frame clock (s).
    """

    frame_period_s: float = 1.0 / 60.0
    exposure_s: float = 0.002
    readout_s: float = 0.003
    trigger: str = "hardware"
    phase_s: float = 0.0

    def __post_init__(self) -> None:
        if self.trigger not in ("hardware", "free"):
            raise InputError(f"trigger must be 'hardware' or 'free', got {self.trigger!r}")
        if not (self.frame_period_s > 0 and 0 < self.exposure_s <= self.frame_period_s and self.readout_s >= 0):
            raise InputError("need frame_period_s > 0, 0 < exposure_s <= frame_period_s, readout_s >= 0")

    def next_start(self, earliest_s: float, last_start_s: float | None) -> float:
        """The first allowed exposure start at or after ``earliest_s`` (s)."""
        t = earliest_s if last_start_s is None else max(earliest_s, last_start_s + self.frame_period_s)
        if self.trigger == "free":
            k = math.ceil((t - self.phase_s) / self.frame_period_s - 1e-9)
            t = self.phase_s + k * self.frame_period_s
        return t


@dataclass(frozen=True)
class SensorNoise:
    """Sensor noise and quantisation of the virtual camera.

    Uses :class:`tdfd.sensor.SensorModel` (Poisson–Gaussian noise, full-well clipping,
    black level, quantisation) when that module is available, else an equivalent
    Poisson–Gaussian model without black level.

    Attributes:
        full_well_e: electrons at white level.
        read_noise_e: read noise, electrons RMS.
        bits: ADC bits.
        black_level_dn: black level in codes (kept in the output, as a raw frame has it).
        enabled: ``False`` gives noise-free, unquantised frames.
    """

    full_well_e: float = 10000.0
    read_noise_e: float = 3.0
    bits: int = 12
    black_level_dn: float = 64.0
    enabled: bool = True

    def apply(self, image: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Noisy, quantised frame in [0, 1] from a noise-free linear irradiance in [0, 1]."""
        x = np.clip(image, 0.0, 1.0).astype(np.float64)
        if not self.enabled:
            return x.astype(np.float32)
        seed = int(rng.integers(0, 2**62))
        try:
            import torch

            from ..sensor import SensorModel
        except ImportError:
            electrons = rng.poisson(x * self.full_well_e) + rng.normal(0.0, self.read_noise_e, x.shape)
            levels = 2**self.bits - 1
            y = np.clip(np.round(electrons / self.full_well_e * levels), 0, levels) / levels
            return y.astype(np.float32)
        model = SensorModel(full_well_e=self.full_well_e, read_noise_e=self.read_noise_e, bits=self.bits,
                            black_level_dn=self.black_level_dn)
        with torch.no_grad(), torch_threads(1):
            y = model(torch.from_numpy(x.astype(np.float32))[None, None], generator=torch.Generator().manual_seed(seed))
        return y[0, 0].numpy().astype(np.float32)


def _procedural_texture(hw: tuple[int, int], seed: int, albedo_contrast: float = 1.0) -> np.ndarray:
    """A seeded 1/f ("pink") noise texture in [0.1, 0.9] (fallback for :mod:`tdfd.textures`)."""
    h, w = hw
    rng = np.random.default_rng(seed)
    fy = np.fft.fftfreq(h)[:, None]
    fx = np.fft.rfftfreq(w)[None, :]
    f = np.sqrt(fx * fx + fy * fy)
    f[0, 0] = 1.0
    amp = 1.0 / f ** rng.uniform(0.8, 1.2)
    amp[0, 0] = 0.0
    phase = rng.uniform(0, 2 * np.pi, amp.shape)
    x = np.fft.irfft2(amp * np.exp(1j * phase), s=(h, w))
    x = (x - x.mean()) / (x.std() + 1e-12)
    return np.clip(0.5 + 0.16 * albedo_contrast * x, 0.1, 0.9)


#: texture families of the bench's default targets (textured surfaces; ``flat`` and
#: ``gradient`` are the texture-less cases, tested separately with ``uniform=True``).
BENCH_TEXTURE_FAMILIES = ("fractal", "bandlimited", "voronoi", "dead_leaves", "stripes", "checkers", "dots",
                          "line_art", "glyphs")


def _library_texture(hw: tuple[int, int], seed: int, families: Sequence[str] = BENCH_TEXTURE_FAMILIES
                     ) -> tuple[np.ndarray, str] | None:
    """A seeded texture from :func:`tdfd.textures.random_texture` (``None`` if unavailable)."""
    try:
        import torch

        from ..textures import random_texture
    except ImportError:
        return None
    g = torch.Generator().manual_seed(int(seed))
    tex, params = random_texture(g, hw, families=list(families), albedo=(0.5, 0.9), contrast=(0.3, 1.0))
    return tex[0, 0].double().numpy(), str(params.get("family", "texture"))


@dataclass
class Scene:
    """What the virtual camera looks at: sharp radiance and depth on the read-out window.

    Attributes:
        sharp: ``(H, W)`` all-in-focus linear radiance in [0, 1].
        depth_m: ``(H, W)`` object distance in metres.
        name: a label.
    """

    sharp: np.ndarray
    depth_m: np.ndarray
    name: str = "scene"

    def __post_init__(self) -> None:
        self.sharp = np.asarray(self.sharp, dtype=np.float64)
        self.depth_m = np.asarray(self.depth_m, dtype=np.float64)
        if self.sharp.ndim != 2 or self.sharp.shape != self.depth_m.shape:
            raise InputError(f"scene image and depth must be (H, W) of one shape, got {self.sharp.shape} and {self.depth_m.shape}")
        if not np.isfinite(self.depth_m).all() or (self.depth_m <= 0).any():
            raise InputError("scene depth must be finite and > 0")

    @property
    def planar(self) -> bool:
        """``True`` if the depth is one value everywhere (exact, fast rendering)."""
        return bool(self.depth_m.max() == self.depth_m.min())

    def roi_depth_m(self, roi: Roi) -> float:
        """The depth whose blur the ROI shows on average: the mean inverse depth, inverted (m)."""
        return float(1.0 / np.mean(1.0 / roi.crop(self.depth_m)))

    @classmethod
    def texture_plane(cls, hw: tuple[int, int], depth_m: float, seed: int = 0, uniform: bool = False,
                      families: Sequence[str] | None = None) -> "Scene":
        """A procedural texture (seeded) on a plane at ``depth_m``.

        Args:
            hw: ``(H, W)`` pixels.
            depth_m: plane distance (m).
            seed: texture seed.
            uniform: a texture-less grey plane instead.
            families: :mod:`tdfd.textures` families to draw from (default
                :data:`BENCH_TEXTURE_FAMILIES`); ``("pink",)`` is a built-in 1/f noise.
        """
        name = "uniform"
        families = tuple(families) if families else BENCH_TEXTURE_FAMILIES
        if uniform:
            sharp = np.full(hw, 0.5)
        else:
            lib = None if families == ("pink",) else _library_texture(hw, seed, families)
            sharp, name = lib if lib is not None else (_procedural_texture(hw, seed), "pink noise")
        return cls(sharp, np.full(hw, float(depth_m)), name=name)

    @classmethod
    def from_files(cls, image_path: str | Path, depth_path: str | Path, hw: tuple[int, int] | None = None,
                   linearise: bool = True) -> "Scene":
        """A user's image and depth map (``.npy`` in metres), resized to ``hw`` (default: the image's size).

        Args:
            image_path: any image OpenCV reads; converted to grey. 8/16-bit images are
                scaled by their white level.
            depth_path: ``.npy`` array ``(H, W)`` of distances in metres.
            hw: the read-out window size to resize both to.
            linearise: undo the sRGB gamma of an 8-bit image (linear radiance is needed).

        Raises:
            InputError: unreadable files or bad depth.
        """
        import cv2

        img = cv2.imread(str(image_path), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise InputError(f"cannot read the scene image {image_path}")
        if img.ndim == 3:
            img = cv2.cvtColor(img[..., :3], cv2.COLOR_BGR2GRAY)
        white = 65535.0 if img.dtype == np.uint16 else 255.0 if img.dtype == np.uint8 else 1.0
        x = img.astype(np.float64) / white
        if linearise and img.dtype == np.uint8:
            x = np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)
        try:
            depth = np.load(str(depth_path)).astype(np.float64)
        except (OSError, ValueError) as exc:
            raise InputError(f"cannot read the scene depth {depth_path}: {exc}") from exc
        depth = np.squeeze(depth)
        if hw is None:
            hw = x.shape[:2]
        x = cv2.resize(x, (hw[1], hw[0]), interpolation=cv2.INTER_AREA)
        depth = cv2.resize(depth, (hw[1], hw[0]), interpolation=cv2.INTER_NEAREST)
        return cls(np.clip(0.05 + 0.9 * x, 0.0, 1.0), depth, name=Path(image_path).name)

    def at_distance(self, target_m: float, roi: Roi) -> "Scene":
        """The scene with its depth scaled so that the ROI sits at ``target_m`` (m)."""
        scale = target_m / self.roi_depth_m(roi)
        return Scene(self.sharp, self.depth_m * scale, self.name)


class VirtualCamera:
    """Renders frames of a :class:`Scene` at the lens's optical power during the exposure.

    Args:
        camera: optics (aperture, sensor distance, fixed lens, pixel pitch, ``mu``).
        scene: what is seen.
        power_at: the optical ECVFL power at a simulated time, ``t -> dpt``.
        timing: frame timing.
        noise: sensor noise.
        rng: noise generator (seeded by the bench).
        psf: PSF shape of the simulated optics (``"gaussian"``, ``"pillbox"`` or a
            power-exponential ``beta``).
        mu: true blur constant in px/m (default ``camera.mu_px_per_m``).
        threads: torch threads while rendering (restored afterwards; ``None``: unchanged).
    """

    def __init__(self, camera: Camera, scene: Scene, power_at: Callable[[float], float],
                 timing: CameraTiming = CameraTiming(), noise: SensorNoise = SensorNoise(),
                 rng: np.random.Generator | None = None, psf: Any = "gaussian", mu: float | None = None,
                 threads: int | None = 1) -> None:
        self.camera, self.scene, self.power_at = camera, scene, power_at
        self.timing, self.noise = timing, noise
        self.rng = rng if rng is not None else np.random.default_rng(0)
        self.psf, self.mu, self.threads = psf, mu, threads
        self.last_start_s: float | None = None
        self._cache: tuple[Scene, Any, Any] | None = None

    def _tensors(self):
        import torch

        key = self.scene
        if self._cache is None or self._cache[0] is not key:
            # numpy does the dtype conversion: no torch thread pool involved
            sharp = torch.from_numpy(np.ascontiguousarray(self.scene.sharp, dtype=np.float32))[None, None]
            depth = torch.from_numpy(np.ascontiguousarray(self.scene.depth_m, dtype=np.float32))[None, None]
            self._cache = (key, sharp, depth)
        return self._cache[1], self._cache[2]

    def render(self, powers_dpt: Sequence[float]) -> np.ndarray:
        """Noise-free frame: the mean of the renders at ``powers_dpt`` (the exposure's samples)."""
        import torch

        from ..optics.render import render_at_power

        sharp, depth = self._tensors()
        p = torch.tensor(list(powers_dpt), dtype=torch.float32)
        with torch.no_grad(), torch_threads(self.threads):
            out = render_at_power(self.camera, sharp.expand(len(p), -1, -1, -1), depth.expand(len(p), -1, -1, -1),
                                  p, shape=self.psf, mu=self.mu)
            out = out[0, 0] if len(p) == 1 else out.mean(0)[0]
        return out.numpy().astype(np.float64)

    def expose(self, t_start_s: float) -> tuple[np.ndarray, float]:
        """Expose from ``t_start_s`` for ``timing.exposure_s``.

        Returns:
            ``(frame (H, W) float32 in [0, 1], mean optical power during the exposure in dpt)``.
        """
        e = self.timing.exposure_s
        samples = [self.power_at(t_start_s + f * e) for f in (0.0, 0.5, 1.0)]
        powers = [samples[1]] if max(samples) - min(samples) < 2e-3 else samples
        self.last_start_s = t_start_s
        return self.noise.apply(self.render(powers), self.rng), float(np.mean(samples))


# ------------------------------------------------------------------------------ lens
class _TimedPort:
    """A pyserial-like proxy that charges simulated time for the serial traffic.

    Writes advance the clock by the bytes' wire time *before* they reach the emulator (so
    the emulator stamps a command with its arrival time) and then wait until the emulator
    has processed the command, which keeps the bench deterministic. Reads advance the
    clock by the wire time of what arrives; a short read (a timeout) costs the timeout.
    """

    def __init__(self, port: Any, clock: SimClock, device: Any, baud: int = _BAUD) -> None:
        self._port, self._clock, self._device, self._baud = port, clock, device, baud

    def _wire(self, n: int) -> float:
        return n * _BITS_PER_BYTE / self._baud

    @property
    def timeout(self) -> float:
        return self._port.timeout

    @timeout.setter
    def timeout(self, value: float) -> None:
        self._port.timeout = value

    @property
    def in_waiting(self) -> int:
        return self._port.in_waiting

    @property
    def port(self) -> str:
        return getattr(self._port, "port", "emulator")

    def write(self, data: bytes) -> int:
        before = self._device.command_count
        self._clock.advance(self._wire(len(data)))
        n = self._port.write(data)
        try:
            self._port.flush()
        except Exception:  # noqa: BLE001 - the real write reports a vanished port
            pass
        deadline = time.monotonic() + 1.0
        while self._device.command_count == before and time.monotonic() < deadline:
            time.sleep(0.0002)
        return n

    def flush(self) -> None:
        pass

    def read(self, n: int = 1) -> bytes:
        t0 = time.monotonic()
        data = self._port.read(n)
        waited = time.monotonic() - t0
        self._clock.advance(self._wire(len(data)))
        if len(data) < n:
            self._clock.advance(float(self._port.timeout or 0.0))
        elif waited > 0.05:  # a late reply: charge the wait
            self._clock.advance(waited)
        return data

    def reset_input_buffer(self) -> None:
        self._port.reset_input_buffer()

    def close(self) -> None:
        self._port.close()


def command_lens(lens: Any, power_dpt: float, verify: bool = True, clock: Callable[[], float] = time.monotonic,
                 tolerance_dpt: float = 0.006) -> float:
    """Set ``lens`` to ``power_dpt`` and (``verify``) read the set-point back, re-sending once on a mismatch.

    ``PwDA`` has no reply, so a command lost on the wire is only seen by reading the
    set-point back (``PrDA``).

    Args:
        lens: an :class:`~tdfd.driver.OptotuneLens` in focal-power mode.
        power_dpt: the set-point (dpt).
        verify: read the set-point back.
        clock: time source; its reading right after the command is returned.
        tolerance_dpt: accepted read-back difference (one raw step is 0.005 dpt).

    Returns:
        The time the command was written (after its bytes), by ``clock`` (s).

    Raises:
        DriverError: the driver failed (after its own retries), or the read-back disagrees twice.
    """
    got = math.nan
    for attempt in range(2):
        lens.set_focal_power_dpt(power_dpt)
        arrived = clock()
        if not verify:
            return arrived
        got = lens.get_focal_power_dpt()
        if abs(got - power_dpt) <= tolerance_dpt:
            return arrived
        log.warning("lens set-point read back %.3f dpt, expected %.3f dpt (attempt %d)", got, power_dpt, attempt + 1)
    raise DriverError(f"lens set-point reads back {got:.3f} dpt instead of {power_dpt:.3f} dpt")


class EmulatedLens:
    """The lens emulator on a pty, opened through the real :class:`~tdfd.driver.OptotuneLens`.

    Args:
        clock: the bench clock (the emulator's clock too).
        settling_time_s: the emulator's 1 % settling time (s).
        timeout_s: the driver's reply timeout (s).
        retries: the driver's retries per query.
        temperature_limits_c: sent before switching to focal-power mode.
        temperature_c: the emulated lens temperature (°C).

    Attributes:
        server: the :class:`~tdfd.driver.EmulatorServer` (``.device`` is the model).
        lens: the connected driver, in focal-power mode.
        power_limits_dpt: ``(min, max)`` focal power the driver reported.
    """

    def __init__(self, clock: SimClock, settling_time_s: float = 0.015, timeout_s: float = 0.1, retries: int = 2,
                 temperature_limits_c: tuple[float, float] = BENCH_TEMPERATURE_LIMITS_C,
                 temperature_c: float = 22.0) -> None:
        import serial

        from ..driver import EmulatorServer, OptotuneLens

        self.clock = clock
        self.server = EmulatorServer(clock=clock, settling_time_s=settling_time_s, temperature_c=temperature_c).start()
        try:
            raw = serial.serial_for_url(self.server.port, baudrate=_BAUD, timeout=timeout_s, write_timeout=1.0)
            self.port = _TimedPort(raw, clock, self.server.device)
            self.lens = OptotuneLens(self.port, timeout_s=timeout_s, retries=retries, owns_port=True)
            self.lens.connect(handshake=True)
            limits = self.lens.set_focal_power_mode(temperature_limits_c)
        except BaseException:
            self.close()
            raise
        self.power_limits_dpt = (float(limits.min_dpt), float(limits.max_dpt))
        log.info("bench lens on %s: focal-power range %.3f to %.3f dpt", self.server.port, *self.power_limits_dpt)

    def set_faults(self, faults: Any | None) -> None:
        """Turn the emulator's fault injection on (a :class:`~tdfd.driver.Faults`) or off (``None``)."""
        from ..driver import Faults

        self.server.faults = faults if faults is not None else Faults()

    def optical_power_at(self, t_s: float) -> float:
        """The lens's optical focal power at simulated time ``t_s`` (dpt)."""
        return float(self.server.device.focal_power_at(t_s))

    def command(self, power_dpt: float, verify: bool = True) -> float:
        """Set the focal power and read the set-point back; return the arrival time of the command (s).

        Raises:
            DriverError: the driver failed (after its retries), or the read-back disagrees twice.
        """
        return command_lens(self.lens, power_dpt, verify=verify, clock=self.clock.now)

    def close(self) -> None:
        """Close the driver and stop the emulator. Idempotent."""
        lens = getattr(self, "lens", None)
        if lens is not None:
            lens.close()
        else:
            port = getattr(self, "port", None)
            if port is not None:
                port.close()
        self.server.stop()


# ----------------------------------------------------------------------------- plant
class BenchPlant:
    """Executes controller commands on the bench (implements :class:`~tdfd.autofocus.controller.Plant`).

    Args:
        clock: simulated clock.
        lens: the emulated lens.
        camera: the virtual camera.
        estimator: the depth estimator.
        compute_s: ``"measured"`` (charge the estimator's wall time) or a fixed time per
            estimate in seconds.
        halt_at_s: simulated time at which :meth:`should_halt` turns true (continuous mode).
        on_time: called with the simulated time whenever it advances past a frame
            (continuous mode moves the target with it).
    """

    def __init__(self, clock: SimClock, lens: EmulatedLens, camera: VirtualCamera, estimator: Estimator | None,
                 compute_s: float | str = "measured", halt_at_s: float | None = None,
                 on_time: Callable[[float], None] | None = None) -> None:
        self.clock, self.lens, self.camera, self.estimator = clock, lens, camera, estimator
        if compute_s != "measured" and not (isinstance(compute_s, (int, float)) and compute_s >= 0):
            raise InputError(f"compute_s must be 'measured' or a time >= 0 (s), got {compute_s!r}")
        self.compute_s = compute_s
        self.halt_at_s, self.on_time = halt_at_s, on_time
        self.lens_ready_s = clock.now()
        self.compute_times_s: list[float] = []
        self.frames: list[tuple[float, float, str]] = []  # (t_start, optical power, tag)

    def now(self) -> float:
        return self.clock.now()

    def should_halt(self) -> bool:
        return self.halt_at_s is not None and self.clock.now() >= self.halt_at_s

    def _command(self, power_dpt: float, settle_s: float) -> LensAck | LensFault:
        t_issue = self.clock.now()
        try:
            arrived = self.lens.command(power_dpt)
        except TdfdError as exc:
            return LensFault(power_dpt, f"{type(exc).__name__}: {exc}", self.clock.now())
        self.lens_ready_s = arrived + settle_s
        return LensAck(power_dpt, t_issue, self.lens_ready_s)

    def set_power(self, cmd: SetPower) -> LensAck | LensFault:
        return self._command(cmd.power_dpt, cmd.settle_s)

    def capture(self, cmd: Capture) -> Frame | CaptureFault:
        timing = self.camera.timing
        start = timing.next_start(max(self.clock.now(), self.lens_ready_s), self.camera.last_start_s)
        self.clock.advance_to(start)
        if self.on_time is not None:
            self.on_time(start)
        image, optical = self.camera.expose(start)
        self.frames.append((start, optical, cmd.tag))
        end = start + timing.exposure_s
        self.clock.advance_to(end)
        lens = None
        if cmd.then_power_dpt is not None:
            lens = self._command(cmd.then_power_dpt, cmd.settle_s)
        ready = end + timing.readout_s
        self.clock.advance_to(ready)
        return Frame(image, float(optical), start, end, max(ready, self.clock.now()), cmd.tag, lens=lens)

    def estimate(self, cmd: Estimate) -> Estimation | EstimateFault:
        if self.estimator is None:
            return EstimateFault("no depth estimator", self.clock.now())
        t0 = time.perf_counter()
        try:
            depth, conf = self.estimator(cmd.image_f1, cmd.image_f2)
        except TdfdError as exc:
            return EstimateFault(f"{type(exc).__name__}: {exc}", self.clock.now())
        wall = time.perf_counter() - t0
        charged = wall if self.compute_s == "measured" else float(self.compute_s)
        self.compute_times_s.append(wall)
        self.clock.advance(charged)
        return Estimation(np.asarray(depth), np.asarray(conf), self.estimator.tile, self.estimator.stride,
                          t_s=self.clock.now(), elapsed_s=charged)


# ----------------------------------------------------------------------------- trials
@dataclass
class TrialRecord:
    """One autofocus trial on the bench (the contract fields plus what the report summary needs).

    Attributes:
        target_depth_m: true distance of the ROI (m).
        estimated_depth_m: the DFD estimate (m), ``None`` without one.
        ideal_power_dpt: in-focus ECVFL power of the target (dpt).
        final_power_dpt: the lens's optical power when focus was declared (or at the end
            of a failed trial) (dpt).
        residual_blur_px: ``|r_b|`` at ``final_power_dpt`` (px).
        frames: frames captured.
        lens_commands: set-point commands sent.
        time_ms: simulated time from the request to focus (or to the failure) (ms).
        method: ``"dfd"`` or ``"contrast"``: the method that set the final power.
        requested: the method asked for.
        status: ``"focused"``, ``"failed"``, ...
        reason: failure or fall-back reason, ``None`` if none.
        confidence: ROI confidence of the DFD estimate.
        compute_ms: estimator time charged (ms).
        verified: verification outcome, ``None`` if not verified.
        trial: index.
    """

    target_depth_m: float
    estimated_depth_m: float | None
    ideal_power_dpt: float
    final_power_dpt: float | None
    residual_blur_px: float | None
    frames: int
    lens_commands: int
    time_ms: float | None
    method: str
    requested: str = "dfd"
    status: str = "focused"
    reason: str | None = None
    confidence: float | None = None
    compute_ms: float | None = None
    verified: bool | None = None
    trial: int = 0
    scene: str = ""
    extra: dict = field(default_factory=dict)

    @property
    def in_focus(self) -> bool:
        """Focus declared and residual blur radius under 1 px."""
        return self.status == "focused" and self.residual_blur_px is not None and self.residual_blur_px < 1.0


def trial_depths(n: int, seed: int = 0, depth_range_m: tuple[float, float] = (0.3, 1.0)) -> list[float]:
    """``n`` target distances spread across ``depth_range_m``: stratified, uniform in inverse depth, seeded.

    Example:
        >>> d = trial_depths(4, seed=0)
        >>> len(d), all(0.3 <= x <= 1.0 for x in d)
        (4, True)
    """
    if n < 1:
        raise InputError(f"need at least one trial, got {n}")
    near, far = depth_range_m
    q_lo, q_hi = 1.0 / far, 1.0 / near
    rng = np.random.default_rng(seed)
    u = (np.arange(n) + rng.uniform(0.0, 1.0, n)) / n
    q = q_lo + u * (q_hi - q_lo)
    rng.shuffle(q)
    return [float(1.0 / x) for x in q]


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
    """

    def __init__(self, camera: Camera | None = None, estimator: Estimator | None = None,
                 readout_hw: tuple[int, int] = DEFAULT_READOUT_HW, roi: Roi | None = None,
                 timing: CameraTiming = CameraTiming(), noise: SensorNoise = SensorNoise(), settle_s: float = 0.015,
                 compute_s: float | str = "calibrated", seed: int = 0, psf: Any = "gaussian", scene: Scene | None = None,
                 faults: Any | None = None, driver_timeout_s: float = 0.1, controller: dict | None = None,
                 contrast: dict | None = None, texture_families: Sequence[str] | None = None) -> None:
        if camera is None:
            camera = estimator.camera if estimator is not None else Camera.preset("reference")
        self.camera, self.estimator = camera, estimator
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
        self.rng = np.random.default_rng(self.seed)
        self._phase_rng = np.random.default_rng([self.seed, 1])
        self.lens: EmulatedLens | None = None
        self.last_plant: BenchPlant | None = None
        if compute_s not in ("calibrated", "measured") and not (isinstance(compute_s, (int, float)) and compute_s >= 0):
            raise InputError(f"compute_s must be 'calibrated', 'measured' or a time >= 0 (s), got {compute_s!r}")
        self.compute_charge_s: float | str = compute_s if compute_s != "calibrated" else "measured"

    def calibrate_compute(self, repeats: int = 7) -> float:
        """Median wall time (s) of the estimator on a pair of frames of the size the DFD
        controller sends (the grid-aligned crop around the ROI), after one warm-up run."""
        from .controller import roi_crop_box

        if self.estimator is None:
            return 0.0
        y0, y1, x0, x1 = roi_crop_box(self.roi, self.readout_hw, self.estimator.tile, self.estimator.stride)
        rng = np.random.default_rng(12345)
        a = rng.uniform(0.2, 0.8, (y1 - y0, x1 - x0)).astype(np.float32)
        b = rng.uniform(0.2, 0.8, (y1 - y0, x1 - x0)).astype(np.float32)
        self.estimator(a, b)
        times = []
        for _ in range(max(1, repeats)):
            t0 = time.perf_counter()
            self.estimator(a, b)
            times.append(time.perf_counter() - t0)
        return float(np.median(times))

    # ------------------------------------------------------------------ life cycle
    def open(self) -> "SimBench":
        """Start the emulator and connect the driver."""
        if self.lens is None:
            self.lens = EmulatedLens(self.clock, settling_time_s=self.settle_s, timeout_s=self.driver_timeout_s)
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
            from .estimators import suggested_min_confidence

            kwargs = dict(roi=self.roi, settle_s=self.settle_s, power_limits_dpt=limits, contrast=self.contrast_kwargs,
                          grid=grid, min_confidence=suggested_min_confidence(self.estimator))
            kwargs.update(self.controller_kwargs)
            kwargs.update(overrides)
            return DFDController(self.camera, **kwargs)
        if method == "contrast":
            kwargs = dict(roi=self.roi, settle_s=self.settle_s, power_limits_dpt=limits, **self.contrast_kwargs)
            kwargs.update(overrides)
            return ContrastController(self.camera, **kwargs)
        raise InputError(f"method must be 'dfd' or 'contrast', got {method!r}")

    def _plant(self, scene: Scene, halt_at_s: float | None = None,
               on_time: Callable[[float], None] | None = None) -> BenchPlant:
        assert self.lens is not None
        cam = VirtualCamera(self.camera, scene, self.lens.optical_power_at, self.timing, self.noise, self.rng, psf=self.psf)
        return BenchPlant(self.clock, self.lens, cam, self.estimator, self.compute_charge_s, halt_at_s=halt_at_s,
                          on_time=on_time)

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
        try:
            result = drive(ctrl, plant)
        finally:
            self.lens.set_faults(None)
        rec = self._record(result, target, method, plant, trial)
        rec.scene = scene.name
        return rec

    def _record(self, result: AFResult, target: float, requested: str, plant: BenchPlant, trial: int) -> TrialRecord:
        from ..optics.thin_lens import camera_blur_radii_px

        assert self.lens is not None
        ideal = self.camera.in_focus_power_dpt(target)
        t_end = result.t_focus_s if result.t_focus_s is not None else self.clock.now()
        final = self.lens.optical_power_at(t_end)
        resid = abs(float(camera_blur_radii_px(self.camera, target, final)))
        t0 = result.t_start_s if result.t_start_s is not None else t_end
        reason = result.error if result.status != "focused" else result.fallback_reason
        if result.status == "focused" and result.error:  # e.g. clamped to the lens range
            reason = result.error + (f"; {result.fallback_reason}" if result.fallback_reason else "")
        compute = sum(plant.compute_times_s) * 1e3 if plant.compute_times_s else None
        if compute is not None and self.compute_charge_s != "measured":
            compute = float(self.compute_charge_s) * 1e3 * len(plant.compute_times_s)
        return TrialRecord(
            target_depth_m=float(target), estimated_depth_m=result.estimated_depth_m, ideal_power_dpt=float(ideal),
            final_power_dpt=float(final), residual_blur_px=resid, frames=result.frames,
            lens_commands=result.lens_commands, time_ms=(t_end - t0) * 1e3, method=result.method,
            requested=requested, status=result.status, reason=reason, confidence=result.confidence,
            compute_ms=compute, verified=result.verified, trial=trial)

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
        from ..optics.thin_lens import camera_blur_radii_px

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
            result = drive(ctrl, plant)
        finally:
            self.lens.set_faults(None)
        rows = []
        for start, optical, tag in plant.frames:
            d = schedule(start - t0)
            rows.append({"t_s": start - t0, "tag": tag, "target_depth_m": d,
                         "residual_blur_px": abs(float(camera_blur_radii_px(self.camera, d, optical)))})
        return result, rows
