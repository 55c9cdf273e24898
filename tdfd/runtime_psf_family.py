"""The PSF family an exported model's CNN is told, read and overridden without torch.

A model trained with the family input (:mod:`tdfd.model.psf_family_code`) is exported with
one family baked in (``python -m export --camera FILE`` takes the camera file's measured
``psf_family``; without a file: unknown). Its graph keeps the code as one initializer,
named in the ``tdfd.psf_family`` metadata (:data:`tdfd.contract.PSF_FAMILY_KEY`), so ONNX
Runtime can run the same file for another family: the session option ``add_initializer``
replaces the code's value, no graph edit and no ``onnx`` package needed. The model is the
same, the CNN's input says another family.

Example:
    >>> info = read_psf_family({"tdfd.psf_family": {"input": True, "family": None,
    ...                                              "initializer": "psf_family_code"}}, "m.onnx")
    >>> info.takes_input, info.exported, code_array("pillbox").ravel().tolist()
    (True, None, [0.0, 1.0])
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from .camera_file import PSF_FAMILY_VALUES
from .contract import PSF_FAMILY_KEY
from .errors import InputError, ModelError

__all__ = ["FAMILIES", "EXPORTED", "UNKNOWN", "PsfFamilyInfo", "read_psf_family", "code_array", "requested_family"]

#: The families a model may be told, in code-channel order: the camera file's ``psf_family`` values.
FAMILIES = PSF_FAMILY_VALUES
#: ``psf_family`` value that keeps the family the file was exported with.
EXPORTED = "exported"
#: ``psf_family`` value for a lens whose family was not measured (also ``None``).
UNKNOWN = "unknown"


@dataclass(frozen=True)
class PsfFamilyInfo:
    """What a file's ``tdfd.psf_family`` metadata says.

    Attributes:
        takes_input: whether the CNN has the family input (``False``: the key is absent).
        exported: the family baked in at export (``None``: unknown).
        initializer: the graph initializer holding the code (``""`` without the input).
    """

    takes_input: bool
    exported: str | None
    initializer: str


def read_psf_family(metadata: dict[str, Any], path: str) -> PsfFamilyInfo:
    """Parse the ``tdfd.psf_family`` entry of decoded ``metadata`` (``path`` names the file in errors).

    Raises:
        ModelError: an entry that is not ``{"input": true, "family": ..., "initializer": ...}``
            with a known family and a non-empty name.
    """
    info = metadata.get(PSF_FAMILY_KEY)
    if info is None:
        return PsfFamilyInfo(False, None, "")
    try:
        takes, family, name = info["input"], info["family"], info["initializer"]
    except (KeyError, TypeError) as exc:
        raise ModelError(f"{path}: invalid {PSF_FAMILY_KEY!r} metadata {info!r}") from exc
    if takes is not True or family not in (None, *FAMILIES) or not isinstance(name, str) or not name:
        raise ModelError(f"{path}: invalid {PSF_FAMILY_KEY!r} metadata {info!r}")
    return PsfFamilyInfo(True, family, name)


def requested_family(value: str | None, info: PsfFamilyInfo, path: str) -> str | None:
    """The family a caller's ``psf_family`` asks for (``None``: unknown).

    Args:
        value: ``"exported"`` (the file's own), ``"unknown"`` or ``None``, ``"gaussian"`` or
            ``"pillbox"``.
        info: the file's :func:`read_psf_family`.
        path: the file, for messages.

    Raises:
        InputError: any other value.
        ModelError: a family (or unknown) for a file whose CNN has no family input.
    """
    if value == EXPORTED:
        return info.exported
    if value is not None and value != UNKNOWN and value not in FAMILIES:
        raise InputError(f"psf_family must be one of {FAMILIES}, {UNKNOWN!r} (or None) or {EXPORTED!r}, got {value!r}")
    family = None if value in (None, UNKNOWN) else value
    if not info.takes_input:
        raise ModelError(f"{path} was exported without the PSF family input ({PSF_FAMILY_KEY!r} metadata), so it "
                         f"cannot be told psf_family={value!r}; use a model trained with model.psf_family_input")
    return family


def code_array(family: str | None) -> np.ndarray:
    """The code ``(1, 2, 1, 1)`` float32 of ``family`` (``None``: zeros), C-contiguous.

    Raises:
        InputError: an unknown family.
    """
    if family is not None and family not in FAMILIES:
        raise InputError(f"psf_family must be one of {FAMILIES} or None, got {family!r}")
    code = np.zeros((1, len(FAMILIES), 1, 1), np.float32)
    if family is not None:
        code[0, FAMILIES.index(family)] = 1.0
    return code
