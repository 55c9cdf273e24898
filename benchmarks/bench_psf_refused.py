r"""Section ``psf_model``'s plane fits fused again with other scales files (issue 19).

Run from the repository root, on the rows a ``bench_psf_model`` run saved::

    .venv/bin/python -m benchmarks.bench_psf_model --samples 256 --world full --structure 0 \
        --bias-scales models/reference.likelihood-calibrated-bias.json --rows ROWS.pt
    .venv/bin/python -m benchmarks.bench_psf_refused --rows ROWS.pt [--calibrated-scales S.json]
        [--bias-scales S.json] [--no-write]

The likelihood stage's fits do not depend on its scales (each tile's fit is seeded by the
model's map; the scales only weigh it against the model), so a new scales file is scored on the
very same fits in seconds instead of the benchmark's hour of sweeps and fits: the ``calibrated``
and ``told`` stages are fused again with ``--calibrated-scales`` and ``calibrated_bias`` with
``--bias-scales`` (:func:`benchmarks.stage_rows.refuse`, on each plane's fitted interior tiles);
``profiled`` and ``calibrated_shipped_scales`` stay as the run fused them. Reports section
``psf_model``'s tables (median error per tile and per plane, against the Cramér-Rao bound, per
texture family, paired bootstrap) and each confidence per decile, the run's own beside the new,
and writes section ``psf_model_refused`` of docs/BENCHMARKS.md.
"""

from __future__ import annotations

import argparse
import math
import sys

import torch

from benchmarks.bench_psf_model import (BIAS_STAGE, bound_line, confidence_table, family_table, plane_table,
                                        stages_of)
from benchmarks.report import ROOT, given_options, machine, markdown_table, repo_path, update_section
from benchmarks.stage_rows import refuse
from tdfd.dfd.inverse_variance import LikelihoodScales
from tdfd.model import DFDModel

__all__ = ["REFUSED", "refuse_planes", "main"]

#: the stages fused again, with the scales file each takes (``calibrated``: ``--calibrated-scales``)
REFUSED = {"calibrated": "calibrated", "told": "told", BIAS_STAGE: "calibrated"}


def refuse_planes(rows: list[dict], confidence_scale: float, calibrated: LikelihoodScales,
                  bias: LikelihoodScales | None) -> list[dict]:
    """``rows`` (``bench_psf_model --rows``'s planes) with :data:`REFUSED`'s stages fused again:
    each from its fits on the plane's interior tiles (a square grid, every tile fitted), the
    ``calibrated`` and ``told`` stages with ``calibrated``, :data:`BIAS_STAGE` (where ``bias`` is
    given) from the ``calibrated`` stage's fits with ``bias``.

    Raises:
        ValueError: a row without the fits, or whose tiles are not a square grid.
    """
    out = []
    for r in rows:
        n = r["true_q"].numel()
        side = math.isqrt(n)
        if side * side != n:
            raise ValueError(f"plane {r.get('index')}: {n} tiles are not a square grid of interior tiles")
        row = dict(r)
        q_model = r["model_q"].reshape(side, side)
        conf = r["model_conf"].reshape(side, side)
        for stage, fits in REFUSED.items():
            scales = bias if stage == BIAS_STAGE else calibrated
            if scales is None:
                continue
            try:
                q_fit, sigma, slope = (r[f"{fits}_{k}"].reshape(side, side)
                                       for k in ("fit_q", "fit_sigma_raw", "slope"))
            except KeyError as e:
                raise ValueError(f"plane {r.get('index')} has no {fits} fits to fuse again ({e})") from e
            d, c = refuse(torch.ones(side, side, dtype=torch.bool), 1.0 / q_fit, sigma, slope, 1.0 / q_model, conf,
                          confidence_scale, scales)
            row[f"{stage}_q"], row[f"{stage}_conf"] = (1.0 / d).flatten().double(), c.flatten().double()
        out.append(row)
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--rows", required=True, help="a bench_psf_model run's --rows file")
    p.add_argument("--model", default=str(ROOT / "models" / "reference"))
    p.add_argument("--calibrated-scales", default="",
                   help="for the calibrated and told stages (default: MODEL.likelihood-calibrated.json)")
    p.add_argument("--bias-scales", default="",
                   help="for calibrated_bias, fitted with --shared-bias (default: "
                        "MODEL.likelihood-calibrated-bias.json)")
    p.add_argument("--no-write", action="store_true", help="print only; leave docs/ alone")
    args = p.parse_args(argv)
    model = DFDModel.load(args.model)
    paths = (args.calibrated_scales or f"{args.model}.likelihood-calibrated.json",
             args.bias_scales or f"{args.model}.likelihood-calibrated-bias.json")
    calibrated, bias = LikelihoodScales.load(paths[0]), LikelihoodScales.load(paths[1])
    if not bias.shared_bias:
        p.error(f"{paths[1]} does not remove the model's bias (fitted without --shared-bias)")
    saved = torch.load(args.rows, weights_only=True)["planes"]
    if not saved:
        p.error(f"{args.rows} holds no planes")
    rows = refuse_planes(saved, model.confidence_scale, calibrated, bias)
    planes, lines = plane_table(rows)
    before = confidence_table(saved, model.confidence_scale)
    after = confidence_table(rows, model.confidence_scale)
    shown = [repo_path(x) for x in paths]
    body = "\n".join([
        f"Machine: {machine()}; the {len(rows)} planes of `{repo_path(args.rows)}` (a `bench_psf_model --rows` run: "
        f"the whole world, each lens calibrated from its own sweep, their interior tiles), the stages' fits fused "
        f"again: `calibrated` and `told` with `{shown[0]}`, `{BIAS_STAGE}` with `{shown[1]}` "
        f"(`profiled` and `calibrated_shipped_scales` as the run fused them).",
        "",
        "Median error on the planes' interior tiles, per tile / per plane:",
        "",
        markdown_table(["estimator", "per tile", "per plane"], planes),
        "",
        bound_line(rows),
        "",
        "Per texture family, median error per tile and its ratio to the family's per-tile bound:",
        "",
        markdown_table(["family", "planes", "per tile: bound", "model", *stages_of(rows)], family_table(rows)),
        "",
        "Paired bootstrap over planes (1000 resamples, seed 0):",
        "",
        *lines,
        "",
        "Confidence per decile (observed / predicted median error within 20 %, section `uncertainty`'s deciles, 100 "
        "resamples of the planes): as the run fused them, then fused again with these scales:",
        "",
        markdown_table(["confidence of", "fusion", "tiles", "deciles within 20 %", "outside by > 2 s.e.",
                        "ratio range", "worst ratio"],
                       [[r[0], "the run's", *r[1:]] for r in before if r[0] in REFUSED]
                       + [[r[0], "fused again", *r[1:]] for r in after if r[0] in REFUSED]),
    ])
    print(body)
    if not args.no_write:
        cmd = (f".venv/bin/python -m benchmarks.bench_psf_refused --rows {args.rows}"
               + given_options(args, "calibrated_scales", "bias_scales"))
        update_section("psf_model_refused", "Section psf_model's plane fits fused with the scales files as they are "
                                            "(issue 19)", body, cmd)
    return 0


if __name__ == "__main__":
    sys.exit(main())
