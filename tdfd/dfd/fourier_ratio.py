r"""The analytic Fourier-ratio depth-from-defocus estimator (paper sec. 3, Fig. 6).

For two images of the same scene at focal lengths ``F1, F2`` (or two sensor distances or
apertures: :mod:`tdfd.optics.thin_lens`) with Gaussian PSFs, the
power spectra of a tile obey (eqs. 10-12, written for power ``|G|^2``):

.. math:: y(\omega) = \log\frac{|G_1|^2}{|G_2|^2} = -(\sigma_1^2 - \sigma_2^2)\,\omega^2 .

Two estimators of ``D = sigma1^2 - sigma2^2`` per tile:

* ``"eq13"``: the paper's eq. 13, the average of ``-y / omega^2`` over a fixed region R
  of the (u, v) plane (rings ``min_bin <= |k| <= max_bin``).
* ``"wls"`` (default): a weighted least-squares fit of ``y = -D omega^2`` over radial rings,
  with noise-aware weights: the noise power in each ring (white sensor noise of a
  per-tile variance estimated from the images, times the window and pre-whitening gain)
  is subtracted, each ring is weighted by the inverse variance of its log ratio
  ``~ 2 (N/S1 + N/S2) / n_ring``, and rings whose signal does not clear the noise in
  *both* images are gated out smoothly (the adaptive band). Each tile's power is
  normalised by its squared windowed mean, so a gain difference between the frames does
  not bias ``D``.

Then eq. 6 fixes ``c = sigma1 - sigma2``, so ``sigma1 + sigma2 = D / c`` gives both signed
sigmas, and eq. 5 the depth (a camera whose sensor distance or aperture varies solves eq. 4's
quadratic instead, :func:`tdfd.optics.thin_lens.depth_from_square_difference`; its frame 2
must be registered to frame 1's scale first, :func:`tdfd.dfd.register_sensor_pair`) (computed as inverse depth, finite everywhere). The confidence
in [0, 1] comes from the fit's own error propagated to a relative depth error,
``conf = 1 / (1 + (rel_err / rel_err_scale)^2)``, times the fraction of usable rings and a
factor that vanishes outside the extended working range; a texture-less tile gets a
confidence near 0 and a finite depth.

Example:
    >>> import torch
    >>> from tdfd import Camera
    >>> from tdfd.optics import render_pair
    >>> cam = Camera.preset("reference")
    >>> g = torch.Generator().manual_seed(0)
    >>> x = torch.rand(1, 1, 128, 128, generator=g)
    >>> i1, i2 = render_pair(cam, x, torch.full((1, 1, 128, 128), 0.45))
    >>> depth, conf = FourierRatioDFD(cam, tile=64, stride=64)(i1, i2)
    >>> depth.shape, abs(float(depth.median()) - 0.45) < 0.01, bool(conf.min() > 0.5)
    (torch.Size([1, 1, 2, 2]), True, True)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from ..camera import Camera
from ..errors import DTypeError, InputError, NonFiniteError, RangeError, ShapeError
from ..grid import check_grid, grid_shape
from ..optics.thin_lens import depth_from_square_difference, square_difference_slope
from .spectra import TileSpectra, periodic_hann

__all__ = ["validate_pair", "DFDResult", "FourierRatioDFD", "fourier_ratio_dfd", "whole_image_dfd", "noise_variance_per_tile"]

#: Intensities outside this interval are rejected (inputs are linear intensity in [0, 1];
#: a margin allows for noise around a black level).
INTENSITY_LIMITS = (-0.25, 1.25)


def validate_pair(image_f1: torch.Tensor, image_f2: torch.Tensor, tile: int) -> None:
    """Check a DFD image pair and raise a typed error naming the problem.

    Raises:
        DTypeError: not a float32/float64 tensor.
        ShapeError: not ``(B, 1, H, W)``, shapes differ, or smaller than one tile.
        NonFiniteError: NaN or inf values.
        RangeError: values outside ``[-0.25, 1.25]`` (not linear intensity in [0, 1]).
    """
    for name, im in (("image_f1", image_f1), ("image_f2", image_f2)):
        if not isinstance(im, torch.Tensor):
            raise DTypeError(f"{name} must be a torch.Tensor, got {type(im).__name__}")
        if im.dtype not in (torch.float32, torch.float64):
            raise DTypeError(f"{name} must be float32 or float64, got {im.dtype} (scale integer images by their white level)")
        if im.ndim != 4 or im.shape[1] != 1:
            raise ShapeError(f"{name} must have shape (B, 1, H, W), got {tuple(im.shape)}")
    if image_f1.shape != image_f2.shape:
        raise ShapeError(f"image_f1 {tuple(image_f1.shape)} and image_f2 {tuple(image_f2.shape)} differ in shape")
    if image_f1.shape[-2] < tile or image_f1.shape[-1] < tile:
        raise ShapeError(f"images {image_f1.shape[-2]}x{image_f1.shape[-1]} are smaller than one {tile}x{tile} tile")
    for name, im in (("image_f1", image_f1), ("image_f2", image_f2)):
        if not bool(torch.isfinite(im).all()):
            raise NonFiniteError(f"{name} contains NaN or inf")
        lo, hi = float(im.detach().min()), float(im.detach().max())
        if lo < INTENSITY_LIMITS[0] or hi > INTENSITY_LIMITS[1]:
            raise RangeError(f"{name} has values in [{lo:.3g}, {hi:.3g}]; expected linear intensity in [0, 1]")


def noise_variance_per_tile(image_f1: torch.Tensor, image_f2: torch.Tensor, tile: int, stride: int) -> torch.Tensor:
    """Per-tile white-noise variance estimate ``(B, 1, h, w)``.

    Uses the diagonal second difference ``x[i,j] - x[i+1,j] - x[i,j+1] + x[i+1,j+1]``
    (variance ``4 s^2`` for white noise of variance ``s^2``), whose pass band is the
    highest diagonal frequencies where defocused signal is weakest, once per
    non-overlapping 2x2 block (independent differences, a quarter of the cost); of the
    two frames the smaller estimate (the blurrier one, least signal) is taken. With an odd
    ``tile`` or ``stride`` the difference is taken at every pixel instead.
    """
    x = torch.cat([image_f1, image_f2], 0)
    return _tile_stats(x, tile, stride, periodic_hann(tile, x.dtype), image_f1.shape[0])[1]


_BLOCK = torch.tensor([[[[1.0, -1.0], [-1.0, 1.0]]], [[[0.25, 0.25], [0.25, 0.25]]]])  # diagonal difference, block mean


def _tile_stats(x: torch.Tensor, tile: int, stride: int, window: torch.Tensor, batch: int
                ) -> tuple[torch.Tensor, torch.Tensor]:
    """Windowed tile means ``(2B, 1, h, w)`` and per-tile noise variance ``(B, 1, h, w)`` of
    frames stacked along the batch (``(2B, 1, H, W)``, frame 1 first).

    For even ``tile`` and ``stride`` both come from one stride-2 convolution giving each 2x2
    block's diagonal difference and mean; the window mean then weights each block by the
    sum of its two window taps per axis (exact for images constant within blocks).
    """
    k = _BLOCK.to(x)
    w = window / window.sum()
    if tile % 2 == 0 and stride % 2 == 0:
        blocks = F.conv2d(x, k, stride=2)  # (2B, 2, H//2, W//2)
        d, mean_img = blocks[:, 0:1], blocks[:, 1:2]
        v = F.avg_pool2d(d * d, tile // 2, stride // 2) / 4.0
        w, s = w[0::2] + w[1::2], stride // 2
    else:
        d = F.pad(F.conv2d(x, k[0:1]), (0, 1, 0, 1), mode="replicate")
        v = F.avg_pool2d(d * d, tile, stride) / 4.0
        mean_img, s = x, stride
    m = F.conv2d(F.conv2d(mean_img, w[None, None, None, :], stride=(1, s)), w[None, None, :, None], stride=(s, 1))
    return m, torch.minimum(v[:batch], v[batch:])


@dataclass
class DFDResult:
    """Everything the analytic estimator computes, per tile ``(B, ., h, w)``.

    Attributes:
        depth: object distance in metres (inverse depth clamped to the extended range).
        confidence: in [0, 1].
        inverse_depth: unclamped ``1/d_o`` in 1/m.
        square_difference: ``sigma1^2 - sigma2^2`` in px^2.
        sigma1, sigma2: signed blur parameters in px.
        log_ratio: per-ring ``log(S1/S2)`` (noise-subtracted, gain-normalised), ``(B, R, h, w)``.
        ring_weight: per-ring fit weight ``(B, R, h, w)``.
        ring_snr: per-ring ``log(min(S1, S2) / N)``, ``(B, R, h, w)``.
        residual: weighted fit residual per degree of freedom.
        rel_error: predicted relative depth error (standard deviation).
        energy: log of the tile's normalised spectral energy in the band, for each image ``(B, 2, h, w)``.
        ring_log_power: per-ring noise-subtracted power of each frame, normalised by the
            frame's squared tile mean, as logs ``(B, 2R, h, w)`` (frame 1's rings first).
        log_noise: log of the noise variance relative to the product of the two tile means
            ``(B, 1, h, w)``.
    """

    depth: torch.Tensor
    confidence: torch.Tensor
    inverse_depth: torch.Tensor
    square_difference: torch.Tensor
    sigma1: torch.Tensor
    sigma2: torch.Tensor
    log_ratio: torch.Tensor
    ring_weight: torch.Tensor
    ring_snr: torch.Tensor
    residual: torch.Tensor
    rel_error: torch.Tensor
    energy: torch.Tensor
    ring_log_power: torch.Tensor
    log_noise: torch.Tensor


class FourierRatioDFD(nn.Module):
    """Analytic Fourier-ratio DFD on the tile grid.

    Args:
        camera: camera description (focal settings, aperture, ``mu``, working range).
        tile: tile side in pixels.
        stride: tile stride in pixels.
        estimator: ``"wls"`` (noise-aware weighted fit, default) or ``"eq13"`` (paper eq. 13).
        min_bin: lowest ring (in DFT bins) used; lower rings carry window leakage.
        max_bin: highest ring used; defaults to ``round(0.2 * tile)``.
        prewhiten: Laplacian pre-whitening before the window (see :mod:`tdfd.dfd.spectra`).
        snr_threshold: per-ring signal-to-noise ratio below which a ring is gated out.
        min_noise_std: floor of the noise standard deviation (intensity units); covers
            quantisation and float rounding of noise-free inputs.
        leakage_floor: fraction of the tile's band power treated as an extra noise floor in
            every ring (window leakage), so rings drowned in leakage are gated out.
        rel_error_scale: relative depth error at which the confidence is 0.5.
        gate_sharpness: slope of the adaptive-band gate in log-SNR. The default (2) suits
            small tiles, whose per-ring SNR estimates are themselves noisy; regions of
            hundreds of pixels, with precise ring SNRs, do better with a sharp gate (8),
            so that noise-level rings cannot steer the fit.
        mu: blur constant in px/m (defaults to ``camera.mu_px_per_m``).
        validate: check inputs (:func:`validate_pair`); export turns this off.

    Shape:
        - ``image_f1``, ``image_f2``: ``(B, 1, H, W)`` float, linear intensity in [0, 1].
        - Output: ``(depth, confidence)``, each ``(B, 1, h, w)``; depth in metres.
    """

    def __init__(self, camera: Camera, tile: int = 64, stride: int = 32, estimator: str = "wls",
                 min_bin: int = 2, max_bin: int | None = None, prewhiten: bool = True,
                 snr_threshold: float = 4.0, min_noise_std: float = 1e-4, leakage_floor: float = 1e-5,
                 rel_error_scale: float = 0.03, gate_sharpness: float = 2.0, mu: float | None = None,
                 validate: bool = True) -> None:
        super().__init__()
        check_grid(tile, stride)
        if estimator not in ("wls", "eq13"):
            raise InputError(f"estimator must be 'wls' or 'eq13', got {estimator!r}")
        self.camera = camera
        self.tile, self.stride, self.estimator, self.validate = int(tile), int(stride), estimator, validate
        self.spectra = TileSpectra(tile, stride, max_bin, prewhiten)
        k = self.spectra.max_bin
        if not 1 <= min_bin < k:
            raise InputError(f"min_bin must be in [1, max_bin), got {min_bin} (max_bin {k})")
        self.min_bin = int(min_bin)
        self.snr_threshold, self.min_noise_std = float(snr_threshold), float(min_noise_std)
        self.leakage_floor, self.rel_error_scale = float(leakage_floor), float(rel_error_scale)
        self.gate_sharpness = float(gate_sharpness)
        self.mu = float(camera.mu_px_per_m if mu is None else mu)
        # ring membership: ring r holds bins with round(|k|) == r, min_bin <= r <= max_bin
        radius = torch.sqrt(self.spectra.ky.double() ** 2 + self.spectra.kx.double() ** 2)
        rings = torch.arange(self.min_bin, k + 1, dtype=torch.float64)
        member = (torch.round(radius)[None, :] == rings[:, None]).double()  # (R, N)
        omega2 = self.spectra.omega() ** 2
        count = member.sum(1)
        # squared DFT coefficients -> ring powers (TileSpectra.ring_weights), one 1x1 conv
        self.register_buffer("ring_weights", self.spectra.ring_weights(rings)[:, :, None, None], persistent=False)
        self.register_buffer("ring_count", count[None, :, None, None], persistent=False)
        self.register_buffer("ring_omega2", ((member @ omega2) / count)[None, :, None, None], persistent=False)
        # expected ring power of unit-variance white noise (sum of the exact per-bin gains)
        self.register_buffer("ring_noise_gain", (member @ self.spectra.noise_gain())[None, :, None, None], persistent=False)
        self.register_buffer("window", periodic_hann(tile, torch.float64), persistent=False)
        # per-bin -1/omega^2 over region R, for eq. 13
        in_band = member.sum(0)
        self.register_buffer("eq13_weight", (in_band / omega2.clamp_min(1e-12) / in_band.sum())[None, :, None, None], persistent=False)
        near, far = camera.depth_range_m
        self.inv_depth_limits = (1.0 / (2.0 * far), 2.0 / near)

    @property
    def num_rings(self) -> int:
        return int(self.ring_count.shape[1])

    def grid_shape(self, height: int, width: int) -> tuple[int, int]:
        return grid_shape(height, width, self.tile, self.stride)

    def analyse(self, image_f1: torch.Tensor, image_f2: torch.Tensor) -> DFDResult:
        """Run the estimator and return every intermediate (see :class:`DFDResult`)."""
        if self.validate:
            validate_pair(image_f1, image_f2, self.tile)
        r1, r2, noise, m1, m2 = self.measure(image_f1, image_f2)
        per_bin = None
        if self.estimator == "eq13":  # per-bin powers (B, N, h, w) of each frame
            eps = 1e-12 if image_f1.dtype == torch.float64 else 1e-6
            per_bin = torch.log(self.spectra(image_f1) + eps) - torch.log(self.spectra(image_f2) + eps)
        return self.fit(r1, r2, noise, m1, m2, per_bin=per_bin)

    def measure(self, image_f1: torch.Tensor, image_f2: torch.Tensor
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """The measurements the fit uses, per tile: ring power sums of both frames
        ``(B, R, h, w)`` each, the white-noise variance and both windowed tile means
        ``(B, 1, h, w)`` each (no input validation)."""
        dt = image_f1.dtype
        b = image_f1.shape[0]
        x = torch.cat([image_f1, image_f2], 0)  # both frames in one batch (2B, 1, H, W)
        # windowed tile means (gain normalisation) and white-noise variance
        m, noise = _tile_stats(x, self.tile, self.stride, self.window.to(dt), b)
        m = m.abs().clamp_min(1e-3)
        noise = noise.clamp_min(self.min_noise_std ** 2)
        a = self.spectra.coefficients(x)  # (2B, 4 K1^2, h, w)
        r = F.conv2d(a * a, self.ring_weights.to(dt))  # (2B, R, h, w) ring power sums
        return r[:b], r[b:], noise, m[:b], m[b:]

    def fit(self, r1: torch.Tensor, r2: torch.Tensor, noise: torch.Tensor, m1: torch.Tensor, m2: torch.Tensor,
            count_scale: float | torch.Tensor = 1.0, per_bin: torch.Tensor | None = None) -> DFDResult:
        """Estimate from :meth:`measure`'s output (see :class:`DFDResult`).

        ``count_scale`` multiplies the number of independent samples per ring (for
        measurements averaged over several tiles; a number or a ``(B, 1, 1, 1)`` tensor); ``per_bin`` holds per-bin log power
        ratios for the ``"eq13"`` estimator.
        """
        dt = r1.dtype
        buf = lambda t: t.to(dt)  # noqa: E731
        eps = 1e-12 if dt == torch.float64 else 1e-6
        ring_noise = noise * buf(self.ring_noise_gain)
        total1, total2 = r1.sum(1, keepdim=True), r2.sum(1, keepdim=True)
        n1 = ring_noise + self.leakage_floor * total1
        n2 = ring_noise + self.leakage_floor * total2
        s1 = (r1 - n1).clamp_min(eps) + 1e-3 * r1.clamp_min(0.0)
        s2 = (r2 - n2).clamp_min(eps) + 1e-3 * r2.clamp_min(0.0)
        log_s1, log_s2 = torch.log(s1 + eps), torch.log(s2 + eps)
        log_m1, log_m2 = torch.log(m1), torch.log(m2)
        gain = 2.0 * (log_m1 - log_m2)  # log ratio of the frames' squared tile means
        y = (log_s1 - log_s2) - gain  # gain-normalised log ratio
        omega2 = buf(self.ring_omega2)
        count = buf(self.ring_count) * count_scale
        snr = torch.minimum(log_s1 - torch.log(n1 + eps), log_s2 - torch.log(n2 + eps))
        gate = torch.sigmoid(self.gate_sharpness * (snr - math.log(self.snr_threshold)))
        var = 2.0 * (n1 / s1 + n2 / s2) / count + 1e-4
        w = gate / var
        sw4 = (w * omega2 * omega2).sum(1, keepdim=True)
        if self.estimator == "wls":
            dsq = -(w * y * omega2).sum(1, keepdim=True) / (sw4 + eps)
        else:  # eq. 13: mean of -log(P1/P2) / omega^2 over region R (bins, not rings)
            if per_bin is None:
                raise InputError("the eq13 estimator needs per-bin log power ratios (per_bin)")
            dsq = -F.conv2d(per_bin - gain, buf(self.eq13_weight))
        resid = y + dsq * omega2
        dof = (gate.sum(1, keepdim=True) - 1.0).clamp_min(1.0)
        chi2 = (w * resid * resid).sum(1, keepdim=True) / dof
        var_d = chi2.clamp_min(1.0) / (sw4 + eps)
        inv_depth, sig1, sig2 = depth_from_square_difference(self.camera, dsq, self.mu)
        q_lo, q_hi = self.inv_depth_limits
        q = inv_depth.clamp(q_lo, q_hi)
        # error propagation: |dD/d(1/d_o)| (-2 mu (A d_s / 2) (sigma1 - sigma2) for the ECVFL pair)
        if self.camera.turning_inverse_depth is None:  # ECVFL pair: a constant (the shipped graph)
            slope = float(square_difference_slope(self.camera, 1.0, self.mu))
        else:
            slope = square_difference_slope(self.camera, q, self.mu).clamp_min(eps)
        rel = torch.sqrt(var_d) / slope / q
        in_range = torch.sigmoid((inv_depth - q_lo) / (0.05 * q_lo)) * torch.sigmoid((q_hi - inv_depth) / (0.05 * q_lo))
        usable = (gate.sum(1, keepdim=True) / 3.0).clamp(max=1.0)
        conf = in_range * usable / (1.0 + (rel / self.rel_error_scale) ** 2)
        energy = torch.cat([torch.log(total1 + eps) - 2.0 * log_m1, torch.log(total2 + eps) - 2.0 * log_m2], 1)
        ring_log_power = torch.cat([log_s1 - 2.0 * log_m1, log_s2 - 2.0 * log_m2], 1)
        log_noise = torch.log(noise) - log_m1 - log_m2
        return DFDResult(depth=1.0 / q, confidence=conf.clamp(0.0, 1.0), inverse_depth=inv_depth,
                         square_difference=dsq, sigma1=sig1, sigma2=sig2, log_ratio=y, ring_weight=w,
                         ring_snr=snr, residual=chi2, rel_error=rel, energy=energy,
                         ring_log_power=ring_log_power, log_noise=log_noise)

    def forward(self, image_f1: torch.Tensor, image_f2: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        r = self.analyse(image_f1, image_f2)
        return r.depth, r.confidence


def fourier_ratio_dfd(image_f1: torch.Tensor, image_f2: torch.Tensor, camera: Camera, tile: int = 64,
                      stride: int = 32, **kwargs) -> tuple[torch.Tensor, torch.Tensor]:
    """Functional form of :class:`FourierRatioDFD`: ``(depth, confidence)`` on the tile grid."""
    return FourierRatioDFD(camera, tile=tile, stride=stride, **kwargs).to(image_f1.device)(image_f1, image_f2)


def whole_image_dfd(image_f1: torch.Tensor, image_f2: torch.Tensor, camera: Camera, **kwargs) -> tuple[torch.Tensor, torch.Tensor]:
    """One region covering the (central square of the) whole image, as in the paper.

    Returns ``(depth, confidence)`` each ``(B, 1, 1, 1)``.
    """
    size = min(image_f1.shape[-2], image_f1.shape[-1])
    top, left = (image_f1.shape[-2] - size) // 2, (image_f1.shape[-1] - size) // 2
    crop = lambda im: im[..., top : top + size, left : left + size]  # noqa: E731
    return fourier_ratio_dfd(crop(image_f1), crop(image_f2), camera, tile=size, stride=size, **kwargs)
