r"""The in-focus power from all frames of a run by cross-blurring, for a Gaussian or a disk PSF.

Two frames of one scene at powers ``P_i``, ``P_j`` are the texture blurred by PSFs
``h_i``, ``h_j``; blurring each by the other's PSF gives the same image whatever the
texture, ``I_i * h_j = I_j * h_i``, for any PSF family. With the thin lens each frame's
blur follows from the in-focus power ``P*`` (``sigma_k = M |P_k - P*|``, paper eq. 7), so
``P*`` and the family are found by minimising, over candidates, the profile likelihood of
white noise summed over frame pairs and frequencies,

    ``sum |S_i H_j - S_j H_i|^2 / (|H_i|^2 + |H_j|^2)``

(``S``: the windowed ROI spectra; ``H``: the OTFs, analytic: ``exp(-2 pi^2 sigma^2 f^2)``
for the Gaussian, ``2 J1(2 pi f R) / (2 pi f R)`` with ``R = 2 sigma`` for the disk of the
same RMS radius). Unlike the relative blur's Gaussian fit (:mod:`~tdfd.autofocus.relative_blur`)
it models a disk's MTF, zeros and contrast reversals included, at a periodic texture's few
frequencies. No regulariser in the denominator: one creates minima where every frame is
blurred away. The OTFs being real, each pair's residual comes from the spectra's powers and
real cross terms, computed once; the disk's ``2 J1(a) / a`` is tabulated (0.001 steps of
``a``): one search on three 128x160 ROIs takes about 25 ms of numpy on the 2-core machine.

Example:
    >>> import numpy as np
    >>> from tdfd import Camera
    >>> from tdfd.autofocus.evidence import sigma_px_per_dpt
    >>> cam = Camera.preset("reference")
    >>> scene = np.random.default_rng(0).random((96, 128))
    >>> spec = np.fft.rfft2(scene)
    >>> f2 = np.fft.fftfreq(96)[:, None] ** 2 + np.fft.rfftfreq(128)[None, :] ** 2
    >>> def frame(p, focus=2.2):  # Gaussian blur of the thin lens, by its OTF
    ...     s = sigma_px_per_dpt(cam) * abs(p - focus)
    ...     return np.fft.irfft2(spec * np.exp(-2 * np.pi**2 * s**2 * f2), s=(96, 128))
    >>> est = cross_blur_focus([(frame(p), p) for p in (1.7, 2.7, 2.4)], cam)
    >>> round(est.power_dpt, 2), est.shape, est.at_edge
    (2.2, 'gaussian', False)
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Sequence

import numpy as np

from ..camera import Camera
from ..errors import InputError
from .evidence import sigma_px_per_dpt, working_powers_dpt
from .roi import Roi

__all__ = ["CrossBlurFocus", "cross_blur_focus", "windowed_spectra", "profile_cost", "otf", "bessel_j1", "disk_otf",
           "evenly_thinned", "PSF_FAMILIES"]

#: the PSF families the search fits: a Gaussian and a uniform disk (pillbox) of the same RMS radius
PSF_FAMILIES = ("gaussian", "pillbox")


@dataclass(frozen=True)
class CrossBlurFocus:
    """The in-focus power the frames give (:func:`cross_blur_focus`).

    Attributes:
        power_dpt: the in-focus power ``P*`` (dpt).
        shape: the PSF family that explains the frames best (``"gaussian"`` or ``"pillbox"``).
        at_edge: the best coarse candidate lay at an edge of the searched span (the minimum
            may lie beyond it: not an estimate to act on).
        cost: the profile likelihood at ``P*`` (per frame pair and frequency).
        other_power_dpt, other_cost_ratio: the other family's best power and its cost over
            the best's (``nan``, ``inf`` with one family).
        contrast: how sharply the frames single ``P*`` out: the median coarse candidate's
            cost over the best's, minus one. Frames that differ by little more than their
            noise (a texture near the noise floor) give a flat cost: on the reliability
            benchmark's tuning seeds, five of the seven 3-frame minima over 1 px from focus
            had a contrast under 0.1.
        runner_up_power_dpt, runner_up_ratio: the best other local minimum of this family's coarse
            cost curve (at least two coarse steps from the best) and its cost over the best's, both
            on the coarse grid (``nan``, ``inf`` without one). A periodic texture (one frequency)
            is explained by several powers: a runner-up close to 1 says the frames do not single
            the power out, whichever family is known.
    """

    power_dpt: float
    shape: str
    at_edge: bool
    cost: float
    other_power_dpt: float = math.nan
    other_cost_ratio: float = math.inf
    contrast: float = math.nan
    runner_up_power_dpt: float = math.nan
    runner_up_ratio: float = math.inf


def _runner_up(candidates: np.ndarray, costs: np.ndarray, best: int) -> tuple[float, float]:
    """The lowest local minimum of ``costs`` at least two candidates from ``best``: ``(power, cost / best cost)``."""
    n = len(costs)
    minima = [i for i in range(n) if abs(i - best) >= 2
              and (i == 0 or costs[i] <= costs[i - 1]) and (i == n - 1 or costs[i] <= costs[i + 1])]
    if not minima:
        return math.nan, math.inf
    k = min(minima, key=lambda i: costs[i])
    return float(candidates[k]), float(costs[k] / max(costs[best], 1e-300))


def evenly_thinned(items: Sequence, n: int) -> list:
    """At most ``n`` of ``items`` (e.g. frames sorted by power), evenly spread, both ends kept:
    a long sweep or contrast scan costs a search in proportion to its frame pairs.

    Example:
        >>> evenly_thinned(list(range(10)), 4)
        [0, 3, 6, 9]
    """
    items = list(items)
    if len(items) <= n:
        return items
    return [items[int(round(k * (len(items) - 1) / (n - 1)))] for k in range(n)]


def bessel_j1(x: np.ndarray) -> np.ndarray:
    """Bessel function of the first kind, order 1 (Abramowitz & Stegun 9.4.4 and 9.4.6,
    absolute error below 1e-7).

    Example:
        >>> float(np.round(bessel_j1(np.array(1.0)), 6))
        0.440051
    """
    x = np.asarray(x, dtype=np.float64)
    ax = np.abs(x)
    y = (np.minimum(ax, 3.0) / 3.0) ** 2
    small = x * (0.5 + y * (-0.56249985 + y * (0.21093573 + y * (-0.03954289 + y * (0.00443319
                 + y * (-0.00031761 + y * 0.00001109))))))
    t = 3.0 / np.maximum(ax, 3.0)
    f1 = 0.79788456 + t * (0.00000156 + t * (0.01659667 + t * (0.00017105 + t * (-0.00249511
                          + t * (0.00113653 - t * 0.00020033)))))
    th = ax - 2.35619449 + t * (0.12499612 + t * (0.00005650 + t * (-0.00637879 + t * (0.00074348
                               + t * (0.00079824 - t * 0.00029166)))))
    large = np.sign(x) * f1 * np.cos(th) / np.sqrt(np.maximum(ax, 3.0))
    return np.where(ax <= 3.0, small, large)


#: ``2 J1(a) / a`` tabulated at 0.001 steps of ``a`` up to 400 (linear interpolation error
#: under 1e-7), built on first use: the disk OTF of every candidate without evaluating J1
_DISK_TABLE_STEP, _DISK_TABLE_END = 1e-3, 400.0
_disk_table: np.ndarray | None = None


def _disk_profile(a: np.ndarray) -> np.ndarray:
    """``2 J1(a) / a`` (1 at 0) for ``a >= 0``: tabulated where the table reaches, exact beyond."""
    global _disk_table
    if _disk_table is None:
        x = np.arange(0.0, _DISK_TABLE_END + _DISK_TABLE_STEP, _DISK_TABLE_STEP)
        x[0] = 1.0
        _disk_table = 2.0 * bessel_j1(x) / x
        _disk_table[0] = 1.0
    if a.size and float(a.max()) < _DISK_TABLE_END:
        x = a / _DISK_TABLE_STEP
        k = x.astype(np.intp)
        w = x - k
        return _disk_table[k] * (1.0 - w) + _disk_table[k + 1] * w
    safe = np.where(a > 1e-9, a, 1.0)
    return np.where(a > 1e-9, 2.0 * bessel_j1(safe) / safe, 1.0)


def disk_otf(radius_px: float, f: np.ndarray) -> np.ndarray:
    """OTF of a uniform disk of radius ``radius_px`` at spatial frequencies ``f`` (cycles/px)."""
    return _disk_profile(np.abs(2.0 * math.pi * float(radius_px) * np.asarray(f, dtype=np.float64)))


def otf(sigma_px: float, shape: str, f2: np.ndarray, f: np.ndarray) -> np.ndarray:
    """The OTF of a ``shape`` PSF of RMS radius ``sigma_px`` at frequencies ``f`` (``f2 = f**2``): a
    Gaussian's ``exp(-2 pi^2 sigma^2 f^2)``, a disk's of radius ``2 sigma`` (:func:`disk_otf`)."""
    if shape == "gaussian":
        return np.exp(-2.0 * math.pi**2 * sigma_px**2 * f2)
    return disk_otf(2.0 * sigma_px, f)


def profile_cost(power: list[np.ndarray], cross: dict[tuple[int, int], np.ndarray], offsets: np.ndarray, m: float,
                 shape: str, f2: np.ndarray, f: np.ndarray) -> float:
    """The profile likelihood of the candidate whose frames lie ``offsets`` dpt from focus.
    The OTFs are real, so ``|S_i H_j - S_j H_i|^2 = |S_i|^2 H_j^2 + |S_j|^2 H_i^2 - 2 H_i H_j Re(S_i S_j*)``
    from the spectra's powers ``power`` and cross terms ``cross`` (real arrays, :func:`windowed_spectra`,
    or their sums over rings of ``|f|`` with ``f`` the rings' frequencies); summed, not averaged."""
    otfs = [otf(m * abs(float(o)), shape, f2, f) for o in offsets]
    sq = [h * h for h in otfs]
    total = 0.0
    for (i, j), c in cross.items():
        num = power[i] * sq[j] + power[j] * sq[i] - 2.0 * otfs[i] * otfs[j] * c
        den = sq[i] + sq[j]
        total += float((np.maximum(num, 0.0) / np.where(den > 1e-300, den, 1e-300)).sum())
    return total


def windowed_spectra(frames: Sequence[tuple[np.ndarray, float]], roi: Roi | None = None,
                     shapes: Sequence[str] = PSF_FAMILIES):
    """``(power, cross, f2, f, powers)``: the Hann-windowed ROI spectra's powers (a list) and real
    cross terms (``{(i, j): Re(S_i S_j*)}``), the squared and plain frequency grids (cycles/px, the
    ``rfft2`` layout) and the frames' powers (dpt), checked as :func:`cross_blur_focus` checks them."""
    if len(frames) < 2 or max(p for _, p in frames) - min(p for _, p in frames) < 0.02:
        raise InputError("cross_blur_focus needs at least two frames 0.02 dpt apart")
    if not set(shapes) <= set(PSF_FAMILIES) or not shapes:
        raise InputError(f"shapes must be among {PSF_FAMILIES}, got {tuple(shapes)}")
    crops = [np.asarray(im if roi is None else roi.crop(np.asarray(im)), dtype=np.float64) for im, _ in frames]
    if len({c.shape for c in crops}) != 1 or crops[0].ndim != 2 or min(crops[0].shape) < 16:
        raise InputError(f"frames must be (H, W) of one shape with an ROI of at least 16 px, got {[c.shape for c in crops]}")
    h, w = crops[0].shape
    window = np.hanning(h)[:, None] * np.hanning(w)[None, :]
    spectra = [np.fft.rfft2((c - c.mean()) * window) for c in crops]
    power = [np.abs(sp) ** 2 for sp in spectra]
    cross = {(i, j): (spectra[i] * spectra[j].conj()).real for i in range(len(spectra)) for j in range(i + 1, len(spectra))}
    f2 = np.fft.fftfreq(h)[:, None] ** 2 + np.fft.rfftfreq(w)[None, :] ** 2
    return power, cross, f2, np.sqrt(f2), np.array([float(p) for _, p in frames])


def cross_blur_focus(frames: Sequence[tuple[np.ndarray, float]], camera: Camera, roi: Roi | None = None, *,
                     span_dpt: tuple[float, float] | None = None, shapes: Sequence[str] = PSF_FAMILIES,
                     coarse_dpt: float = 0.1, fine_dpt: float = 0.01, sigma_scale: float = 1.0) -> CrossBlurFocus:
    """The in-focus power (and PSF family) that best explains the frames (module docstring).

    Args:
        frames: ``(image, power_dpt)`` of one scene, at least two powers 0.02 dpt apart.
        camera: thin-lens constants (``M``, px of Gaussian sigma per dpt).
        roi: region used (default: the whole frame).
        span_dpt: candidate in-focus powers (default: :func:`working_powers_dpt`).
        shapes: PSF families tried.
        coarse_dpt, fine_dpt: the search's coarse step over the span, then its fine step
            within one coarse step of the coarse minimum.
        sigma_scale: the PSF's RMS blur per dioptre over the camera's ``M`` (1: the camera's
            ``mu`` describes the PSF; a disk lens calibrated through the Gaussian relative blur
            has a ``mu`` below its disk's, :mod:`tdfd.calibration.psf_family`).

    Raises:
        InputError: fewer than two frames at distinct powers, frames of different shapes,
            an ROI under 16 px, an unknown shape or non-positive steps.
    """
    if not (coarse_dpt > 0 and fine_dpt > 0 and sigma_scale > 0):
        raise InputError("coarse_dpt, fine_dpt and sigma_scale must be > 0")
    power, cross, f2, f, powers = windowed_spectra(frames, roi, shapes)
    lo, hi = working_powers_dpt(camera) if span_dpt is None else sorted(float(v) for v in span_dpt)
    m = sigma_px_per_dpt(camera) * float(sigma_scale)
    per_shape: list[CrossBlurFocus] = []
    for shape in shapes:
        coarse = np.arange(lo, hi + 1e-9, coarse_dpt)
        costs = [profile_cost(power, cross, powers - c, m, shape, f2, f) for c in coarse]
        k = int(np.argmin(costs))
        fine = np.arange(max(lo, coarse[k] - coarse_dpt), min(hi, coarse[k] + coarse_dpt) + 1e-9, fine_dpt)
        fcosts = [profile_cost(power, cross, powers - c, m, shape, f2, f) for c in fine]
        kf = int(np.argmin(fcosts))
        runner_power, runner_ratio = _runner_up(coarse, np.asarray(costs), k)
        per_shape.append(CrossBlurFocus(float(fine[kf]), shape, k in (0, len(coarse) - 1), fcosts[kf] / f2.size,
                                        contrast=float(np.median(costs)) / max(fcosts[kf], 1e-300) - 1.0,
                                        runner_up_power_dpt=runner_power, runner_up_ratio=runner_ratio))
    best, *others = sorted(per_shape, key=lambda c: c.cost)
    if not others:
        return best
    return replace(best, other_power_dpt=others[0].power_dpt, other_cost_ratio=others[0].cost / max(best.cost, 1e-300))
