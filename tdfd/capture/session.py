"""A capture session: focus sweeps and DFD pairs written as a capture folder.

Any rig with ``capture(commanded_dpt) -> (raw, sidecar dict)`` works:
:class:`~tdfd.capture.sim.SimulatedRig` or :class:`~tdfd.capture.hardware.HardwareRig`.
File names: ``{prefix}sweep{k:03d}`` for sweep frames, ``{prefix}pair{k:02d}_{1,2}`` for
pairs (pair tag ``{prefix}pair{k:02d}``).
"""

from __future__ import annotations

import logging
import math
import os
from pathlib import Path
from typing import Any, Sequence

from tqdm import tqdm

from ..errors import InputError
from .folder import write_frame

__all__ = ["parse_sweep", "parse_pair", "capture_session"]

log = logging.getLogger(__name__)


def parse_sweep(text: str) -> list[float]:
    """``"FROM:TO:STEP"`` dioptres -> the powers, both ends included.

    Raises:
        InputError: malformed, a zero step, a step of the wrong sign, or over 1000 frames.

    Example:
        >>> parse_sweep("0:1:0.25")
        [0.0, 0.25, 0.5, 0.75, 1.0]
    """
    try:
        lo, hi, step = (float(v) for v in text.split(":"))
    except ValueError:
        raise InputError(f"--sweep must be FROM:TO:STEP in dioptres, got {text!r}") from None
    if not all(math.isfinite(v) for v in (lo, hi, step)) or step == 0 or (hi - lo) * step < 0:
        raise InputError(f"--sweep {text!r}: STEP must be non-zero and go from FROM towards TO")
    n = int(math.floor((hi - lo) / step + 1e-9)) + 1
    if n > 1000:
        raise InputError(f"--sweep {text!r} gives {n} frames; at most 1000")
    return [round(lo + k * step, 9) for k in range(n)]


def parse_pair(text: str) -> tuple[float, float]:
    """``"P1,P2"`` dioptres -> a pair of different powers.

    Example:
        >>> parse_pair("1.7,2.7")
        (1.7, 2.7)
    """
    try:
        p1, p2 = (float(v) for v in text.split(","))
    except ValueError:
        raise InputError(f"--pair must be P1,P2 in dioptres, got {text!r}") from None
    if not (math.isfinite(p1) and math.isfinite(p2)) or p1 == p2:
        raise InputError(f"--pair {text!r}: two finite, different powers needed")
    return p1, p2


def capture_session(rig: Any, folder: str | os.PathLike, sweep: Sequence[float] = (),
                    pairs: Sequence[tuple[float, float]] = (), distance_m: float | None = None,
                    prefix: str = "", progress: bool = False) -> list[Path]:
    """Capture a focus sweep and DFD pairs into ``folder``.

    Args:
        rig: the capture rig.
        folder: capture folder (created if needed).
        sweep: ECVFL powers of the sweep, dioptres.
        pairs: ``(P1, P2)`` of each DFD pair, dioptres.
        distance_m: known target distance to record in every sidecar, or ``None``.
        prefix: file-name prefix (several scenes in one folder).
        progress: show a progress bar.

    Returns:
        The written PNG paths.
    """
    if not sweep and not pairs:
        raise InputError("nothing to capture: give a sweep and/or pairs")
    extra: dict[str, Any] = {} if distance_m is None else {"distance_m": float(distance_m)}
    jobs: list[tuple[str, float, str | None]] = [(f"{prefix}sweep{k:03d}", p, None) for k, p in enumerate(sweep)]
    for k, (p1, p2) in enumerate(pairs):
        tag = f"{prefix}pair{k:02d}"
        jobs += [(f"{tag}_1", p1, tag), (f"{tag}_2", p2, tag)]
    out = []
    for name, power, tag in tqdm(jobs, desc="capture", disable=not progress, unit="frame"):
        raw, meta = rig.capture(power)
        meta = {**meta, **extra}
        if tag is not None:
            meta["pair"] = tag
        out.append(write_frame(folder, name, raw, **meta))
        log.debug("%s at %.3f dpt", name, meta["lens_power_dpt"])
    log.info("wrote %d frames to %s", len(out), folder)
    return out
