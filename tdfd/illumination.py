r"""Active illumination (paper sec. 2.1 and 4): a coherent conditioned pattern and an
incoherent projector, rendered onto a scene seen by a :class:`~tdfd.Camera`.

Both modules sit at the camera (no baseline unless ``axis_offset_*`` says otherwise) and
project a mask pattern (:class:`MaskPattern`) specified in **physical units on the target**:

* :class:`CoherentIllumination`: a collimated laser beam shaped by a programmable mask
  (paper Fig. 3). The beam keeps its physical size and its sharp edges at every distance
  ("sharpness retaining"), so in camera pixels the pattern shrinks as ``1/d``:
  a feature of ``s`` metres at distance ``d`` covers ``s * d_s / (d * pitch)`` pixels (the
  chief ray through the lens centre maps target point ``X`` to sensor point ``X d_s / d``).
  A diffractive optical element (DOE) copies the beam into diffraction orders at angles
  ``sin(theta_k) = k sin(theta_1)``; order ``k`` lands at ``d tan(theta_k)`` on the target,
  a fixed offset in pixels. Optional laser speckle multiplies the pattern. A collimated
  beam's irradiance does not change with distance.
* :class:`ProjectorIllumination`: an incoherent projector focused at ``focus_m``
  (paper: 56.8 cm). Its pattern is defined on the plane of best focus and scales with
  distance like the projection cone, so in camera pixels it keeps its size (the same
  ``d`` cancels); its irradiance falls as ``(focus_m / d)^2`` and it is blurred by the
  projector's own defocus.

**Projector blur from its depth of field.** A thin-lens projector of aperture ``A_p``
focused at ``d_f`` images a pattern point to a cone that converges at ``d_f``; at distance
``d`` it covers a disk of diameter ``A_p |d - d_f| / d_f`` on the target, i.e. the angle (seen
from the projector, which is also the camera's viewpoint)

.. math:: \beta(d) = A_p \left| \frac{1}{d} - \frac{1}{d_f} \right| .

The depth of field ends where ``beta`` reaches the acceptable circle of confusion
``c`` (an angle; default 1 mrad, 0.57 mm at 56.8 cm, about one projector pixel). The paper
gives the limits 56.8 - 12.5 = 44.3 cm and 56.8 + 16.5 = 73.3 cm, i.e. ``0.497`` dpt nearer
and ``0.396`` dpt farther than focus. A single thin lens would give equal dioptric
half-widths; we honour the measured asymmetry with one effective aperture per side,
``A_near = c / 0.497 dpt`` (2.0 mm) and ``A_far = c / 0.396 dpt`` (2.5 mm), so the blur is
zero at 56.8 cm, equals ``c`` exactly at both DOF limits and grows linearly in dioptres
beyond (``symmetric=True`` uses their dioptric mean instead). In camera pixels the blur disk
has diameter ``beta d_s / pitch`` (independent of ``d``, like the pattern); it is rendered as a
pillbox of radius ``beta d_s / (2 pitch)``, i.e. RMS radius ``sigma = beta d_s / (4 pitch)``.

Example:
    >>> import torch
    >>> from tdfd import Camera
    >>> cam = Camera.preset("reference")
    >>> proj = ProjectorIllumination()
    >>> [round(abs(float(proj.blur_angle_rad(d))) * 1e3, 3) for d in (0.443, 0.568, 0.733)]
    [1.0, 0.0, 1.0]
    >>> las = CoherentIllumination()
    >>> img = las.render(cam, torch.full((1, 1, 64, 64), 0.5))
    >>> img.shape, float(img.max())
    (torch.Size([1, 1, 64, 64]), 1.0)
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch

from .camera import Camera
from .errors import InputError, ShapeError
from .optics.render import defocus_layered_multi

__all__ = [
    "MaskPattern",
    "PAPER_MASK",
    "CoherentIllumination",
    "ProjectorIllumination",
    "target_coordinates",
    "speckle",
    "speckle_grain_px",
    "illuminate",
    "box_square_wave",
]


# ----------------------------------------------------------------------------- helpers
def box_square_wave(u: torch.Tensor, period: float | torch.Tensor, duty: float, width: float | torch.Tensor = 1.0
                    ) -> torch.Tensor:
    """Exact box-filtered square wave.

    The bright intervals ``[k P + P (1 - duty) / 2, k P + P (1 + duty) / 2]`` (``P = period``)
    are averaged over ``[u - width/2, u + width/2]`` using the wave's antiderivative, so any
    period (even below ``width``) is anti-aliased correctly. Units are arbitrary but shared.
    """
    half = 0.5 * duty * period
    lo = 0.5 * period - half

    def antider(v: torch.Tensor) -> torch.Tensor:
        k = torch.floor(v / period)
        return k * (2.0 * half) + (v - k * period - lo).clamp(min=0.0).clamp(max=2.0 * half)

    return ((antider(u + 0.5 * width) - antider(u - 0.5 * width)) / width).clamp(0.0, 1.0)


def _box_interval(u: torch.Tensor, half: float, width: torch.Tensor) -> torch.Tensor:
    """Fraction of ``[u - width/2, u + width/2]`` inside ``[-half, half]``."""
    lo = torch.maximum(u - 0.5 * width, torch.full_like(u, -half))
    hi = torch.minimum(u + 0.5 * width, torch.full_like(u, half))
    return ((hi - lo) / width).clamp(0.0, 1.0)


def target_coordinates(camera: Camera, depth_m: torch.Tensor, centre_px: tuple[float, float] | None = None
                       ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Physical target coordinates seen by each pixel.

    Pixel ``(i, j)`` looks along the chief ray through the lens centre, so at distance
    ``d`` it sees ``X = (j - c_x) pitch d / d_s``, ``Y = (i - c_y) pitch d / d_s``.

    Args:
        camera: the camera (pitch, ``d_s``).
        depth_m: ``(B, 1, H, W)`` object distance per pixel in metres.
        centre_px: the optical axis in this image's pixel coordinates ``(row, col)``;
            default the image centre.

    Returns:
        ``(Y, X, footprint)`` in metres, each ``(B, 1, H, W)``; ``footprint`` is the side of
        one pixel on the target, ``pitch d / d_s``.
    """
    if depth_m.ndim != 4 or depth_m.shape[1] != 1:
        raise ShapeError(f"depth_m must be (B, 1, H, W), got {tuple(depth_m.shape)}")
    if not torch.isfinite(depth_m).all() or bool((depth_m <= 0).any()):
        raise InputError("depth_m must be finite and > 0")
    h, w = depth_m.shape[-2:]
    cy, cx = ((h - 1) / 2.0, (w - 1) / 2.0) if centre_px is None else centre_px
    scale = camera.pixel_pitch_m / camera.sensor_distance_m
    rows = (torch.arange(h, dtype=depth_m.dtype, device=depth_m.device) - cy)[:, None]
    cols = (torch.arange(w, dtype=depth_m.dtype, device=depth_m.device) - cx)[None, :]
    fp = depth_m * scale
    return rows * fp, cols * fp, fp


# ----------------------------------------------------------------------------- masks
@dataclass(frozen=True)
class MaskPattern:
    """A binary mask pattern in physical units on the target plane (metres).

    Kinds:
        * ``"bars"``: ``count`` rectangles of ``width_m`` x ``height_m`` side by side with
          gaps ``gap_m`` (the paper's mask: two 6.2 mm x 18.9 mm cut-outs 6.2 mm apart).
        * ``"rect"``: one ``width_m`` x ``height_m`` rectangle (the square mask of Fig. 3).
        * ``"grating"``: stripes of period ``period_m``, bright fraction ``duty``, at
          ``angle_rad``, inside a square beam of side ``beam_m``.
        * ``"dots"``: a square lattice of discs of radius ``radius_m``, pitch ``period_m``,
          inside the beam.
        * ``"checker"``: a checkerboard of period ``period_m`` inside the beam.
        * ``"random"``: random binary cells of side ``period_m`` (a programmable spatial
          light modulator), filled with probability ``duty``, from ``seed``, inside the beam.

    Coverage is box-filtered over each pixel's footprint (anti-aliased).
    """

    kind: str = "bars"
    width_m: float = 6.2e-3
    height_m: float = 18.9e-3
    gap_m: float = 6.2e-3
    count: int = 2
    period_m: float = 2e-3
    duty: float = 0.5
    radius_m: float = 0.5e-3
    angle_rad: float = 0.0
    beam_m: float = 25e-3
    seed: int = 0

    def __post_init__(self) -> None:
        if self.kind not in ("bars", "rect", "grating", "dots", "checker", "random"):
            raise InputError(f"unknown mask kind {self.kind!r}")
        for name in ("width_m", "height_m", "period_m", "radius_m", "beam_m"):
            if not getattr(self, name) > 0:
                raise InputError(f"mask {name} must be > 0, got {getattr(self, name)}")
        if self.gap_m < 0 or int(self.count) < 1 or not 0 < self.duty < 1:
            raise InputError("mask needs gap_m >= 0, count >= 1 and 0 < duty < 1")

    @property
    def half_extent_m(self) -> tuple[float, float]:
        """Half-size ``(y, x)`` of the pattern's bounding box in metres."""
        if self.kind == "bars":
            return 0.5 * self.height_m, 0.5 * (self.count * self.width_m + (self.count - 1) * self.gap_m)
        if self.kind == "rect":
            return 0.5 * self.height_m, 0.5 * self.width_m
        return 0.5 * self.beam_m, 0.5 * self.beam_m

    def coverage(self, y_m: torch.Tensor, x_m: torch.Tensor, footprint_m: torch.Tensor | float) -> torch.Tensor:
        """Fraction of each pixel footprint (a square of side ``footprint_m`` centred at
        ``(y_m, x_m)``, metres, relative to the pattern centre) that the mask lets through."""
        fp = torch.as_tensor(footprint_m, dtype=x_m.dtype, device=x_m.device)
        if self.kind == "bars":
            pitch = self.width_m + self.gap_m
            x0 = x_m + 0.5 * (self.count - 1) * pitch  # first bar centred at 0
            k = torch.round(x0 / pitch).clamp(0, self.count - 1)
            cx = _box_interval(x0 - k * pitch, 0.5 * self.width_m, fp)
            # a footprint wider than the gap may touch the neighbouring bars too
            for dk in (-1.0, 1.0):
                kk = k + dk
                ok = ((kk >= 0) & (kk <= self.count - 1)).to(x_m.dtype)
                cx = cx + ok * _box_interval(x0 - kk * pitch, 0.5 * self.width_m, fp)
            return cx.clamp(0.0, 1.0) * _box_interval(y_m, 0.5 * self.height_m, fp)
        if self.kind == "rect":
            return _box_interval(x_m, 0.5 * self.width_m, fp) * _box_interval(y_m, 0.5 * self.height_m, fp)
        beam = _box_interval(x_m, 0.5 * self.beam_m, fp) * _box_interval(y_m, 0.5 * self.beam_m, fp)
        c, s = math.cos(self.angle_rad), math.sin(self.angle_rad)
        u, v = c * x_m + s * y_m, c * y_m - s * x_m
        if self.kind == "grating":
            return beam * box_square_wave(u, self.period_m, self.duty, fp)
        if self.kind == "checker":
            a, b = box_square_wave(u, self.period_m, 0.5, fp), box_square_wave(v, self.period_m, 0.5, fp)
            return beam * (a * b + (1 - a) * (1 - b))
        if self.kind == "dots":
            du = u - (torch.floor(u / self.period_m) + 0.5) * self.period_m
            dv = v - (torch.floor(v / self.period_m) + 0.5) * self.period_m
            sd = self.radius_m - torch.sqrt(du * du + dv * dv)
            return beam * (sd / fp + 0.5).clamp(0.0, 1.0)
        # random SLM cells: a seeded table; each footprint mixes the cells it overlaps
        n = int(math.ceil(self.beam_m / self.period_m)) + 4
        table = torch.rand(n, n, generator=torch.Generator().manual_seed(int(self.seed))) < self.duty
        table = table.to(device=x_m.device, dtype=x_m.dtype)
        fu, fv = u / self.period_m + n / 2, v / self.period_m + n / 2
        iu, iv = torch.floor(fu), torch.floor(fv)
        w_rel = (fp / self.period_m).clamp(max=1.0)

        def weights(frac: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
            left = ((0.5 * w_rel - frac) / w_rel).clamp(0.0, 1.0)
            right = ((frac + 0.5 * w_rel - 1.0) / w_rel).clamp(0.0, 1.0)
            return left, 1.0 - left - right, right

        wu, wv = weights(fu - iu), weights(fv - iv)
        acc = torch.zeros_like(u)
        for a, wa in zip((-1, 0, 1), wu):
            for b, wb in zip((-1, 0, 1), wv):
                cell = table[(iv + b).long().clamp(0, n - 1), (iu + a).long().clamp(0, n - 1)]
                acc = acc + wa * wb * cell
        return beam * acc


#: The paper's mask (sec. 4): two 6.2 mm (horizontal) x 18.9 mm (vertical) cut-outs, 6.2 mm apart.
PAPER_MASK = MaskPattern("bars", width_m=6.2e-3, height_m=18.9e-3, gap_m=6.2e-3, count=2)


# ----------------------------------------------------------------------------- speckle
def speckle_grain_px(camera: Camera, wavelength_m: float = 632.8e-9) -> float:
    """Mean subjective speckle diameter in pixels, ``2.44 lambda (d_s / A) / pitch`` (the
    diffraction-limited spot of the camera's aperture)."""
    return 2.44 * wavelength_m * camera.sensor_distance_m / camera.aperture_m / camera.pixel_pitch_m


def speckle(shape: Sequence[int], generator: torch.Generator, grain_px: float, batch: int = 1) -> torch.Tensor:
    """Fully developed laser speckle intensity, mean 1 (exponential statistics).

    A circular complex Gaussian field is low-passed by a disk pupil of cut-off
    ``1 / grain_px`` cycles/px and squared; ``grain_px`` is the mean speckle diameter.

    Returns:
        ``(batch, 1, H, W)``, mean 1, standard deviation about 1.
    """
    h, w = (int(v) for v in shape)
    if grain_px <= 0:
        raise InputError(f"speckle grain must be > 0 px, got {grain_px}")
    fy = torch.fft.fftfreq(h)[:, None]
    fx = torch.fft.fftfreq(w)[None, :]
    pupil = (torch.sqrt(fy * fy + fx * fx) <= 1.0 / grain_px).to(torch.complex64)
    field_ = torch.complex(torch.randn(batch, 1, h, w, generator=generator),
                           torch.randn(batch, 1, h, w, generator=generator))
    e = torch.fft.ifft2(torch.fft.fft2(field_) * pupil)
    inten = e.real ** 2 + e.imag ** 2
    # per-image mean in float64 numpy (pairwise summation): the same bits whatever the
    # number of torch threads, so a seeded pattern is reproducible everywhere
    mean = np.mean(inten.detach().double().cpu().numpy().reshape(batch, -1), axis=1)
    return inten / torch.as_tensor(np.maximum(mean, 1e-12), dtype=inten.dtype).reshape(batch, 1, 1, 1)


# ----------------------------------------------------------------------------- modules
def _orders(n: int) -> list[int]:
    if int(n) != n or n < 1:
        raise InputError(f"diffraction order count must be a positive integer, got {n}")
    return list(range(-(int(n) - 1) // 2, int(n) // 2 + 1))


@dataclass(frozen=True)
class CoherentIllumination:
    """The paper's coherent conditioned illumination module (sec. 2.1, Fig. 3).

    Args:
        mask: the programmable mask (physical units on the target; default the paper's).
        orders: number of diffraction orders ``(rows, cols)`` the DOE makes (1 = none).
        order_angle_rad: angle ``(theta_y, theta_x)`` of the first order.
        order_efficiency: relative intensity of order ``k`` is ``order_efficiency^|k|``
            (per axis); 1 is a designed, uniform DOE.
        axis_offset_m: offset ``(y, x)`` of the beam axis from the camera axis (constant
            with distance: the beam is parallel to the optical axis).
        speckle_contrast: 0 (no speckle) to 1 (fully developed speckle).
        speckle_grain: mean speckle diameter in px (default :func:`speckle_grain_px`).
        wavelength_m: laser wavelength (He-Ne 632.8 nm in the paper).
    """

    mask: MaskPattern = PAPER_MASK
    orders: tuple[int, int] = (1, 1)
    order_angle_rad: tuple[float, float] = (0.03, 0.03)
    order_efficiency: float = 1.0
    axis_offset_m: tuple[float, float] = (0.0, 0.0)
    speckle_contrast: float = 0.0
    speckle_grain: float | None = None
    wavelength_m: float = 632.8e-9

    def __post_init__(self) -> None:
        for n in self.orders:
            _orders(n)
        if not 0 <= self.speckle_contrast <= 1 or not 0 < self.order_efficiency <= 1:
            raise InputError("speckle_contrast must lie in [0, 1] and order_efficiency in (0, 1]")

    def _order_offsets(self, axis: int) -> tuple[list[int], list[float]]:
        ks = _orders(self.orders[axis])
        s1 = math.sin(self.order_angle_rad[axis])
        tans = []
        for k in ks:
            sk = k * s1
            if abs(sk) >= 1:
                raise InputError(f"diffraction order {k} does not propagate (sin theta = {sk:.3f})")
            tans.append(sk / math.sqrt(1 - sk * sk))
        return ks, tans

    def on_target(self, y_m: torch.Tensor, x_m: torch.Tensor, depth_m: torch.Tensor | float,
                  footprint_m: torch.Tensor | float = 1e-5) -> torch.Tensor:
        """Irradiance (relative, peak 1) at target points ``(y_m, x_m)`` (metres from the
        camera axis) at distance ``depth_m``, averaged over a ``footprint_m`` square.

        Without diffraction orders this does not depend on ``depth_m``: the beam keeps
        its size and sharpness at every distance.
        """
        d = torch.as_tensor(depth_m, dtype=x_m.dtype, device=x_m.device)
        y0, x0 = y_m - self.axis_offset_m[0], x_m - self.axis_offset_m[1]
        (ky, ty), (kx, tx) = self._order_offsets(0), self._order_offsets(1)
        y0, x0, d = torch.broadcast_tensors(y0, x0, d)
        fpt = torch.as_tensor(footprint_m, dtype=x_m.dtype, device=x_m.device).expand_as(x0)
        out = torch.zeros(x0.numel(), dtype=x0.dtype, device=x0.device)
        hy, hx = self.mask.half_extent_m
        yf, xf, df, ff = y0.reshape(-1), x0.reshape(-1), d.reshape(-1), fpt.reshape(-1)
        for i, tyi in zip(ky, ty):
            for j, txj in zip(kx, tx):
                yy, xx = yf - df * tyi, xf - df * txj
                # evaluate each order only where it can land (its bounding box)
                idx = ((yy.abs() <= hy + ff) & (xx.abs() <= hx + ff)).nonzero(as_tuple=True)[0]
                if idx.numel() == 0:
                    continue
                w = self.order_efficiency ** (abs(i) + abs(j))
                out.index_add_(0, idx, w * self.mask.coverage(yy[idx], xx[idx], ff[idx]))
        out = out.reshape(x0.shape)
        return out.clamp(0.0, 1.0) if self.order_efficiency == 1.0 else out

    def render(self, camera: Camera, depth_m: torch.Tensor, generator: torch.Generator | None = None,
               centre_px: tuple[float, float] | None = None) -> torch.Tensor:
        """The pattern's irradiance on a scene, in camera pixels.

        Args:
            camera: the imaging camera.
            depth_m: ``(B, 1, H, W)`` object distance per pixel (m).
            generator: random source of the speckle (needed if ``speckle_contrast > 0``).
            centre_px: optical axis in pixel coordinates (default the image centre).

        Returns:
            ``(B, 1, H, W)`` relative irradiance (peak 1 without speckle), sharp at every
            distance (edges anti-aliased over one pixel).
        """
        y, x, fp = target_coordinates(camera, depth_m, centre_px)
        out = self.on_target(y, x, depth_m, fp)
        if self.speckle_contrast > 0:
            if generator is None:
                raise InputError("speckle needs a torch.Generator")
            grain = self.speckle_grain or speckle_grain_px(camera, self.wavelength_m)
            s = speckle(depth_m.shape[-2:], generator, grain, depth_m.shape[0]).to(out.dtype)
            out = out * (1.0 + self.speckle_contrast * (s - 1.0))
        return out


@dataclass(frozen=True)
class ProjectorIllumination:
    """An incoherent projector focused at ``focus_m`` (the paper's comparison source).

    Args:
        mask: the projected pattern, in metres on the plane of best focus.
        focus_m: best-focus distance (paper: 0.568 m).
        dof_near_m: depth of field in front of the focus (paper: 0.125 m).
        dof_far_m: depth of field behind the focus (paper: 0.165 m).
        coc_rad: acceptable circle of confusion (blur diameter) at the DOF limits, as an
            angle seen from the projector (default 1 mrad).
        symmetric: use one aperture (the dioptric mean of the two sides), a pure thin lens.
        axis_offset_rad: direction ``(y, x)`` of the pattern centre from the camera axis.

    See the module documentation for the blur model.
    """

    mask: MaskPattern = PAPER_MASK
    focus_m: float = 0.568
    dof_near_m: float = 0.125
    dof_far_m: float = 0.165
    coc_rad: float = 1e-3
    symmetric: bool = False
    axis_offset_rad: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self) -> None:
        if not (self.focus_m > 0 and 0 < self.dof_near_m < self.focus_m and self.dof_far_m > 0 and self.coc_rad > 0):
            raise InputError("projector needs focus_m > dof_near_m > 0, dof_far_m > 0 and coc_rad > 0")

    @property
    def dioptric_half_widths(self) -> tuple[float, float]:
        """``(1/d_near - 1/d_f, 1/d_f - 1/d_far)`` in dioptres."""
        f = self.focus_m
        return 1.0 / (f - self.dof_near_m) - 1.0 / f, 1.0 / f - 1.0 / (f + self.dof_far_m)

    @property
    def apertures_m(self) -> tuple[float, float]:
        """Effective projector aperture diameters ``(A_near, A_far)`` in metres."""
        n, f = self.dioptric_half_widths
        if self.symmetric:
            n = f = 0.5 * (n + f)
        return self.coc_rad / n, self.coc_rad / f

    def blur_angle_rad(self, depth_m: torch.Tensor | float) -> torch.Tensor:
        """Signed blur-disk diameter as an angle (rad): negative nearer than focus."""
        d = torch.as_tensor(depth_m, dtype=torch.get_default_dtype()) if not isinstance(depth_m, torch.Tensor) else depth_m
        a_near, a_far = self.apertures_m
        q = 1.0 / self.focus_m - 1.0 / d  # > 0 beyond focus
        return torch.where(q < 0, a_near * q, a_far * q)

    def blur_sigma_px(self, camera: Camera, depth_m: torch.Tensor | float) -> torch.Tensor:
        """Signed RMS radius in camera pixels of the projector's pillbox blur,
        ``beta d_s / (4 pitch)``."""
        return self.blur_angle_rad(depth_m) * camera.sensor_distance_m / (4.0 * camera.pixel_pitch_m)

    def on_target(self, y_m: torch.Tensor, x_m: torch.Tensor, footprint_m: torch.Tensor | float, depth_m: float
                  ) -> torch.Tensor:
        """Sharp (unblurred) pattern on a plane at ``depth_m``: the mask scaled by
        ``depth_m / focus_m``, irradiance scaled by ``(focus_m / depth_m)^2``. Blur it with
        :meth:`blur_angle_rad` ``* depth_m`` (physical diameter) for the real projection."""
        k = self.focus_m / float(depth_m)
        yy = (y_m - depth_m * math.tan(self.axis_offset_rad[0])) * k
        xx = (x_m - depth_m * math.tan(self.axis_offset_rad[1])) * k
        return k * k * self.mask.coverage(yy, xx, torch.as_tensor(footprint_m) * k)

    def render(self, camera: Camera, depth_m: torch.Tensor, generator: torch.Generator | None = None,
               centre_px: tuple[float, float] | None = None, layer_spacing: float = 0.5) -> torch.Tensor:
        """The projected pattern's irradiance on a scene, in camera pixels.

        The sharp pattern (fixed in pixels) is blurred per pixel by the projector's defocus
        at that pixel's depth (pillbox, through :func:`tdfd.optics.render.defocus_layered_multi`
        in gather mode: the projector shares the camera's viewpoint, so every surface point
        receives the pattern blurred by its own distance and nothing is occluded).

        Args:
            camera: the imaging camera.
            depth_m: ``(B, 1, H, W)`` object distance per pixel (m).
            generator: unused (the projector is deterministic); kept for a uniform interface.
            centre_px: optical axis in pixel coordinates (default the image centre).
            layer_spacing: blur-level spacing (px of sigma) of the per-pixel interpolation.

        Returns:
            ``(B, 1, H, W)`` relative irradiance (1 = pattern peak at the focus distance).
        """
        f = torch.full_like(depth_m, self.focus_m)
        y, x, fp = target_coordinates(camera, f, centre_px)
        yy = y - self.focus_m * math.tan(self.axis_offset_rad[0])
        xx = x - self.focus_m * math.tan(self.axis_offset_rad[1])
        sharp = self.mask.coverage(yy, xx, fp)
        sigma = self.blur_sigma_px(camera, depth_m).to(depth_m.dtype)
        blurred = defocus_layered_multi(sharp, sigma, None, "pillbox", layer_spacing=layer_spacing,
                                        exact_planes=True, occlusion=False)[:, 0]
        return blurred.clamp_min(0.0) * (self.focus_m / depth_m) ** 2


def illuminate(albedo: torch.Tensor, pattern: torch.Tensor | None, ambient: float | torch.Tensor = 1.0,
               power: float | torch.Tensor = 1.0) -> torch.Tensor:
    """Scene radiance ``albedo * (ambient + power * pattern)`` (Lambertian target).

    Args:
        albedo: ``(B, 1, H, W)`` reflectance in [0, 1] (possibly texture-less).
        pattern: ``(B, 1, H, W)`` relative irradiance of the active source, or ``None``.
        ambient: ambient irradiance (float or ``(B,)``).
        power: scale of the active source (float or ``(B,)``).
    """
    a = torch.as_tensor(ambient, dtype=albedo.dtype).reshape(-1, 1, 1, 1)
    if pattern is None:
        return albedo * a
    p = torch.as_tensor(power, dtype=albedo.dtype).reshape(-1, 1, 1, 1)
    return albedo * (a + p * pattern)
