r"""Where in each ring the power lies: the ring's orientation moments (issue 19).

The Fourier-ratio fit (:mod:`tdfd.dfd.fourier_ratio`) sums each tile's power over rings of
``|k|``, which is all a rotationally symmetric PSF needs. An astigmatic PSF blurs more along
one axis (``data_synth`` draws astigmatism at any angle), so the log ratio of a ring then
depends on where in the ring the texture's power lies; a ring sum cannot tell a stripe
texture at 0 degrees from one at 90. The second-order orientation moments of each ring,

.. math:: c_r = \frac{\sum_{k \in r} P(k) \cos 2\theta_k}{\sum_{k \in r} P(k)}, \qquad
          s_r = \frac{\sum_{k \in r} P(k) \sin 2\theta_k}{\sum_{k \in r} P(k)},

with ``theta_k = atan2(k_y, k_x)``, give that layout (a power spread evenly around the ring
gives 0, a single line at angle ``theta`` gives ``(cos 2 theta, sin 2 theta)``). Taken per
frame, their difference between the frames shows an orientation-dependent blur.

Both numerators are quadratic in :meth:`~tdfd.dfd.spectra.TileSpectra.coefficients`:
``cos 2 theta`` is even in ``k_y``, so ``c``'s sum is a weighted sum of squared coefficients
like the ring sums; ``sin 2 theta`` is odd, so ``s``'s sum is a weighted sum of the cross
products that tell a ``+k_y`` bin from its ``-k_y`` mirror. Both are 1x1 convolutions, so
the moments export to ONNX with no new operator.

Example:
    >>> import math, torch
    >>> from tdfd.dfd.spectra import TileSpectra
    >>> spectra = TileSpectra(64, 64)
    >>> moments = RingOrientation(spectra, torch.arange(2, 14))
    >>> n = torch.arange(64.0)
    >>> stripes = torch.cos(2 * math.pi * 8 * n / 64).expand(64, 64).reshape(1, 1, 64, 64)
    >>> c, s = moments(spectra.coefficients(stripes)).squeeze().reshape(2, 12)[:, 6]  # ring 8
    >>> round(float(c), 3), round(float(s), 3)
    (1.0, 0.0)
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from ..errors import ShapeError
from .spectra import TileSpectra

__all__ = ["RingOrientation", "orientation_weights"]


def orientation_weights(spectra: TileSpectra, rings: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Weights of the rings' orientation sums, float64.

    Args:
        spectra: the tile spectra whose :meth:`~TileSpectra.coefficients` the weights apply to.
        rings: integer ring radii ``(R,)`` in DFT bins (ring ``r`` holds ``round(|k|) == r``).

    Returns:
        ``(cos_weights, sin_weights)``: ``(R, 4 K1^2)`` weights of the squared coefficients
        giving ``sum_{k in r} P cos 2 theta`` over the half plane, and ``(R, K1^2)`` weights
        of ``cc * ss - sc * cs`` (``(k_x, k_y)``-major, ``k_x, k_y >= 0``) giving
        ``sum_{k in r} P sin 2 theta`` (``K1 = max_bin + 1``). The ring sums of
        :meth:`~TileSpectra.ring_weights` are the matching denominators.
    """
    k1 = spectra.max_bin + 1
    kk = torch.arange(k1, dtype=torch.float64)
    kx, ky = kk[:, None], kk[None, :]  # (kx, ky)
    k2 = (kx ** 2 + ky ** 2).clamp_min(1.0)
    member = (torch.round(torch.sqrt(kx ** 2 + ky ** 2))[None] == rings.double()[:, None, None]).double()
    # cos 2theta is even in ky: the +ky and -ky bins of a (kx, ky) pair add their powers,
    # 2 * base, as in TileSpectra.ring_weights
    cos_w = member * torch.where((kx >= 1) & (ky >= 1), 2.0, 1.0) * (kx ** 2 - ky ** 2) / k2
    # sin 2theta is odd in ky: P(+ky) - P(-ky) = -2 cross = -4 (cc ss - sc cs), off the axes only
    sin_w = member * torch.where((kx >= 1) & (ky >= 1), -4.0, 0.0) * (2.0 * kx * ky) / k2
    cos_full = cos_w[:, None, :, None, :].expand(-1, 2, k1, 2, k1).reshape(len(rings), -1)
    return cos_full, sin_w.reshape(len(rings), -1)


class RingOrientation(nn.Module):
    """Per-ring orientation moments ``(c_r, s_r)`` of each tile (module docstring).

    Args:
        spectra: the :class:`~tdfd.dfd.spectra.TileSpectra` whose coefficients it is given.
        rings: integer ring radii ``(R,)`` in DFT bins.
        eps: floor of a ring's power sum (a ring without power gives moments near 0).

    Shape:
        - Input: :meth:`~TileSpectra.coefficients` output ``(B, 4 K1^2, h, w)``.
        - Output: ``(B, 2R, h, w)``: the ``R`` moments ``c_r``, then the ``R`` moments
          ``s_r``, each in ``[-1, 1]``.
    """

    def __init__(self, spectra: TileSpectra, rings: torch.Tensor, eps: float = 1e-6) -> None:
        super().__init__()
        self.k1 = spectra.max_bin + 1
        self.num_rings = int(len(rings))
        self.eps = float(eps)
        cos_w, sin_w = orientation_weights(spectra, rings)
        self.register_buffer("total_weights", spectra.ring_weights(rings)[:, :, None, None], persistent=False)
        self.register_buffer("cos_weights", cos_w[:, :, None, None], persistent=False)
        self.register_buffer("sin_weights", sin_w[:, :, None, None], persistent=False)

    def forward(self, coefficients: torch.Tensor, totals: torch.Tensor | None = None) -> torch.Tensor:
        """``totals``: the rings' power sums ``(B, R, h, w)`` when the caller has them
        (:meth:`~tdfd.dfd.FourierRatioDFD.measure`'s), else computed here."""
        k1, r = self.k1, self.num_rings
        if coefficients.ndim != 4 or coefficients.shape[1] != 4 * k1 * k1:
            raise ShapeError(f"expected (B, {4 * k1 * k1}, h, w) coefficients, got {tuple(coefficients.shape)}")
        dt = coefficients.dtype
        b, _, h, w = coefficients.shape
        squares = coefficients * coefficients
        if totals is None:
            totals = F.conv2d(squares, self.total_weights.to(dt))
        elif totals.shape != (b, r, h, w):
            raise ShapeError(f"expected ({b}, {r}, {h}, {w}) ring totals, got {tuple(totals.shape)}")
        cos_sums = F.conv2d(squares, self.cos_weights.to(dt))
        a = coefficients.reshape(b, 2, k1, 2, k1, h, w)  # (x-trig, kx, y-trig, ky, h, w)
        cross = (a[:, 0, :, 0] * a[:, 1, :, 1] - a[:, 0, :, 1] * a[:, 1, :, 0]).reshape(b, k1 * k1, h, w)
        sin_sums = F.conv2d(cross, self.sin_weights.to(dt))
        total = totals.clamp_min(self.eps)
        return torch.cat([cos_sums / total, sin_sums / total], 1).clamp(-1.0, 1.0)
