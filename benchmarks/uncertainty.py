"""Does the confidence state an uncertainty? The predicted error scale against the observed error, per confidence decile.

The model predicts, per tile, a Laplace scale ``b`` of the relative inverse-depth error
``e = (q - q_true) / q_true`` (:mod:`tdfd.model.combined`; from a confidence,
:func:`benchmarks.depth_models.predicted_scale`). The tiles are split into ten equal-count
bins by confidence (deciles); in each, the median ``|e|`` observed is compared with the median
that the predicted Laplace errors would give (:func:`laplace_mixture_median`: the tiles of a
decile have different ``b``, so their errors are a mixture). Calibrated: the ratio observed /
predicted is 1, and half of the tiles have ``|e|`` at most their own predicted median
``b ln 2``.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from tdfd.errors import InputError

__all__ = ["laplace_mixture_median", "decile_table", "fit_scale_remap", "apply_scale_remap", "plot_calibration",
           "CALIBRATION_TOLERANCE"]

#: the target: observed / predicted within 20 % in every decile (issue 19)
CALIBRATION_TOLERANCE = 0.2


def laplace_mixture_median(scales: torch.Tensor) -> float:
    """Median of ``|e|`` over tiles whose errors ``e`` are Laplace with scales ``scales``.

    The ``m`` at which the tiles' mean ``P(|e| <= m) = 1 - exp(-m / b)`` is one half.

    Example:
        >>> round(laplace_mixture_median(torch.tensor([0.01, 0.01])), 6)  # one Laplace: b ln 2
        0.006931
    """
    b = torch.as_tensor(scales, dtype=torch.float64).flatten()
    if b.numel() == 0 or not bool((b >= 0).all()) or bool(torch.isnan(b).any()):
        raise InputError("scales must be a non-empty set of values >= 0")
    finite = b[torch.isfinite(b)]
    if finite.numel() * 2 <= b.numel():  # half the tiles or more with no prediction: no finite median
        return math.inf
    lo, hi = 0.0, max(float(finite.max()), 1e-300) * 50.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        # b = 0 counts as P = 1 (exact), b = inf as P = 0
        p = torch.where(b > 0, 1.0 - torch.exp(-mid / b.clamp_min(1e-300)), torch.ones_like(b)).mean()
        if float(p) < 0.5:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def decile_table(confidence: torch.Tensor, scale: torch.Tensor, error: torch.Tensor, bins: int = 10) -> list[dict]:
    """Per confidence bin (equal counts, by rank): predicted and observed error.

    Args:
        confidence: ``(N,)`` per-tile confidence.
        scale: ``(N,)`` predicted Laplace scale ``b`` of the relative error.
        error: ``(N,)`` observed signed relative inverse-depth error.
        bins: number of bins (10: deciles), from the lowest confidence up.

    Returns:
        One dict per bin: ``conf_lo``, ``conf_hi`` (its confidence range), ``tiles``,
        ``predicted`` (:func:`laplace_mixture_median` of its scales), ``observed`` (median
        ``|e|``), ``ratio`` (observed / predicted), ``within`` (share of tiles with ``|e| <=
        b ln 2``; 0.5 when calibrated) and ``ok`` (ratio within :data:`CALIBRATION_TOLERANCE`).

    Raises:
        InputError: shapes differ, fewer tiles than bins, or non-finite errors.
    """
    c = torch.as_tensor(confidence, dtype=torch.float64).flatten()
    b = torch.as_tensor(scale, dtype=torch.float64).flatten()
    e = torch.as_tensor(error, dtype=torch.float64).flatten().abs()
    if not (c.numel() == b.numel() == e.numel()):
        raise InputError(f"confidence, scale and error must have as many values, got {c.numel()}, {b.numel()}, {e.numel()}")
    if bins < 1 or c.numel() < bins:
        raise InputError(f"need at least {bins} tiles for {bins} bins, got {c.numel()}")
    if not bool(torch.isfinite(e).all()) or not bool(torch.isfinite(c).all()):
        raise InputError("confidence and error must be finite")
    order = torch.argsort(c, stable=True)
    rows = []
    for part in torch.tensor_split(order, bins):
        pred = laplace_mixture_median(b[part])
        obs = float(e[part].median())
        ratio = obs / pred if pred > 0 else math.inf
        rows.append({"conf_lo": float(c[part].min()), "conf_hi": float(c[part].max()), "tiles": int(part.numel()),
                     "predicted": pred, "observed": obs, "ratio": ratio,
                     "within": float((e[part] <= b[part] * math.log(2.0)).double().mean()),
                     "ok": abs(ratio - 1.0) <= CALIBRATION_TOLERANCE})
    return rows


def fit_scale_remap(scale: torch.Tensor, error: torch.Tensor, bins: int = 20) -> tuple[torch.Tensor, torch.Tensor]:
    """A monotone post-hoc remap of the predicted scale that makes it match the observed errors.

    The tiles are split into ``bins`` equal-count bins by ``b``; in each, the factor ``f``
    that makes the Laplace mixture median of ``f b`` equal the observed median ``|e|`` moves
    the bin's median ``b`` to a knot ``b'``; the knots are made non-decreasing in ``b`` (a
    remap must keep the confidence's order).

    Args:
        scale: ``(N,)`` predicted Laplace scale ``b`` (> 0).
        error: ``(N,)`` observed signed relative error.
        bins: number of bins.

    Returns:
        ``(log_b, log_b_remapped)`` knots, ``(bins,)`` each, increasing in ``log_b``.

    Raises:
        InputError: shapes differ, fewer tiles than bins, or a scale that is not positive and finite.

    Example:
        >>> g = torch.Generator().manual_seed(0)
        >>> b = torch.rand(20000, generator=g, dtype=torch.float64) * 0.05 + 0.01
        >>> u = torch.rand(20000, generator=g, dtype=torch.float64) - 0.5
        >>> e = 2 * b * -u.sign() * torch.log1p(-2 * u.abs())  # Laplace errors of scale 2 b
        >>> kb, kr = fit_scale_remap(b, e, bins=10)
        >>> bool(((kr - kb).exp() - 2).abs().max() < 0.25)  # errors twice the predicted: factor 2
        True
    """
    b = torch.as_tensor(scale, dtype=torch.float64).flatten()
    e = torch.as_tensor(error, dtype=torch.float64).flatten().abs()
    if b.numel() != e.numel():
        raise InputError(f"scale and error must have as many values, got {b.numel()} and {e.numel()}")
    if bins < 1 or b.numel() < bins:
        raise InputError(f"need at least {bins} tiles for {bins} bins, got {b.numel()}")
    if not bool(((b > 0) & torch.isfinite(b)).all()):
        raise InputError("scale must be positive and finite")
    order = torch.argsort(b, stable=True)
    log_b, log_r = [], []
    for part in torch.tensor_split(order, bins):
        factor = float(e[part].median()) / laplace_mixture_median(b[part])
        mid = float(b[part].median())
        log_b.append(math.log(mid))
        log_r.append(math.log(max(mid * factor, 1e-300)))
    kb = torch.tensor(log_b, dtype=torch.float64)
    kr = torch.cummax(torch.tensor(log_r, dtype=torch.float64), 0).values
    return kb, kr


def apply_scale_remap(scale: torch.Tensor, remap: tuple[torch.Tensor, torch.Tensor]) -> torch.Tensor:
    """``b'`` of :func:`fit_scale_remap`'s knots: piecewise linear in ``log b``, the end knots'
    factors held beyond them."""
    kb, kr = (torch.as_tensor(k, dtype=torch.float64).numpy() for k in remap)
    lb = torch.as_tensor(scale, dtype=torch.float64).log()
    shift = np.interp(lb.numpy(), kb, kr - kb)  # the end knots' shifts held beyond them
    return (lb + torch.from_numpy(shift)).exp()


def plot_calibration(tables: dict[str, list[dict]], path: Path, title: str = "") -> None:
    """Predicted vs observed median error per decile (log-log, with the +-20 % band) and the
    ratio per decile, one series per scene set; written to ``path`` (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(11, 4.5))
    lo, hi = math.inf, 0.0
    for name, rows in tables.items():
        pred = [100 * r["predicted"] for r in rows]
        obs = [100 * r["observed"] for r in rows]
        ax0.plot(pred, obs, "o-", label=name)
        ax1.plot(range(1, len(rows) + 1), [r["ratio"] for r in rows], "o-", label=name)
        fin = [v for v in pred + obs if 0 < v < math.inf]
        if fin:
            lo, hi = min(lo, min(fin)), max(hi, max(fin))
    if hi > 0:
        x = [lo / 1.5, hi * 1.5]
        ax0.plot(x, x, "k-", lw=1, label="calibrated")
        ax0.fill_between(x, [v * (1 - CALIBRATION_TOLERANCE) for v in x], [v * (1 + CALIBRATION_TOLERANCE) for v in x],
                         color="0.85", label="+-20 %")
    ax0.set(xscale="log", yscale="log", xlabel="predicted median |relative error| (%)",
            ylabel="observed median |relative error| (%)", title="per confidence decile")
    ax0.legend(fontsize=8)
    ax1.axhspan(1 - CALIBRATION_TOLERANCE, 1 + CALIBRATION_TOLERANCE, color="0.85")
    ax1.axhline(1.0, color="k", lw=1)
    ax1.set(yscale="log", xlabel="confidence decile (1 = least confident)", ylabel="observed / predicted",
            title="calibration ratio (target: inside the band)")
    ax1.legend(fontsize=8)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
