r"""``tdfd depth``: depth from a DFD pair of image files with the exported ONNX model.

::

    tdfd depth IMAGE_F1 IMAGE_F2 [--model M] [-o depth.npy|.tiff|.png] [--white-level L]
               [--full-resolution] [--threshold C] [--centre FRACTION] [--threads T]
               [--psf-family gaussian|pillbox|unknown|CAM.json] [--tiles]
               [--likelihood-stage SCALES.json [--black-level DN] [--psf-model CAM.json] [--likelihood-walk N]
                [--likelihood-pool] [--likelihood-ambiguity] [--likelihood-register]]

Reads single-channel 8- or 16-bit PNG/TIFF frames (or float32 TIFF in [0, 1]) with OpenCV
(``IMREAD_UNCHANGED``), runs :class:`tdfd.runtime.DepthRuntime` (no torch), prints a
summary (median depth of the confident cells in the centre region, valid fraction, the
in-focus ECVFL power for that depth) and, with ``-o``, writes:

* the depth map: ``.npy`` float32 metres, ``.tif``/``.tiff`` float32 metres, or ``.png``
  uint16 millimetres (0 where the confidence is below the threshold); on the tile grid,
  or at image resolution with ``--full-resolution``. A model with the structure pooling
  (:data:`tdfd.contract.POOLED_OUTPUT_NAMES`) writes its pooled map and that map's confidence;
  ``--tiles`` writes each tile's own estimate instead (the printed summary reads the tiles);
* ``<stem>_color.png``: the depth at image resolution in a fixed colour scale over the
  camera's working range (turbo colour map, near = red, far = blue), low-confidence
  regions greyed, with a labelled scale bar in metres.

With ``--likelihood-stage`` the map is refined tile by tile by the likelihood stage
(:mod:`tdfd.runtime_likelihood`: torch, seconds per pair), told the sensor's ``--black-level``
and, with ``--psf-model CAM.json``, the lens's whole PSF a focus sweep measured
(``tdfd calibrate --psf-model``) instead of profiling the family's shapes; with
``--likelihood-pool`` its fused map is also pooled along the depth structure by the model's own
structure pooling (:mod:`tdfd.dfd.stage_pooling`); with ``--likelihood-ambiguity`` a pair whose
likelihood prefers depths 10 % from its fits (narrow-band or periodic textures) keeps its map
with every confidence capped (:mod:`tdfd.dfd.scene_ambiguity`); with ``--likelihood-register`` the
stage fits each pair's focus breathing and shift to its own likelihood first
(:mod:`tdfd.dfd.pair_registration`).

Colour (3- or 4-channel) files are rejected: DFD needs the raw single-channel sensor
frames (convert a colour image yourself if you must; gamma-encoded JPEG-like data is not
linear intensity). Both files must have the same size and the same pixel type. Errors are
one line, ``tdfd depth: error: ...``.
"""

from __future__ import annotations

import argparse
import logging
import math
import os
from pathlib import Path
from typing import Any

from .errors import CameraError, DTypeError, InputError, ShapeError

__all__ = ["register", "read_frame", "write_depth", "check_writable", "colorize_depth", "psf_family_option", "measured_psf_model", "run"]

logger = logging.getLogger(__name__)

_DEPTH_SUFFIXES = (".npy", ".tif", ".tiff", ".png")


def register(subparsers: Any) -> None:
    """Add the ``depth`` subcommand to ``tdfd``'s parser."""
    p = subparsers.add_parser(
        "depth", help="depth map from a DFD image pair (ONNX Runtime)",
        description="Estimate depth from two frames taken at the camera's two ECVFL powers, with the exported "
                    "ONNX model. Frames: single-channel 8/16-bit PNG or TIFF (or float32 TIFF in [0, 1]).")
    p.add_argument("image_f1", help="frame at the first ECVFL power (PNG/TIFF)")
    p.add_argument("image_f2", help="frame at the second ECVFL power (PNG/TIFF)")
    p.add_argument("--model", default=None,
                   help="ONNX model (default: $TDFD_MODEL, else the model shipped with tdfd)")
    p.add_argument("-o", "--output", default=None,
                   help="depth map to write: .npy / .tif(f) float32 metres, .png uint16 millimetres; "
                        "also writes <stem>_color.png")
    p.add_argument("--white-level", type=float, default=None,
                   help="raw value of full scale (default 255 for 8-bit, 65535 for 16-bit; e.g. 4095 for 12-bit data)")
    p.add_argument("--full-resolution", action="store_true", help="write the depth map at image resolution")
    p.add_argument("--threshold", type=float, default=0.1,
                   help="confidence at which a cell counts as valid (default 0.1: predicted error about 3 %% for the "
                        "reference model)")
    p.add_argument("--centre", type=float, default=0.5,
                   help="fraction of the image height and width forming the centre region (default 0.5)")
    p.add_argument("--tiles", action="store_true",
                   help="write each tile's own estimate instead of the depth map pooled along the scene's depth "
                        "structure (a model with that stage writes the pooled map by default)")
    p.add_argument("--threads", type=int, default=2, help="ONNX Runtime threads (default 2)")
    p.add_argument("--likelihood-stage", default=None, metavar="SCALES.json",
                   help="refine the depth map by each tile's cross-residual likelihood fit, fused with the model "
                        "(tdfd.dfd.likelihood_stage, torch, seconds per pair); SCALES.json holds its sigma factors "
                        "(the shipped model's: models/reference.likelihood.json)")
    p.add_argument("--black-level", type=float, default=0.0,
                   help="the sensor's black level in raw values (default 0), for --likelihood-stage")
    p.add_argument("--psf-model", default=None, metavar="CAM.json",
                   help="a camera JSON from 'tdfd calibrate --psf-model': the lens's whole PSF measured from a focus "
                        "sweep, the likelihood stage's one PSF (default: profiled over the family's shapes)")
    p.add_argument("--likelihood-walk", type=int, default=0, metavar="N",
                   help="for --likelihood-stage: let a tile whose fit finds no minimum within 5 %% of the model's "
                        "depth move its search window up to N times; a walk that ends farther from the fitted "
                        "neighbours than the model's depth is undone (default 0; section psf_structure's notes)")
    p.add_argument("--likelihood-pool", action="store_true",
                   help="for --likelihood-stage: pool its fused map along the depth structure with the model's own "
                        "structure pooling, each tile weighted by its fused confidence (tdfd.dfd.stage_pooling; "
                        "section psf_structure)")
    p.add_argument("--likelihood-ambiguity", action="store_true",
                   help="for --likelihood-stage: check each pair's fit against its likelihood over the whole depth "
                        "range and cap every confidence of a pair whose likelihood prefers depths 10 %% from its fits "
                        "(tdfd.dfd.scene_ambiguity; section psf_structure's notes)")
    p.add_argument("--likelihood-register", action="store_true",
                   help="for --likelihood-stage: fit each pair's focus breathing and sub-pixel shift to its own "
                        "likelihood before the fit (tdfd.dfd.pair_registration; section psf_structure's notes); "
                        "needed for a model file that registers breathing")
    p.add_argument("--psf-family", default="exported", metavar="FAMILY",
                   help="the lens's PSF family the model's CNN is told: gaussian, pillbox, unknown, a camera JSON "
                        "from 'tdfd calibrate' (its measured psf_family), or exported (default: the family the ONNX "
                        "file was exported with); only for a model with the family input")
    p.set_defaults(func=run)


def measured_psf_model(path: str) -> dict:
    """The ``psf_model`` of the camera file at ``path`` (``--psf-model``).

    Raises:
        CameraError: a file that cannot be read, or one without a measured ``psf_model`` (the
            message says how to measure one).
    """
    from .camera_file import load_camera_file

    cf = load_camera_file(path)
    if cf.psf_model is None:
        raise CameraError(f"{path} has no measured psf_model: measure one with 'tdfd calibrate ... --psf-model' "
                          f"on capture folders that hold a focus sweep")
    return cf.psf_model


def psf_family_option(text: str) -> str | None:
    """The ``psf_family`` of :class:`~tdfd.runtime.DepthRuntime` that ``--psf-family text`` names.

    Raises:
        InputError: neither a family, ``unknown``, ``exported`` nor a ``.json`` path.
        CameraError: a camera file that cannot be read (the message names it).
    """
    from .autofocus.psf_family_option import resolve_psf_family
    from .camera_file import PSF_FAMILY_VALUES

    if text in (*PSF_FAMILY_VALUES, "unknown", "exported"):
        return text
    if Path(text).suffix.lower() != ".json":
        raise InputError(f"--psf-family must be one of {PSF_FAMILY_VALUES}, 'unknown', 'exported' or a camera JSON "
                         f"file, got {text!r}")
    return resolve_psf_family(text)[0]  # the camera file's measured family (unknown, with a warning, when it has none)


def read_frame(path: str | Path) -> Any:
    """Read a single-channel frame with OpenCV, unchanged (uint8, uint16 or float32).

    Raises:
        InputError: missing or unreadable file.
        ShapeError: a colour (multi-channel) image.
        DTypeError: a pixel type other than 8/16-bit unsigned or 32-bit float.
    """
    import cv2
    import numpy as np

    p = Path(path)
    if not p.is_file():
        raise InputError(f"cannot read {p}: no such file")
    img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputError(f"cannot read {p}: not an image OpenCV can decode")
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[..., 0]
    if img.ndim != 2:
        raise ShapeError(f"{p} has {img.shape[2]} channels; DFD needs single-channel (raw or greyscale) frames")
    if img.dtype not in (np.uint8, np.uint16, np.float32):
        raise DTypeError(f"{p} has {img.dtype} pixels; expected 8- or 16-bit unsigned integers (or float32 in [0, 1])")
    return img


def colorize_depth(depth: Any, confidence: Any, depth_range: tuple[float, float], threshold: float = 0.1,
                   min_width: int = 480) -> Any:
    """A BGR uint8 picture of a depth map with a labelled scale bar in metres.

    Args:
        depth: ``(H, W)`` depth in metres.
        confidence: ``(H, W)`` confidence in [0, 1].
        depth_range: ``(near, far)`` of the colour scale in metres (near = red, far = blue).
        threshold: pixels below this confidence are shown greyed.
        min_width: the picture is upscaled (nearest) to at least this width.

    Returns:
        ``(H' + bar, W', 3)`` uint8 BGR image.
    """
    import cv2
    import numpy as np

    near, far = float(depth_range[0]), float(depth_range[1])
    inv = 1.0 / np.asarray(depth, dtype=np.float64)
    # colour linear in inverse depth (like the blur); near -> 255 (red in turbo)
    t = np.clip((inv - 1.0 / far) / (1.0 / near - 1.0 / far), 0.0, 1.0)
    img = cv2.applyColorMap(np.round(t * 255).astype(np.uint8), cv2.COLORMAP_TURBO)
    low = np.asarray(confidence) < threshold
    if low.any():
        grey = np.full_like(img, 96)
        img[low] = (0.35 * img[low] + 0.65 * grey[low]).astype(np.uint8)
    scale = max(1, int(math.ceil(min_width / img.shape[1])))
    if scale > 1:
        img = cv2.resize(img, (img.shape[1] * scale, img.shape[0] * scale), interpolation=cv2.INTER_NEAREST)
    width = img.shape[1]
    bar_h, pad = 60, 20
    bar = np.full((bar_h, width, 3), 255, np.uint8)
    x0, x1 = pad, width - pad
    ramp = np.linspace(1.0, 0.0, x1 - x0)  # left = near ... right = far, in inverse depth
    colours = cv2.applyColorMap(np.round(ramp * 255).astype(np.uint8)[None, :], cv2.COLORMAP_TURBO)
    bar[8:24, x0:x1] = colours
    cv2.rectangle(bar, (x0, 8), (x1 - 1, 23), (0, 0, 0), 1)
    ticks = _nice_ticks(near, far)
    for d in ticks:
        u = (1.0 / near - 1.0 / d) / (1.0 / near - 1.0 / far)
        x = int(round(x0 + u * (x1 - x0 - 1)))
        cv2.line(bar, (x, 24), (x, 30), (0, 0, 0), 1)
        label = f"{d:g}"
        (tw, _), _ = cv2.getTextSize(label, cv2.FONT_HERSHEY_SIMPLEX, 0.4, 1)
        cv2.putText(bar, label, (min(max(x - tw // 2, 0), width - tw), 44), cv2.FONT_HERSHEY_SIMPLEX, 0.4,
                    (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(bar, "depth [m] (grey: low confidence)", (x0, 57), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (0, 0, 0), 1,
                cv2.LINE_AA)
    return np.concatenate([img, bar], 0)


def _nice_ticks(near: float, far: float) -> list[float]:
    span = far - near
    for step in (0.05, 0.1, 0.2, 0.25, 0.5, 1.0, 2.0, 5.0):
        if span / step <= 8:
            break
    first = math.ceil(near / step - 1e-9) * step
    ticks = [round(first + k * step, 6) for k in range(int((far - first) / step + 1e-9) + 1)]
    return [t for t in ticks if near - 1e-9 <= t <= far + 1e-9] or [near, far]


def write_depth(path: str | Path, depth: Any, confidence: Any, threshold: float = 0.1) -> Path:
    """Write a depth map in metres: ``.npy``/``.tif(f)`` float32 metres, ``.png`` uint16 mm.

    In the PNG, cells below ``threshold`` confidence are 0 (no depth) and depths are
    clipped to 65.535 m.

    Raises:
        InputError: an unsupported suffix or a failed write.
    """
    import cv2
    import numpy as np

    p = Path(path)
    suffix = p.suffix.lower()
    if suffix not in _DEPTH_SUFFIXES:
        raise InputError(f"output {p} must end in one of {', '.join(_DEPTH_SUFFIXES)}")
    d = np.asarray(depth, dtype=np.float32)
    if suffix == ".npy":
        return _write(p, lambda target: np.save(target, d))
    if suffix == ".png":
        mm = np.clip(np.round(d * 1000.0), 0, 65535).astype(np.uint16)
        mm[np.asarray(confidence) < threshold] = 0
        return _write(p, lambda target: cv2.imwrite(str(target), mm))
    return _write(p, lambda target: cv2.imwrite(str(target), d))


def check_writable(path: str | Path) -> Path:
    """Fail early (before any work) if ``path``'s folder cannot be created or written.

    Raises:
        InputError: the folder cannot be created, is not a folder, or is not writable.
    """
    p = Path(path)
    parent = p.parent if str(p.parent) else Path(".")
    try:
        parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"cannot write {p}: {exc.strerror or exc}") from exc
    if not os.access(parent, os.W_OK | os.X_OK):
        raise InputError(f"cannot write {p}: folder {parent} is not writable")
    if p.is_dir():
        raise InputError(f"cannot write {p}: it is a folder")
    return p


def _write(p: Path, write: Any) -> Path:
    """Run ``write(p)`` (returns ``False`` on failure, like ``cv2.imwrite``) with one typed error."""
    import cv2

    check_writable(p)
    try:
        ok = write(p)
    except (OSError, cv2.error) as exc:
        reason = getattr(exc, "strerror", None) or str(exc).strip().splitlines()[-1]
        raise InputError(f"cannot write {p}: {reason}") from exc
    if ok is False:
        raise InputError(f"cannot write {p}")
    return p


def run(args: argparse.Namespace) -> int:
    """Body of ``tdfd depth`` (see the module docstring)."""
    import cv2
    import numpy as np

    from .runtime import DepthRuntime, default_model_path

    if args.output is not None and Path(args.output).suffix.lower() not in _DEPTH_SUFFIXES:
        raise InputError(f"output {args.output} must end in one of {', '.join(_DEPTH_SUFFIXES)}")
    if not 0.0 <= args.threshold <= 1.0:
        raise InputError(f"--threshold must be in [0, 1], got {args.threshold}")
    if not 0.0 < args.centre <= 1.0:
        raise InputError(f"--centre must be in (0, 1], got {args.centre}")
    if args.output is not None:
        check_writable(args.output)
    f1, f2 = read_frame(args.image_f1), read_frame(args.image_f2)
    if f1.shape != f2.shape:
        raise ShapeError(f"{args.image_f1} is {f1.shape[0]}x{f1.shape[1]} but {args.image_f2} is "
                         f"{f2.shape[0]}x{f2.shape[1]}; the frames must have the same size")
    if f1.dtype != f2.dtype:
        raise DTypeError(f"{args.image_f1} has {f1.dtype} pixels but {args.image_f2} has {f2.dtype}")
    model = Path(args.model) if args.model else default_model_path()
    rt = DepthRuntime(model, threads=args.threads, psf_family=psf_family_option(args.psf_family))
    res = rt(f1, f2, white_level=args.white_level, pooled=not args.tiles)
    if args.psf_model and not args.likelihood_stage:
        raise InputError("--psf-model is the likelihood stage's PSF; give --likelihood-stage SCALES.json too")
    if args.likelihood_walk and not args.likelihood_stage:
        raise InputError("--likelihood-walk moves the likelihood stage's windows; give --likelihood-stage "
                         "SCALES.json too")
    if args.likelihood_pool and not args.likelihood_stage:
        raise InputError("--likelihood-pool pools the likelihood stage's map; give --likelihood-stage SCALES.json too")
    if args.likelihood_ambiguity and not args.likelihood_stage:
        raise InputError("--likelihood-ambiguity checks the likelihood stage's fit; give --likelihood-stage SCALES.json "
                         "too")
    if args.likelihood_register and not args.likelihood_stage:
        raise InputError("--likelihood-register registers the pair for the likelihood stage; give --likelihood-stage "
                         "SCALES.json too")
    if args.likelihood_stage:
        if args.tiles:
            raise InputError("--likelihood-stage refines the depth map; it cannot be combined with --tiles")
        from .runtime_likelihood import refine_result, stage_for_runtime  # torch: only when asked for

        white = args.white_level if args.white_level is not None else (
            float(np.iinfo(f1.dtype).max) if np.issubdtype(f1.dtype, np.integer) else 1.0)
        stage = stage_for_runtime(rt, args.likelihood_stage, args.black_level / white,
                                  psf_model=measured_psf_model(args.psf_model) if args.psf_model else None,
                                  walk=args.likelihood_walk, pool=args.likelihood_pool,
                                  ambiguity=args.likelihood_ambiguity, register=args.likelihood_register)
        res = refine_result(rt, stage, f1, f2, res, args.white_level)
    h, w = res.depth.shape
    valid = res.valid(args.threshold)
    centre = res.centre_depth(args.centre, args.threshold)
    print(f"{args.image_f1}, {args.image_f2}: {f1.shape[0]}x{f1.shape[1]} {f1.dtype}, {h}x{w} tiles "
          f"({rt.tile} px, stride {rt.stride}), model {model.name}"
          + (f", told PSF family {rt.psf_family or 'unknown'}" if rt.psf_family_info.takes_input else ""))
    if math.isfinite(centre):
        print(f"centre depth: {centre:.4f} m (median of confident cells in the central {args.centre:.0%}); "
              f"in-focus ECVFL power {rt.in_focus_power_dpt(centre):+.3f} dpt")
    else:
        loose = res.centre_depth(args.centre, 0.0)
        best = float(np.max(res.confidence[res._centre_mask(args.centre)]))
        print(f"centre depth: {loose:.4f} m UNRELIABLE (no cell in the central {args.centre:.0%} reaches confidence "
              f"{args.threshold:g}; best {best:.3g})")
    if res.problem:
        print(f"no DFD pair: {res.problem}; every cell has confidence 0")
    print(f"valid: {valid.mean():.1%} of {valid.size} cells (confidence >= {args.threshold:g}); "
          f"depth {np.nanmin(res.depth):.3f}-{np.nanmax(res.depth):.3f} m")
    if args.output:
        full = res.at_full_resolution()
        out = full if args.full_resolution else res
        depth, conf = out.depth_map
        path = write_depth(args.output, depth, conf, args.threshold)
        picture = colorize_depth(*full.depth_map, rt.camera.depth_range_m, args.threshold)
        pic = _write(path.with_name(path.stem + "_color.png"), lambda target: cv2.imwrite(str(target), picture))
        if args.likelihood_stage:
            kind = "refined by the likelihood stage" + (", pooled along the depth structure" if args.likelihood_pool
                                                        else "")
        else:
            kind = "pooled along the depth structure" if out.depth_pooled is not None else "each tile's own estimate"
        print(f"wrote {path} ({'x'.join(map(str, depth.shape))} "
              f"{'uint16 mm' if path.suffix.lower() == '.png' else 'float32 m'}; {kind}) and {pic}")
    return 0
