"""Evaluation on held-out procedural planes: per-distance error curves, confidence behaviour.

The scenes come from the configured dataset (``data_synth``) with the ``eval`` options:
by default fronto-parallel planes with textured families, ambient light, the synthesiser's
realistic sensor noise (Poisson-Gaussian, 8-12 bits, dim to bright exposures, gain) and a
PSF shape drawn per sample (Gaussian, pillbox, power-exponential, with diffraction and mild
aberration). Planes are drawn uniformly in inverse depth; tiles are binned by their true
depth into ``bins`` equal depth intervals over the working range. The report compares the
analytic estimate with the refined one:

* median absolute relative depth error per distance bin and overall (tiles in range),
* median error per confidence bin (it should fall as the confidence rises),
* the confidence of texture-less planes' tiles (it should stay below 0.1).

:func:`write_report` writes ``<stem>.json``, ``<stem>.md`` and ``<stem>.png``.
"""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path
from typing import Any

import torch

from tdfd.model import FAMILY_CODES, DFDModel, training_codes

from .config import DataConfig, EvalConfig, ModelConfig, TrainConfig
from .data import fetch_batch, make_dataset
from .losses import depth_relative_error

__all__ = ["collect", "summarise", "evaluate_model", "evaluate_planes", "write_report", "report_markdown",
           "plot_report", "CONF_EDGES"]

logger = logging.getLogger(__name__)

#: Confidence bin edges of the report.
CONF_EDGES = (0.0, 0.1, 0.3, 0.5, 0.7, 0.9, 1.0)


def _signal_e(params: Any) -> float:
    """Mean photo-electrons per pixel of a ``data_synth`` sample (``nan`` if unknown)."""
    try:
        return float(params["target_level"]) * float(params["full_well_e"]) / float(params["gain"])
    except (KeyError, TypeError, ValueError, ZeroDivisionError):
        return float("nan")


def _contrast(params: Any) -> float:
    """Texture contrast of a ``data_synth`` sample (``nan`` when the dataset does not say)."""
    try:
        details = params.get("details")
        details = json.loads(details) if isinstance(details, str) else details
        return float(max(t.get("contrast", float("nan")) for t in details["textures"]))
    except (AttributeError, KeyError, TypeError, ValueError):
        return float("nan")


def _family_id(name: str) -> int:
    """Index of a texture family in :data:`tdfd.textures.TEXTURE_FAMILIES` (-1 if unknown)."""
    from tdfd.textures import TEXTURE_FAMILIES

    names = list(TEXTURE_FAMILIES)
    return names.index(name) if name in names else -1


@torch.no_grad()
def collect(model: DFDModel, dataset: Any, count: int, chunk: int = 8, tell_family: bool = False
            ) -> dict[str, torch.Tensor]:
    """Run the whole model on samples ``0 .. count-1``; per-tile results (flattened).

    With ``tell_family`` (a model with the PSF family input) each Gaussian or pillbox sample
    is told its own family (:func:`tdfd.model.training_codes` with every sample told);
    otherwise the model's own family (the saved model's: unknown).

    Returns:
        ``true``, ``refined``, ``analytic`` depths (m), ``confidence``, and per tile the
        sample's texture ``contrast``, mean photo-electrons ``signal_e`` and PSF shape id (``psf``: 0 Gaussian, 1 pillbox,
        2 other).
    """
    model = model.eval()
    out: dict[str, list[torch.Tensor]] = {k: [] for k in ("true", "refined", "analytic", "confidence", "contrast",
                                                         "signal_e", "psf", "family")}
    for start in range(0, count, chunk):
        batch = fetch_batch(dataset, list(range(start, min(count, start + chunk))))
        n = batch["image_f1"].shape[0]
        params = batch.get("params") or [{}] * n
        params = params if isinstance(params, list) else [{}] * n
        codes = training_codes(params, 1.0) if tell_family else None
        r = model.analyse(batch["image_f1"].float(), batch["image_f2"].float(), codes)
        (depth, conf), depth_a = r.depth_map, r.depth_analytic  # the pooled map when the model pools
        tiles = depth[0].numel()
        out["true"].append(batch["tile_depth"].float().flatten())
        out["refined"].append(depth.flatten())
        out["analytic"].append(depth_a.flatten())
        out["confidence"].append(conf.flatten())
        out["contrast"].append(torch.tensor([_contrast(p) for p in params]).repeat_interleave(tiles))
        out["signal_e"].append(torch.tensor([_signal_e(p) for p in params]).repeat_interleave(tiles))
        shapes = [str(p.get("psf_shape", "")) if isinstance(p, dict) else "" for p in params]
        out["psf"].append(torch.tensor([{"gaussian": 0, "pillbox": 1}.get(s, 2) for s in shapes]).repeat_interleave(tiles))
        fams = [str(p.get("texture_families", "")).split(",")[0] if isinstance(p, dict) else "" for p in params]
        out["family"].append(torch.tensor([_family_id(f) for f in fams]).repeat_interleave(tiles))
    return {k: torch.cat(v) for k, v in out.items()}


def _spearman(a: torch.Tensor, b: torch.Tensor) -> float:
    """Spearman rank correlation of two 1-D tensors (``nan`` if fewer than 3 values)."""
    if a.numel() < 3:
        return float("nan")
    ra = torch.argsort(torch.argsort(a)).double()
    rb = torch.argsort(torch.argsort(b)).double()
    ra, rb = ra - ra.mean(), rb - rb.mean()
    return float((ra * rb).sum() / (ra.norm() * rb.norm()).clamp_min(1e-12))


def _median(x: torch.Tensor) -> float | None:
    return float(x.median()) if x.numel() else None


def summarise(tiles: dict[str, torch.Tensor], camera_range: tuple[float, float], bins: int,
              textureless_conf: torch.Tensor | None = None, min_contrast: float = 0.0,
              min_signal_e: float = 0.0) -> dict[str, Any]:
    """Per-distance, per-confidence and texture-less statistics from :func:`collect` output.

    Subsets reported besides all tiles: planes with texture contrast >= ``min_contrast``
    (if > 0), those also with >= ``min_signal_e`` mean photo-electrons (if > 0), and tiles
    with confidence >= 0.5.
    """
    near, far = camera_range
    t = tiles["true"]
    in_range = (t >= near) & (t <= far)
    er = depth_relative_error(tiles["refined"], t)
    ea = depth_relative_error(tiles["analytic"], t)
    c = tiles["confidence"]
    per_distance = []
    edges = [near + (far - near) * i / bins for i in range(bins + 1)]
    for k, (lo, hi) in enumerate(zip(edges[:-1], edges[1:])):
        m = (t >= lo) & ((t < hi) if k < bins - 1 else (t <= hi))
        per_distance.append({"depth_lo_m": round(lo, 4), "depth_hi_m": round(hi, 4), "depth_m": round(0.5 * (lo + hi), 4),
                             "tiles": int(m.sum()), "mre_analytic": _median(ea[m]), "mre_refined": _median(er[m]),
                             "bias_analytic": _median(((tiles["analytic"] - t) / t)[m]),
                             "bias_refined": _median(((tiles["refined"] - t) / t)[m]), "conf_median": _median(c[m])})
    conf_bins = []
    for lo, hi in zip(CONF_EDGES[:-1], CONF_EDGES[1:]):
        m = in_range & (c >= lo) & ((c < hi) if hi < 1.0 else (c <= hi))
        n = int(m.sum())
        conf_bins.append({"conf_lo": lo, "conf_hi": hi, "tiles": n, "mre_refined": _median(er[m]),
                          "p90_refined": float(er[m].quantile(0.9)) if n else None})
    filled = [b for b in conf_bins if b["tiles"] >= 20]
    monotone = all(a["mre_refined"] >= b["mre_refined"] for a, b in zip(filled[:-1], filled[1:]))
    rho = _spearman(c[in_range], er[in_range])
    overall_r, overall_a = _median(er[in_range]), _median(ea[in_range])
    by_bin_r = [r["mre_refined"] for r in per_distance if r["mre_refined"] is not None]
    by_bin_a = [r["mre_analytic"] for r in per_distance if r["mre_analytic"] is not None]
    summary: dict[str, Any] = {
        "tiles": int(in_range.sum()), "mre_refined": overall_r, "mre_analytic": overall_a,
        "improvement": (overall_a / max(overall_r, 1e-12)) if overall_r is not None else None,
        "mean_of_bins_refined": sum(by_bin_r) / len(by_bin_r) if by_bin_r else None,
        "mean_of_bins_analytic": sum(by_bin_a) / len(by_bin_a) if by_bin_a else None,
        "worst_bin_refined": max(by_bin_r) if by_bin_r else None,
        "error_falls_with_confidence": bool(rho < 0 and filled and filled[0]["mre_refined"] > filled[-1]["mre_refined"]),
        "confidence_bins_monotone": bool(monotone),
        "spearman_conf_error": rho,
    }
    by_psf = {}
    for pid, name in ((0, "gaussian"), (1, "pillbox"), (2, "other")):
        m = in_range & (tiles["psf"] == pid)
        if int(m.sum()):
            by_psf[name] = {"tiles": int(m.sum()), "mre_refined": _median(er[m]), "mre_analytic": _median(ea[m])}
    by_family = {}
    if "family" in tiles:
        from tdfd.textures import TEXTURE_FAMILIES

        for fid, name in enumerate(TEXTURE_FAMILIES):
            m = in_range & (tiles["family"] == fid)
            if int(m.sum()):
                by_family[name] = {"tiles": int(m.sum()), "mre_refined": _median(er[m]), "mre_analytic": _median(ea[m])}
    result: dict[str, Any] = {"per_distance": per_distance, "confidence_bins": conf_bins, "by_psf": by_psf,
                              "by_family": by_family, "summary": summary}
    subsets = []
    if min_contrast > 0:
        subsets.append((f"texture contrast >= {min_contrast:g}", tiles["contrast"] >= min_contrast))
        if min_signal_e > 0:
            subsets.append((f"texture contrast >= {min_contrast:g} and >= {min_signal_e:g} e- per pixel",
                            (tiles["contrast"] >= min_contrast) & (tiles["signal_e"] >= min_signal_e)))
    subsets.append(("confidence >= 0.5", c >= 0.5))
    result["subsets"] = []
    for name, sel in subsets:
        m = in_range & sel
        n = int(m.sum())
        r, a = _median(er[m]), _median(ea[m])
        result["subsets"].append({"name": name, "tiles": n, "fraction": n / max(1, int(in_range.sum())),
                                  "mre_refined": r, "mre_analytic": a,
                                  "improvement": (a / max(r, 1e-12)) if n else None})
    if textureless_conf is not None and textureless_conf.numel():
        tc = textureless_conf
        result["textureless"] = {"tiles": int(tc.numel()), "conf_median": float(tc.median()), "conf_max": float(tc.max()),
                                 "conf_p99": float(tc.quantile(0.99)), "frac_below_0.1": float((tc < 0.1).float().mean())}
        summary["textureless_conf_max"] = result["textureless"]["conf_max"]
        summary["textureless_frac_below_0.1"] = result["textureless"]["frac_below_0.1"]
    return result


def evaluate_model(model: DFDModel, data: DataConfig, model_cfg: ModelConfig, ev: EvalConfig) -> dict[str, Any]:
    """Evaluate ``model`` on held-out planes (see the module docstring)."""
    opts = DataConfig(**{**data.__dict__, "options": dict(ev.options)})
    ds = make_dataset(opts, model_cfg, ev.seed, ev.height, ev.width)
    tiles = collect(model, ds, ev.samples)
    tconf = None
    if ev.textureless_samples:
        topts = DataConfig(**{**data.__dict__, "options": dict(ev.textureless_options)})
        tds = make_dataset(topts, model_cfg, ev.seed + 1, ev.height, ev.width)
        tt = collect(model, tds, ev.textureless_samples)
        tconf = tt["confidence"]
    result = summarise(tiles, model.camera.depth_range_m, ev.bins, tconf, ev.min_contrast, ev.min_signal_e)
    if model.psf_family_input:  # the same planes, each Gaussian or pillbox one told its family
        told = summarise(collect(model, ds, ev.samples, tell_family=True), model.camera.depth_range_m, ev.bins)
        result["by_psf_told"] = {k: v for k, v in told["by_psf"].items() if k in FAMILY_CODES}
    result["setup"] = {"samples": ev.samples, "textureless_samples": ev.textureless_samples, "seed": ev.seed,
                       "height": ev.height, "width": ev.width, "options": ev.options,
                       "textureless_options": ev.textureless_options, "dataset": data.dataset}
    return result


def evaluate_planes(model: DFDModel, cfg: TrainConfig) -> dict[str, Any]:
    """:func:`evaluate_model` with the sections of a training config."""
    return evaluate_model(model, cfg.data, cfg.model, cfg.eval)


# ----------------------------------------------------------------------------- report
def _pct(v: Any) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "–"
    return f"{100 * v:.2f} %"


def report_markdown(result: dict[str, Any], plot_name: str | None = None) -> str:
    """The evaluation as Markdown (errors in percent)."""
    s = result["summary"]
    lines = [f"Median absolute relative depth error over {s['tiles']} tiles in range: "
             f"**refined {_pct(s['mre_refined'])}**, analytic {_pct(s['mre_analytic'])} "
             f"({s['improvement']:.2f}x lower). Mean of the per-distance medians: refined "
             f"{_pct(s['mean_of_bins_refined'])}, analytic {_pct(s['mean_of_bins_analytic'])}.", ""]
    if result.get("subsets"):
        lines += ["| subset (tiles in range) | tiles | share | analytic | refined | improvement |", "|---|---|---|---|---|---|"]
        for sub in result["subsets"]:
            imp = "–" if sub["improvement"] is None else f"{sub['improvement']:.2f}x"
            lines.append(f"| {sub['name']} | {sub['tiles']} | {100 * sub['fraction']:.0f} % | {_pct(sub['mre_analytic'])} | "
                         f"{_pct(sub['mre_refined'])} | {imp} |")
        lines.append("")
    lines += ["| distance (m) | tiles | analytic | refined | analytic bias | refined bias | median conf |",
              "|---|---|---|---|---|---|---|"]
    for r in result["per_distance"]:
        conf = "–" if r["conf_median"] is None else f"{r['conf_median']:.3f}"
        lines.append(f"| {r['depth_lo_m']:.2f}–{r['depth_hi_m']:.2f} | {r['tiles']} | {_pct(r['mre_analytic'])} | "
                     f"{_pct(r['mre_refined'])} | {_pct(r['bias_analytic'])} | {_pct(r['bias_refined'])} | {conf} |")
    if result.get("by_psf"):
        told = result.get("by_psf_told")
        if told is None:
            lines += ["", "| PSF shape | tiles | analytic | refined |", "|---|---|---|---|"]
        else:
            lines += ["", "| PSF shape | tiles | analytic | refined (family unknown) | refined, told the family |",
                      "|---|---|---|---|---|"]
        for name, r in result["by_psf"].items():
            row = f"| {name} | {r['tiles']} | {_pct(r['mre_analytic'])} | {_pct(r['mre_refined'])} |"
            if told is not None:
                row += f" {_pct(told[name]['mre_refined']) if name in told else '–'} |"
            lines.append(row)
    if result.get("by_family"):
        lines += ["", "| texture family (first texture of the plane) | tiles | analytic | refined |", "|---|---|---|---|"]
        for name, r in result["by_family"].items():
            lines.append(f"| {name} | {r['tiles']} | {_pct(r['mre_analytic'])} | {_pct(r['mre_refined'])} |")
    lines += ["", "| confidence | tiles | refined median error | refined 90th percentile |", "|---|---|---|---|"]
    for b in result["confidence_bins"]:
        lines.append(f"| {b['conf_lo']:.1f}–{b['conf_hi']:.1f} | {b['tiles']} | {_pct(b['mre_refined'])} | {_pct(b['p90_refined'])} |")
    lines += ["", f"Error falls as confidence rises: {'yes' if s['error_falls_with_confidence'] else 'NO'} (Spearman rank "
              f"correlation of confidence and error {s['spearman_conf_error']:.2f}; median error monotone over the bins "
              f"with >= 20 tiles: {'yes' if s['confidence_bins_monotone'] else 'no'})."]
    t = result.get("textureless")
    if t:
        lines += [f"Texture-less planes ({t['tiles']} tiles): confidence median {t['conf_median']:.4f}, 99th percentile "
                  f"{t['conf_p99']:.4f}, max {t['conf_max']:.4f}; {100 * t['frac_below_0.1']:.1f} % of tiles below 0.1."]
    if plot_name:
        lines += ["", f"![refinement error]({plot_name})"]
    return "\n".join(lines) + "\n"


def plot_report(result: dict[str, Any], path: Path, title: str = "") -> None:
    """Per-distance error curves (analytic vs refined) and error per confidence bin, as PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FormatStrFormatter

    rows = [r for r in result["per_distance"] if r["mre_refined"] is not None]
    d = [r["depth_m"] for r in rows]
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4))
    ax1.semilogy(d, [100 * r["mre_analytic"] for r in rows], "o-", label="analytic")
    ax1.semilogy(d, [100 * r["mre_refined"] for r in rows], "s-", label="refined (CNN)")
    ax1.axhline(1.0, color="grey", ls="--", lw=0.8, label="1 % target")
    ax1.set_xlabel("true depth (m), bin centres")
    ax1.set_ylabel("median |relative depth error| (%)")
    ax1.legend()
    ax1.grid(True, which="both", alpha=0.3)
    ax1.set_title("error per distance (textured planes)")
    bins = [b for b in result["confidence_bins"] if b["tiles"]]
    labels = [f"{b['conf_lo']:.1f}–{b['conf_hi']:.1f}\n({b['tiles']})" for b in bins]
    ax2.bar(range(len(bins)), [100 * b["mre_refined"] for b in bins], color="tab:orange")
    ax2.set_xticks(range(len(bins)), labels, fontsize=8)
    ax2.set_yscale("log")
    ax2.set_xlabel("confidence bin (tiles)")
    ax2.set_ylabel("refined median |rel. error| (%)")
    t = result.get("textureless")
    ax2.set_title("error vs confidence" + (f"; texture-less conf max {t['conf_max']:.3f}" if t else ""))
    ax2.grid(True, axis="y", which="both", alpha=0.3)
    for ax in (ax1, ax2):
        ax.yaxis.set_major_formatter(FormatStrFormatter("%g"))
        ax.yaxis.set_minor_formatter(FormatStrFormatter("%g"))
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def write_report(result: dict[str, Any], stem: Path, title: str = "Refinement evaluation") -> tuple[Path, Path, Path]:
    """Write ``<stem>.json``, ``<stem>.md`` (with the plot linked) and ``<stem>.png``."""
    stem = Path(stem)
    stem.parent.mkdir(parents=True, exist_ok=True)
    js, md, png = (stem.with_name(stem.name + ext) for ext in (".json", ".md", ".png"))
    js.write_text(json.dumps(result, indent=2, sort_keys=True) + "\n")
    plot_report(result, png, title)
    md.write_text(f"# {title}\n\n" + report_markdown(result, png.name))
    return js, md, png
