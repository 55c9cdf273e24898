"""Evaluation on held-out procedural planes: per-distance error curves, confidence behaviour.

Scenes are fronto-parallel textured planes at fixed distances across the working range,
rendered with a PSF shape drawn per sample (Gaussian, pillbox or a power-exponential in
between) and realistic sensor noise, plus texture-less planes for the confidence check. The
report compares the analytic estimate with the refined one:

* median absolute relative depth error per distance and overall,
* median error per confidence bin (it should fall as the confidence rises),
* the confidence of texture-less tiles (it should stay below 0.1).

``write_report`` writes ``<stem>.json``, ``<stem>.md`` and ``<stem>.png``.
"""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path
from typing import Any, Sequence

import torch

from tdfd.model import DFDModel

from .config import TrainConfig
from .losses import depth_relative_error

__all__ = ["plane_pairs", "evaluate_planes", "evaluate_model", "write_report", "CONF_EDGES"]

logger = logging.getLogger(__name__)

#: Confidence bin edges of the report.
CONF_EDGES = (0.0, 0.1, 0.3, 0.5, 0.7, 0.9, 1.0)


#: Texture families of the "textured plane" scenes (every family but the near-uniform ones).
TEXTURED_FAMILIES = ("fractal", "bandlimited", "voronoi", "dead_leaves", "stripes", "checkers", "dots",
                     "line_art", "glyphs")


def plane_pairs(model: DFDModel, depth_m: float, count: int, seed: int, height: int, width: int,
                textureless: bool = False) -> tuple[torch.Tensor, torch.Tensor, list[str]]:
    """``count`` noisy image pairs of a fronto-parallel plane at ``depth_m`` (held-out scenes).

    Each sample draws a texture (:func:`tdfd.textures.random_texture` over
    :data:`TEXTURED_FAMILIES`, albedo in [0.3, 0.9], contrast log-uniform in [0.1, 1]; the
    ``flat`` family if ``textureless``), a PSF shape (Gaussian, pillbox or a
    power-exponential with beta in [3, 8], one third each), an exposure in [0.3, 0.9] and a
    sensor (:class:`tdfd.sensor.SensorModel`: full well 4000-20000 e-, read noise 2-6 e-,
    12 bits, black level 64 codes).

    Returns:
        ``(image_f1, image_f2, psf_names)``; images ``(count, 1, height, width)``.
    """
    from tdfd.optics import render_pair
    from tdfd.sensor import SensorModel
    from tdfd.textures import random_texture

    cam = model.camera
    g = torch.Generator().manual_seed(int(seed))
    i1s, i2s, names = [], [], []
    for _ in range(count):
        if textureless:
            tex, _p = random_texture(g, (height, width), family="flat", albedo=(0.3, 0.9))
        else:
            tex, _p = random_texture(g, (height, width), families=TEXTURED_FAMILIES, albedo=(0.3, 0.9), contrast=(0.1, 1.0))
        u = torch.rand(5, generator=g).tolist()
        kind = int(torch.randint(3, (), generator=g))
        shape: Any = ["gaussian", "pillbox", 3.0 + 5.0 * u[0]][kind]
        depth = torch.full((1, 1, height, width), float(depth_m))
        i1, i2 = render_pair(cam, tex.float(), depth, shape=shape)
        sensor = SensorModel(full_well_e=4000.0 + 16000.0 * u[1], read_noise_e=2.0 + 4.0 * u[2], bits=12,
                             black_level_dn=64.0, exposure=0.3 + 0.6 * u[3])
        frames = sensor(torch.cat([i1, i2], 1), generator=g)
        i1s.append(frames[:, 0:1])
        i2s.append(frames[:, 1:2])
        names.append(shape if isinstance(shape, str) else f"beta={shape:.1f}")
    return torch.cat(i1s), torch.cat(i2s), names


@torch.no_grad()
def _run(model: DFDModel, i1: torch.Tensor, i2: torch.Tensor, chunk: int = 16) -> tuple[torch.Tensor, ...]:
    outs = [model(i1[k : k + chunk], i2[k : k + chunk]) for k in range(0, len(i1), chunk)]
    return tuple(torch.cat([o[j] for o in outs]) for j in range(3))


def evaluate_model(model: DFDModel, distances: Sequence[float], samples_per_distance: int, seed: int,
                   height: int, width: int, textureless_samples: int | None = None) -> dict[str, Any]:
    """Evaluate ``model`` on held-out planes (see the module docstring).

    Returns:
        A dict with ``per_distance`` rows, ``confidence_bins`` rows, ``textureless`` stats
        and a ``summary`` (overall medians, improvement factor, confidence checks).
    """
    model = model.eval()
    per_distance, all_r, all_a, all_c = [], [], [], []
    for k, d in enumerate(distances):
        i1, i2, _ = plane_pairs(model, d, samples_per_distance, seed + 7919 * k, height, width)
        depth, conf, depth_a = _run(model, i1, i2)
        er = depth_relative_error(depth, torch.full_like(depth, d)).flatten()
        ea = depth_relative_error(depth_a, torch.full_like(depth, d)).flatten()
        per_distance.append({"depth_m": round(float(d), 4), "tiles": int(er.numel()),
                             "mre_analytic": float(ea.median()), "mre_refined": float(er.median()),
                             "bias_analytic": float(((depth_a - d) / d).median()),
                             "bias_refined": float(((depth - d) / d).median()),
                             "conf_median": float(conf.median())})
        all_r.append(er)
        all_a.append(ea)
        all_c.append(conf.flatten())
    er, ea, c = torch.cat(all_r), torch.cat(all_a), torch.cat(all_c)
    bins = []
    for lo, hi in zip(CONF_EDGES[:-1], CONF_EDGES[1:]):
        m = (c >= lo) & ((c < hi) if hi < 1.0 else (c <= hi))
        n = int(m.sum())
        bins.append({"conf_lo": lo, "conf_hi": hi, "tiles": n,
                     "mre_refined": float(er[m].median()) if n else None,
                     "p90_refined": float(er[m].quantile(0.9)) if n else None})
    # texture-less planes spread over the range
    nt = textureless_samples if textureless_samples is not None else max(2, samples_per_distance // 2)
    tl_conf = []
    for k, d in enumerate(distances):
        i1, i2, _ = plane_pairs(model, d, nt, seed + 104729 + 7919 * k, height, width, textureless=True)
        tl_conf.append(_run(model, i1, i2)[1].flatten())
    tc = torch.cat(tl_conf)
    textureless = {"tiles": int(tc.numel()), "conf_median": float(tc.median()), "conf_max": float(tc.max()),
                   "frac_below_0.1": float((tc < 0.1).float().mean())}
    filled = [b for b in bins if b["tiles"] >= 20]
    monotone = all(a["mre_refined"] >= b["mre_refined"] for a, b in zip(filled[:-1], filled[1:]))
    overall_r, overall_a = float(er.median()), float(ea.median())
    summary = {"mre_refined": overall_r, "mre_analytic": overall_a,
               "improvement": overall_a / max(overall_r, 1e-12),
               "worst_distance_mre_refined": max(r["mre_refined"] for r in per_distance),
               "error_falls_with_confidence": bool(monotone),
               "textureless_conf_max": textureless["conf_max"],
               "textureless_frac_below_0.1": textureless["frac_below_0.1"],
               "tiles": int(er.numel())}
    return {"per_distance": per_distance, "confidence_bins": bins, "textureless": textureless, "summary": summary,
            "setup": {"distances_m": [float(d) for d in distances], "samples_per_distance": samples_per_distance,
                      "seed": seed, "height": height, "width": width}}


def evaluate_planes(model: DFDModel, cfg: TrainConfig) -> dict[str, Any]:
    """:func:`evaluate_model` with the ``eval`` section of a training config."""
    near, far = model.camera.depth_range_m
    n = cfg.eval.distances
    distances = [near + (far - near) * i / (n - 1) for i in range(n)]
    return evaluate_model(model, distances, cfg.eval.samples_per_distance, cfg.eval.seed, cfg.eval.height, cfg.eval.width)


def _fmt(v: Any) -> str:
    if v is None:
        return "–"
    if isinstance(v, float):
        return f"{100 * v:.2f} %"
    return str(v)


def report_markdown(result: dict[str, Any], plot_name: str | None = None) -> str:
    """The evaluation as Markdown tables (errors in percent)."""
    s = result["summary"]
    lines = [f"Overall median absolute relative depth error: **refined {_fmt(s['mre_refined'])}**, "
             f"analytic {_fmt(s['mre_analytic'])} ({s['improvement']:.1f}x lower), over {s['tiles']} tiles.", "",
             "| distance (m) | tiles | analytic | refined | analytic bias | refined bias | median conf |",
             "|---|---|---|---|---|---|---|"]
    for r in result["per_distance"]:
        lines.append(f"| {r['depth_m']:.3f} | {r['tiles']} | {_fmt(r['mre_analytic'])} | {_fmt(r['mre_refined'])} | "
                     f"{_fmt(r['bias_analytic'])} | {_fmt(r['bias_refined'])} | {r['conf_median']:.3f} |")
    lines += ["", "| confidence | tiles | refined median error | refined 90th pct |", "|---|---|---|---|"]
    for b in result["confidence_bins"]:
        lines.append(f"| {b['conf_lo']:.1f}–{b['conf_hi']:.1f} | {b['tiles']} | {_fmt(b['mre_refined'])} | {_fmt(b['p90_refined'])} |")
    t = result["textureless"]
    lines += ["", f"Texture-less planes ({t['tiles']} tiles): median confidence {t['conf_median']:.4f}, "
                  f"max {t['conf_max']:.4f}, {100 * t['frac_below_0.1']:.1f} % below 0.1."]
    if plot_name:
        lines += ["", f"![refinement error]({plot_name})"]
    return "\n".join(lines) + "\n"


def plot_report(result: dict[str, Any], path: Path, title: str = "") -> None:
    """Per-distance error curves (analytic vs refined) and error per confidence bin, as PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = result["per_distance"]
    d = [r["depth_m"] for r in rows]
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4))
    ax1.semilogy(d, [100 * r["mre_analytic"] for r in rows], "o-", label="analytic")
    ax1.semilogy(d, [100 * r["mre_refined"] for r in rows], "s-", label="refined")
    ax1.axhline(1.0, color="grey", ls="--", lw=0.8, label="1 % target")
    ax1.set_xlabel("plane distance (m)")
    ax1.set_ylabel("median |relative depth error| (%)")
    ax1.legend()
    ax1.grid(True, which="both", alpha=0.3)
    ax1.set_title("error per distance")
    bins = [b for b in result["confidence_bins"] if b["tiles"]]
    labels = [f"{b['conf_lo']:.1f}–{b['conf_hi']:.1f}\n({b['tiles']})" for b in bins]
    ax2.bar(range(len(bins)), [100 * b["mre_refined"] for b in bins], color="tab:orange")
    ax2.set_xticks(range(len(bins)), labels, fontsize=8)
    ax2.set_yscale("log")
    ax2.set_xlabel("confidence bin (tiles)")
    ax2.set_ylabel("refined median |rel. error| (%)")
    t = result["textureless"]
    ax2.set_title(f"error vs confidence; texture-less conf max {t['conf_max']:.3f}")
    ax2.grid(True, axis="y", which="both", alpha=0.3)
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
    js.write_text(json.dumps(result, indent=2, sort_keys=True, default=lambda o: None if isinstance(o, float) and math.isnan(o) else o) + "\n")
    plot_report(result, png, title)
    md.write_text(f"# {title}\n\n" + report_markdown(result, png.name))
    return js, md, png
