"""Does the confidence state an uncertainty? The predicted error scale against the observed error, per confidence decile.

The model predicts, per tile, a Laplace scale ``b`` of the relative inverse-depth error
``e = (q - q_true) / q_true`` (:mod:`tdfd.model.combined`; from a confidence,
:func:`benchmarks.depth_models.predicted_scale`). The tiles are split into ten equal-count
bins by confidence (deciles); in each, the median ``|e|`` observed is compared with the median
that the predicted Laplace errors would give (:func:`laplace_mixture_median`: the tiles of a
decile have different ``b``, so their errors are a mixture). Calibrated: the ratio observed /
predicted is 1, and half of the tiles have ``|e|`` at most their own predicted median
``b ln 2``. The shipped model's ``b`` is calibrated after training
(:mod:`tdfd.model.scale_calibration`); a decile's ratio carries the sampling error of the
scenes behind it (:func:`scene_bootstrap`).
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from pathlib import Path

import torch

from tdfd.errors import InputError
from tdfd.model.scale_calibration_fit import laplace_mixture_median

__all__ = ["laplace_mixture_median", "decile_table", "scene_bootstrap", "resample_scenes", "plot_calibration",
           "outside_band", "worst_decile", "CALIBRATION_TOLERANCE"]

#: the target: observed / predicted within 20 % in every decile (issue 19)
CALIBRATION_TOLERANCE = 0.2


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


def outside_band(row: dict) -> bool:
    """A :func:`decile_table` row (with its ``ratio_se``) outside the 20 % band by more than two
    standard errors."""
    gap = max(row["ratio"] - (1 + CALIBRATION_TOLERANCE), (1 - CALIBRATION_TOLERANCE) - row["ratio"])
    return gap > 2 * row["ratio_se"]


def worst_decile(table: list[dict]) -> int:
    """The index of the :func:`decile_table` row whose ratio is farthest from 1 (in ``log``; a ratio
    of 0 or ``inf`` first)."""
    return max(range(len(table)),
               key=lambda k: abs(math.log(table[k]["ratio"])) if 0 < table[k]["ratio"] < math.inf else math.inf)


def scene_bootstrap(confidence: torch.Tensor, scale: torch.Tensor, error: torch.Tensor, scene: torch.Tensor,
                    bins: int = 10, reps: int = 200, seed: int = 0) -> torch.Tensor:
    """Standard error of each bin's observed / predicted ratio, resampling whole scenes.

    A scene's tiles share its texture, PSF and noise, so their errors are correlated; the
    bootstrap draws scenes with replacement (``reps`` times, a seeded generator) and
    recomputes :func:`decile_table` on their tiles.

    Args:
        confidence, scale, error: as :func:`decile_table`, ``(N,)``.
        scene: ``(N,)`` scene identifier per tile.
        bins: as :func:`decile_table`.
        reps: bootstrap resamples (>= 2).
        seed: the generator's seed.

    Returns:
        ``(bins,)`` float64 standard deviations of the ratio over the resamples.

    Raises:
        InputError: shapes differ, ``reps < 2`` or fewer than two scenes.
    """
    sc = torch.as_tensor(scene).flatten()
    if sc.numel() != torch.as_tensor(confidence).numel():
        raise InputError(f"scene must have one value per tile, got {sc.numel()} for {torch.as_tensor(confidence).numel()}")
    if reps < 2 or torch.unique(sc).numel() < 2:
        raise InputError(f"need reps >= 2 and at least two scenes, got {reps} and {torch.unique(sc).numel()}")
    ratios = [[r["ratio"] for r in decile_table(confidence[idx], scale[idx], error[idx], bins)]
              for idx in resample_scenes(sc, reps, torch.Generator().manual_seed(seed))]
    return torch.tensor(ratios, dtype=torch.float64).std(0)


def resample_scenes(scene: torch.Tensor, reps: int, generator: torch.Generator) -> Iterator[torch.Tensor]:
    """Bootstrap resamples of whole scenes: ``reps`` times, as many scenes as there are drawn
    with replacement, each resample the indices of their tiles (a scene drawn twice, twice).

    Args:
        scene: ``(N,)`` scene identifier per tile.
        reps: number of resamples.
        generator: the random source.

    Example:
        >>> [t.tolist() for t in resample_scenes(torch.tensor([7, 7, 9]), 2, torch.Generator().manual_seed(1))]
        [[2, 2], [0, 1, 0, 1]]
    """
    ids, inverse = torch.unique(torch.as_tensor(scene).flatten(), return_inverse=True)
    members = [torch.nonzero(inverse == k).flatten() for k in range(ids.numel())]
    for _ in range(reps):
        pick = torch.randint(ids.numel(), (ids.numel(),), generator=generator)
        yield torch.cat([members[int(k)] for k in pick])


def plot_calibration(tables: dict[str, list[dict]], path: Path, title: str = "") -> None:
    """Predicted vs observed median error per decile (log-log, with the +-20 % band) and the
    ratio per decile with its standard error (a row's ``ratio_se`` when present), one series
    per scene set (dashed: names starting "CNN's own scale"); written to ``path`` (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(11, 5.5))
    lo, hi = math.inf, 0.0
    for name, rows in tables.items():
        pred = [100 * r["predicted"] for r in rows]
        obs = [100 * r["observed"] for r in rows]
        style = "o--" if name.startswith("CNN's own scale") else "o-"
        ax0.plot(pred, obs, style, label=name)
        ax1.errorbar(range(1, len(rows) + 1), [r["ratio"] for r in rows], yerr=[r.get("ratio_se", 0.0) for r in rows],
                     fmt=style, capsize=2, label=name)
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
    ax0.legend(fontsize=7)
    ax1.axhspan(1 - CALIBRATION_TOLERANCE, 1 + CALIBRATION_TOLERANCE, color="0.85")
    ax1.axhline(1.0, color="k", lw=1)
    ax1.set(yscale="log", xlabel="confidence decile (1 = least confident)", ylabel="observed / predicted",
            title="calibration ratio (target: inside the band)")
    ax1.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.14), ncol=2)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
