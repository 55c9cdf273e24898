r"""Tile power spectra by a separable windowed DFT (ONNX-friendly, no ``torch.fft``).

Each ``T x T`` tile (stride ``S``, the contract grid of :mod:`tdfd.grid`) is optionally
pre-whitened, multiplied by a separable window and transformed with a 2-D DFT restricted
to the frequency band ``|k| <= K`` bins. The DFT is two 1-D passes of windowed cos/sin
kernels, one along H and one along W, combined into the power of each half-plane bin:

.. math:: P(\pm k_y, k_x) = CC^2 + SS^2 + SC^2 + CS^2 \mp 2 (CC\,SS - SC\,CS),

with ``CC = sum w cos cos x`` etc. This equals ``|FFT(w * tile)|^2`` (tested against
``torch.fft``) and exports to ONNX at any opset as two strided ``conv2d`` passes (along W,
then along H). A matrix-product form over non-overlapping stride blocks computes the same
sums but ran slower in ONNX Runtime 1.32 at 1200x1600 (an ad-hoc comparison of the two
exports, 2026-11-23), so the convolutions stay.

Pre-whitening (on by default) applies the discrete Laplacian ``4x - sum(4 neighbours)``
before the window (at interior pixels; the 1-pixel image border is set to 0, where the
periodic Hann window's weight is 0 or below 0.003). Both images get the same linear filter, so the ratio ``G1/G2`` of
paper eq. 10 is unchanged, but the steep ``1/f^2`` spectrum of natural textures becomes
nearly flat, which cuts the window leakage that biases the ratio fit at large blur. The
filter also removes each tile's mean (no DC), which keeps float32 error low.

Frequencies: bin ``(k_y, k_x)`` has angular frequency ``omega = 2 pi |k| / T`` rad/pixel.

Example:
    >>> import torch
    >>> spec = TileSpectra(tile=32, stride=16, max_bin=8)
    >>> p = spec(torch.rand(2, 1, 64, 80))
    >>> p.shape  # (B, bins, h, w)
    torch.Size([2, 145, 3, 4])
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from kornia.filters import get_hanning_kernel1d
from torch import nn

from .._tracing import is_exporting
from ..errors import InputError, ShapeError
from ..grid import check_grid

__all__ = [
    "periodic_hann",
    "laplacian_valid",
    "laplacian_prewhiten",
    "prewhiten_gain",
    "TileSpectra",
    "fft_tile_power",
]


def periodic_hann(size: int, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """Periodic Hann window of length ``size`` (DFT-even), built from kornia's symmetric
    Hann kernel of length ``size + 1`` without its last tap."""
    return get_hanning_kernel1d(size + 1, dtype=dtype)[:size].contiguous()


_LAPLACE = torch.tensor([[0.0, -1.0, 0.0], [-1.0, 4.0, -1.0], [0.0, -1.0, 0.0]])


def laplacian_valid(x: torch.Tensor) -> torch.Tensor:
    """Discrete Laplacian ``4x - (up + down + left + right)`` at interior pixels:
    ``(B, 1, H, W)`` -> ``(B, 1, H-2, W-2)``.

    While exporting it is a 3x3 ``Conv`` (ONNX Runtime's fastest form); in torch it is four
    shifted subtractions, because torch's CPU convolution of one channel with a 3x3 kernel
    is 5-20x slower than that. The two forms are the same arithmetic.
    """
    if is_exporting():
        return F.conv2d(x, _LAPLACE.to(x)[None, None])
    c = x[..., 1:-1, 1:-1]
    return 4.0 * c - x[..., :-2, 1:-1] - x[..., 2:, 1:-1] - x[..., 1:-1, :-2] - x[..., 1:-1, 2:]


def laplacian_prewhiten(x: torch.Tensor) -> torch.Tensor:
    """:func:`laplacian_valid` zero-padded back to ``(B, 1, H, W)`` (0 on the 1-pixel border)."""
    return F.pad(laplacian_valid(x), (1, 1, 1, 1))


def prewhiten_gain(omega_y: torch.Tensor, omega_x: torch.Tensor) -> torch.Tensor:
    """Power gain ``|L(omega)|^2`` of :func:`laplacian_prewhiten`: ``(4 - 2cos wy - 2cos wx)^2``."""
    return (4.0 - 2.0 * torch.cos(omega_y) - 2.0 * torch.cos(omega_x)) ** 2


class TileSpectra(nn.Module):
    """Windowed power spectra of every tile on the contract grid.

    Args:
        tile: tile side ``T`` in pixels (>= 8).
        stride: tile stride ``S`` in pixels.
        max_bin: highest frequency bin ``K`` kept (``|k_x|, |k_y| <= K``); defaults to
            ``round(0.2 T)`` (0.2 cycles/pixel: on noisy, defocused tiles higher bins rarely clear the noise, and they cost the most).
        prewhiten: apply :func:`laplacian_prewhiten` first.

    Shape:
        - Input: ``(B, 1, H, W)``.
        - Output: ``(B, N, h, w)`` with ``N = (K+1)^2 + K^2`` half-plane bins; see
          :attr:`ky`, :attr:`kx` for each bin's integer frequency (``kx >= 0``).
    """

    def __init__(self, tile: int = 64, stride: int = 32, max_bin: int | None = None, prewhiten: bool = True) -> None:
        super().__init__()
        check_grid(tile, stride)
        k = int(round(0.2 * tile)) if max_bin is None else int(max_bin)
        if not 1 <= k <= tile // 2:
            raise InputError(f"max_bin must be in [1, tile/2], got {k}")
        self.tile, self.stride, self.max_bin, self.prewhiten = int(tile), int(stride), k, bool(prewhiten)
        win = periodic_hann(tile, torch.float64)
        n = torch.arange(tile, dtype=torch.float64)
        f = torch.arange(k + 1, dtype=torch.float64)
        phase = 2.0 * math.pi * f[:, None] * n[None, :] / tile  # (K+1, T)
        trig = torch.cat([torch.cos(phase), torch.sin(phase)], 0) * win  # (2(K+1), T)
        self.register_buffer("kernel_w", trig[:, None, None, :], persistent=False)  # along W
        self.register_buffer("kernel_h", trig[:, None, :, None], persistent=False)  # along H
        kk = torch.arange(k + 1)
        ky_pos, kx_pos = torch.meshgrid(kk, kk, indexing="ij")  # (+ky, kx) bins, ky-major
        ky_neg, kx_neg = torch.meshgrid(kk[1:], kk[1:], indexing="ij")
        self.register_buffer("ky", torch.cat([ky_pos.reshape(-1), -ky_neg.reshape(-1)]), persistent=False)
        self.register_buffer("kx", torch.cat([kx_pos.reshape(-1), kx_neg.reshape(-1)]), persistent=False)
        self.window_energy = float((win[:, None] * win[None, :]).pow(2).sum())
        self.window_sum = float(win.sum() ** 2)

    @property
    def num_bins(self) -> int:
        return int(self.kx.numel())

    def omega(self) -> torch.Tensor:
        """Angular frequency ``2 pi |k| / T`` (rad/pixel) of each bin, ``(N,)``."""
        return 2.0 * math.pi * torch.sqrt(self.ky.double() ** 2 + self.kx.double() ** 2) / self.tile

    def noise_gain(self) -> torch.Tensor:
        """Expected power per bin of unit-variance white noise, ``(N,)``.

        Exact for the windowed (and pre-whitened) DFT: the bin is the inner product of the
        noise with the kernel ``L * (w e^{-i k x})``, so its variance is that kernel's energy.
        """
        t = self.tile
        win = periodic_hann(t, torch.float64)
        n = torch.arange(t, dtype=torch.float64)

        def one_axis(k: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
            # a = w e^{-i k n}, zero-padded by one tap each side; d = second difference of a
            a = win * torch.exp(-2j * math.pi * k.double()[:, None] * n / t)
            a = F.pad(torch.view_as_real(a).permute(0, 2, 1), (1, 1))  # (N, 2, T+2) real/imag
            a = torch.view_as_complex(a.permute(0, 2, 1).contiguous())
            d = 2 * a - F.pad(a[:, :-1], (1, 0)) - F.pad(a[:, 1:], (0, 1))
            return a.abs().pow(2).sum(1), d.abs().pow(2).sum(1), (d.conj() * a).sum(1)

        ay, dy, cy = one_axis(self.ky)
        ax, dx, cx = one_axis(self.kx)
        if not self.prewhiten:
            return ay * ax
        # the Laplacian is (2 - shifts along y) + (2 - shifts along x): two separable terms
        return dy * ax + ay * dx + 2.0 * (cy * cx.conj()).real

    def coefficients(self, x: torch.Tensor) -> torch.Tensor:
        """Windowed DFT products of every tile, before squaring: ``(B, 4 K1^2, h, w)``.

        Channel ``((tx * K1 + kx) * 2 + ty) * K1 + ky`` holds ``sum w(n) w(m) t_y(k_y n) t_x(k_x m) x``
        with ``t = cos`` for trig index 0 and ``sin`` for 1 (``K1 = max_bin + 1``).
        """
        if x.ndim != 4 or x.shape[1] != 1:
            raise ShapeError(f"expected (B, 1, H, W), got {tuple(x.shape)}")
        kw, kh = self.kernel_w.to(x.dtype), self.kernel_h.to(x.dtype)
        if self.prewhiten:  # the Laplacian's zero border is the row pass's zero padding
            rows = F.conv2d(laplacian_valid(x), kw, stride=(1, self.stride), padding=(1, 1))
        else:
            rows = F.conv2d(x, kw, stride=(1, self.stride))  # (B, 2K1, H, w): [cos kx | sin kx]
        b = rows.shape[0]
        # the same column kernels for every row channel: fold channels into the batch
        a = F.conv2d(rows.reshape(-1, 1, rows.shape[2], rows.shape[3]), kh, stride=(self.stride, 1))
        return a.reshape(b, -1, a.shape[2], a.shape[3])

    def ring_weights(self, rings: torch.Tensor) -> torch.Tensor:
        """``(R, 4 K1^2)`` weights that turn squared :meth:`coefficients` into ring power sums.

        Summed over the half-plane bins of a ring, the cross terms of the ``+k_y`` and
        ``-k_y`` powers cancel, so ``sum_{bins in ring} P = sum_c W[r, c] a_c^2`` with weight
        2 off the axes (both half-plane bins) and 1 on them (``rings``: integer radii).
        """
        k1 = self.max_bin + 1
        kk = torch.arange(k1, dtype=torch.float64)
        kx, ky = kk[:, None], kk[None, :]  # (kx, ky)
        member = (torch.round(torch.sqrt(kx ** 2 + ky ** 2))[None] == rings.double()[:, None, None]).double()
        w = member * torch.where((kx >= 1) & (ky >= 1), 2.0, 1.0)  # (R, kx, ky)
        return w[:, None, :, None, :].expand(-1, 2, k1, 2, k1).reshape(len(rings), -1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        k1 = self.max_bin + 1
        a = self.coefficients(x)
        b, _, h, w = a.shape
        a = a.reshape(b, 2, k1, 2, k1, h, w)  # (x-trig, kx, y-trig, ky, h, w)
        cc, cs = a[:, 0, :, 0], a[:, 1, :, 0]  # y-cos applied to x-cos / x-sin
        sc, ss = a[:, 0, :, 1], a[:, 1, :, 1]  # y-sin applied to x-cos / x-sin
        base = cc * cc + ss * ss + sc * sc + cs * cs  # (B, kx, ky, h, w)
        cross = 2.0 * (cc * ss - sc * cs)
        p_pos = (base - cross).transpose(1, 2).reshape(b, k1 * k1, h, w)  # ky-major
        p_neg = (base + cross)[:, 1:, 1:].transpose(1, 2).reshape(b, (k1 - 1) ** 2, h, w)
        return torch.cat([p_pos, p_neg], 1)


def fft_tile_power(x: torch.Tensor, tile: int, stride: int, prewhiten: bool = True) -> torch.Tensor:
    """Reference implementation with ``torch.fft``: ``|FFT2(window * tile)|^2``,
    shape ``(B, h, w, T, T)`` (not exportable; used to test :class:`TileSpectra`)."""
    if prewhiten:
        x = laplacian_prewhiten(x)
    win = periodic_hann(tile, x.dtype)
    tiles = x[:, 0].unfold(1, tile, stride).unfold(2, tile, stride)  # (B, h, w, T, T)
    return torch.fft.fft2(tiles * (win[:, None] * win[None, :])).abs() ** 2
