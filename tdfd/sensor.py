r"""Image sensor forward model: irradiance in, normalised raw frame out.

``sensor(noise(blur(x)))`` in the deepinv sense: the optics (:mod:`tdfd.optics.render`)
blur the scene radiance; :class:`SensorModel` turns the blurred irradiance into what a
machine-vision camera delivers, in this order:

1. **Vignetting**: radial fall-off ``1 - v * rho^2`` (``rho`` = distance from the optical
   centre relative to the image half-diagonal, ``v`` the corner loss).
2. **Exposure**: ``lambda = x * exposure * full_well_e`` photo-electrons. With exposure 1 an
   irradiance of 1 fills the well exactly.
3. **Shot noise** (Poisson) and **full-well saturation**: ``e ~ Poisson(lambda)``, clipped to
   ``full_well_e``. Poisson is sampled exactly where ``lambda < exact_poisson_below``
   electrons and by its normal approximation ``N(lambda, lambda)`` above (the two agree in
   mean and variance; the approximation's skewness error is below ``1 / sqrt(lambda)``).
4. **Read noise**: ``+ N(0, read_noise_e^2)`` electrons (input-referred). Steps 3 and 4 are
   :func:`poisson_gaussian`, the one noise draw of tdfd (when no pixel can reach the full
   well, shot and read noise of the normal-approximated pixels are one draw
   ``N(lambda, lambda + r^2)``, the same distribution).
5. **Gain and black level**: ``DN = black_level_dn + gain * e * (white - black) / full_well_e``
   with ``white = 2^bits - 1``; at ``gain = 1`` the full well maps to the white level, a
   higher (analog) gain brightens and clips the ADC before the well is full.
6. **Quantisation and ADC clipping**: ``round(DN)`` clipped to ``[0, white]``.

The output is ``DN / white`` in ``[0, 1]``: linear, no gamma, the tdfd input convention
(``raw value / white level``, ``CONTRACT.md``). The black level is **not** subtracted: as
from a real sensor, a black scene reads ``black_level_dn / white`` (plus noise, which may go
below it). Use :meth:`SensorModel.expected_mean` / :meth:`SensorModel.expected_variance`
for the noise-free mean and the variance of a frame at a given irradiance.

Every parameter is a float or a ``(B,)`` tensor (one value per sample of the batch).

Example:
    >>> import torch
    >>> sensor = SensorModel(full_well_e=10000, read_noise_e=3, bits=12, black_level_dn=64)
    >>> x = torch.full((1, 1, 64, 64), 0.5)
    >>> y = sensor(x, generator=torch.Generator().manual_seed(0))
    >>> abs(float(y.mean()) - float(sensor.expected_mean(torch.tensor(0.5)))) < 1e-3
    True
    >>> bool((y * 4095).round().eq(y * 4095).all())  # integer codes over the white level
    True
"""

from __future__ import annotations

from typing import Union

import numpy as np
import torch
from torch import nn

from .errors import InputError, ShapeError

__all__ = [
    "SensorModel",
    "vignetting",
    "shot_noise",
    "poisson_gaussian",
    "quantize",
    "white_level",
]

Param = Union[float, torch.Tensor]


def white_level(bits: int) -> int:
    """The largest code of a ``bits``-bit ADC, ``2**bits - 1``."""
    if int(bits) != bits or not 1 <= bits <= 16:
        raise InputError(f"bit depth must be an integer in [1, 16], got {bits!r}")
    return 2 ** int(bits) - 1


def _per_sample(value: Param, like: torch.Tensor, name: str) -> torch.Tensor:
    """A float or ``(B,)`` tensor as ``(B or 1, 1, 1, 1)`` broadcastable over ``like``."""
    t = torch.as_tensor(value, dtype=like.dtype, device=like.device)
    if t.ndim == 0:
        return t.reshape(1, 1, 1, 1)
    t = t.reshape(-1)
    if t.numel() not in (1, like.shape[0]):
        raise ShapeError(f"{name} must be a float or have one value per sample ({like.shape[0]}), got {t.numel()}")
    if not torch.isfinite(t).all():
        raise InputError(f"{name} must be finite")
    return t.reshape(-1, 1, 1, 1)


def vignetting(x: torch.Tensor, strength: Param, centre: tuple[float, float] = (0.0, 0.0)) -> torch.Tensor:
    """Radial fall-off ``x * (1 - strength * rho^2)``.

    Args:
        x: ``(B, C, H, W)`` irradiance.
        strength: relative loss at the image corners, in [0, 1) (float or ``(B,)``).
        centre: optical centre offset from the image centre, as a fraction of the
            half-height and half-width.

    Returns:
        ``(B, C, H, W)``.
    """
    if x.ndim != 4:
        raise ShapeError(f"expected (B, C, H, W), got {tuple(x.shape)}")
    v = _per_sample(strength, x, "vignetting strength")
    if bool(((v < 0) | (v >= 1)).any()):
        raise InputError("vignetting strength must lie in [0, 1)")
    h, w = x.shape[-2:]
    y = (torch.arange(h, dtype=x.dtype, device=x.device) - (h - 1) / 2) / max((h - 1) / 2, 1) - centre[0]
    xx = (torch.arange(w, dtype=x.dtype, device=x.device) - (w - 1) / 2) / max((w - 1) / 2, 1) - centre[1]
    rho2 = (y[:, None] ** 2 + xx[None, :] ** 2) / 2.0  # 1 at the corners of a centred frame
    return x * (1.0 - v * rho2)


def shot_noise(electrons: torch.Tensor, generator: torch.Generator | None = None,
               exact_poisson_below: float = 64.0) -> torch.Tensor:
    """Photon shot noise: a Poisson draw of mean ``electrons`` (``(B, C, H, W)``, >= 0).

    Pixels with a mean below ``exact_poisson_below`` electrons are drawn exactly
    (``torch.poisson``); above, from the normal approximation ``N(lambda, lambda)``.
    """
    lam = electrons.clamp_min(0.0)
    z = torch.randn(lam.shape, generator=generator, dtype=lam.dtype, device=lam.device)
    shot = lam + torch.sqrt(lam) * z
    low = lam < exact_poisson_below
    if bool(low.any()):
        shot = shot.masked_scatter(low, torch.poisson(lam[low], generator=generator))
    return shot


def poisson_gaussian(electrons: torch.Tensor, read_noise_e: Param, generator: torch.Generator | None = None,
                     exact_poisson_below: float = 64.0, full_well_e: Param | None = None) -> torch.Tensor:
    """Shot noise, full-well saturation and Gaussian read noise on a mean electron count.

    The one noise draw of tdfd (:class:`SensorModel` calls it). The order is physical: shot
    noise (:func:`shot_noise`), the well clips at ``full_well_e``, then read noise adds.
    When no pixel can reach the full well (``lambda + 8 sqrt(lambda) < full_well_e``
    everywhere, or no ``full_well_e``), shot and read noise of the normal-approximated
    pixels are drawn together as ``N(lambda, lambda + r^2)`` (the same distribution, one
    draw); pixels below ``exact_poisson_below`` get an exact Poisson draw plus read noise.

    Args:
        electrons: ``(B, C, H, W)`` expected electrons ``lambda >= 0``.
        read_noise_e: read noise, electrons RMS (float or ``(B,)``).
        generator: random source.
        exact_poisson_below: see :func:`shot_noise`.
        full_well_e: well capacity in electrons (float or ``(B,)``); ``None``: no saturation.

    Returns:
        Noisy electron counts (float, may be negative through read noise).
    """
    lam = electrons.clamp_min(0.0)
    rn = _per_sample(read_noise_e, lam, "read_noise_e")
    fw = None if full_well_e is None else _per_sample(full_well_e, lam, "full_well_e")
    if fw is None or bool((lam + 8.0 * torch.sqrt(lam) < fw).all()):
        z = torch.randn(lam.shape, generator=generator, dtype=lam.dtype, device=lam.device)
        e = lam + torch.sqrt(lam + rn * rn) * z
        low = lam < exact_poisson_below
        if bool(low.any()):
            exact = torch.poisson(lam[low], generator=generator) + (rn.expand_as(lam)[low] * z[low])
            e = e.masked_scatter(low, exact)
        return e
    e = shot_noise(lam, generator, exact_poisson_below)
    e = torch.minimum(e, fw)  # the well overflows: saturation
    return e + rn * torch.randn(e.shape, generator=generator, dtype=e.dtype, device=e.device)


def quantize(dn: torch.Tensor, bits: Param) -> torch.Tensor:
    """Round digital numbers to integer codes and clip to ``[0, 2^bits - 1]`` (per sample)."""
    b = _per_sample(bits, dn, "bits")
    white = torch.pow(2.0, b) - 1.0
    return torch.minimum(torch.round(dn).clamp_min(0.0), white)


class SensorModel(nn.Module):
    """A Poisson–Gaussian sensor with black level, gain, ADC and vignetting (see module doc).

    Args:
        full_well_e: full-well capacity in electrons (>= 1).
        read_noise_e: read noise in electrons RMS (>= 0).
        bits: ADC bit depth, 8 to 16 (8 to 12 for machine-vision cameras).
        black_level_dn: black-level offset in digital numbers (codes).
        gain: analog gain (>= ~0; 1 maps the full well to the white level).
        exposure: exposure scale: electrons per unit irradiance are ``exposure * full_well_e``.
        vignetting: corner fall-off in [0, 1).
        noise: ``False`` gives the noise-free expected frame (still offset, clipped and,
            if ``quantize``, quantised).
        quantize: round to integer codes.
        exact_poisson_below: see :func:`poisson_gaussian`.

    Every numeric argument may be a float or a ``(B,)`` tensor.

    Shape:
        - input: ``(B, C, H, W)`` irradiance (linear, ``>= 0``; 1 is the well-filling level
          at ``exposure = gain = 1``). Channels are independent (e.g. the two DFD frames).
        - output: ``(B, C, H, W)`` in [0, 1], ``DN / (2^bits - 1)``.
    """

    def __init__(self, full_well_e: Param = 10000.0, read_noise_e: Param = 3.0, bits: Param = 12,
                 black_level_dn: Param = 64.0, gain: Param = 1.0, exposure: Param = 1.0, vignetting: Param = 0.0,
                 noise: bool = True, quantize: bool = True, exact_poisson_below: float = 64.0) -> None:
        super().__init__()
        self.full_well_e, self.read_noise_e, self.bits = full_well_e, read_noise_e, bits
        self.black_level_dn, self.gain, self.exposure, self.vignetting = black_level_dn, gain, exposure, vignetting
        self.noise, self.quantize, self.exact_poisson_below = bool(noise), bool(quantize), float(exact_poisson_below)
        self._check()

    def _check(self) -> None:
        def t(v: Param) -> torch.Tensor:
            return torch.as_tensor(v, dtype=torch.float64).reshape(-1)

        if bool((t(self.full_well_e) < 1).any()):
            raise InputError("full_well_e must be >= 1 electron")
        if bool((t(self.read_noise_e) < 0).any()):
            raise InputError("read_noise_e must be >= 0")
        b = t(self.bits)
        if bool(((b != b.round()) | (b < 1) | (b > 16)).any()):
            raise InputError("bits must be integers in [1, 16]")
        if bool(((t(self.black_level_dn) < 0) | (t(self.black_level_dn) >= torch.pow(2.0, b) - 1)).any()):
            raise InputError("black_level_dn must lie in [0, white level)")
        if bool((t(self.gain) <= 0).any()) or bool((t(self.exposure) < 0).any()):
            raise InputError("gain must be > 0 and exposure >= 0")
        v = t(self.vignetting)
        if bool(((v < 0) | (v >= 1)).any()):
            raise InputError("vignetting must lie in [0, 1)")

    def _params(self, like: torch.Tensor) -> dict[str, torch.Tensor]:
        p = {k: _per_sample(getattr(self, k), like, k) for k in
             ("full_well_e", "read_noise_e", "bits", "black_level_dn", "gain", "exposure")}
        p["white"] = torch.pow(2.0, p["bits"]) - 1.0
        p["dn_per_e"] = p["gain"] * (p["white"] - p["black_level_dn"]) / p["full_well_e"]
        return p

    def forward(self, x: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
        """Noisy normalised raw frame ``(B, C, H, W)`` in [0, 1] from irradiance ``x``."""
        if x.ndim != 4:
            raise ShapeError(f"sensor input must be (B, C, H, W), got {tuple(x.shape)}")
        if not x.is_floating_point():
            raise InputError(f"sensor input must be floating point, got {x.dtype}")
        p = self._params(x)
        irr = vignetting(x, self.vignetting) if not _is_zero(self.vignetting) else x
        lam = irr.clamp_min(0.0) * p["exposure"] * p["full_well_e"]
        if self.noise:
            e = poisson_gaussian(lam, p["read_noise_e"], generator, self.exact_poisson_below, p["full_well_e"])
        else:
            e = torch.minimum(lam, p["full_well_e"])
        dn = p["black_level_dn"] + p["dn_per_e"] * e
        dn = quantize(dn, p["bits"]) if self.quantize else torch.minimum(dn.clamp_min(0.0), p["white"])
        return dn / p["white"]

    def expected_mean(self, x: torch.Tensor) -> torch.Tensor:
        """Mean output for irradiance ``x`` far from clipping (no vignetting, ignoring the
        clipping of the noise distribution at 0 and at the white level)."""
        x = torch.as_tensor(x, dtype=torch.float64)
        x4 = x.reshape(1, 1, 1, -1) if x.ndim < 4 else x
        p = self._params(x4.to(torch.float64))
        lam = torch.minimum(x4 * p["exposure"] * p["full_well_e"], p["full_well_e"])
        return ((p["black_level_dn"] + p["dn_per_e"] * lam) / p["white"]).reshape(x.shape)

    def expected_variance(self, x: torch.Tensor) -> torch.Tensor:
        """Variance of the output for irradiance ``x`` (shot + read noise through the gain,
        plus the uniform quantisation noise ``1/12`` code^2), in output units squared."""
        x = torch.as_tensor(x, dtype=torch.float64)
        x4 = x.reshape(1, 1, 1, -1) if x.ndim < 4 else x
        p = self._params(x4.to(torch.float64))
        lam = x4 * p["exposure"] * p["full_well_e"]
        var_dn = p["dn_per_e"] ** 2 * (lam + p["read_noise_e"] ** 2) if self.noise else torch.zeros_like(lam)
        if self.quantize:
            var_dn = var_dn + 1.0 / 12.0
        return (var_dn / p["white"] ** 2).reshape(x.shape)

    def apply_numpy(self, image: np.ndarray, seed: int) -> np.ndarray:
        """:meth:`forward` for numpy callers: ``(H, W)`` or ``(B, C, H, W)`` irradiance in,
        the noisy normalised frame of the same shape out (float32), seeded by ``seed``."""
        a = np.asarray(image)
        if a.ndim not in (2, 4):
            raise ShapeError(f"image must be (H, W) or (B, C, H, W), got shape {a.shape}")
        x = torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))
        with torch.no_grad():
            y = self(x[None, None] if a.ndim == 2 else x, generator=torch.Generator().manual_seed(int(seed)))
        return (y[0, 0] if a.ndim == 2 else y).numpy().astype(np.float32)

    def extra_repr(self) -> str:
        return (f"full_well_e={self.full_well_e}, read_noise_e={self.read_noise_e}, bits={self.bits}, "
                f"black_level_dn={self.black_level_dn}, gain={self.gain}, exposure={self.exposure}, "
                f"vignetting={self.vignetting}, noise={self.noise}")


def _is_zero(v: Param) -> bool:
    return bool((torch.as_tensor(v) == 0).all())
