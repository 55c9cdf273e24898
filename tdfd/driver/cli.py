"""``tdfd lens-emulator``: serve an emulated Lens Driver 4 on a pseudo-terminal.

The first line of standard output is the pty device path (e.g. ``/dev/pts/7``), flushed
at once, so a parent process can read it and open the port; everything else goes to the
log (standard error). The emulator serves until SIGINT or SIGTERM (exit status 0), or
until an injected disconnect closes the port.
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading

__all__ = ["register", "run"]

log = logging.getLogger(__name__)


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``lens-emulator`` subcommand."""
    parser = subparsers.add_parser(
        "lens-emulator",
        help="serve an emulated Optotune Lens Driver 4 on a pseudo-terminal",
        description=(
            "Serve an emulated Optotune Lens Driver 4 (EL-10-30) on a pseudo-terminal. "
            "Prints the device path as the first line of output, then serves until "
            "interrupted (SIGINT/SIGTERM)."
        ),
    )
    parser.add_argument("--firmware-type", default="A", help="firmware type letter reported by H (default A)")
    parser.add_argument(
        "--fault",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help=(
            "inject faults, repeatable: bad_crc=P, drop=P, late=P, garbage=P (probabilities per reply), "
            "corrupt=P (probability per command received), "
            "late_s=SECONDS, garbage_max_bytes=N, disconnect_after=COMMANDS, limit=N"
        ),
    )
    parser.add_argument("--seed", type=int, default=0, help="seed of the fault generator (default 0)")
    parser.add_argument("--error-style", choices=("E", "N"), default="E", help="reply to a bad command CRC: E 1 or bare N")
    parser.add_argument("--settling-time-ms", type=float, default=15.0, help="focal-power settling time to 1%% (default 15)")
    parser.add_argument("--temperature-c", type=float, default=25.0, help="lens temperature, degrees C (default 25)")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run the emulator until interrupted; returns the exit status."""
    from .emulator import Emulator, EmulatorServer, Faults

    try:
        faults = Faults.parse(args.fault, seed=args.seed)
        device = Emulator(
            firmware_type=args.firmware_type,
            error_style=args.error_style,
            settling_time_s=args.settling_time_ms / 1000.0,
            temperature_c=args.temperature_c,
        )
    except ValueError as exc:
        print(f"tdfd lens-emulator: error: {exc}", file=sys.stderr)
        return 2

    stop = threading.Event()

    def _on_signal(signum: int, _frame: object) -> None:
        log.info("signal %d: stopping", signum)
        stop.set()

    previous = {}
    for sig in (signal.SIGINT, signal.SIGTERM):
        try:
            previous[sig] = signal.signal(sig, _on_signal)
        except ValueError:  # not the main thread: rely on KeyboardInterrupt / stop()
            pass
    server = EmulatorServer(device, faults=faults)
    try:
        server.start()
        sys.stdout.write(f"{server.port}\n")
        sys.stdout.flush()
        log.info("lens emulator (firmware type %s) on %s; faults: %s", device.firmware_type, server.port, faults)
        while not stop.wait(0.1):
            if not server.running:
                log.warning("the emulated port was disconnected; exiting")
                break
    except KeyboardInterrupt:
        pass
    finally:
        server.stop()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return 0
