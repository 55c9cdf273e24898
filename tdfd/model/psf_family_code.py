r"""The lens's PSF family as an input of the refinement CNN.

The Fourier-ratio fit assumes a Gaussian PSF (paper, eq. 7). A lens whose defocus blur is a
uniform disk ("pillbox") biases it by a few per cent with distance, and the CNN, trained
over a mix of PSF shapes, learns the *average* correction: right for no lens in particular
(models/README.md, "Where the paper experiment's refined estimate loses"). ``tdfd calibrate``
measures the family (:mod:`tdfd.calibration.psf_family`, the camera file's ``psf_family``),
so the CNN may be told it.

The code is two constant feature maps appended to the CNN's input features, one per family
of :data:`FAMILY_CODES`: ``(1, 0)`` Gaussian, ``(0, 1)`` pillbox, ``(0, 0)`` unknown. In
training each sample whose PSF is one of the two families is told it with probability
``told_share`` (a draw seeded by the sample's own seed, so a step's data depends on the step
only); the other samples, and every power-exponential ("beta") PSF, are unknown. So one
trained model serves a lens of either family and one whose family was not measured.

Example:
    >>> import torch
    >>> family_code("pillbox").tolist(), family_code(None).tolist()
    ([0.0, 1.0], [0.0, 0.0])
    >>> append_family_maps(torch.zeros(2, 5, 3, 4), family_code("gaussian")).shape
    torch.Size([2, 7, 3, 4])
"""

from __future__ import annotations

from typing import Any, Sequence

import torch

from ..errors import InputError, ShapeError
from ..runtime_psf_family import FAMILIES, code_array

__all__ = ["FAMILY_CODES", "NUM_FAMILY_CHANNELS", "family_code", "append_family_maps", "training_codes",
           "TOLD_SEED_SALT"]

#: The families the code names, in channel order (the camera file's ``psf_family`` values; the
#: runtime's :data:`tdfd.runtime_psf_family.FAMILIES`, which encodes the same code without torch).
FAMILY_CODES = FAMILIES
#: Feature channels the code adds.
NUM_FAMILY_CHANNELS = len(FAMILY_CODES)
#: Mixed into a sample's seed for the told/unknown draw (independent of the sample's content).
TOLD_SEED_SALT = 0x5F3759DF


def family_code(family: str | None) -> torch.Tensor:
    """The code ``(2,)`` float32 of ``family`` (``None``: unknown, all zeros).

    Raises:
        InputError: ``family`` is neither ``None`` nor one of :data:`FAMILY_CODES`.
    """
    return torch.from_numpy(code_array(family)).reshape(NUM_FAMILY_CHANNELS)


def append_family_maps(features: torch.Tensor, codes: torch.Tensor) -> torch.Tensor:
    """``features`` ``(B, C, h, w)`` with the code broadcast to two more channels.

    Args:
        features: the CNN's per-tile features.
        codes: one code ``(2,)`` or ``(1, 2, 1, 1)`` for the whole batch, or one per sample
            ``(B, 2)``.

    Returns:
        ``(B, C + 2, h, w)`` in the dtype of ``features``.

    Raises:
        ShapeError: ``codes`` of another shape.
    """
    b, _, h, w = features.shape
    if codes.dim() == 4 and tuple(codes.shape) == (1, NUM_FAMILY_CHANNELS, 1, 1):
        maps = codes  # a model's own code, used as is: the export keeps it one initializer
    elif codes.dim() == 1 and codes.shape[0] == NUM_FAMILY_CHANNELS:
        maps = codes.reshape(1, NUM_FAMILY_CHANNELS, 1, 1)
    elif codes.dim() == 2 and codes.shape[1] == NUM_FAMILY_CHANNELS and codes.shape[0] in (1, b):
        maps = codes.reshape(codes.shape[0], NUM_FAMILY_CHANNELS, 1, 1)
    else:
        raise ShapeError(f"PSF family codes must be ({NUM_FAMILY_CHANNELS},), ({b}, {NUM_FAMILY_CHANNELS}) or "
                         f"(1, {NUM_FAMILY_CHANNELS}, 1, 1), got {tuple(codes.shape)}")
    return torch.cat([features, maps.to(features.dtype).expand(b, -1, h, w)], 1)


def training_codes(params: Sequence[Any], told_share: float) -> torch.Tensor:
    """Per-sample codes ``(B, 2)`` for a training batch of ``data_synth`` samples.

    A sample whose ``psf_shape`` is one of :data:`FAMILY_CODES` is told it when a uniform
    draw seeded by ``sample_seed ^ TOLD_SEED_SALT`` falls below ``told_share``; anything else
    (a power-exponential PSF, a dataset that records no shape) is unknown.

    Args:
        params: the batch's per-sample parameter dicts (``psf_shape``, ``sample_seed``).
        told_share: probability in [0, 1] that a sample of a known family is told it.

    Raises:
        InputError: ``told_share`` outside [0, 1], or a known-family sample without an
            integer ``sample_seed`` (the draw would not be reproducible).

    Example:
        >>> training_codes([{"psf_shape": "pillbox", "sample_seed": 7}, {"psf_shape": "beta"}], 1.0).tolist()
        [[0.0, 1.0], [0.0, 0.0]]
    """
    if not 0.0 <= told_share <= 1.0:
        raise InputError(f"told_share must be in [0, 1], got {told_share!r}")
    codes = torch.zeros(len(params), NUM_FAMILY_CHANNELS)
    for i, p in enumerate(params):
        shape = p.get("psf_shape") if isinstance(p, dict) else None
        if shape not in FAMILY_CODES or told_share == 0.0:
            continue
        seed = p.get("sample_seed")
        if isinstance(seed, bool) or not isinstance(seed, int):
            raise InputError(f"sample {i} has PSF shape {shape!r} but no integer sample_seed to draw told/unknown from")
        draw = float(torch.rand((), generator=torch.Generator().manual_seed((seed ^ TOLD_SEED_SALT) & (2**63 - 1))))
        if draw < told_share:
            codes[i, FAMILY_CODES.index(shape)] = 1.0
    return codes
