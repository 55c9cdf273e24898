"""``python -m export``: export a trained DFD model to ONNX and verify it.

::

    python -m export --weights models/reference.safetensors --out models/reference.onnx

Loads :class:`tdfd.model.DFDModel` from ``<stem>.safetensors`` + ``<stem>.json``, exports it
(:func:`export.export_model`), then runs :func:`export.verify_onnx` (checker, contract,
ONNX Runtime versus torch on rendered pairs). Exit status 1 with a one-line error when
anything fails; ``--analytic`` exports the bare analytic layer instead (for development).

``--camera PRESET|FILE.json`` names the camera (a preset or a camera JSON file,
:func:`tdfd.camera_file.resolve_camera_file`): the analytic layer's camera with ``--analytic``
(default ``reference``); with ``--weights`` a check that the trained model was built for
that camera's optics (a model is trained for one camera: ``python -m training --set
model.camera=FILE.json``), refused when it was not. The file's focus breathing
(``magnification_per_dpt``) goes into the exported model: both frames are registered to a
common scale before the estimator (:mod:`tdfd.registration`), and the ``tdfd.breathing``
metadata records it. A model trained with the PSF family input (``model.psf_family_input``) is
told the file's measured ``psf_family`` (``tdfd calibrate``; absent: unknown), baked in as
the graph's code and recorded in ``tdfd.psf_family``; without ``--camera`` it exports the
family it was saved with (the shipped model: unknown). ONNX Runtime can run the file told
another family (``DepthRuntime(..., psf_family=...)``).
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

__all__ = ["main"]


def _parse_size(text: str) -> tuple[int, int]:
    try:
        h, w = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must look like 480x640, got {text!r}") from None
    return h, w


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m export", description=__doc__.split("\n\n")[0])
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--weights", type=Path, help="trained model: <stem>.safetensors (with <stem>.json beside it)")
    src.add_argument("--analytic", action="store_true",
                     help="export the analytic layer alone (depth_analytic = depth; camera from --camera)")
    p.add_argument("--camera", default=None, metavar="PRESET|FILE.json",
                   help="camera preset or camera JSON file: the --analytic layer's camera (default reference), "
                        "or the camera a --weights model must have been trained for")
    p.add_argument("--out", type=Path, required=True, help="output .onnx file")
    p.add_argument("--opset", type=int, default=18, help="ONNX opset (>= 18, default 18)")
    p.add_argument("--no-optimize", action="store_true", help="skip the ONNX optimiser")
    p.add_argument("--sizes", type=_parse_size, nargs="+", default=None,
                   help="parity image sizes HxW (default 64x64 150x203 480x640 1200x1600)")
    p.add_argument("--batches", type=int, nargs="+", default=[1, 3], help="parity batch sizes (default 1 3)")
    p.add_argument("--no-verify", action="store_true", help="export only")
    p.add_argument("-v", "--verbose", action="store_true")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    if not args.verbose:  # the exporter logs every pass at INFO and missing torchvision at WARNING
        for name in ("onnx_ir", "onnxscript", "torch.onnx", "torch.export"):
            logging.getLogger(name).setLevel(logging.ERROR)
    from tdfd.errors import TdfdError

    from .onnx_export import export_model
    from .verify import verify_onnx

    try:
        from tdfd.camera_file import resolve_camera_file

        camera_file = resolve_camera_file(args.camera) if args.camera is not None else None
        camera = camera_file.camera if camera_file is not None else None
        if args.analytic:
            from .standin import analytic_model

            if camera_file is not None and camera_file.magnification_per_dpt:
                from tdfd.errors import CameraError

                raise CameraError(f"{args.camera}: --analytic exports no breathing registration; export a "
                                  "trained model with --weights for a camera with magnification_per_dpt")
            model = analytic_model(camera)
        else:
            from tdfd.errors import ModelError
            from tdfd.model import DFDModel

            model = DFDModel.load(args.weights)
            if camera is not None and camera != model.camera:
                raise ModelError(f"{args.weights} was trained for camera {model.camera.to_dict()}, not for "
                                 f"{args.camera} ({camera.to_dict()}); train one for it with "
                                 f"python -m training --set model.camera={args.camera}")
            if camera_file is not None:
                model.set_breathing(camera_file.magnification_per_dpt)
                if model.psf_family_input:
                    model.set_psf_family(camera_file.psf_family)
                elif camera_file.psf_family is not None:
                    logging.getLogger("export").warning(
                        "%s names psf_family %r, but %s was trained without the PSF family input: not used",
                        args.camera, camera_file.psf_family, args.weights)
        model.eval()
        t0 = time.perf_counter()
        path = export_model(model, args.out, opset=args.opset, optimize=not args.no_optimize)
        print(f"exported {path} ({path.stat().st_size / 1024:.0f} kB) in {time.perf_counter() - t0:.1f} s")
        if not args.no_verify:
            sizes = args.sizes or [(64, 64), (150, 203), (480, 640), (1200, 1600)]
            t0 = time.perf_counter()
            report = verify_onnx(path, model, sizes=sizes, batches=args.batches)
            print(report)
            print(f"verified in {time.perf_counter() - t0:.1f} s")
    except TdfdError as exc:
        print(f"python -m export: error: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
