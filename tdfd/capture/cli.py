"""``tdfd capture``: write focus sweeps and DFD pairs into a capture folder.

Hardware: ``tdfd capture OUT --port /dev/ttyACM0 --camera 0 --sweep 0:4:0.25 --pair 1.7,2.7``
(the lens power in each sidecar is read back from the driver; ``--distance`` records a
measured target distance). Simulation: ``tdfd capture OUT --sim --camera-file TRUE.json
--distance 0.5 --sweep 0:4:0.25`` renders a textured plane with the true camera of
``TRUE.json`` (its ``ecvfl_offset_dpt`` and ``magnification_per_dpt`` included); the
distance goes into the sidecars only with ``--record-distance``.
"""

from __future__ import annotations

import argparse
import logging

from ..errors import InputError

__all__ = ["register", "run"]

log = logging.getLogger(__name__)


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``capture`` subcommand."""
    p = subparsers.add_parser("capture", help="capture focus sweeps and DFD pairs into a capture folder",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("out", metavar="DIR", help="capture folder to write (created if missing)")
    p.add_argument("--sweep", metavar="FROM:TO:STEP", help="focus sweep, ECVFL powers in dioptres")
    p.add_argument("--pair", metavar="P1,P2", action="append", default=[],
                   help="a DFD pair at these ECVFL powers (repeatable; default with --camera-file: its lens_powers_dpt)")
    p.add_argument("--camera-file", metavar="CAM.json", help="camera JSON (required with --sim: the true simulated camera)")
    p.add_argument("--distance", type=float, metavar="M", help="target distance, metres (hardware: recorded; --sim: the plane)")
    p.add_argument("--prefix", default="", help="file-name prefix, e.g. one per scene")
    g = p.add_argument_group("hardware")
    g.add_argument("--port", help="serial port of the Optotune Lens Driver 4")
    g.add_argument("--camera", metavar="INDEX_OR_URL", help="OpenCV camera index or URL")
    g.add_argument("--settle-ms", type=float, default=50.0, help="wait after each lens command (default 50 ms)")
    g.add_argument("--flush", type=int, default=2, help="frames dropped before each capture (default 2)")
    g.add_argument("--white-level", type=float, help="raw value of full scale (e.g. 4095 for 12-bit data)")
    s = p.add_argument_group("simulation")
    s.add_argument("--sim", action="store_true", help="simulated bench instead of hardware")
    s.add_argument("--record-distance", action="store_true", help="--sim: write the plane distance into the sidecars")
    s.add_argument("--size", type=int, nargs=2, default=(256, 256), metavar=("H", "W"), help="--sim frame size")
    s.add_argument("--seed", type=int, default=0, help="--sim texture and noise seed")
    s.add_argument("--texture", default="dead_leaves", help="--sim texture family (tdfd.textures)")
    s.add_argument("--psf", default="gaussian", help="--sim PSF shape: gaussian, pillbox or a power-exponential beta")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..camera_file import load_camera_file
    from .session import capture_session, parse_pair, parse_sweep

    sweep = parse_sweep(args.sweep) if args.sweep else []
    pairs = [parse_pair(t) for t in args.pair]
    cam_file = load_camera_file(args.camera_file) if args.camera_file else None
    if not pairs and not sweep and cam_file is not None:
        pairs = [cam_file.camera.lens_powers_dpt]
    if not pairs and not sweep:
        raise InputError("nothing to capture: give --sweep and/or --pair (or --camera-file for its pair)")
    if args.sim:
        if args.port or args.camera:
            raise InputError("--sim takes no --port or --camera")
        if cam_file is None or args.distance is None:
            raise InputError("--sim needs --camera-file TRUE.json and --distance M")
        from .sim import SimulatedRig

        psf = args.psf if args.psf in ("gaussian", "pillbox") else float(args.psf)
        rig = SimulatedRig(cam_file, args.distance, size=tuple(args.size), seed=args.seed, texture=args.texture, psf=psf)
        recorded = args.distance if args.record_distance else None
    else:
        if not (args.port and args.camera is not None):
            raise InputError("hardware capture needs --port and --camera (or --sim for the simulated bench)")
        if args.record_distance:
            raise InputError("--record-distance is for --sim; on hardware --distance is always recorded")
        from .hardware import HardwareRig

        rig = HardwareRig.open(args.port, args.camera, settle_s=args.settle_ms / 1000.0, flush=args.flush,
                               white_level=args.white_level)
        recorded = args.distance
    try:
        paths = capture_session(rig, args.out, sweep, pairs, distance_m=recorded, prefix=args.prefix, progress=True)
    finally:
        rig.close()
    print(f"wrote {len(paths)} frames to {args.out}")
    return 0
