"""``tdfd calibrate DIR [DIR ...] --camera NOMINAL.json -o CAM.json``: fit a camera to capture folders.

Routes (``--route``): ``self`` (focus sweep + pairs of a textured scene, no distance
needed), ``known-distance`` (pairs of a target at known distances, the paper's route), or
``auto`` (self when the folders hold a sweep, else known-distance). Several folders are
several scenes calibrated together (one fit: each scene's own in-focus powers, one K and
one breathing): a self-calibration from one scene carries that scene's error in K (about
1-2 %), three scenes at different distances average it down (docs/CALIBRATION.md). Writes the camera JSON
(``tdfd.camera`` contract + ``magnification_per_dpt`` + ``calibration`` provenance), the
fit plot ``CAM.png`` beside it, and prints the fitted values and residuals. With
``--psf-model`` it also measures the lens's whole PSF from the sweeps
(:mod:`tdfd.calibration.psf_model`), writes it as ``psf_model`` and draws it in ``CAM_psf.png``.
"""

from __future__ import annotations

import argparse
import json
import logging
from dataclasses import replace
from pathlib import Path
from typing import Any, Sequence

from ..errors import InputError

__all__ = ["register", "run"]

log = logging.getLogger(__name__)


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``calibrate`` subcommand."""
    p = subparsers.add_parser("calibrate", help="fit a camera JSON to a capture folder", description=__doc__,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("folders", nargs="+", metavar="DIR",
                   help="capture folder(s) (CONTRACT.md section 4); several folders: one scene each")
    p.add_argument("--camera", required=True, metavar="NOMINAL.json", help="datasheet camera JSON")
    p.add_argument("-o", "--output", required=True, metavar="CAM.json", help="fitted camera JSON to write")
    p.add_argument("--route", choices=("auto", "self", "known-distance"), default="auto")
    p.add_argument("--region", type=int, default=64, help="region (tile) side in px (default 64)")
    p.add_argument("--psf-family", choices=("measure", "gaussian", "pillbox", "unknown"), default="measure",
                   help="the lens's PSF family written to the camera file: measured from the scenes with three or more "
                        "frames (default; left out when they do not decide it), given, or left out")
    p.add_argument("--psf-model", action="store_true",
                   help="also measure the lens's whole PSF (shape, astigmatism, spherical aberration) from the scenes "
                        "with three or more frames (a focus sweep that brackets focus; frames repeated at a power are "
                        "averaged), written as psf_model for the likelihood stage (tdfd depth --psf-model); tens of "
                        "seconds")
    p.add_argument("--max-mu-uncertainty", type=_fraction, default=None, metavar="FRACTION",
                   help="known-distance route: refuse pairs that leave mu more uncertain than this relative standard "
                        "uncertainty (default 0.05): a target near the distance where the pair blurs both frames "
                        "equally measures no mu")
    p.add_argument("--no-plot", action="store_true", help="do not write the fit plot")
    p.set_defaults(func=run)


def _fraction(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a fraction such as 0.05, got {text!r}") from None
    if not (0.0 < value < 1.0):
        raise argparse.ArgumentTypeError(f"expected a fraction in (0, 1), got {text!r}")
    return value


def _psf_family(choice: str, frames: Sequence[Any], camera_file: Any) -> tuple[str | None, float, str]:
    """The PSF family to write (``None``: none), its blur scale and a line saying where they came from."""
    from .psf_family import psf_family_from_captures  # lazily, as the fit: building the CLI imports no numpy work

    if choice in ("gaussian", "pillbox"):
        try:
            fit = psf_family_from_captures(frames, camera_file, min_ratio=1.0)
            scale = fit.sigma_scale.get(choice, 1.0)
        except InputError as exc:
            log.warning("no blur scale measured for the given family (1 assumed): %s", exc)
            scale = 1.0
        return choice, scale, f"{choice} (given with --psf-family), blur scale {scale:.3f}"
    if choice == "unknown":
        return None, 1.0, "not written (--psf-family unknown)"
    try:
        fit = psf_family_from_captures(frames, camera_file)
    except InputError as exc:
        return None, 1.0, f"not measured: {exc}"
    if fit.family is None:
        return None, 1.0, (f"not written: the captures do not decide it (the other family fits {fit.cost_ratio:.2f}x "
                           f"worse over {fit.regions} regions; measured from a focus sweep of a textured scene)")
    scale = fit.family_sigma_scale
    return fit.family, scale, (f"{fit.family}, measured (the other family fits {fit.cost_ratio:.2f}x worse over "
                               f"{fit.regions} regions), blur scale {scale:.3f}")


def _psf_model(frames: Sequence[Any], result: Any) -> tuple[str, Any]:
    """Measure the PSF model into ``result.camera_file`` (and its provenance); a line saying what
    came of it, and the fit.

    Raises:
        InputError: the captures hold no scene with three powers.
    """
    from .psf_model import psf_model_from_captures  # lazily: the fit needs torch

    fit = psf_model_from_captures(frames, result.camera_file)
    result.camera_file = replace(result.camera_file, psf_model=fit.to_dict())
    result.camera_file.calibration["psf_model"] = fit.summary()  # type: ignore[index]
    h = fit.hypothesis
    shape = h.shape if isinstance(h.shape, str) else f"beta {h.shape:.2f}"
    return (f"{shape}, astigmatism {h.astigmatism:.3f} at {h.astigmatism_angle:.2f} rad, spherical {h.spherical:+.3f}, "
            f"blur scale {h.sigma_scale:.3f} (the best plain family fits {fit.family_cost_ratio:.2f}x worse over "
            f"{fit.regions} regions)"), fit


def run(args: argparse.Namespace) -> int:
    from ..camera_file import load_camera_file
    from ..capture.folder import read_folder
    from .fit import calibrate_known_distance, calibrate_self

    nominal = load_camera_file(args.camera)
    frames = [f for folder in args.folders for f in read_folder(folder)]
    route = args.route
    if route == "auto":
        route = "self" if any(f.metadata.pair is None for f in frames) else "known-distance"
    if route == "self":
        result = calibrate_self(frames, nominal, region=args.region, nominal_path=str(args.camera))
    else:
        extra = {} if args.max_mu_uncertainty is None else {"max_mu_uncertainty": args.max_mu_uncertainty}
        result = calibrate_known_distance(frames, nominal, region=args.region, nominal_path=str(args.camera), **extra)
    result.camera_file.calibration["folder"] = (  # type: ignore[index]
        str(args.folders[0]) if len(args.folders) == 1 else [str(f) for f in args.folders])
    family, scale, family_line = _psf_family(args.psf_family, frames, result.camera_file)
    if family is not None:
        result.camera_file = replace(result.camera_file, psf_family=family, psf_sigma_scale=scale)
    result.camera_file.calibration["psf_family"] = family_line  # type: ignore[index]
    model_line, psf_fit = "not measured (no --psf-model)", None
    if args.psf_model:
        model_line, psf_fit = _psf_model(frames, result)
    out = result.camera_file.write(args.output)
    s = result.summary()
    print(f"calibrated {len(frames)} frames of {', '.join(map(str, args.folders))} ({route} route) -> {out}")
    cam = result.camera_file.camera
    print(f"  K = {result.k_px_per_dpt:.5g} px/dpt  ->  mu = {cam.mu_px_per_m:.5g} px/m "
          f"(nominal {nominal.camera.mu_px_per_m:.5g})")
    if "mu_relative_uncertainty" in result.camera_file.calibration:  # type: ignore[operator]
        print(f"  mu standard uncertainty {100 * result.camera_file.calibration['mu_relative_uncertainty']:.2f} % "
              f"(pairs' in-focus power uncertain by {result.camera_file.calibration['pair_power_sd_dpt']:.3g} dpt)")
    print(f"  in-focus offset B = {result.in_focus_offset_dpt:+.4f} dpt ({result.offset_source})")
    print(f"  -> fixed_focal_length_m = {cam.fixed_focal_length_m:.6g} (nominal {nominal.camera.fixed_focal_length_m:.6g}); "
          f"power offset vs datasheet {result.camera_file.calibration['power_offset_vs_datasheet_dpt']:+.4f} dpt")
    print(f"  breathing: magnification_per_dpt = {result.magnification_per_dpt:.5g} ({100 * result.magnification_per_dpt:.3f} %/dpt)")
    print(f"  PSF family: {family_line}")
    print(f"  PSF model: {model_line}")
    for kind, rms in s["residual_rms_dpt"].items():
        print(f"  residuals {kind}: RMS {rms:.4f} dpt over {s['counts'][kind]}" if rms is not None else f"  residuals {kind}: none")
    log.info("calibration summary: %s", json.dumps(s))
    if not args.no_plot:
        from .plot import plot_calibration, plot_psf_model

        png = plot_calibration(result, Path(args.output).with_suffix(".png"))
        print(f"  fit plot: {png}")
        if psf_fit is not None:
            out_png = Path(args.output)
            png = plot_psf_model(psf_fit, out_png.with_name(out_png.stem + "_psf.png"))
            print(f"  PSF plot: {png}")
    return 0
