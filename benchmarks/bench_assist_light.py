"""Active DFD autofocus on the simulated bench: coherent light, projector, no light (paper Fig. 10 as autofocus).

Run from the repository root:

    .venv/bin/python -m benchmarks.bench_assist_light                 # 100 targets per configuration
    .venv/bin/python -m benchmarks.bench_assist_light --trials 40     # fewer (the 2-core machine)
    .venv/bin/python -m benchmarks.bench_assist_light --quick         # 10 targets, a smoke run

Texture-less targets (a uniform grey plane, albedo 0.5, with sensor noise) across 0.3-1.0 m
(stratified, uniform in inverse depth): the DFD controller with the bench's assist light
(:class:`tdfd.light.SimulatedLight`: the paper's mask, two 6.2 x 18.9 mm bars, from the
coherent module or from the projector focused at 56.8 cm with the paper's depth of field)
or without one, side by side, on the same targets. The same for ``Camera.preset("paper")``
(with the analytic estimator: the shipped model is built for the reference camera).
Then textured targets (the autofocus benchmark's texture families) with the light allowed
and without it, and the ambient-subtraction measurement (the lit frames with and without
the ambient frame subtracted). Writes the ``assist_light`` section of docs/BENCHMARKS.md,
the reports to ``out/assist_light/`` and the figure ``docs/assist_light.png``.
"""

from __future__ import annotations

import argparse
import logging
import statistics
import sys
import time
from pathlib import Path
from typing import Any

from .report import markdown_table, update_section

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "out" / "assist_light"
FIGURE = ROOT / "docs" / "assist_light.png"

log = logging.getLogger("bench_assist_light")

#: the analytic estimator's grid for the 4x-binned paper camera (px): its blur radius reaches 64 binned px.
PAPER_TILE, PAPER_STRIDE = 128, 32

HEADER = ["camera", "targets", "light", "in focus (blur < 1 px)", "in focus with <= 3 frames", "frames median / max",
          "bench time ms median / max", "residual blur px median / max", "lit trials", "declared focus, blur >= 1 px",
          "contrast fall-backs"]


def _fmt(x: Any, spec: str = ".1f") -> str:
    return "-" if x is None else format(x, spec)


def summarise(recs: list) -> dict:
    """The figures of one configuration."""
    n = len(recs)
    ok = [r for r in recs if r.in_focus]
    ok3 = [r for r in ok if r.frames <= 3]
    times = [r.time_ms for r in recs if r.status == "focused" and r.time_ms is not None]
    blur = [r.residual_blur_px for r in recs if r.residual_blur_px is not None]
    wrong = [r for r in recs if r.status == "focused" and r.residual_blur_px is not None and r.residual_blur_px >= 1.0]
    return {"n": n, "in_focus": len(ok), "in_focus_3": len(ok3), "frames": [r.frames for r in recs], "times": times,
            "blur": blur, "lit": sum(1 for r in recs if r.extra.get("light")), "wrong": len(wrong),
            "fallback": sum(1 for r in recs if r.method != r.requested)}


def row(camera: str, targets: str, light: str, s: dict) -> list[str]:
    n = s["n"]
    return [camera, targets, light, f"{s['in_focus']}/{n} ({100 * s['in_focus'] / n:.0f} %)",
            f"{s['in_focus_3']}/{n} ({100 * s['in_focus_3'] / n:.0f} %)",
            f"{statistics.median(s['frames']):g} / {max(s['frames'])}",
            f"{_fmt(statistics.median(s['times']) if s['times'] else None)} / {_fmt(max(s['times']) if s['times'] else None)}",
            f"{statistics.median(s['blur']):.2f} / {max(s['blur']):.2f}", str(s["lit"]), str(s["wrong"]),
            str(s["fallback"])]


def failures(recs: list, label: str) -> list[str]:
    out = []
    for r in recs:
        if r.in_focus and r.frames <= 3:
            continue
        what = ("out of focus" if r.status == "focused" and not r.in_focus else
                "failed" if r.status != "focused" else f"{r.frames} frames")
        out.append(f"{label}, {r.target_depth_m:.3f} m: {what}; estimate {_fmt(r.estimated_depth_m, '.3f')} m, blur "
                   f"{_fmt(r.residual_blur_px, '.2f')} px, {r.frames} frames, {r.method}"
                   + (f"; {r.reason}" if r.reason else ""))
    return out


def plot(results: dict[str, list], path: Path) -> None:
    """Residual blur against target distance per light (reference camera, texture-less targets)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.5, 4.2))
    marks = {"coherent": ("o", "tab:red"), "projector": ("s", "tab:blue"), "none": ("x", "0.4")}
    for name, recs in results.items():
        m, c = marks.get(name, ("+", "k"))
        xs = [r.target_depth_m * 100 for r in recs]
        ys = [max(r.residual_blur_px, 1e-3) for r in recs]
        ax.scatter(xs, ys, marker=m, color=c, s=16, label=f"{name} ({sum(1 for r in recs if r.in_focus and r.frames <= 3)}"
                   f"/{len(recs)} in focus, <= 3 frames)", alpha=0.8)
    ax.axhline(1.0, color="k", lw=0.8, ls="--")
    ax.axvspan(44.3, 73.3, color="tab:blue", alpha=0.07, label="projector depth of field (44.3-73.3 cm)")
    ax.set_yscale("log")
    ax.set_xlabel("target distance (cm)")
    ax.set_ylabel("residual blur radius at focus (px)")
    ax.set_title("Texture-less targets, reference camera: DFD autofocus with an assist light")
    ax.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)


def paper_summary(recs: list) -> str:
    """The paper camera's coherent trials by distance band: how they ended (markdown list)."""
    if not recs:
        return "- not run"
    lines = []
    for lo, hi in ((0.0, 0.5), (0.5, 0.8), (0.8, 9.0)):
        band = [r for r in recs if lo <= r.target_depth_m < hi]
        if not band:
            continue
        ok = [r for r in band if r.in_focus]
        frames = sorted(r.frames for r in ok)
        causes: dict[str, int] = {}
        for r in band:
            if not r.in_focus:
                key = (r.reason or r.status).split(";")[0].split(" (")[0].split(":")[0]
                causes[key] = causes.get(key, 0) + 1
        span = f"{max(lo, 0.3):g}-{min(hi, 1.0):g} m"
        text = f"- {span}: {len(ok)}/{len(band)} in focus"
        if frames:
            text += f" (frames {frames[0]}-{frames[-1]})"
        if causes:
            text += "; not in focus: " + ", ".join(f"{k} ({v})" for k, v in sorted(causes.items(), key=lambda kv: -kv[1]))
        lines.append(text)
    oof = sum(bool(r.declared_out_of_focus) for r in recs)
    lines.append(f"- declared out of focus: {oof}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--trials", type=int, default=100, help="texture-less targets per configuration (default 100)")
    ap.add_argument("--textured", type=int, default=None, help="textured targets (default: --trials)")
    ap.add_argument("--paper-trials", type=int, default=20,
                    help="targets for the paper camera (default 20: its huge blur makes each trial slow to render; "
                         "0 leaves it out)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--model", default=None, help="ONNX file or 'analytic' (default: the shipped model)")
    ap.add_argument("--quick", action="store_true", help="10 targets everywhere")
    ap.add_argument("--no-doc", action="store_true", help="do not write docs/BENCHMARKS.md")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")

    import numpy as np

    from tdfd import Camera
    from tdfd.autofocus.estimators import AnalyticEstimator, OnnxEstimator, load_estimator
    from tdfd.autofocus.report import write_report
    from tdfd.autofocus.roi import Roi
    from tdfd.autofocus.sim import SimBench, trial_depths
    from tdfd.light import SimulatedLight

    from tdfd.autofocus.evidence import blur_px_per_dpt

    from .paper_experiment import paper_camera

    n = 10 if args.quick else args.trials
    n_tex = 10 if args.quick else (args.textured or n)
    n_paper = 10 if args.quick else args.paper_trials
    est = load_estimator(args.model)
    is_onnx = isinstance(est, OnnxEstimator)
    est_name = f"shipped ONNX model via {est.backend}" if is_onnx else "analytic Fourier-ratio estimator (torch)"
    OUT.mkdir(parents=True, exist_ok=True)
    t_wall = time.perf_counter()
    compute_ms: dict[str, float] = {}

    def run(name: str, estimator: Any, depths: list[float], light: str | None, uniform: bool,
            subtract: bool = False, options: dict | None = None, bench_kwargs: dict | None = None) -> list:
        t0 = time.perf_counter()
        key = estimator.camera.name
        charge = compute_ms[key] / 1e3 if key in compute_ms else "calibrated"
        controller = {} if light is None else {"illumination": light, "subtract_ambient": subtract, **(options or {})}
        sim_light = SimulatedLight(estimator.camera) if light is not None else None
        with SimBench(estimator=estimator, seed=args.seed, controller=controller, light=sim_light,
                      compute_s=charge, **(bench_kwargs or {})) as bench:
            if key not in compute_ms and bench.compute_charge_s != "measured":
                compute_ms[key] = float(bench.compute_charge_s) * 1e3
            recs = []
            for i, d in enumerate(depths):
                # sensor noise seeded per trial: every configuration draws the same noise for the same
                # frame of the same trial, whatever the frames the trials before it took
                bench.rng = np.random.default_rng([args.seed, i])
                recs.append(bench.run_trial(d, "dfd", trial=i, uniform=uniform))
        write_report(OUT / f"{name}.json", recs, {"configuration": name, "estimator": type(estimator).__name__,
                                                   "seed": args.seed, "light": light, "subtract_ambient": subtract,
                                                   "options": options or {}})
        print(f"  {name}: {len(recs)} trials in {time.perf_counter() - t0:.0f} s wall", flush=True)
        return recs

    ref = est.camera
    depths = trial_depths(n, args.seed, ref.depth_range_m)
    print(f"estimator: {est_name}; {n} texture-less targets per light", flush=True)
    uni = {light or "none": run(f"reference_uniform_{light or 'none'}", est, depths, light, True)
           for light in ("coherent", "projector", None)}
    # the ambient frame measured: taken (texture probe and lit-tile reference) and kept, or subtracted
    amb = {light: run(f"reference_uniform_{light}_ambient_frame", est, depths, light, True,
                      options={"ambient_frame": True}) for light in ("coherent", "projector")}
    sub = {light: run(f"reference_uniform_{light}_subtracted", est, depths, light, True, subtract=True)
           for light in ("coherent", "projector")}
    # a disk (pillbox) lens: the same targets and lights through the other PSF family
    disk = {light or "none": run(f"reference_uniform_{light or 'none'}_pillbox", est, depths, light, True,
                                 bench_kwargs={"psf": "pillbox"}) for light in ("coherent", "projector", None)}
    paper = {}
    if n_paper > 0:
        # the paper camera binned 4x (as benchmarks/paper_experiment.py does): its whole sensor is the
        # read-out window, and the analytic estimator works on 128-px tiles (the blur radius reaches 64 binned px)
        paper_cam = paper_camera(4)
        paper_est = AnalyticEstimator(paper_cam, tile=PAPER_TILE, stride=PAPER_STRIDE)
        paper_depths = trial_depths(n_paper, args.seed, paper_cam.depth_range_m)
        paper_bench = {"readout_hw": paper_cam.sensor_size_px, "roi": Roi.centre(paper_cam.sensor_size_px, 0.9)}
        paper = {light or "none": run(f"paper_uniform_{light or 'none'}", paper_est, paper_depths, light, True,
                                      bench_kwargs=paper_bench) for light in ("coherent", "projector", None)}
    tex_depths = trial_depths(n_tex, args.seed, ref.depth_range_m)
    tex = {"coherent allowed": run("reference_textured_coherent", est, tex_depths, "coherent", False),
           "none": run("reference_textured_none", est, tex_depths, None, False)}
    wall = time.perf_counter() - t_wall

    rows = [row("reference", f"texture-less, {n}", k, summarise(v)) for k, v in uni.items()]
    rows += [row("reference", f"texture-less, {n}", f"{k}, ambient frame taken", summarise(v)) for k, v in amb.items()]
    rows += [row("reference", f"texture-less, {n}", f"{k}, ambient frame subtracted", summarise(v))
             for k, v in sub.items()]
    rows += [row("reference, disk (pillbox) optics", f"texture-less, {n}", k, summarise(v)) for k, v in disk.items()]
    rows += [row(f"paper, 4x binned (analytic, {PAPER_TILE}-px tiles)", f"texture-less, {n_paper}", k, summarise(v))
             for k, v in paper.items()]
    rows += [row("reference", f"textured, {n_tex}", k, summarise(v)) for k, v in tex.items()]
    table = markdown_table(HEADER, rows)
    print(table)

    s_coh = summarise(uni["coherent"])
    share = s_coh["in_focus_3"] / s_coh["n"]
    s_tl, s_tn = summarise(tex["coherent allowed"]), summarise(tex["none"])
    f3 = {k: (summarise(uni[k])["in_focus_3"], summarise(amb[k])["in_focus_3"], summarise(sub[k])["in_focus_3"])
          for k in amb}
    dropped = sum(1 for r in tex["coherent allowed"] if r.extra.get("lit_dropped"))
    checks = [
        f"- Texture-less targets with the coherent light, reference camera: **{100 * share:.0f} %** in focus with "
        f"at most 3 frames ({'met' if share >= 0.95 else 'NOT met'}: >= 95 % asked).",
        f"- Textured targets: in focus with the light allowed {s_tl['in_focus']}/{s_tl['n']}, without "
        f"{s_tn['in_focus']}/{s_tn['n']} ({'met' if s_tl['in_focus'] >= s_tn['in_focus'] else 'NOT met'}: no lower "
        f"asked); declared out of focus {s_tl['wrong']} and {s_tn['wrong']}. The lit pair was estimated in "
        f"{s_tl['lit']} of them; in {dropped} a lit frame clipped (a bright texture under the pattern) and the pair "
        f"was taken unlit.",
        f"- The ambient frame (in focus with <= 3 frames of {n}; without it / taken / taken and subtracted): coherent "
        f"{' / '.join(map(str, f3['coherent']))}, projector {' / '.join(map(str, f3['projector']))}. It does not "
        f"pay for its frame: the controller's default takes no ambient frame (`ambient_frame` is only implied by "
        f"`--subtract-ambient`).",
    ]
    s_dc = summarise(disk["coherent"])
    checks.append(f"- The same texture-less targets through a disk (pillbox) lens, the controller not told the "
                  f"family: coherent {s_dc['in_focus']}/{s_dc['n']} in focus, {s_dc['in_focus_3']}/{s_dc['n']} with "
                  f"<= 3 frames; declared out of focus {s_dc['wrong']}.")
    if paper:
        s_pc = summarise(paper["coherent"])
        checks.append(f"- Paper camera (4x binned, analytic estimator): coherent {s_pc['in_focus']}/{s_pc['n']} in "
                      f"focus, {s_pc['in_focus_3']}/{s_pc['n']} with <= 3 frames; declared out of focus "
                      f"{s_pc['wrong']} (blur in binned 21.2 um pixels: 1 px there is 4 native pixels).")
    print("\n".join(checks))
    if not args.no_doc:
        plot(uni, FIGURE)
    notes = (failures(uni["coherent"], "coherent") + failures(uni["projector"], "projector")
             + failures(tex["coherent allowed"], "textured, light allowed"))
    body = f"""
Estimator: {est_name} for the reference camera; the analytic Fourier-ratio estimator for
`Camera.preset("paper")` (the shipped model is built for the reference camera). Targets: a
uniform grey plane (albedo 0.5: no texture at all) across 0.3-1.0 m, stratified and uniform
in inverse depth (seed {args.seed}), with sensor noise (10 000 e- full well, 3 e- read noise,
12 bit); textured rows use the autofocus benchmark's texture families. Every light sees the
same targets, and the sensor noise is seeded per trial (the same noise for the same frame of the
same trial in every configuration). The bench is the autofocus benchmark's (lens emulator on a pty through the real
driver, 60 fps hardware-triggered camera, 2 ms exposure, 3 ms read-out, 15 ms settling,
estimator charged its median wall time on this machine: {', '.join(f'{k} {v:.1f} ms' for k, v in compute_ms.items())}).

The light (`tdfd.light.SimulatedLight`): the paper's mask (two 6.2 x 18.9 mm bars 6.2 mm
apart) from the coherent module (sharp, the same physical size at every distance) or from the
projector focused at 56.8 cm (depth of field 44.3-73.3 cm, blurred beyond, irradiance falling
as 1/d^2, its peak set equal to the laser's at 0.3 m so that one exposure never saturates);
ambient light 1 (the unlit bench scene), pattern peak 0.8 of it. The light is switched through
the `LightGuard` on the bench's clock, on for each lit exposure only.

Policy (`AssistedDFDController`), default: with a light named the DFD pair is lit from its
first frame (f1 at P_e1, f2 at P_e2: two frames, so that a lit verification frame still makes
three) and the depth pooled over the tiles with a cue in the lit pair
(`tdfd.autofocus.lit_tiles.pair_cue_mask`: contrast clear of each frame's noise floor, the
pattern's edges on a texture-less target; `pool_lit_tiles`); a lit frame that clips more than
1 % of the ROI (a bright texture under the pattern) sends the pair unlit (a clipped lit f1:
f2 and f1 unlit from where the lens is, one frame lost). The one-region fit fused with the lit
tiles (step 3, since 2026-11-26) needs the pattern inside the ROI's outer ring of tiles: on this
bench's ROI (160 x 128 px) the two bars reach it nearly everywhere: one region fit in the
whole benchmark (counted ad hoc by wrapping `fuse_with_region`, 2026-11-26 evening: one
projector target, region weight 0.12; its time, 1.3 ms per fit, 5 ms for a lens told it is a
disk, is charged when it runs). The charges are wall times measured when the bench opens, so a
run's maximum frames and times can move a little from one run to the next (the projector's
maximum went 10 -> 13 -> 10 frames over three runs that evening, every count unchanged).
Focus is declared on the controller's own evidence only (issue 20's rules, unchanged: an uncertainty under 0.25 px
with the pair's own relative blur agreeing, or a verification frame). "ambient frame taken":
the former policy, kept as an option (`ambient_frame=True`): the first frame is taken unlit
and probes the texture; below 1.2x the noise floor the pair is lit (f2 at P_e2, f1 at P_e1:
three frames before any verification frame) and pooled over the tiles the pattern covers
(lit minus ambient f1); "subtracted": the ambient frame is also subtracted from the lit ones.
"none": plain DFD, which falls back to contrast-detect AF on a texture-less target. "declared
focus, blur >= 1 px": focus declared on a wrong estimate.

{table}

{chr(10).join(checks)}

![residual blur per light](assist_light.png)

The paper camera (`Camera.preset("paper")`: 1 cm aperture, 9.8 cm sensor distance) blurs a
target in the working range by 26-257 px (radius, native 5.3 um pixels) in at least one frame
of the DFD pair (0.3 m: 258 and 180 px; 1.0 m: 42 and 35 px), beyond any 64-px tile. Its rows
use the camera binned 4x as `benchmarks/paper_experiment.py` does (`paper_camera(4)`: 21.2 um
pixels, the whole 300 x 400 binned sensor read out, ROI its centred 90 %), so the blur radius
is 6.5-64 binned px, and the analytic Fourier-ratio estimator on {PAPER_TILE}-px tiles (stride
{PAPER_STRIDE}); the shipped model covers the reference camera only (`tdfd.coverage`). "In focus"
there is a blur radius under 1 binned pixel (4 native pixels). Binned blur radii of the pair:
0.3 m 64 and 45 px, 0.5 m 34 and 14 px, 0.8 m 16 and 3 px, 1.0 m 10 and 9 px. The controller's
model-free evidence (`tdfd.autofocus.evidence.relative_blur_px2`) searches the relative blur up
to (1.5 sigma_max)^2 of the camera (`relative_blur_search_px2`: 2330 px^2 here, 64 px^2 for the
reference camera). Measured (seed 0, coherent), by distance:
{paper_summary(paper.get("coherent", []))}

(The reasons are the controller's own.) This camera's depth of field is shallow: 1 binned px of
blur is {1 / blur_px_per_dpt(paper_camera(4)):.3f} dpt of focus error, 1.3 % of depth at 0.3 m, so its single-shot
estimate is mostly confirmed by a verification frame and a correction (4 frames). Nearer than
about 0.5 m the pattern's bars (about 8 binned px wide) are blurred by 34-64 px in both frames of
the pair, and the lit ROI's contrast stays under 1.5x its noise floor: no texture for DFD. The
contrast search that takes over is lit with the coherent pattern (sharp at every distance, so
the search's frames show it at focus; a projector's searches stay unlit,
`tdfd.autofocus.assist.SHARP_PATTERNS`), and since one 0.4 dpt scan step is 9 px of blur for
this camera it scans again around its peak in steps of 1 px of blur (`ContrastSearch`,
`fine_scan_px`; the reference camera, 1.1 px per step, never does): in focus, at 19-21 frames.
A pair at stronger powers for the near range would see the pattern with far fewer frames; the
controller uses the camera's one pair.

Trials not in focus within 3 frames (coherent, projector, textured with the light; {len(notes)}):
{chr(10).join('- ' + x for x in notes[:40]) if notes else '- none'}

Reports: `out/assist_light/*.json`. Wall time of this benchmark: {wall:.0f} s.
"""
    if not args.no_doc:
        cmd = ".venv/bin/python -m benchmarks.bench_assist_light" + (
            " --quick" if args.quick else "" if n == 100 and n_tex == 100 and n_paper == 20 else
            f" --trials {n} --textured {n_tex} --paper-trials {n_paper}")
        update_section("assist_light", "Active DFD autofocus: assist light on texture-less targets", body, cmd)
        print("wrote the assist_light section of docs/BENCHMARKS.md")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
