r"""Sensor noise and quantisation of the virtual camera (:class:`tdfd.sensor.SensorModel`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..threads import torch_threads

__all__ = ["SensorNoise"]


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

            from ...sensor import SensorModel
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
