"""The ``tdfd`` command.

Each subcommand lives in its own module, which exposes ``register(subparsers)``: it adds
its parser and sets ``func`` (called with the parsed namespace, returns an exit code).
Modules are imported when the parser is built; they keep heavy imports (torch,
onnxruntime) inside their ``func``.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

from . import __version__
from .errors import TdfdError

__all__ = ["main", "build_parser", "SUBCOMMAND_MODULES"]

#: module path of each subcommand, in the order ``tdfd --help`` lists them.
SUBCOMMAND_MODULES: list[str] = [
    "tdfd.depth_cli",
    "tdfd.driver.cli",
    "tdfd.autofocus.cli",
    "tdfd.capture.cli",
    "tdfd.calibration.cli",
]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="tdfd", description="Motionless depth-from-defocus autofocus.")
    parser.add_argument("--version", action="version", version=f"tdfd {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more logging (-v info, -vv debug)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in SUBCOMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    level = [logging.WARNING, logging.INFO, logging.DEBUG][min(args.verbose, 2)]
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except TdfdError as exc:  # one-line errors for the user, typed errors for callers
        print(f"tdfd {args.command}: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
