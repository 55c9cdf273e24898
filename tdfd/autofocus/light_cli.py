"""The assist-light options of ``tdfd autofocus`` (kept apart from the rest of the CLI).

Simulated bench::

    tdfd autofocus --sim --scene uniform --illumination coherent     # the paper's laser pattern
    tdfd autofocus --sim --scene uniform --illumination projector    # the projector (focused at 56.8 cm)
    tdfd autofocus --sim --illumination coherent                     # textured targets: lit only when needed

Real hardware (the light is opened only when named, before the lens is touched)::

    tdfd autofocus --port /dev/ttyACM0 --camera 0 --assist-light serial:/dev/ttyUSB0:rts
    tdfd autofocus --port /dev/ttyACM0 --camera 0 --assist-light "cmd:laser on,laser off"

Bad input is one line and nothing opened: an unknown ``--assist-light`` form, a port that
does not exist, ``--assist-light`` on the bench, ``--illumination`` on hardware without
``--assist-light``.
"""

from __future__ import annotations

import argparse
import contextlib
import signal
import threading
from typing import Any, Iterator

from ..errors import InputError
from ..light.guard import DEFAULT_LIMITS, LightLimits
from ..light.spec import SPEC_FORMS, parse_light_spec

__all__ = ["ILLUMINATIONS", "add_light_arguments", "check_light_args", "light_limits", "sim_light",
           "open_named_light", "light_summary", "sigterm_as_interrupt"]

#: values of ``--illumination``.
ILLUMINATIONS = ("coherent", "projector", "none")


def add_light_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the assist-light option group."""
    g = parser.add_argument_group("assist light (active DFD for texture-less targets)")
    g.add_argument("--illumination", choices=ILLUMINATIONS, default=None,
                   help="bench: light texture-less targets with the coherent laser pattern or the projector "
                        "(none: no light, the default); hardware: 'none' keeps a named --assist-light off")
    g.add_argument("--assist-light", default=None, metavar="SPEC",
                   help=f"hardware: the assist light, {SPEC_FORMS} (opened only when given)")
    g.add_argument("--subtract-ambient", action="store_true",
                   help="subtract the ambient (light-off) frame from the lit ones before estimating")
    g.add_argument("--light-max-on-ms", type=float, default=DEFAULT_LIMITS.max_on_s * 1e3,
                   help=f"longest light on-time per focus request, ms (default {DEFAULT_LIMITS.max_on_s * 1e3:g})")
    g.add_argument("--light-max-duty", type=float, default=DEFAULT_LIMITS.max_duty,
                   help=f"largest light duty cycle over {DEFAULT_LIMITS.duty_window_s:g} s (default "
                        f"{DEFAULT_LIMITS.max_duty:g})")


def check_light_args(args: argparse.Namespace) -> None:
    """Reject bad light options before anything is opened (one clear line each).

    Raises:
        InputError: ``--assist-light`` on the bench, ``--illumination`` on hardware without
            ``--assist-light``, a subtraction without a light, bad caps.
        LightSpecError: an unknown ``--assist-light`` form.
    """
    if args.assist_light is not None:
        parse_light_spec(args.assist_light)  # the form first: it is wrong wherever it is used
        if args.sim:
            raise InputError("--assist-light names a real light; the simulated bench takes --illumination "
                             "coherent|projector")
    if not args.sim and args.illumination is not None and args.assist_light is None:
        raise InputError("--illumination on hardware needs the light named with --assist-light "
                         f"({SPEC_FORMS})")
    lit = args.illumination not in (None, "none") if args.sim else (args.assist_light is not None
                                                                     and args.illumination != "none")
    if args.subtract_ambient and not lit:
        raise InputError("--subtract-ambient needs a light (--illumination coherent|projector on the bench, "
                         "--assist-light on hardware)")
    light_limits(args)


def light_limits(args: argparse.Namespace) -> LightLimits:
    """The caps from ``--light-max-on-ms`` and ``--light-max-duty``."""
    return LightLimits(max_on_s=args.light_max_on_ms / 1e3, max_duty=args.light_max_duty,
                       duty_window_s=DEFAULT_LIMITS.duty_window_s)


def sim_light(args: argparse.Namespace, camera: Any) -> tuple[Any | None, dict]:
    """The bench's light and the controller options for ``--illumination`` (``(None, {})`` without one)."""
    if args.illumination in (None, "none"):
        return None, {}
    from ..light.simulated import SimulatedLight

    return SimulatedLight(camera), {"illumination": args.illumination, "subtract_ambient": args.subtract_ambient}


def open_named_light(args: argparse.Namespace) -> Any | None:
    """Open the ``--assist-light`` the user named (``None`` if none): off on return.

    Raises:
        LightSpecError, LightConnectionError, ModemLineError, LightVerifyError,
        LightCommandError: see :func:`tdfd.light.open_light`.
    """
    if args.assist_light is None:
        return None
    from ..light.spec import open_light

    return open_light(args.assist_light)


def light_summary(records: list) -> str | None:
    """One line on what the light did over bench trials, ``None`` if no trial could use it."""
    used = [r for r in records if "light" in r.extra]
    if not used:
        return None
    lit = [r for r in used if r.extra.get("light")]
    on_ms = sum(float(r.extra.get("light_on_ms", 0.0)) for r in used)
    sub = sum(1 for r in lit if r.extra.get("ambient_subtracted"))
    tiles = [r.extra["lit_tiles"] / max(r.extra["roi_tiles"], 1) for r in lit if r.extra.get("roi_tiles")]
    share = f"; pattern on {100 * sum(tiles) / len(tiles):.0f} % of the ROI tiles (mean)" if tiles else ""
    return (f"assist light: lit {len(lit)} of {len(used)} DFD trials, on {on_ms:.1f} ms in all"
            f"{'; ambient subtracted' if sub else ''}{share}")


@contextlib.contextmanager
def sigterm_as_interrupt() -> Iterator[None]:
    """Turn SIGTERM into ``KeyboardInterrupt`` for the block (main thread only), so that a
    ``kill`` runs the same exit path as Ctrl-C: the light guard's ``finally`` switches the
    light off (a default SIGTERM ends the process without ``finally`` or ``atexit``)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def interrupt(signum, frame):  # noqa: ANN001, ARG001
        raise KeyboardInterrupt("SIGTERM")

    before = signal.signal(signal.SIGTERM, interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, before)
