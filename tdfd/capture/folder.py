"""The capture folder (CONTRACT.md section 4): PNG frames with one JSON sidecar each.

A frame ``NAME.png`` (8- or 16-bit, one channel, linear sensor values) has a sidecar
``NAME.json`` holding one JSON object:

* ``lens_power_dpt`` (required): ECVFL power at the exposure, dioptres (read back from the
  lens driver where it can be).
* ``distance_m`` (optional): known target distance, metres (known-distance calibration).
* ``white_level`` (optional): raw value of full scale; default the PNG's own full scale
  (255 or 65535).
* ``exposure_s``, ``temperature_c``, ``time_s`` (optional): as measured.
* ``pair`` (optional): a string shared by the two frames of one DFD pair; frames without
  it belong to a focus sweep.

Unknown keys are kept (:attr:`CaptureFrame.extra`) and ignored. Every problem is a
:class:`CaptureFolderError` that names the file: a frame without a readable sidecar, a
sidecar without ``lens_power_dpt`` or with a malformed value, an unreadable or multi-channel
PNG, a saturated or black frame, frames of different sizes.

Example:
    >>> import tempfile, numpy as np
    >>> d = tempfile.mkdtemp()
    >>> raw = (np.arange(64 * 64).reshape(64, 64) % 4000 + 50).astype(np.uint16)
    >>> _ = write_frame(d, "f1", raw, lens_power_dpt=1.7, white_level=4095, pair="a")
    >>> _ = write_frame(d, "f2", raw, lens_power_dpt=2.7, white_level=4095, pair="a")
    >>> [(f.name, f.power_dpt, f.metadata.pair) for f in read_folder(d)]
    [('f1', 1.7, 'a'), ('f2', 2.7, 'a')]
"""

from __future__ import annotations

import json
import logging
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError

__all__ = ["CaptureFolderError", "FrameMetadata", "CaptureFrame", "write_frame", "read_frame", "read_folder",
           "check_exposure", "SATURATED_FRACTION", "BLACK_LEVEL_FRACTION", "KNOWN_KEYS"]

log = logging.getLogger(__name__)

#: a frame with more than this fraction of its pixels at the white level is saturated.
SATURATED_FRACTION = 0.01
#: a frame whose 99.9th percentile lies below this fraction of full scale is black.
BLACK_LEVEL_FRACTION = 0.03
#: the sidecar keys the contract defines.
KNOWN_KEYS = ("lens_power_dpt", "distance_m", "white_level", "exposure_s", "temperature_c", "time_s", "pair")


class CaptureFolderError(InputError):
    """A capture folder, frame or sidecar that cannot be used; the message names the file."""


@dataclass(frozen=True)
class FrameMetadata:
    """One sidecar's contents (SI units). ``extra`` keeps unknown keys, unused."""

    lens_power_dpt: float
    distance_m: float | None = None
    white_level: float | None = None
    exposure_s: float | None = None
    temperature_c: float | None = None
    time_s: float | None = None
    pair: str | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """The sidecar JSON object (optional keys only when set; unknown keys kept)."""
        out: dict[str, Any] = dict(self.extra)
        for k in KNOWN_KEYS:
            v = getattr(self, k)
            if v is not None:
                out[k] = v
        return out

    @classmethod
    def from_dict(cls, data: Any, source: str) -> "FrameMetadata":
        """Validate a parsed sidecar; ``source`` names the file in errors."""
        if not isinstance(data, dict):
            raise CaptureFolderError(f"{source}: the sidecar must be a JSON object, got {type(data).__name__}")
        if "lens_power_dpt" not in data:
            raise CaptureFolderError(f"{source}: the sidecar lacks the required key 'lens_power_dpt'")

        def number(key: str, positive: bool = False) -> float | None:
            if key not in data or data[key] is None:
                return None
            v = data[key]
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(float(v)):
                raise CaptureFolderError(f"{source}: '{key}' must be a finite number, got {v!r}")
            if positive and float(v) <= 0:
                raise CaptureFolderError(f"{source}: '{key}' must be > 0, got {v!r}")
            return float(v)

        pair = data.get("pair")
        if pair is not None and not isinstance(pair, str):
            raise CaptureFolderError(f"{source}: 'pair' must be a string, got {pair!r}")
        return cls(lens_power_dpt=number("lens_power_dpt"),  # type: ignore[arg-type]
                   distance_m=number("distance_m", True), white_level=number("white_level", True),
                   exposure_s=number("exposure_s", True), temperature_c=number("temperature_c"),
                   time_s=number("time_s"), pair=pair,
                   extra={k: v for k, v in data.items() if k not in KNOWN_KEYS})


@dataclass(frozen=True)
class CaptureFrame:
    """A frame of a capture folder.

    Attributes:
        name: the file stem (``NAME`` of ``NAME.png``).
        path: the PNG's path.
        image: ``(H, W)`` float64 linear intensity, raw value / white level, in [0, 1].
        metadata: the sidecar.
    """

    name: str
    path: Path
    image: np.ndarray
    metadata: FrameMetadata

    @property
    def power_dpt(self) -> float:
        return self.metadata.lens_power_dpt

    @property
    def shape(self) -> tuple[int, int]:
        return self.image.shape  # type: ignore[return-value]


def check_exposure(image: np.ndarray, source: str) -> None:
    """Raise :class:`CaptureFolderError` for a saturated or black frame (``image`` in [0, 1])."""
    sat = float(np.mean(image >= 1.0))
    if sat > SATURATED_FRACTION:
        raise CaptureFolderError(f"{source}: saturated frame ({100 * sat:.1f} % of pixels at the white level, "
                                 f"limit {100 * SATURATED_FRACTION:.0f} %); lower the exposure or gain")
    top = float(np.percentile(image, 99.9))
    if top < BLACK_LEVEL_FRACTION:
        raise CaptureFolderError(f"{source}: black frame (99.9th percentile at {100 * top:.2f} % of full scale, "
                                 f"limit {100 * BLACK_LEVEL_FRACTION:.0f} %); raise the exposure or light the scene")


def write_frame(folder: str | os.PathLike, name: str, raw: np.ndarray, lens_power_dpt: float,
                **metadata: Any) -> Path:
    """Write ``NAME.png`` (raw values, uint8 or uint16, one channel) and ``NAME.json``.

    Args:
        folder: the capture folder (created if missing).
        name: file stem.
        raw: ``(H, W)`` uint8 or uint16 raw sensor values.
        lens_power_dpt: ECVFL power (read back), dioptres.
        **metadata: the optional sidecar keys (``distance_m``, ``white_level``, ``pair``, …)
            and any extra keys; ``None`` values are left out.

    Returns:
        The PNG's path.

    Raises:
        CaptureFolderError: not a 2-D uint8/uint16 array, or the PNG cannot be written.
    """
    import cv2

    a = np.asarray(raw)
    if a.ndim != 2 or a.dtype not in (np.uint8, np.uint16):
        raise CaptureFolderError(f"{name}: frames are (H, W) uint8 or uint16 raw values, got {a.dtype} {a.shape}")
    d = Path(folder)
    d.mkdir(parents=True, exist_ok=True)
    meta = FrameMetadata.from_dict({"lens_power_dpt": lens_power_dpt,
                                    **{k: v for k, v in metadata.items() if v is not None}}, name)
    png = d / f"{name}.png"
    if not cv2.imwrite(str(png), a):
        raise CaptureFolderError(f"{png}: cannot write the PNG")
    (d / f"{name}.json").write_text(json.dumps(meta.to_dict(), indent=1, sort_keys=True) + "\n")
    return png


def read_frame(png: str | os.PathLike, check: bool = True) -> CaptureFrame:
    """Read one frame and its sidecar.

    Raises:
        CaptureFolderError: unreadable or multi-channel PNG, missing or malformed sidecar,
            raw values above the white level, or (``check``) a saturated or black frame.
    """
    import cv2

    png = Path(png)
    side = png.with_suffix(".json")
    if not side.is_file():
        raise CaptureFolderError(f"{png}: no sidecar {side.name} beside the frame")
    try:
        data = json.loads(side.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CaptureFolderError(f"{side}: malformed sidecar: {exc}") from exc
    meta = FrameMetadata.from_dict(data, str(side))
    raw = cv2.imread(str(png), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise CaptureFolderError(f"{png}: not a readable PNG")
    if raw.ndim != 2:
        raise CaptureFolderError(f"{png}: frames must have one channel, got shape {raw.shape}")
    if raw.dtype not in (np.uint8, np.uint16):
        raise CaptureFolderError(f"{png}: frames must be 8- or 16-bit, got {raw.dtype}")
    full = 255.0 if raw.dtype == np.uint8 else 65535.0
    white = meta.white_level if meta.white_level is not None else full
    if white > full:
        raise CaptureFolderError(f"{side}: white_level {white:g} exceeds the PNG's full scale {full:g}")
    top = int(raw.max())
    if top > white:
        raise CaptureFolderError(f"{png}: raw value {top} above white_level {white:g}")
    image = raw.astype(np.float64) / white
    if check:
        check_exposure(image, str(png))
    return CaptureFrame(name=png.stem, path=png, image=image, metadata=meta)


def read_folder(folder: str | os.PathLike, check: bool = True) -> list[CaptureFrame]:
    """Every frame of a capture folder, sorted by name.

    Raises:
        CaptureFolderError: the folder is missing or holds no PNG, a sidecar without its
            frame, any frame error (:func:`read_frame`), frames of different sizes, or a
            ``pair`` tag not shared by exactly two frames.
    """
    d = Path(folder)
    if not d.is_dir():
        raise CaptureFolderError(f"{d}: not a folder")
    pngs = sorted(p for p in d.iterdir() if p.suffix.lower() == ".png" and p.is_file())
    if not pngs:
        raise CaptureFolderError(f"{d}: no PNG frames")
    stems = {p.stem for p in pngs}
    for side in sorted(d.glob("*.json")):
        if side.stem not in stems:
            log.warning("%s: sidecar without a frame, ignored", side)
    frames = [read_frame(p, check) for p in pngs]
    first = frames[0]
    for f in frames[1:]:
        if f.shape != first.shape:
            raise CaptureFolderError(f"{f.path}: size {f.shape[1]}x{f.shape[0]} differs from "
                                     f"{first.path.name} ({first.shape[1]}x{first.shape[0]})")
    tags: dict[str, list[CaptureFrame]] = {}
    for f in frames:
        if f.metadata.pair is not None:
            tags.setdefault(f.metadata.pair, []).append(f)
    for tag, members in tags.items():
        if len(members) != 2:
            raise CaptureFolderError(f"{members[0].path}: pair {tag!r} has {len(members)} frames "
                                     f"({', '.join(m.name for m in members)}), a DFD pair has two")
        if members[0].power_dpt == members[1].power_dpt:
            raise CaptureFolderError(f"{members[1].path}: the two frames of pair {tag!r} have the same lens power")
    return frames
