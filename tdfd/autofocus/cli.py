"""``tdfd autofocus``: the simulated bench (``--sim``) or real hardware (``--port``, ``--camera``).

Examples::

    tdfd autofocus --sim                                  # 20 targets, DFD vs contrast AF
    tdfd autofocus --sim --trials 40 --seed 1 --json out/af.json
    tdfd autofocus --sim --scene uniform                  # texture-less: DFD falls back
    tdfd autofocus --sim --faults drop=0.2,bad_crc=0.1    # driver faults on the emulator
    tdfd autofocus --sim --continuous --duration 2        # moving target
    tdfd autofocus --port /dev/ttyACM0 --camera 0         # real lens and camera
    tdfd autofocus --camera 0 --dry-run                   # capture + estimate, lens untouched
    tdfd autofocus --sim --scene uniform --illumination coherent      # active DFD (laser pattern)
    tdfd autofocus --port /dev/ttyACM0 --camera 0 --assist-light serial:/dev/ttyUSB0:rts
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import math
import sys
from pathlib import Path
from typing import Any

from ..camera import Camera
from ..driver import Faults
from ..errors import InputError
from .estimators import default_model_path, load_estimator
from .psf_family_option import add_psf_family_argument, calibrated_mu_uncertainty, resolve_psf_family, tell_estimator
from .hardware import run_hardware
from .light_cli import (
    add_light_arguments,
    check_light_args,
    light_limits,
    light_summary,
    open_named_light,
    sigterm_as_interrupt,
    sim_light,
)
from .report import build_report, format_summary, format_table, write_report
from .roi import Roi
from .sim import DEFAULT_READOUT_HW, CameraTiming, Scene, SensorNoise, SimBench, trial_depths

__all__ = ["register", "run"]

log = logging.getLogger(__name__)

DEFAULT_TRIALS = 20


def _readout(text: str) -> tuple[int, int]:
    try:
        h, w = (int(v) for v in text.lower().replace(",", "x").split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"read-out window must be HxW, e.g. 256x320, got {text!r}") from None
    if h < 16 or w < 16:
        raise argparse.ArgumentTypeError("read-out window must be at least 16x16")
    return h, w


def _compute(text: str) -> float | str:
    if text in ("calibrated", "measured"):
        return text
    try:
        ms = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError("--compute is 'calibrated', 'measured' or milliseconds") from None
    if ms < 0:
        raise argparse.ArgumentTypeError("--compute milliseconds must be >= 0")
    return ms / 1000.0


def register(subparsers: Any) -> argparse.ArgumentParser:
    """Add the ``autofocus`` subcommand."""
    p = subparsers.add_parser(
        "autofocus", help="autofocus with DFD: the simulated bench (--sim) or real hardware",
        description="Put the ECVFL at the focus the target needs from two frames and one lens move. "
                    "--sim runs the simulated bench (lens emulator on a pty through the real driver, virtual "
                    "camera on a simulated clock) and prints a table; --port/--camera run real hardware.",
        formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__.split("Examples::", 1)[1])
    where = p.add_argument_group("where")
    where.add_argument("--sim", action="store_true", help="run the simulated bench")
    where.add_argument("--port", help="serial port (or pyserial URL) of the Lens Driver 4")
    where.add_argument("--camera", help="OpenCV camera index or URL")
    where.add_argument("--dry-run", action="store_true", help="capture and estimate without moving the lens")

    what = p.add_argument_group("what")
    what.add_argument("--method", choices=("dfd", "contrast", "both"), default=None,
                      help="autofocus method (default: both on --sim, dfd on hardware)")
    what.add_argument("--model", default=None,
                      help="ONNX model, or 'analytic' for the Fourier-ratio stand-in (default: models/reference.onnx "
                           "if present, else analytic)")
    what.add_argument("--roi", default=None, help="region of interest x,y,w,h in frame pixels (default: centred half)")
    ver = what.add_mutually_exclusive_group()
    ver.add_argument("--verify", dest="verify", action="store_const", const="always", default="auto",
                     help="always check the DFD focus with a verification frame (default: only when the "
                          "estimate's own uncertainty is above --max-uncertainty)")
    ver.add_argument("--no-verify", dest="verify", action="store_const", const="never",
                     help="never take a verification frame: focus is declared on the estimate's uncertainty "
                          "alone, else the contrast search decides")
    what.add_argument("--max-uncertainty", type=float, default=0.25,
                      help="DFD uncertainty (px of blur) up to which focus is declared without a verification "
                           "frame (default 0.25)")
    add_psf_family_argument(what)
    what.add_argument("--continuous", action="store_true", help="keep re-estimating as the target moves")
    what.add_argument("--duration", type=float, default=2.0, help="continuous run length in seconds (default 2)")
    what.add_argument("--min-confidence", type=float, default=None,
                      help="ROI confidence below which DFD falls back to contrast AF (default: the estimator's, "
                           "0.003 for the ONNX model, 0.005 for the analytic one)")
    what.add_argument("--min-texture-snr", type=float, default=1.5,
                      help="ROI contrast over the noise floor below which the target counts as texture-less "
                           "(default 1.5; 0 disables)")
    what.add_argument("--contrast-strategy", choices=("scan", "golden"), default="scan",
                      help="contrast-detect search (default scan: coarse scan + parabolic peak)")
    what.add_argument("--contrast-step", type=float, default=0.4, help="contrast scan step in dpt (default 0.4)")
    what.add_argument("--settle-ms", type=float, default=15.0, help="lens settling time in ms (default 15)")

    sim = p.add_argument_group("simulated bench")
    sim.add_argument("--trials", type=int, default=DEFAULT_TRIALS, help=f"targets across 0.3-1.0 m (default {DEFAULT_TRIALS})")
    sim.add_argument("--seed", type=int, default=0, help="seed of targets, textures and noise (default 0)")
    sim.add_argument("--json", type=Path, default=None, help="write the report (CONTRACT.md section 3) here")
    sim.add_argument("--scene", default="texture",
                     help="'texture' (procedural plane, default), 'uniform' (texture-less) or an image file")
    sim.add_argument("--scene-depth", default=None, help="depth map (.npy, metres) for an image --scene")
    sim.add_argument("--readout", type=_readout, default=None, help="sensor read-out window HxW (default 256x320)")
    sim.add_argument("--fps", type=float, default=60.0, help="camera frame rate (default 60)")
    sim.add_argument("--exposure-ms", type=float, default=2.0, help="exposure time in ms (default 2)")
    sim.add_argument("--readout-ms", type=float, default=3.0, help="exposure end to frame on host, ms (default 3)")
    sim.add_argument("--trigger", choices=("hardware", "free"), default="hardware",
                     help="hardware-triggered exposures (default) or free-running frame boundaries")
    sim.add_argument("--compute", type=_compute, default="calibrated",
                     help="estimator time charged: 'calibrated' (median on this machine, default), 'measured' "
                          "(per call) or milliseconds")
    sim.add_argument("--psf", default="gaussian", help="PSF of the simulated optics: gaussian, pillbox or a beta")
    sim.add_argument("--faults", default=None,
                     help="emulator fault injection, e.g. drop=0.2,bad_crc=0.1,late=0.05,garbage=0.1,disconnect_after=50")
    sim.add_argument("--no-noise", action="store_true", help="noise-free sensor")
    sim.add_argument("--no-progress", action="store_true", help="no progress bar")

    hw = p.add_argument_group("real hardware")
    hw.add_argument("--linearise", action="store_true", help="undo an sRGB gamma (prefer a camera in raw/linear mode)")
    hw.add_argument("--white-level", type=float, default=None, help="raw value of white (default from the dtype)")
    add_light_arguments(p)
    p.set_defaults(func=run)
    return p


def _roi(args: argparse.Namespace):
    return Roi.parse(args.roi) if args.roi else None


def _psf(text: str) -> Any:
    try:
        return float(text)
    except ValueError:
        return text


def _faults(text: str | None, seed: int):
    if not text:
        return None
    try:
        return Faults.parse([s for s in text.split(",") if s.strip()], seed=seed)
    except ValueError as exc:
        raise InputError(str(exc)) from exc


def run(args: argparse.Namespace) -> int:
    """Entry point of ``tdfd autofocus``."""
    if args.sim and (args.port or args.camera):
        raise InputError("--sim runs the simulated bench: drop --port/--camera (or drop --sim)")
    if not args.sim and not args.camera:
        raise InputError("give --sim for the simulated bench, or --camera (and --port) for real hardware")
    check_light_args(args)  # before anything is opened
    if args.sim:
        return _run_sim(args)
    return _run_hardware(args)


def _estimator(args: argparse.Namespace, needed: bool):
    if not needed:
        return None
    if args.model is None and not default_model_path().is_file():
        print(f"note: shipped model {default_model_path()} not found; using the analytic Fourier-ratio estimator "
              "(torch) as a stand-in", file=sys.stderr)
    return load_estimator(args.model)


def _estimator_name(est: Any) -> str:
    if est is None:
        return "none"
    path = getattr(est, "path", None)
    return f"ONNX {path} via {est.backend}" if path is not None else getattr(est, "backend", type(est).__name__)


def _run_sim(args: argparse.Namespace) -> int:
    import numpy as np

    if args.trials < 1:
        raise InputError("--trials must be >= 1")
    method = args.method or "both"
    methods = ("dfd", "contrast") if method == "both" else (method,)
    est = _estimator(args, "dfd" in methods)
    readout = args.readout or DEFAULT_READOUT_HW
    uniform = args.scene == "uniform"
    scene = None
    if args.scene not in ("texture", "uniform"):
        if not args.scene_depth:
            raise InputError("an image --scene needs --scene-depth DEPTH.npy (metres)")
        scene = Scene.from_files(args.scene, args.scene_depth, readout)
    timing = CameraTiming(frame_period_s=1.0 / args.fps, exposure_s=args.exposure_ms / 1e3,
                          readout_s=args.readout_ms / 1e3, trigger=args.trigger,
                          phase_s=float(np.random.default_rng(args.seed).uniform(0, 1.0 / args.fps)))
    roi = _roi(args)
    contrast = {"strategy": args.contrast_strategy, "step_dpt": args.contrast_step}
    controller = {"verify": args.verify, "min_texture_snr": args.min_texture_snr,
                  "max_uncertainty_px": args.max_uncertainty}
    if args.min_confidence is not None:
        controller["min_confidence"] = args.min_confidence
    optics = est.camera if est is not None else Camera.preset("reference")
    controller["psf_family"], controller["psf_sigma_scale"] = resolve_psf_family(args.psf_family, sim_camera=optics,
                                                                                 sim_psf=_psf(args.psf))
    tell_estimator(est, controller["psf_family"])
    light, light_controller = sim_light(args, optics)
    controller.update(light_controller)
    mu_uncertainty = calibrated_mu_uncertainty(args.psf_family)
    if mu_uncertainty is not None and controller.get("illumination") is not None:  # the lit pair's region fit
        controller["region_mu_uncertainty"] = mu_uncertainty
    bench = SimBench(light=light, light_limits=light_limits(args), estimator=est, readout_hw=readout, roi=roi, timing=timing,
                     noise=SensorNoise(enabled=not args.no_noise), settle_s=args.settle_ms / 1e3,
                     compute_s=args.compute, seed=args.seed, psf=_psf(args.psf), scene=scene,
                     faults=_faults(args.faults, args.seed), controller=controller, contrast=contrast)
    cam = bench.camera
    with bench:
        charge = bench.compute_charge_s
        charge_txt = "measured per call" if charge == "measured" else f"{float(charge) * 1e3:.1f} ms per estimate"
        print(f"tdfd autofocus --sim: {cam.name} camera (ECVFL pair {cam.lens_powers_dpt[0]:g}/{cam.lens_powers_dpt[1]:g} dpt), "
              f"estimator: {_estimator_name(est)}")
        print(f"bench: lens emulator on {bench.lens.server.port} via the OptotuneLens driver, range "
              f"{bench.lens.power_limits_dpt[0]:.2f}..{bench.lens.power_limits_dpt[1]:.2f} dpt, settling {args.settle_ms:g} ms; "
              f"camera {args.fps:g} fps ({args.trigger} trigger), exposure {args.exposure_ms:g} ms, read-out "
              f"{args.readout_ms:g} ms, window {readout[0]}x{readout[1]} px, ROI {bench.roi}; compute {charge_txt}; "
              f"PSF {args.psf}, the controller told {controller['psf_family'] or 'no family'} (--psf-family {args.psf_family})"
              + (f", the model's CNN {est.psf_family or 'unknown'}" if getattr(est, "takes_psf_family", False) else ""))
        if args.faults:
            print(f"fault injection on the emulator: {args.faults}")
        if args.continuous:
            return _continuous(args, bench)
        depths = trial_depths(args.trials, args.seed, cam.depth_range_m)
        records = []
        bar = None
        if not args.no_progress:
            from tqdm import tqdm

            bar = tqdm(total=len(depths) * len(methods), desc="autofocus trials", unit="trial", file=sys.stderr,
                       leave=False, disable=None)
        try:
            for i, d in enumerate(depths):
                for m in methods:
                    records.append(bench.run_trial(d, m, trial=i, uniform=uniform))
                    if bar is not None:
                        bar.update(1)
        finally:
            if bar is not None:
                bar.close()
        settings = {
            "estimator": _estimator_name(est), "camera": cam.to_dict(), "readout_hw": list(readout),
            "roi": str(bench.roi), "frame_rate_hz": args.fps, "exposure_ms": args.exposure_ms,
            "readout_ms": args.readout_ms, "trigger": args.trigger, "settle_ms": args.settle_ms,
            "compute_ms_per_estimate": None if charge == "measured" else float(charge) * 1e3,
            "compute_mode": args.compute if isinstance(args.compute, str) else "fixed",
            "seed": args.seed, "scene": args.scene, "verify": args.verify, "psf": args.psf,
            "contrast": contrast, "faults": args.faults,
            "min_confidence": args.min_confidence if args.min_confidence is not None else
            (getattr(est, "min_confidence", None) if est is not None else None),
            "min_texture_snr": args.min_texture_snr,
            "lens_range_dpt": list(bench.lens.power_limits_dpt),
            "illumination": args.illumination, "subtract_ambient": args.subtract_ambient,
        }
    report = build_report(records, settings)
    print()
    print(format_table(records))
    print()
    print(format_summary(report["summary"]))
    lit = light_summary(records)
    if lit:
        print(lit)
    if args.json:
        write_report(args.json, records, settings)
        print(f"report written to {args.json}")
    ok = all(r.status == "focused" for r in records)
    return 0 if ok else 1


def _continuous(args: argparse.Namespace, bench) -> int:
    near, far = bench.camera.depth_range_m
    q_mid, q_amp = 0.5 * (1 / near + 1 / far), 0.4 * (1 / near - 1 / far)
    period = max(args.duration, 0.5)

    def schedule(t: float) -> float:
        return 1.0 / (q_mid + q_amp * math.sin(2 * math.pi * t / period))

    extra = {"min_confidence": args.min_confidence} if args.min_confidence is not None else {}
    result, rows = bench.run_continuous(schedule, duration_s=args.duration, verify=args.verify,
                                        max_uncertainty_px=args.max_uncertainty,
                                        min_texture_snr=args.min_texture_snr, **extra)
    live = [r for r in rows if r["tag"] == "live"]
    in_focus = sum(1 for r in live if r["residual_blur_px"] < 1.0)
    print(f"\ncontinuous DFD for {args.duration:g} s, target moving {schedule(period / 4):.2f}..{schedule(3 * period / 4):.2f} m")
    print(f"{'t ms':>8} {'target m':>8} {'focus dpt':>9} {'est. m':>7}")
    for t, power, depth in result.history:
        print(f"{(t - (result.t_start_s or 0)) * 1e3:8.1f} {schedule(t - (result.t_start_s or 0)):8.3f} {power:9.3f} "
              f"{depth if depth is not None else float('nan'):7.3f}")
    print(f"re-estimates: {result.refocus_count}; frames: {result.frames} ({len(live)} live at focus); live frames in "
          f"focus (blur < 1 px): {in_focus}/{len(live)}; status: {result.status}"
          + (f" ({result.error})" if result.error and result.status != "halted" else ""))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"result": {"status": result.status, "refocus_count": result.refocus_count,
                                                    "frames": result.frames, "history": result.history},
                                         "frames": rows}, indent=2) + "\n")
        print(f"continuous log written to {args.json}")
    return 0 if result.status in ("halted", "focused") else 1


def _run_hardware(args: argparse.Namespace) -> int:
    method = args.method or "dfd"
    if method == "both":
        raise InputError("--method both is for the simulated bench")
    est = _estimator(args, method == "dfd")
    family, scale = resolve_psf_family(args.psf_family)  # before the light and the lens: a bad value touches neither
    mu_uncertainty = calibrated_mu_uncertainty(args.psf_family)
    tell_estimator(est, family)
    light = open_named_light(args)  # before the lens: a missing light port leaves the lens untouched
    on_term = sigterm_as_interrupt() if light is not None else contextlib.nullcontext()  # kill -> Ctrl-C's exit path
    try:
        with on_term:
            res = run_hardware(args.port, args.camera, est, method=method, roi=_roi(args), verify=args.verify,
                               dry_run=args.dry_run, continuous=args.continuous,
                               duration_s=args.duration if args.continuous else None, settle_s=args.settle_ms / 1e3,
                               linearise=args.linearise, white_level=args.white_level,
                               min_confidence=args.min_confidence, max_uncertainty_px=args.max_uncertainty,
                               contrast={"strategy": args.contrast_strategy, "step_dpt": args.contrast_step},
                               light=light, illumination=args.illumination, light_limits=light_limits(args),
                               psf_family=family, psf_sigma_scale=scale, region_mu_uncertainty=mu_uncertainty)
    finally:
        if light is not None:
            light.close()
    dt = res.time_to_focus_s
    print(f"status: {res.status}; method: {res.method}; power: "
          f"{'-' if res.power_dpt is None else f'{res.power_dpt:.3f} dpt'}; depth: "
          f"{'-' if res.estimated_depth_m is None else f'{res.estimated_depth_m:.3f} m'}; confidence: "
          f"{'-' if res.confidence is None else f'{res.confidence:.3f}'}; frames: {res.frames}; lens commands: "
          f"{res.lens_commands}; time: {'-' if dt is None else f'{dt * 1e3:.1f} ms'}")
    if args.continuous and res.history:
        print(f"{'t ms':>8} {'focus dpt':>9} {'est. m':>7}")
        for t, power, depth in res.history:
            print(f"{(t - (res.t_start_s or 0)) * 1e3:8.1f} {power:9.3f} {depth if depth is not None else float('nan'):7.3f}")
    if res.fallback_reason:
        print(f"fell back: {res.fallback_reason}")
    if res.error:
        print(f"error: {res.error}")
    if args.dry_run:
        print("dry run: the lens was not moved" + ("" if res.power_dpt is None else f"; it would be set to {res.power_dpt:.3f} dpt"))
    return 0 if res.ok or res.status == "halted" else 1
