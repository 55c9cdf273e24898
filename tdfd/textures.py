r"""Procedural textures: the albedo of synthetic scenes (no photographs).

Every family is a function ``family(shape, generator, batch=1, **params)`` that returns a
``(batch, 1, H, W)`` float32 tensor in ``[0, 1]``; ``shape`` is ``(H, W)`` or an int for a
square. All randomness comes from the explicit :class:`torch.Generator`, so a texture is a
pure function of ``(shape, generator state, params)``. Lengths are in pixels, frequencies in
cycles per pixel, angles in radians. Edges are anti-aliased over about one pixel (a sensor
integrates over its pixel area), so a texture is a faithful in-focus image.

Families (registered in :data:`TEXTURE_FAMILIES`, each with a parameter sampler):

==================  ==================================================================
``fractal``         1/f^beta ("fractal", pink/brown) noise
``bandlimited``     white noise band-passed around one scale (log-Gaussian band)
``voronoi``         cellular (Voronoi/Worley) cells, cell edges, or distance fields
``dead_leaves``     occluding random discs and squares with power-law sizes
``stripes``         square-wave or sinusoidal gratings at any angle and period
``checkers``        rotated checkerboards
``dots``            dot lattices with jitter and random dot sizes
``line_art``        random straight strokes of random width
``glyphs``          glyph-like strokes in a character grid (text-like)
``gradient``        smooth linear, radial or curved gradients
``flat``            near-texture-less surfaces: constant albedo with very faint variation
==================  ==================================================================

:func:`random_texture` draws a family, its parameters, an albedo and a contrast
(:func:`apply_albedo`) and returns the parameters with the texture.

Example:
    >>> import torch
    >>> g = torch.Generator().manual_seed(0)
    >>> t = stripes((32, 48), g, period=8.0, angle=0.3)
    >>> t.shape, bool(t.min() >= 0) and bool(t.max() <= 1)
    (torch.Size([1, 1, 32, 48]), True)
    >>> tex, params = random_texture(torch.Generator().manual_seed(1), 64)
    >>> tex.shape, params["family"] in TEXTURE_FAMILIES
    (torch.Size([1, 1, 64, 64]), True)
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from typing import Any, Callable, Mapping, Sequence

import torch

from .errors import InputError

__all__ = [
    "TextureFamily",
    "TEXTURE_FAMILIES",
    "register_texture",
    "random_texture",
    "family_weights",
    "apply_albedo",
    "spectral_tilt",
    "fractal",
    "bandlimited",
    "voronoi",
    "dead_leaves",
    "stripes",
    "checkers",
    "dots",
    "line_art",
    "glyphs",
    "gradient",
    "flat",
]

# ----------------------------------------------------------------------------- helpers
def _hw(shape: int | Sequence[int]) -> tuple[int, int]:
    if isinstance(shape, int):
        h = w = shape
    else:
        try:
            h, w = (int(v) for v in shape)
        except (TypeError, ValueError) as exc:
            raise InputError(f"texture shape must be an int or (H, W), got {shape!r}") from exc
    if h < 1 or w < 1:
        raise InputError(f"texture shape must be positive, got {(h, w)}")
    return h, w


def _check_batch(batch: int) -> int:
    if int(batch) != batch or batch < 1:
        raise InputError(f"batch must be a positive integer, got {batch!r}")
    return int(batch)


def _finite_number(value: Any, what: str, minimum: float | None = None) -> float:
    """``value`` as a float if it is a finite number (a bool is no number here) and at least
    ``minimum``; else :class:`InputError` naming ``what``."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) \
            or (minimum is not None and value < minimum):
        bound = "" if minimum is None else f" >= {minimum:g}"
        raise InputError(f"{what} needs a finite number{bound}, got {value!r}")
    return float(value)


def _u(g: torch.Generator, lo: float, hi: float) -> float:
    """A uniform float in [lo, hi) from ``g``."""
    return lo + (hi - lo) * float(torch.rand((), generator=g, dtype=torch.float64))


def _logu(g: torch.Generator, lo: float, hi: float) -> float:
    """A log-uniform float in [lo, hi) from ``g``."""
    return math.exp(_u(g, math.log(lo), math.log(hi)))


def _randint(g: torch.Generator, lo: int, hi: int) -> int:
    """An integer in [lo, hi] from ``g``."""
    return int(torch.randint(lo, hi + 1, (), generator=g))


def _choice(g: torch.Generator, options: Sequence[Any]) -> Any:
    return options[_randint(g, 0, len(options) - 1)]


def _coords(h: int, w: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixel-centre coordinates ``(y (H, 1), x (1, W))`` relative to the image centre."""
    y = torch.arange(h, dtype=torch.float32)[:, None] - (h - 1) / 2.0
    x = torch.arange(w, dtype=torch.float32)[None, :] - (w - 1) / 2.0
    return y, x


def _normalise(x: torch.Tensor) -> torch.Tensor:
    """Per-sample min-max scaling of ``(B, 1, H, W)`` to [0, 1]."""
    lo = x.amin((-1, -2), keepdim=True)
    hi = x.amax((-1, -2), keepdim=True)
    return ((x - lo) / (hi - lo).clamp_min(1e-12)).clamp(0.0, 1.0)


def _coverage(signed_distance: torch.Tensor) -> torch.Tensor:
    """Anti-aliased coverage of a shape from its signed distance (px, > 0 inside)."""
    return (signed_distance + 0.5).clamp(0.0, 1.0)


def _spectral_noise(h: int, w: int, g: torch.Generator, batch: int,
                    gain: Callable[[torch.Tensor], torch.Tensor]) -> torch.Tensor:
    """White Gaussian noise shaped in the Fourier domain by ``gain(f)`` (f in cycles/px)."""
    fy = torch.fft.fftfreq(h)[:, None]
    fx = torch.fft.rfftfreq(w)[None, :]
    f = torch.sqrt(fy * fy + fx * fx)
    white = torch.randn(batch, 1, h, w, generator=g)
    out = torch.fft.irfft2(torch.fft.rfft2(white) * gain(f), s=(h, w))
    return out


# ----------------------------------------------------------------------------- families
def fractal(shape: int | Sequence[int], generator: torch.Generator, batch: int = 1, beta: float = 2.0,
            min_freq: float | None = None) -> torch.Tensor:
    """1/f noise: power spectrum ``~ 1 / f^beta`` (``beta = 2`` is the natural-image slope).

    Args:
        shape: ``(H, W)`` or a side length.
        generator: random source.
        batch: number of textures.
        beta: spectral exponent of the power spectrum (0 white, 2 natural images, 3+ smooth).
        min_freq: frequency (cycles/px) below which the spectrum is flat; default ``1/max(H, W)``.

    Returns:
        ``(batch, 1, H, W)`` in [0, 1] (min-max scaled).
    """
    h, w = _hw(shape)
    batch = _check_batch(batch)
    f0 = 1.0 / max(h, w) if min_freq is None else float(min_freq)
    x = _spectral_noise(h, w, generator, batch, lambda f: f.clamp_min(f0) ** (-0.5 * float(beta)))
    return _normalise(x)


def bandlimited(shape: int | Sequence[int], generator: torch.Generator, batch: int = 1, freq: float = 0.1,
                bandwidth: float = 1.0, binary: bool = False) -> torch.Tensor:
    """Noise band-passed around one scale: a log-Gaussian band of ``bandwidth`` octaves (FWHM).

    Args:
        freq: centre frequency in cycles/px (period ``1/freq`` px), at most 0.5.
        bandwidth: full width at half maximum of the band in octaves.
        binary: threshold at the median (blobs/maze-like patterns with sharp edges).
    """
    h, w = _hw(shape)
    batch = _check_batch(batch)
    if not 0.0 < freq <= 0.5 or bandwidth <= 0:
        raise InputError(f"need 0 < freq <= 0.5 cycles/px and bandwidth > 0, got {freq}, {bandwidth}")
    s = bandwidth / (2.0 * math.sqrt(2.0 * math.log(2.0)))  # octaves -> log2 standard deviation

    def gain(f: torch.Tensor) -> torch.Tensor:
        lf = torch.log2(f.clamp_min(1e-6) / freq)
        out = torch.exp(-0.5 * (lf / s) ** 2)
        out[..., 0, 0] = 0.0
        return out

    x = _spectral_noise(h, w, generator, batch, gain)
    if binary:
        med = x.reshape(batch, -1).median(-1).values[:, None, None, None]
        # anti-aliased threshold: the field's gradient converts level to distance in px
        gy, gx = torch.gradient(x, dim=(-2, -1))
        grad = torch.sqrt(gy * gy + gx * gx).clamp_min(1e-3)
        return _coverage((x - med) / grad)
    return _normalise(x)


def voronoi(shape: int | Sequence[int], generator: torch.Generator, batch: int = 1, cell: float = 24.0,
            mode: str = "cells", edge_width: float = 1.5, jitter: float = 1.0) -> torch.Tensor:
    """Cellular (Voronoi / Worley) texture: one random seed per square of a ``cell`` px grid
    (jittered-grid Worley noise), so every pixel only compares the 3 x 3 nearby seeds.

    Args:
        cell: mean seed spacing in px (>= 3).
        mode: ``"cells"`` (flat random grey per cell, anti-aliased borders), ``"edges"``
            (bright cells with dark borders of ``edge_width`` px) or ``"distance"`` (the
            Worley F1 distance field, smooth cones).
        edge_width: border width in px for ``"edges"``.
        jitter: seed displacement within its grid square, 0 (regular lattice) to 1.
    """
    h, w = _hw(shape)
    batch = _check_batch(batch)
    if cell < 3.0:
        raise InputError(f"voronoi cell must be >= 3 px, got {cell}")
    if mode not in ("cells", "edges", "distance"):
        raise InputError(f"voronoi mode must be 'cells', 'edges' or 'distance', got {mode!r}")
    rows, cols = int(math.ceil(h / cell)) + 3, int(math.ceil(w / cell)) + 3
    off = torch.rand(batch, 2, generator=generator) * cell
    jit = 0.5 + (torch.rand(batch, 2, rows, cols, generator=generator) - 0.5) * jitter
    grey = torch.rand(batch, rows, cols, generator=generator)
    # seed positions in px (grid square (i, j) spans [(i - 1) cell, i cell) minus the offset)
    sy = (torch.arange(rows, dtype=torch.float32)[None, :, None] - 1 + jit[:, 0]) * cell - off[:, 0, None, None]
    sx = (torch.arange(cols, dtype=torch.float32)[None, None, :] - 1 + jit[:, 1]) * cell - off[:, 1, None, None]
    py = torch.arange(h, dtype=torch.float32) + 0.5
    px = torch.arange(w, dtype=torch.float32) + 0.5
    ri = torch.floor((py[None, :] + off[:, 0, None]) / cell).long() + 1  # (B, H) grid row of each pixel
    ci = torch.floor((px[None, :] + off[:, 1, None]) / cell).long() + 1  # (B, W)
    cand_d, cand_k = [], []
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            r = (ri + dr).clamp(0, rows - 1)
            c = (ci + dc).clamp(0, cols - 1)
            k = r[:, :, None] * cols + c[:, None, :]  # (B, H, W) flat seed index
            yy = torch.gather(sy.reshape(batch, -1), 1, k.reshape(batch, -1)).reshape(batch, h, w)
            xx = torch.gather(sx.reshape(batch, -1), 1, k.reshape(batch, -1)).reshape(batch, h, w)
            cand_d.append((yy - py[None, :, None]) ** 2 + (xx - px[None, None, :]) ** 2)
            cand_k.append(k)
    d = torch.stack(cand_d, 1)  # (B, 9, H, W)
    kk = torch.stack(cand_k, 1)
    top = torch.topk(d, 2, dim=1, largest=False)
    d1, d2 = top.values[:, 0], top.values[:, 1]
    k1 = torch.gather(kk, 1, top.indices[:, :1])[:, 0]
    k2 = torch.gather(kk, 1, top.indices[:, 1:2])[:, 0]
    if mode == "distance":
        return _normalise(torch.sqrt(d1)[:, None])

    def seed(k: torch.Tensor, table: torch.Tensor) -> torch.Tensor:
        return torch.gather(table.reshape(batch, -1), 1, k.reshape(batch, -1)).reshape(batch, h, w)

    sep = torch.sqrt((seed(k1, sy) - seed(k2, sy)) ** 2 + (seed(k1, sx) - seed(k2, sx)) ** 2).clamp_min(1e-6)
    edge = ((d2 - d1) / (2.0 * sep))[:, None]  # distance to the bisector of the two nearest seeds
    if mode == "edges":
        return _coverage(edge - 0.5 * float(edge_width))
    g1, g2 = seed(k1, grey)[:, None], seed(k2, grey)[:, None]
    a = _coverage(edge) * 0.5 + 0.5  # weight of the own cell: 0.5 on the border, 1 inside
    return a * g1 + (1.0 - a) * g2


def dead_leaves(shape: int | Sequence[int], generator: torch.Generator, batch: int = 1, leaves: int = 60,
                r_min: float = 3.0, r_max: float = 60.0, exponent: float = 3.0, squares: float = 0.3) -> torch.Tensor:
    """Dead-leaves model: occluding random shapes whose radii follow ``p(r) ~ r^-exponent``.

    Shapes are painted back to front with anti-aliased coverage (each over its bounding box
    only), on a random grey background; the last painted is on top.

    Args:
        leaves: number of shapes.
        r_min, r_max: radius range in px.
        exponent: power-law exponent of the radius density (3 is scale invariant).
        squares: fraction of shapes that are rotated squares (the rest are discs).
    """
    h, w = _hw(shape)
    batch = _check_batch(batch)
    n = int(leaves)
    if n < 1 or not 0 < r_min <= r_max:
        raise InputError(f"need leaves >= 1 and 0 < r_min <= r_max, got {leaves}, {r_min}, {r_max}")
    u = torch.rand(batch, n, generator=generator, dtype=torch.float64)
    if abs(exponent - 1.0) < 1e-9:
        radii = r_min * (r_max / r_min) ** u
    else:  # inverse CDF of r^-a on [r_min, r_max]
        a1 = 1.0 - exponent
        radii = (r_min**a1 + u * (r_max**a1 - r_min**a1)) ** (1.0 / a1)
    cy = torch.rand(batch, n, generator=generator, dtype=torch.float64) * h
    cx = torch.rand(batch, n, generator=generator, dtype=torch.float64) * w
    grey = torch.rand(batch, n, generator=generator)
    is_square = torch.rand(batch, n, generator=generator) < squares
    angle = torch.rand(batch, n, generator=generator, dtype=torch.float64) * (math.pi / 2)
    background = torch.rand(batch, generator=generator)
    out = background[:, None, None, None].expand(batch, 1, h, w).clone()
    radii_l, cy_l, cx_l, grey_l = radii.tolist(), cy.tolist(), cx.tolist(), grey.tolist()
    sq_l, ang_l = is_square.tolist(), angle.tolist()
    for b in range(batch):
        img = out[b, 0]
        for i in range(n):
            r, yc, xc, sq = radii_l[b][i], cy_l[b][i], cx_l[b][i], sq_l[b][i]
            ext = r * (math.sqrt(2.0) if sq else 1.0) + 1.0
            y0, y1 = max(0, int(yc - ext)), min(h, int(yc + ext) + 1)
            x0, x1 = max(0, int(xc - ext)), min(w, int(xc + ext) + 1)
            if y0 >= y1 or x0 >= x1:
                continue
            dy = torch.arange(y0, y1, dtype=torch.float32)[:, None] + (0.5 - yc)
            dx = torch.arange(x0, x1, dtype=torch.float32)[None, :] + (0.5 - xc)
            if sq:
                c, s = math.cos(ang_l[b][i]), math.sin(ang_l[b][i])
                sd = r - torch.maximum((c * dx + s * dy).abs(), (c * dy - s * dx).abs())
            else:
                sd = r - torch.sqrt(dy * dy + dx * dx)
            a = _coverage(sd)
            patch = img[y0:y1, x0:x1]
            patch.add_(a * (grey_l[b][i] - patch))
    return out


def _square_wave(u: torch.Tensor, period: float, duty: float) -> torch.Tensor:
    """Box-filtered square wave of ``u`` (px): 1 on a fraction ``duty`` of each period.

    Each value is the exact fraction of the one-pixel interval ``[u - 1/2, u + 1/2]`` that
    the bright intervals cover (``period >= 2``).
    """
    half = 0.5 * duty * period
    q = (torch.remainder(u, period) - 0.5 * period).abs()  # distance to the nearest bright centre

    def overlap(dist: torch.Tensor) -> torch.Tensor:
        return (torch.minimum(dist + 0.5, torch.full_like(dist, half))
                - torch.maximum(dist - 0.5, torch.full_like(dist, -half))).clamp(0.0, 1.0)

    return (overlap(q) + overlap(period - q)).clamp(0.0, 1.0)


def stripes(shape: int | Sequence[int], generator: torch.Generator, batch: int = 1, period: float = 8.0,
            angle: float = 0.0, duty: float = 0.5, profile: str = "square", phase: float | None = None) -> torch.Tensor:
    """Parallel stripes.

    Args:
        period: stripe period in px (>= 2).
        angle: direction of the stripe normal in radians (0: vertical stripes).
        duty: bright fraction of each period (square profile).
        profile: ``"square"`` (anti-aliased edges) or ``"sine"``.
        phase: offset in px along the normal; random when ``None``.
    """
    h, w = _hw(shape)
    batch = _check_batch(batch)
    if period < 2.0 or not 0.0 < duty < 1.0:
        raise InputError(f"need period >= 2 px and 0 < duty < 1, got {period}, {duty}")
    if phase is None:
        ph = torch.rand(batch, 1, 1, 1, generator=generator) * period
    else:
        ph = torch.full((batch, 1, 1, 1), float(phase))
    y, x = _coords(h, w)
    u = (math.cos(angle) * x + math.sin(angle) * y)[None, None] + ph
    if profile == "sine":
        return 0.5 + 0.5 * torch.sin(2 * math.pi * u / period)
    if profile != "square":
        raise InputError(f"stripes profile must be 'square' or 'sine', got {profile!r}")
    return _square_wave(u, period, duty)


def checkers(shape: int | Sequence[int], generator: torch.Generator, batch: int = 1, period: float = 16.0,
             angle: float = 0.0) -> torch.Tensor:
    """A checkerboard of square ``period / 2`` px cells rotated by ``angle`` (radians)."""
    h, w = _hw(shape)
    batch = _check_batch(batch)
    if period < 2.0:
        raise InputError(f"checkers period must be >= 2 px, got {period}")
    off = torch.rand(batch, 2, 1, 1, generator=generator) * period
    y, x = _coords(h, w)
    c, s = math.cos(angle), math.sin(angle)
    u = (c * x + s * y)[None, None] + off[:, :1, None]
    v = (c * y - s * x)[None, None] + off[:, 1:, None]
    a, b = _square_wave(u, period, 0.5), _square_wave(v, period, 0.5)
    return (a * b + (1 - a) * (1 - b)).reshape(batch, 1, h, w)


def dots(shape: int | Sequence[int], generator: torch.Generator, batch: int = 1, period: float = 12.0,
         radius: float = 3.0, jitter: float = 0.0, radius_jitter: float = 0.0, angle: float = 0.0,
         invert: bool = False) -> torch.Tensor:
    """A lattice of anti-aliased dots.

    Args:
        period: lattice spacing in px.
        radius: dot radius in px (at most ``period / 2``).
        jitter: random displacement of each dot, as a fraction of ``period`` (0 regular).
        radius_jitter: relative random variation of each dot's radius.
        angle: lattice rotation in radians.
        invert: dark dots on a bright ground.
    """
    h, w = _hw(shape)
    batch = _check_batch(batch)
    if period < 2.0 or not 0.0 < radius:
        raise InputError(f"need period >= 2 px and radius > 0, got {period}, {radius}")
    y, x = _coords(h, w)
    c, s = math.cos(angle), math.sin(angle)
    off = torch.rand(batch, 2, generator=generator) * period
    u = (c * x + s * y)[None] + off[:, 0, None, None]  # (B, H, W)
    v = (c * y - s * x)[None] + off[:, 1, None, None]
    iu, iv = torch.floor(u / period), torch.floor(v / period)
    # per-cell random offsets from a hash of the cell index (no per-cell storage)
    n_cells = int(2 * (h + w) / period) + 8
    table = torch.rand(batch, 3, n_cells, n_cells, generator=generator)
    ku = torch.remainder(iu, n_cells).long()
    kv = torch.remainder(iv, n_cells).long()
    bidx = torch.arange(batch)[:, None, None]
    ju = (table[bidx, 0, ku, kv] - 0.5) * jitter * period
    jv = (table[bidx, 1, ku, kv] - 0.5) * jitter * period
    rr = radius * (1.0 + radius_jitter * (2 * table[bidx, 2, ku, kv] - 1))
    du = u - (iu + 0.5) * period - ju
    dv = v - (iv + 0.5) * period - jv
    a = _coverage(rr - torch.sqrt(du * du + dv * dv))[:, None]
    return 1.0 - a if invert else a


def _segment_distance(py: torch.Tensor, px: torch.Tensor, ay: torch.Tensor, ax: torch.Tensor,
                      by: torch.Tensor, bx: torch.Tensor) -> torch.Tensor:
    """Distance from points ``p`` to segments ``a``-``b`` (broadcast)."""
    vy, vx = by - ay, bx - ax
    wy, wx = py - ay, px - ax
    t = ((wy * vy + wx * vx) / (vy * vy + vx * vx).clamp_min(1e-9)).clamp(0.0, 1.0)
    dy, dx = wy - t * vy, wx - t * vx
    return torch.sqrt(dy * dy + dx * dx)


def line_art(shape: int | Sequence[int], generator: torch.Generator, batch: int = 1, lines: int = 12,
             width: tuple[float, float] = (1.0, 4.0), length: tuple[float, float] = (0.2, 1.0),
             invert: bool = False) -> torch.Tensor:
    """Random straight strokes (dark on bright unless ``invert``), like drawings or cables.

    Args:
        lines: number of strokes.
        width: stroke width range in px.
        length: stroke length range as a fraction of the image diagonal.
    """
    h, w = _hw(shape)
    batch = _check_batch(batch)
    n = int(lines)
    if n < 1:
        raise InputError(f"line_art needs lines >= 1, got {lines}")
    diag = math.hypot(h, w)
    cy = torch.rand(batch, n, generator=generator) * h
    cx = torch.rand(batch, n, generator=generator) * w
    ang = torch.rand(batch, n, generator=generator) * math.pi
    ln = (length[0] + (length[1] - length[0]) * torch.rand(batch, n, generator=generator)) * diag / 2
    wd = width[0] + (width[1] - width[0]) * torch.rand(batch, n, generator=generator)
    grey = torch.rand(batch, n, generator=generator) * 0.5
    out = torch.ones(batch, 1, h, w)
    cy_l, cx_l, ang_l, ln_l, wd_l, grey_l = (t.tolist() for t in (cy, cx, ang, ln, wd, grey))
    for b in range(batch):
        img = out[b, 0]
        for i in range(n):  # painter's order: later strokes on top
            dy, dx = math.sin(ang_l[b][i]) * ln_l[b][i], math.cos(ang_l[b][i]) * ln_l[b][i]
            y_c, x_c, half = cy_l[b][i], cx_l[b][i], 0.5 * wd_l[b][i] + 1.0
            y0, y1 = max(0, int(y_c - abs(dy) - half)), min(h, int(y_c + abs(dy) + half) + 1)
            x0, x1 = max(0, int(x_c - abs(dx) - half)), min(w, int(x_c + abs(dx) + half) + 1)
            if y0 >= y1 or x0 >= x1:
                continue
            py = torch.arange(y0, y1, dtype=torch.float32)[:, None] + 0.5
            px = torch.arange(x0, x1, dtype=torch.float32)[None, :] + 0.5
            d = _segment_distance(py, px, torch.tensor(y_c - dy), torch.tensor(x_c - dx), torch.tensor(y_c + dy),
                                  torch.tensor(x_c + dx))
            a = _coverage(0.5 * wd_l[b][i] - d)
            patch = img[y0:y1, x0:x1]
            patch.add_(a * (grey_l[b][i] - patch))
    return 1.0 - out if invert else out


def glyphs(shape: int | Sequence[int], generator: torch.Generator, batch: int = 1, cell: float = 24.0,
           strokes: int = 3, width: float = 2.0, fill: float = 0.8, invert: bool = False) -> torch.Tensor:
    """Glyph-like strokes in a grid of character cells (printed text, labels, symbols).

    Each cell holds ``strokes`` random segments between points of a 3 x 3 anchor grid (as
    in simple letter shapes), drawn with ``width`` px; a fraction ``1 - fill`` of cells is
    left blank (spaces).
    """
    h, w = _hw(shape)
    batch = _check_batch(batch)
    if cell < 6.0 or strokes < 1 or width <= 0:
        raise InputError(f"need cell >= 6 px, strokes >= 1, width > 0, got {cell}, {strokes}, {width}")
    rows, cols = int(math.ceil(h / cell)) + 1, int(math.ceil(w / cell)) + 1
    anchors = torch.tensor([[0.15, 0.2], [0.15, 0.5], [0.15, 0.8], [0.5, 0.2], [0.5, 0.5], [0.5, 0.8],
                            [0.85, 0.2], [0.85, 0.5], [0.85, 0.8]])
    ends = torch.randint(0, 9, (batch, strokes, 2, rows, cols), generator=generator)
    blank = torch.rand(batch, 1, rows, cols, generator=generator) > fill
    off = torch.rand(batch, 2, generator=generator) * cell
    yy = torch.arange(h, dtype=torch.float32)[None, :, None] + off[:, 0, None, None]  # (B, H, 1)
    xx = torch.arange(w, dtype=torch.float32)[None, None, :] + off[:, 1, None, None]  # (B, 1, W)
    r = torch.floor(yy / cell).long().clamp_max(rows - 1)
    c = torch.floor(xx / cell).long().clamp_max(cols - 1)
    ly, lx = (yy / cell - r), (xx / cell - c)  # local coordinates in [0, 1)
    dist = torch.full((batch, h, w), 1e9)
    bidx = torch.arange(batch)[:, None, None]
    for k in range(strokes):
        # endpoints per cell (B, rows, cols), spread to pixels with two gathers
        a, b = anchors[ends[:, k, 0]], anchors[ends[:, k, 1]]  # (B, rows, cols, 2)
        seg = torch.cat([a, b], -1).permute(0, 3, 1, 2)  # (B, 4, rows, cols)
        seg = torch.gather(seg, 2, r[:, None, :, :].expand(-1, 4, -1, cols))  # (B, 4, H, cols)
        seg = torch.gather(seg, 3, c[:, None, :, :].expand(-1, 4, h, -1))  # (B, 4, H, W)
        d = _segment_distance(ly, lx, seg[:, 0], seg[:, 1], seg[:, 2], seg[:, 3]) * cell
        dist = torch.minimum(dist, d)
    empty = torch.gather(torch.gather(blank[:, 0], 1, r.expand(-1, -1, cols)), 2, c.expand(-1, h, -1))
    ink = _coverage(0.5 * width - dist) * (~empty).float()
    ink = ink[:, None]
    return ink if invert else 1.0 - ink


def gradient(shape: int | Sequence[int], generator: torch.Generator, batch: int = 1, kind: str = "linear",
             angle: float = 0.0, curvature: float = 0.0) -> torch.Tensor:
    """A smooth gradient: ``"linear"`` (ramp along ``angle``), ``"radial"`` (from a random
    centre) or ``"curved"`` (a ramp with quadratic bend ``curvature``)."""
    h, w = _hw(shape)
    batch = _check_batch(batch)
    y, x = _coords(h, w)
    n = max(h, w)
    if kind == "radial":
        c = (torch.rand(batch, 2, 1, 1, generator=generator) - 0.5) * n
        r = torch.sqrt((y[None] - c[:, 0:1, 0]) ** 2 + (x[None] - c[:, 1:2, 0]) ** 2)
        return _normalise(r[:, None])
    if kind not in ("linear", "curved"):
        raise InputError(f"gradient kind must be 'linear', 'radial' or 'curved', got {kind!r}")
    u = (math.cos(angle) * x + math.sin(angle) * y) / n
    v = (math.cos(angle) * y - math.sin(angle) * x) / n
    ramp = u + (curvature * v * v if kind == "curved" else 0.0)
    return _normalise(ramp.expand(batch, 1, h, w).clone())


def flat(shape: int | Sequence[int], generator: torch.Generator, batch: int = 1, variation: float = 0.01,
         grain: float = 0.002) -> torch.Tensor:
    """A near-texture-less surface (painted wall, black page): mid-grey with faint smooth
    variation (relative amplitude ``variation``) and faint fine grain (``grain``).

    Use :func:`apply_albedo` to set its level; the result stays close to 0.5 here.
    """
    h, w = _hw(shape)
    batch = _check_batch(batch)
    smooth = fractal((h, w), generator, batch, beta=3.0) - 0.5
    fine = torch.randn(batch, 1, h, w, generator=generator)
    return (0.5 + variation * smooth + grain * fine).clamp(0.0, 1.0)


def apply_albedo(texture: torch.Tensor, albedo: float | torch.Tensor, contrast: float | torch.Tensor) -> torch.Tensor:
    """Set a texture's reflectance: ``albedo * (1 - contrast + contrast * texture)``.

    Args:
        texture: ``(B, 1, H, W)`` in [0, 1].
        albedo: the brightest reflectance in (0, 1] (float or ``(B,)``).
        contrast: Michelson-like modulation depth in [0, 1] (float or ``(B,)``): 0 gives a
            uniform surface, 1 the full texture range.

    Returns:
        ``(B, 1, H, W)`` reflectance in ``[albedo (1 - contrast), albedo]``.
    """
    a = torch.as_tensor(albedo, dtype=texture.dtype).reshape(-1, 1, 1, 1)
    c = torch.as_tensor(contrast, dtype=texture.dtype).reshape(-1, 1, 1, 1)
    if bool(((a < 0) | (a > 1) | (c < 0) | (c > 1)).any()):
        raise InputError("albedo and contrast must lie in [0, 1]")
    return a * (1.0 - c + c * texture)


def spectral_tilt(texture: torch.Tensor, exponent: float, reference_frequency: float = 0.1) -> torch.Tensor:
    """Tilt a texture's spectrum: its Fourier amplitude times ``(f / f_ref)^exponent``, then
    rescaled to [0, 1].

    A frame's own spectral shape is a depth cue only through the scenes' typical spectra: a
    blur steepens a 1/f spectrum just as a texture with a steeper spectrum would. Training
    textures with randomly tilted spectra (``data_synth``'s ``SynthConfig.spectral_tilt``)
    take that cue away, so the depth must come from the ratio of the two frames (paper,
    eq. 10), which no texture spectrum changes.

    Args:
        texture: ``(B, 1, H, W)`` in [0, 1].
        exponent: the tilt ``a`` of the amplitude spectrum (the power spectrum's log-log slope
            changes by ``2 a``); 0 leaves the texture unchanged up to the rescaling.
        reference_frequency: ``f_ref`` in cycles/px, where the amplitude is kept; frequencies
            below one cycle per image side are treated as that lowest one (the mean is kept
            before the rescaling).

    Returns:
        ``(B, 1, H, W)`` in [0, 1], each image's minimum at 0 and maximum at 1 (a constant
        image stays constant).

    Raises:
        InputError: a non-finite exponent or a reference frequency outside (0, 0.5].

    Example:
        >>> import torch
        >>> x = torch.rand(1, 1, 32, 32, generator=torch.Generator().manual_seed(0))
        >>> y = spectral_tilt(x, 0.5)
        >>> y.shape, float(y.min()), float(y.max())
        (torch.Size([1, 1, 32, 32]), 0.0, 1.0)
    """
    exponent = _finite_number(exponent, "the spectral tilt exponent")
    if not 0.0 < reference_frequency <= 0.5:
        raise InputError(f"reference_frequency must lie in (0, 0.5] cycles/px, got {reference_frequency!r}")
    if texture.dim() != 4 or texture.shape[1] != 1:
        raise InputError(f"expected a (B, 1, H, W) texture, got {tuple(texture.shape)}")
    h, w = texture.shape[-2:]
    x = texture.double()
    fy = torch.fft.fftfreq(h, dtype=torch.float64)[:, None]
    fx = torch.fft.rfftfreq(w, dtype=torch.float64)[None, :]
    f = torch.sqrt(fy**2 + fx**2).clamp_min(1.0 / max(h, w))
    mean = x.mean((-2, -1), keepdim=True)
    y = torch.fft.irfft2(torch.fft.rfft2(x - mean) * (f / reference_frequency) ** exponent, s=(h, w)) + mean
    lo = y.amin((-2, -1), keepdim=True)
    span = y.amax((-2, -1), keepdim=True) - lo
    y = torch.where(span > 1e-12, (y - lo) / span.clamp_min(1e-12), torch.full_like(y, 0.5))
    return y.clamp(0.0, 1.0).to(texture.dtype)


# ----------------------------------------------------------------------------- registry
@dataclass(frozen=True)
class TextureFamily:
    """A registered texture family.

    Attributes:
        name: registry key.
        fn: ``fn(shape, generator, batch=1, **params) -> (batch, 1, H, W)``.
        sample_params: ``sample_params(generator, (H, W)) -> dict`` of random parameters
            (plain floats, ints, strings, bools) for ``fn``.
    """

    name: str
    fn: Callable[..., torch.Tensor]
    sample_params: Callable[[torch.Generator, tuple[int, int]], dict]


#: All texture families by name.
TEXTURE_FAMILIES: dict[str, TextureFamily] = {}


def register_texture(name: str, fn: Callable[..., torch.Tensor],
                     sample_params: Callable[[torch.Generator, tuple[int, int]], dict]) -> TextureFamily:
    """Add (or replace) a texture family in :data:`TEXTURE_FAMILIES`."""
    fam = TextureFamily(name, fn, sample_params)
    TEXTURE_FAMILIES[name] = fam
    return fam


def _p_fractal(g: torch.Generator, hw: tuple[int, int]) -> dict:
    return {"beta": _u(g, 1.0, 3.2)}


def _p_bandlimited(g: torch.Generator, hw: tuple[int, int]) -> dict:
    return {"freq": _logu(g, 1.0 / 64, 0.4), "bandwidth": _u(g, 0.5, 2.0), "binary": bool(_u(g, 0, 1) < 0.3)}


def _p_voronoi(g: torch.Generator, hw: tuple[int, int]) -> dict:
    return {"cell": _logu(g, 6.0, 64.0), "mode": _choice(g, ("cells", "cells", "edges", "distance")),
            "edge_width": _u(g, 1.0, 3.0), "jitter": _u(g, 0.5, 1.0)}


def _p_dead_leaves(g: torch.Generator, hw: tuple[int, int]) -> dict:
    n = max(hw)
    r_min = _u(g, 2.0, 6.0)
    return {"leaves": _randint(g, 25, 70), "r_min": r_min, "r_max": max(r_min, _u(g, 0.1, 0.35) * n),
            "exponent": _u(g, 2.0, 3.2), "squares": _u(g, 0.0, 0.6)}


def _p_stripes(g: torch.Generator, hw: tuple[int, int]) -> dict:
    return {"period": _logu(g, 2.5, 48.0), "angle": _u(g, 0.0, math.pi), "duty": _u(g, 0.2, 0.8),
            "profile": _choice(g, ("square", "square", "sine"))}


def _p_checkers(g: torch.Generator, hw: tuple[int, int]) -> dict:
    return {"period": _logu(g, 4.0, 64.0), "angle": _u(g, 0.0, math.pi / 2)}


def _p_dots(g: torch.Generator, hw: tuple[int, int]) -> dict:
    period = _logu(g, 4.0, 32.0)
    return {"period": period, "radius": period * _u(g, 0.12, 0.45), "jitter": _u(g, 0.0, 0.6),
            "radius_jitter": _u(g, 0.0, 0.5), "angle": _u(g, 0.0, math.pi / 2), "invert": bool(_u(g, 0, 1) < 0.5)}


def _p_line_art(g: torch.Generator, hw: tuple[int, int]) -> dict:
    wmin = _u(g, 0.7, 2.5)
    return {"lines": _randint(g, 4, 16), "width": (wmin, wmin * _u(g, 1.0, 3.0)), "length": (0.1, _u(g, 0.3, 1.2)),
            "invert": bool(_u(g, 0, 1) < 0.3)}


def _p_glyphs(g: torch.Generator, hw: tuple[int, int]) -> dict:
    cell = _logu(g, 8.0, 40.0)
    return {"cell": cell, "strokes": _randint(g, 2, 4), "width": max(0.8, cell * _u(g, 0.06, 0.15)),
            "fill": _u(g, 0.5, 1.0), "invert": bool(_u(g, 0, 1) < 0.3)}


def _p_gradient(g: torch.Generator, hw: tuple[int, int]) -> dict:
    return {"kind": _choice(g, ("linear", "radial", "curved")), "angle": _u(g, 0.0, 2 * math.pi),
            "curvature": _u(g, -2.0, 2.0)}


def _p_flat(g: torch.Generator, hw: tuple[int, int]) -> dict:
    return {"variation": _logu(g, 1e-3, 0.03), "grain": _logu(g, 1e-4, 5e-3)}


for _name, _fn, _sp in (
    ("fractal", fractal, _p_fractal),
    ("bandlimited", bandlimited, _p_bandlimited),
    ("voronoi", voronoi, _p_voronoi),
    ("dead_leaves", dead_leaves, _p_dead_leaves),
    ("stripes", stripes, _p_stripes),
    ("checkers", checkers, _p_checkers),
    ("dots", dots, _p_dots),
    ("line_art", line_art, _p_line_art),
    ("glyphs", glyphs, _p_glyphs),
    ("gradient", gradient, _p_gradient),
    ("flat", flat, _p_flat),
):
    register_texture(_name, _fn, _sp)


def family_weights(weights: Mapping[str, Any]) -> dict[str, float]:
    """Relative weights of texture families, checked: each a finite number >= 0 (a bool is no
    number here), at least one > 0.

    Raises:
        InputError: naming the family whose weight is bad, or the all-zero mapping.

    Example:
        >>> family_weights({"stripes": 3, "dots": 0.0})
        {'stripes': 3.0, 'dots': 0.0}
    """
    out = {}
    for name, w in dict(weights).items():
        out[str(name)] = _finite_number(w, f"the weight of texture family {name!r}", minimum=0.0)
    if not any(w > 0 for w in out.values()):
        raise InputError(f"family weights must give some family a weight > 0, got {out}")
    return out


def _weighted_choice(g: torch.Generator, weights: dict[str, float]) -> str:
    """A family drawn with probability proportional to its weight (one uniform draw from ``g``)."""
    u = _u(g, 0.0, sum(weights.values()))
    names = list(weights)
    below = sum(1 for c in itertools.accumulate(weights.values()) if c <= u)  # cumulative weights passed
    return names[min(below, len(names) - 1)]


def random_texture(generator: torch.Generator, size: int | Sequence[int], family: str | None = None,
                   families: Sequence[str] | Mapping[str, float] | None = None,
                   albedo: tuple[float, float] = (0.05, 0.95),
                   contrast: tuple[float, float] = (0.03, 1.0), spectral_tilt_max: float = 0.0
                   ) -> tuple[torch.Tensor, dict]:
    """A random texture of a random (or given) family with random albedo and contrast.

    Args:
        generator: random source (the only one used).
        size: ``(H, W)`` or a side length in px.
        family: force this family; otherwise one of ``families`` (default: all registered)
            is drawn, uniformly from a sequence or by relative weight from a mapping
            ``{family: weight}`` (:func:`family_weights`; a family it leaves out is never drawn).
        families: the families to draw from.
        albedo: range of the brightest reflectance (uniform).
        contrast: range of the modulation depth (log-uniform); the ``flat`` family keeps
            its own faint variation at full contrast.
        spectral_tilt_max: > 0: the texture's spectrum is tilted (:func:`spectral_tilt`) by an
            exponent drawn uniformly from ``[-spectral_tilt_max, spectral_tilt_max]`` (recorded
            as ``params["spectral_tilt"]``), before the albedo and contrast; 0 (default): no
            tilt and no draw.

    Returns:
        ``(texture (1, 1, H, W) in [0, 1], params)`` where ``params`` holds ``family``,
        ``albedo``, ``contrast`` and the family's parameters (plain Python values).
    """
    hw = _hw(size)
    spectral_tilt_max = _finite_number(spectral_tilt_max, "spectral_tilt_max", minimum=0.0)
    if family is None and isinstance(families, Mapping):
        family = _weighted_choice(generator, family_weights(families))
    names = list(TEXTURE_FAMILIES) if families is None else list(families)
    if family is None:
        if not names:
            raise InputError("no texture families to draw from")
        family = _choice(generator, names)
    if family not in TEXTURE_FAMILIES:
        raise InputError(f"unknown texture family {family!r}; known: {sorted(TEXTURE_FAMILIES)}")
    fam = TEXTURE_FAMILIES[family]
    params = fam.sample_params(generator, hw)
    a = _u(generator, *albedo)
    c = 1.0 if family == "flat" else _logu(generator, *contrast)
    raw = fam.fn(hw, generator, 1, **params)
    out = {"family": family, "albedo": a, "contrast": c}
    if spectral_tilt_max > 0 and family != "flat":
        out["spectral_tilt"] = _u(generator, -spectral_tilt_max, spectral_tilt_max)
        raw = spectral_tilt(raw, out["spectral_tilt"])
    tex = apply_albedo(raw, a, c)
    out.update({k: (list(v) if isinstance(v, tuple) else v) for k, v in params.items()})
    return tex, out
