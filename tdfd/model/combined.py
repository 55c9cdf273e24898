r"""The combined model: analytic Fourier-ratio DFD + a learned refinement on the tile grid.

:class:`DFDModel` runs :class:`~tdfd.dfd.FourierRatioDFD` (reused, not copied), turns its
per-tile intermediates into features (:func:`tile_features`), and lets a small CNN
(:class:`~tdfd.model.refine.RefineNet`) predict

* a correction ``dq`` of the analytic inverse depth in dioptres,
  ``q = clamp(q_analytic + dq)`` and ``depth = 1 / q`` (metres);
* a Laplace scale ``b`` of the relative inverse-depth error ``(q - q_true) / q_true``,
  as a log-scale correction of the analytic estimator's own predicted relative error,
  ``log b = clamp(log rel_error) + s``. The confidence is the monotone map
  ``conf = 1 / (1 + (b / b0)^2)`` with ``b0 = confidence_scale`` (the median absolute
  relative error of a Laplace error is ``b ln 2``), so a tile whose error the network
  expects to be large gets a small confidence.

Training minimises the Laplace negative log-likelihood ``|e| / b + log b`` (see
:mod:`training`); after training, a map of ``log b``, the refined inverse depth and the
tile's distance to the grid's edge, fitted on held-out scenes
(:class:`~tdfd.model.scale_calibration.ScaleCalibration`, :mod:`training.calibrate_scale`),
makes the median error in every band of ``b``, of depth and of that distance its Laplace
median ``b ln 2`` (issue 19). The confidence is computed from the calibrated ``b``.

Optionally a last stage pools the tiles along the scene's depth structure
(:class:`~tdfd.model.structure_pooling.StructurePooling`: a robust local surface fit of ``q``
weighted by each tile's calibrated ``b``); its output's scale is calibrated again, by a second
map of the same form fitted on the pooled errors (``pooled_scale_calibration``). The stage adds
to the tiles, it does not replace them: ``depth`` and ``confidence`` stay each tile's own
estimate, independent of its neighbours' (what the autofocus pools over its ROI), and
``depth_pooled`` / ``confidence_pooled`` are the pooled map (:meth:`DFDModel.pool`; the
optional ONNX outputs :data:`tdfd.contract.POOLED_OUTPUT_NAMES`). Training sees the stage only
through the option ``optim.pooled_weight`` (0 in the shipped recipe; :meth:`DFDModel.head_with_family`
is the CNN as trained).

With the refinement head at zero (a fresh model) ``depth`` equals ``depth_analytic``
exactly. The forward pass has no data-dependent Python control flow and no ``torch.fft``,
so it exports to ONNX (turn input validation off first: :meth:`DFDModel.set_validate`).

Example:
    >>> import torch
    >>> from tdfd import Camera
    >>> model = DFDModel(Camera.preset("reference"), tile=32, stride=32, hidden=8, blocks=1)
    >>> i1 = torch.rand(2, 1, 64, 96, generator=torch.Generator().manual_seed(0))
    >>> depth, conf, depth_analytic = model(i1, i1.flip(-1))
    >>> depth.shape, bool(torch.equal(depth, depth_analytic))
    (torch.Size([2, 1, 2, 3]), True)
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any, Sequence

import torch
import torch.nn.functional as F
from torch import nn

from .._tracing import is_exporting
from ..atomic_io import atomic_write_bytes, atomic_write_text, remove_orphans
from ..camera import Camera
from ..dfd.fourier_ratio import DFDResult, FourierRatioDFD, validate_pair
from ..errors import InputError, ModelError
from ..optics.thin_lens import camera_sigmas
from ..registration import BreathingRegistration
from .psf_family_code import NUM_FAMILY_CHANNELS, append_family_maps, family_code
from .refine import RefineNet
from .scale_calibration import ScaleCalibration
from .structure_pooling import StructurePooling

__all__ = ["DFDModel", "RefinedResult", "tile_features", "num_features", "context_sizes", "pool_measurements",
           "MODEL_FORMAT"]

logger = logging.getLogger(__name__)

#: Name of the PSF family code in the exported graph (an initializer ``(1, 2, 1, 1)`` float32
#: that ONNX Runtime may override: :class:`tdfd.runtime.DepthRuntime` ``psf_family``).
PSF_FAMILY_INITIALIZER = "psf_family_code"

#: Format tag written into the JSON side file of :meth:`DFDModel.save`.
MODEL_FORMAT = "tdfd.dfd_model/1"

#: Bounds of the log of the analytic relative error used as the base of the log-scale.
_LOG_REL_BOUNDS = (-7.0, 1.0)
#: Bounds of the final log-scale (relative error from 1e-4 to ~7).
_LOG_SCALE_BOUNDS = (-9.0, 2.0)


def _odd_sides(value: int | Sequence[int], name: str, drop_one: bool) -> tuple[int, ...]:
    """Neighbourhood sides (tiles) from one side or a sequence: positive odd integers, each
    once (after dropping 1 if ``drop_one``), sorted. Raises :class:`InputError` naming ``name``."""
    sides = [value] if isinstance(value, (int, float)) else list(value)
    out = []
    for c in sides:
        if isinstance(c, bool) or not isinstance(c, (int, float)) or int(c) != c or c < 1 or c % 2 == 0:
            raise InputError(f"{name} must be positive odd integers (tiles), got {value!r}")
        if int(c) > 1 or not drop_one:
            out.append(int(c))
    if len(set(out)) != len(out):
        raise InputError(f"{name} sides must differ, got {value!r}")
    return tuple(sorted(out))


def context_sizes(context: int | Sequence[int]) -> tuple[int, ...]:
    """The sides (tiles) of the pooled-context neighbourhoods that ``context`` asks for: one
    odd side or a sequence of them; 1 means none. Sorted, without 1.

    Raises:
        InputError: a side that is not a positive odd integer, or the same side twice.

    Example:
        >>> context_sizes(3), context_sizes([7, 3]), context_sizes(1)
        ((3,), (3, 7), ())
    """
    return _odd_sides(context, "context", drop_one=True)


def num_features(num_rings: int, context: int | Sequence[int] = 1) -> int:
    """Number of channels :func:`tile_features` produces for ``num_rings`` rings (and one
    pooled fit per context side > 1)."""
    return 5 * num_rings + 8 + (2 * num_rings + 3) * len(context_sizes(context))


def pool_measurements(measurements: tuple[torch.Tensor, ...], context: int) -> tuple[torch.Tensor, ...]:
    """Average :meth:`~tdfd.dfd.FourierRatioDFD.measure` output over ``context x context``
    neighbouring tiles (stride 1, borders average the tiles that exist).

    Averaging powers *before* the logarithm of the fit is Welch's method: the noise of the
    power estimate falls and so does the bias it causes in the log ratio of weak rings.
    """
    pad = context // 2
    return tuple(F.avg_pool2d(v, context, 1, pad, count_include_pad=False) for v in measurements)


def _square_difference_scale(camera: Camera, mu: float) -> float:
    near, far = camera.depth_range_m
    s = [camera_sigmas(camera, d, mu) for d in (near, far)]
    return max(abs(float(a) ** 2 - float(b) ** 2) for a, b in s) or 1.0


def _ring_d(result: DFDResult, analytic: FourierRatioDFD, d_scale: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-ring square-difference estimates ``-y_r / omega_r^2`` (normalised, gated) and the gates."""
    gate = torch.sigmoid(2.0 * (result.ring_snr - math.log(analytic.snr_threshold)))
    omega2 = analytic.ring_omega2.to(result.log_ratio.dtype)
    return (-result.log_ratio / omega2 / d_scale).clamp(-4.0, 4.0) * gate, gate


def tile_features(result: DFDResult, analytic: FourierRatioDFD,
                  pooled: DFDResult | Sequence[DFDResult] | None = None) -> torch.Tensor:
    """Per-tile features for the refinement CNN from the analytic estimator's intermediates.

    Channels (``R`` rings): per-ring square-difference estimate ``-y_r / omega_r^2``
    (normalised, gated), per-ring gate, per-ring log SNR, per-ring log power of each frame
    (noise-subtracted, normalised by the tile mean: the two frames' own spectral shapes,
    which tell PSF shapes and texture spectra apart), then the analytic inverse depth
    normalised to the working range, the fitted ``sigma1^2 - sigma2^2`` (normalised), log
    predicted relative error, log fit residual, log spectral energy of both images, log
    relative noise level, and the analytic confidence. With ``pooled`` (the fit of
    measurements averaged over neighbouring tiles, :func:`pool_measurements`, or a sequence
    of such fits over neighbourhoods of growing size) also, per pooled fit, its per-ring
    estimates and gates, its ``sigma1^2 - sigma2^2``, log relative error and confidence.

    Args:
        result: :meth:`FourierRatioDFD.analyse` output.
        analytic: the estimator that produced it (ring frequencies, camera, limits).
        pooled: the pooled fit(s) (optional).

    Returns:
        ``(B, 5R + 8 + P (2R + 3), h, w)`` features for ``P`` pooled fits, finite for every
        finite input.
    """
    near, far = analytic.camera.depth_range_m
    q_lo, q_hi = analytic.inv_depth_limits
    q_mid, q_half = 0.5 * (1.0 / near + 1.0 / far), 0.5 * (1.0 / near - 1.0 / far)
    d_scale = _square_difference_scale(analytic.camera, analytic.mu)
    ring_d, gate = _ring_d(result, analytic, d_scale)
    feats = [
        ring_d,
        gate,
        result.ring_snr.clamp(-5.0, 20.0),
        result.ring_log_power.clamp(-30.0, 30.0),
        (result.inverse_depth.clamp(q_lo, q_hi) - q_mid) / q_half,
        (result.square_difference / d_scale).clamp(-4.0, 4.0),
        torch.log(result.rel_error.clamp_min(1e-6)).clamp(-10.0, 5.0),
        torch.log(result.residual.clamp_min(1e-6)).clamp(-10.0, 10.0),
        result.energy.clamp(-30.0, 30.0),
        result.log_noise.clamp(-30.0, 10.0),
        result.confidence,
    ]
    for p in ([] if pooled is None else [pooled] if isinstance(pooled, DFDResult) else pooled):
        feats += [
            *_ring_d(p, analytic, d_scale),
            (p.square_difference / d_scale).clamp(-4.0, 4.0),
            torch.log(p.rel_error.clamp_min(1e-6)).clamp(-10.0, 5.0),
            p.confidence,
        ]
    return torch.cat(feats, 1)


@dataclass
class RefinedResult:
    """Everything :meth:`DFDModel.analyse` computes, per tile ``(B, 1, h, w)``.

    Attributes:
        depth: refined object distance in metres.
        confidence: in [0, 1].
        depth_analytic: analytic depth in metres.
        inverse_depth: refined inverse depth in dioptres (1/m).
        log_scale: log of the predicted Laplace scale of the relative error.
        features: the CNN's input ``(B, C, h, w)``.
        analytic: the analytic estimator's :class:`~tdfd.dfd.DFDResult`.
        depth_pooled, confidence_pooled, inverse_depth_pooled, log_scale_pooled: the same
            after the structure pooling (:meth:`DFDModel.pool`); ``None`` for a model without it.

    The first four are each tile's own estimate (without the pooling, whether the model has it or not).
    """

    depth: torch.Tensor
    confidence: torch.Tensor
    depth_analytic: torch.Tensor
    inverse_depth: torch.Tensor
    log_scale: torch.Tensor
    features: torch.Tensor
    analytic: DFDResult
    depth_pooled: torch.Tensor | None = None
    confidence_pooled: torch.Tensor | None = None
    inverse_depth_pooled: torch.Tensor | None = None
    log_scale_pooled: torch.Tensor | None = None

    @property
    def depth_map(self) -> tuple[torch.Tensor, torch.Tensor]:
        """``(depth, confidence)`` of the best depth map: the pooled one if the model pools, else the tiles'."""
        if self.depth_pooled is not None and self.confidence_pooled is not None:
            return self.depth_pooled, self.confidence_pooled
        return self.depth, self.confidence


class DFDModel(nn.Module):
    """Analytic DFD plus learned refinement: two frames in, depth and confidence out.

    Args:
        camera: the camera description (the analytic layer's optics and working range).
        tile: tile side in pixels.
        stride: tile stride in pixels.
        analytic: extra keyword arguments of :class:`~tdfd.dfd.FourierRatioDFD`.
        confidence_scale: Laplace scale ``b0`` of the relative error at which the
            confidence is 0.5.
        correction_scale: dioptres per unit of the CNN's first output.
        context: side (odd, in tiles) of the neighbourhood whose averaged measurements give
            a second, pooled analytic fit as extra features (1: none), or a sequence of such
            sides, one pooled fit each (``[3, 7]``: a local and a wider neighbourhood).
        magnification_per_dpt: the camera's focus breathing ``m`` (1/dpt, the camera file's
            key): both frames are registered to a common image scale before the analytic
            stage (:class:`~tdfd.registration.BreathingRegistration`, about the centre of the
            frames given). 0 (default): no registration, no extra operation.
        psf_family_input: the CNN also sees the lens's PSF family as two constant feature
            maps (:mod:`tdfd.model.psf_family_code`; training tells it per sample).
        psf_family: the family the model is told at inference (``"gaussian"``,
            ``"pillbox"``; ``None``: unknown), e.g. the camera file's measured ``psf_family``
            (:meth:`set_psf_family`). Only with ``psf_family_input``.
        scale_calibration: knots of the post-hoc map of the predicted log scale
            (:meth:`~tdfd.model.scale_calibration.ScaleCalibration.to_config`: ``log_b``,
            ``log_b_calibrated`` and optionally ``inverse_depth_per_m``, ``depth_log_shift``,
            ``border_log_shift``); ``None``: identity.
        structure_pooling: options of the last stage,
            :class:`~tdfd.model.structure_pooling.StructurePooling` (``None``: no pooling).
        pooled_scale_calibration: knots of the map of the calibrated log scale to the pooled
            depth's log scale (same form as ``scale_calibration``; ``None``: identity). Only with
            ``structure_pooling``.
        **refine_config: keyword arguments of :class:`~tdfd.model.refine.RefineNet`
            (``hidden``, ``blocks``, ``kernel_size``, ``family_inference``: with
            ``psf_family_input``, an unknown family is inferred from the whole image,
            :mod:`tdfd.model.family_inference`).

    Shape:
        - ``image_f1``, ``image_f2``: ``(B, 1, H, W)`` float32, linear intensity in [0, 1].
        - Output: ``(depth, confidence, depth_analytic)``, each ``(B, 1, h, w)`` float32 on
          the contract grid (``CONTRACT.md`` section 2); depths in metres.
    """

    def __init__(self, camera: Camera, tile: int = 64, stride: int = 32, *, analytic: dict[str, Any] | None = None,
                 confidence_scale: float = 0.01, correction_scale: float = 1.0, context: int | Sequence[int] = 1,
                 magnification_per_dpt: float = 0.0, psf_family_input: bool = False, psf_family: str | None = None,
                 scale_calibration: dict[str, list[float]] | None = None,
                 structure_pooling: dict[str, Any] | None = None,
                 pooled_scale_calibration: dict[str, list[float]] | None = None, **refine_config: Any) -> None:
        super().__init__()
        analytic = dict(analytic or {})
        for key in ("tile", "stride", "validate", "camera"):
            if key in analytic:
                raise InputError(f"analytic option {key!r} is set by DFDModel itself")
        if not (confidence_scale > 0 and correction_scale > 0):
            raise InputError("confidence_scale and correction_scale must be > 0")
        #: the pooled-context sides, sorted (empty: no pooled fit)
        self.contexts = context_sizes(context)
        refine_config = dict(refine_config)
        refine_config.pop("in_channels", None)
        refine_config.pop("out_channels", None)
        self.camera = camera
        self.tile, self.stride = int(tile), int(stride)
        self.analytic_config = analytic
        self.confidence_scale, self.correction_scale = float(confidence_scale), float(correction_scale)
        self.analytic = FourierRatioDFD(camera, tile=tile, stride=stride, validate=False, **analytic)
        #: focus-breathing registration before the analytic stage (no parameters, no state)
        self.registration = BreathingRegistration(magnification_per_dpt, camera.lens_powers_dpt)
        #: whether the CNN's input ends with the PSF family code (two channels)
        self.psf_family_input = bool(psf_family_input)
        #: the code told at inference, ``(1, 2, 1, 1)``: not saved (the JSON's ``psf_family`` is);
        #: the export keeps it one initializer of that name (:data:`PSF_FAMILY_INITIALIZER`)
        self.register_buffer(PSF_FAMILY_INITIALIZER, family_code(None).reshape(1, -1, 1, 1), persistent=False)
        self.psf_family: str | None = None
        channels = num_features(self.analytic.num_rings, self.contexts) + NUM_FAMILY_CHANNELS * self.psf_family_input
        if refine_config.get("family_inference") and not self.psf_family_input:
            raise InputError("family_inference needs psf_family_input (it completes an unknown family code)")
        try:
            self.refine = RefineNet(channels, **refine_config)
        except TypeError as exc:
            raise InputError(f"bad refine option: {exc}") from exc
        self.set_psf_family(psf_family)
        #: the post-hoc map of the predicted log scale (identity until :mod:`training.calibrate_scale` sets one)
        self.scale_calibration = ScaleCalibration.from_config(scale_calibration)
        self.structure_pooling: StructurePooling | None = None
        self.pooled_scale_calibration = ScaleCalibration()
        self.set_structure_pooling(structure_pooling, pooled_scale_calibration)
        self.validate = True
        #: after :meth:`load`: whether the analytic layer still gives the features the CNN
        #: was trained on (``None``: not checked).
        self.analytic_matches: bool | None = None

    # ------------------------------------------------------------------ options
    @property
    def context(self) -> int | list[int]:
        """The ``context`` option as saved: one side as an int (1: none), several as a list."""
        return list(self.contexts) if len(self.contexts) > 1 else (self.contexts or (1,))[0]

    @property
    def magnification_per_dpt(self) -> float:
        """The focus breathing the model registers (1/dpt; 0: none)."""
        return self.registration.magnification_per_dpt

    def set_breathing(self, magnification_per_dpt: float) -> "DFDModel":
        """Register the camera's focus breathing ``m`` (1/dpt) from now on; returns ``self``.

        The weights do not depend on it (the CNN sees registered frames), so a trained model
        serves a camera that breathes once it knows ``m`` (``python -m export --camera FILE``).

        Raises:
            NonFiniteError, RangeError: ``m`` is not finite or ``|m| >= 0.1``.
        """
        self.registration = BreathingRegistration(magnification_per_dpt, self.camera.lens_powers_dpt)
        return self

    def set_psf_family(self, family: str | None) -> "DFDModel":
        """Tell the CNN the lens's PSF family from now on (``None``: unknown); returns ``self``.

        The weights do not depend on it; the export bakes the family in as a constant
        (``python -m export --camera FILE`` takes the camera file's measured ``psf_family``).

        Raises:
            InputError: an unknown family, or a family for a model without the family input.
        """
        if family is not None and not self.psf_family_input:
            raise InputError(f"this model was trained without the PSF family input: it cannot be told {family!r}")
        self.psf_family_code.copy_(family_code(family).reshape(1, -1, 1, 1))
        self.psf_family = family
        return self

    def set_structure_pooling(self, options: dict[str, Any] | None,
                              pooled_scale_calibration: dict[str, list[float]] | None = None) -> "DFDModel":
        """Add the stage that pools the tiles along the depth structure, its map beside the
        tiles' own (``options``: :meth:`~tdfd.model.structure_pooling.StructurePooling.to_config`;
        ``None``: no pooling),
        with the pooled depth's scale map (``None``: identity until
        :mod:`training.calibrate_scale` fits one); returns ``self``. The weights do not depend on it.

        Raises:
            InputError: bad options, or a pooled calibration without pooling.
        """
        if options is None and pooled_scale_calibration is not None:
            raise InputError("a pooled_scale_calibration needs structure_pooling")
        self.structure_pooling = None if options is None else StructurePooling.from_config(dict(options))
        self.pooled_scale_calibration = ScaleCalibration.from_config(pooled_scale_calibration)
        return self

    def set_validate(self, flag: bool) -> "DFDModel":
        """Turn input validation on or off (off for export); returns ``self``."""
        self.validate = bool(flag)
        return self

    def grid_shape(self, height: int, width: int) -> tuple[int, int]:
        """Tile-grid shape ``(h, w)`` for a ``height`` x ``width`` image."""
        return self.analytic.grid_shape(height, width)

    def config(self) -> dict[str, Any]:
        """The JSON-serialisable description that :meth:`save` writes next to the weights."""
        from .. import __version__

        return {"format": MODEL_FORMAT, "tdfd_version": __version__, "camera": self.camera.to_dict(),
                "camera_name": self.camera.name, "tile": self.tile, "stride": self.stride,
                "analytic": self.analytic_config, "confidence_scale": self.confidence_scale,
                "correction_scale": self.correction_scale, "context": self.context,
                "magnification_per_dpt": self.magnification_per_dpt, "psf_family_input": self.psf_family_input,
                "psf_family": self.psf_family, "scale_calibration": self.scale_calibration.to_config(),
                "structure_pooling": None if self.structure_pooling is None else self.structure_pooling.to_config(),
                "pooled_scale_calibration": self.pooled_scale_calibration.to_config(),
                "refine": {k: v for k, v in self.refine.config().items() if k not in ("in_channels", "out_channels")}}

    # ------------------------------------------------------------------ compute
    def features(self, image_f1: torch.Tensor, image_f2: torch.Tensor, psf_family_codes: torch.Tensor | None = None
                 ) -> tuple[torch.Tensor, DFDResult]:
        """The analytic stage: CNN input features ``(B, C, h, w)`` and the analytic result.

        It has no trainable parameters, so training may compute it once per batch (or in a
        data-loading worker) and call :meth:`head` on the result. With the PSF family input,
        ``psf_family_codes`` ``(B, 2)`` (:func:`~tdfd.model.psf_family_code.training_codes`)
        replaces the model's own family for these samples.
        """
        if self.validate and not is_exporting():
            validate_pair(image_f1, image_f2, self.tile)
        feats, r = self._analytic_features(*self.registration(image_f1, image_f2))
        if self.psf_family_input:
            feats = append_family_maps(feats, self.psf_family_code if psf_family_codes is None else psf_family_codes)
        elif psf_family_codes is not None:
            raise InputError("psf_family_codes given to a model without the PSF family input")
        return feats, r

    def _analytic_features(self, image_f1: torch.Tensor, image_f2: torch.Tensor) -> tuple[torch.Tensor, DFDResult]:
        """:meth:`features` on frames already registered."""
        meas = self.analytic.measure(image_f1, image_f2)
        b = image_f1.shape[0]
        r, *pooled = self._fit_stacked(self.analytic, [meas] + [pool_measurements(meas, c) for c in self.contexts],
                                       (1, *self.contexts), b)
        feats = tile_features(r, self.analytic, pooled)
        return feats.to(self.refine.head.weight.dtype), r

    @staticmethod
    def _fit_stacked(estimator: FourierRatioDFD, stacks: list[tuple[torch.Tensor, ...]], sides: Sequence[int],
                     b: int) -> list[DFDResult]:
        """Fit every measurement set of ``stacks`` (averaged over ``sides x sides`` tiles of
        ``estimator``'s grid) in one :meth:`~tdfd.dfd.FourierRatioDFD.fit` call on the sets
        stacked along the batch: fewer operators than separate fits, and ONNX Runtime pays
        per operator on small grids."""
        if len(stacks) == 1 and sides[0] == 1:
            return [estimator.fit(*stacks[0])]
        # independent samples grow as the square of the span of the averaged tiles
        span = [(estimator.tile + (c - 1) * estimator.stride) / estimator.tile for c in sides]
        stacked = tuple(torch.cat(parts, 0) for parts in zip(*stacks))
        count = torch.cat([torch.full((b, 1, 1, 1), s * s) for s in span]).to(stacked[0])
        fitted = estimator.fit(*stacked, count_scale=count)
        return [DFDResult(**{f.name: getattr(fitted, f.name)[k * b:(k + 1) * b] for f in fields(fitted)})
                for k in range(len(stacks))]

    def head(self, features: torch.Tensor, inverse_depth: torch.Tensor, rel_error: torch.Tensor
             ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """The learned stage on precomputed features: each tile's own estimate (no structure pooling).

        Args:
            features: :meth:`features` output ``(B, C, h, w)``.
            inverse_depth: the analytic (unclamped) inverse depth ``(B, 1, h, w)`` in 1/m.
            rel_error: the analytic predicted relative error ``(B, 1, h, w)``.

        Returns:
            ``(inverse_depth, log_scale, confidence, analytic_inverse_depth)``, each
            ``(B, 1, h, w)``: the refined inverse depth (1/m, inside the extended range), the
            log Laplace scale of the relative error (calibrated), the confidence, and the clamped
            analytic inverse depth.
        """
        q, log_scale, conf, q_a, _ = self.head_with_family(features, inverse_depth, rel_error)
        return q, log_scale, conf, q_a

    def pool(self, inverse_depth: torch.Tensor, log_scale: torch.Tensor
             ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The structure pooling stage on :meth:`head`'s tiles.

        Args:
            inverse_depth: the tiles' refined inverse depth ``(B, 1, h, w)`` (1/m).
            log_scale: their calibrated log scale ``(B, 1, h, w)``.

        Returns:
            ``(inverse_depth, log_scale, confidence)`` of the pooled map, each ``(B, 1, h, w)``:
            the pooled inverse depth inside the extended range, its log scale through
            ``pooled_scale_calibration``, and the confidence of that scale.

        Raises:
            InputError: the model has no structure pooling.
        """
        q = self.pooled_inverse_depth(inverse_depth, log_scale)
        pooled_log = self.pooled_scale_calibration(log_scale, q).clamp(*_LOG_SCALE_BOUNDS)
        return q, pooled_log, self._confidence(pooled_log)

    def pooled_inverse_depth(self, inverse_depth: torch.Tensor, log_scale: torch.Tensor) -> torch.Tensor:
        """:meth:`pool`'s depth alone, without its scale and confidence (what training scores):
        the pooled inverse depth ``(B, 1, h, w)`` (1/m) inside the extended range.

        Raises:
            InputError: the model has no structure pooling.
        """
        if self.structure_pooling is None:
            raise InputError("the model has no structure pooling (set_structure_pooling)")
        q_lo, q_hi = self.analytic.inv_depth_limits
        return self.structure_pooling(inverse_depth, torch.exp(log_scale)).clamp(q_lo, q_hi)

    def head_with_family(self, features: torch.Tensor, inverse_depth: torch.Tensor, rel_error: torch.Tensor
                         ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """The CNN stage as trained (:meth:`head` without the structure pooling): its four outputs
        and, from the same pass, the image-wide PSF family logits
        ``(B, 3)`` over :data:`~tdfd.model.family_inference.FAMILY_CLASSES` (``None`` for a CNN
        without ``family_inference``): what training supervises."""
        wdt = self.refine.head.weight.dtype
        out, family_logits = self.refine.forward_with_family(features)
        q_lo, q_hi = self.analytic.inv_depth_limits
        q_a = inverse_depth.to(wdt).clamp(q_lo, q_hi)
        q = (q_a + self.correction_scale * out[:, 0:1]).clamp(q_lo, q_hi)
        base = torch.log(rel_error.to(wdt).clamp_min(1e-6)).clamp(*_LOG_REL_BOUNDS)
        log_scale = self.scale_calibration((base + out[:, 1:2]).clamp(*_LOG_SCALE_BOUNDS), q).clamp(*_LOG_SCALE_BOUNDS)
        return q, log_scale, self._confidence(log_scale), q_a, family_logits

    def _confidence(self, log_scale: torch.Tensor) -> torch.Tensor:
        """``conf = 1 / (1 + (b / b0)^2)`` of the log Laplace scale ``log b`` (module docstring)."""
        ratio = torch.exp(log_scale) / self.confidence_scale
        return 1.0 / (1.0 + ratio * ratio)

    def analyse(self, image_f1: torch.Tensor, image_f2: torch.Tensor, psf_family_codes: torch.Tensor | None = None
                ) -> RefinedResult:
        """Run the whole model and return every intermediate (see :class:`RefinedResult`;
        ``psf_family_codes`` as in :meth:`features`)."""
        feats, r = self.features(image_f1, image_f2, psf_family_codes)
        q, log_scale, conf, q_a = self.head(feats, r.inverse_depth, r.rel_error)
        out = RefinedResult(depth=1.0 / q, confidence=conf, depth_analytic=1.0 / q_a, inverse_depth=q,
                            log_scale=log_scale, features=feats, analytic=r)
        if self.structure_pooling is not None:
            qp, log_p, conf_p = self.pool(q, log_scale)
            out.depth_pooled, out.confidence_pooled, out.inverse_depth_pooled, out.log_scale_pooled = \
                1.0 / qp, conf_p, qp, log_p
        return out

    def forward(self, image_f1: torch.Tensor, image_f2: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """``(depth, confidence, depth_analytic)``, the ONNX contract's outputs
        (:data:`tdfd.contract.OUTPUT_NAMES`), then ``(depth_pooled, confidence_pooled)``
        (:data:`tdfd.contract.POOLED_OUTPUT_NAMES`) for a model with the structure pooling."""
        r = self.analyse(image_f1, image_f2)
        if r.depth_pooled is None:
            return r.depth, r.confidence, r.depth_analytic
        return r.depth, r.confidence, r.depth_analytic, r.depth_pooled, r.confidence_pooled

    # -------------------------------------------------------------- persistence
    @torch.no_grad()
    def analytic_fingerprint(self) -> list[float]:
        """Per-channel mean features of the analytic stage on a fixed synthetic probe pair.

        Stored by :meth:`save`; :meth:`load` recomputes it, so a change of the analytic
        layer under a trained CNN (whose inputs it would shift) is detected.
        """
        from ..optics import render_pair

        size = max(128, 2 * self.tile)
        g = torch.Generator().manual_seed(20_240_613)
        sharp = (0.35 + 0.1 * torch.randn(1, 1, size, size, generator=g, dtype=torch.float64)).clamp(0.0, 1.0)
        near, far = self.camera.depth_range_m
        depth = torch.full((1, 1, size, size), 0.5 * (near + far), dtype=torch.float64)
        i1, i2 = render_pair(self.camera, sharp, depth)
        feats = self._analytic_features(i1.float(), i2.float())[0].double()  # no breathing in the probe
        return [round(float(v), 5) for v in feats.mean((0, 2, 3))]

    def check_analytic(self, expected: list[float], rtol: float = 1e-3, atol: float = 1e-3) -> bool:
        """Compare :meth:`analytic_fingerprint` with ``expected``; log a warning on mismatch."""
        got = torch.tensor(self.analytic_fingerprint(), dtype=torch.float64)
        want = torch.tensor(expected, dtype=torch.float64)
        ok = got.shape == want.shape and bool(torch.allclose(got, want, rtol=rtol, atol=atol))
        if not ok:
            logger.warning("the analytic layer's features differ from those the refinement CNN was trained on "
                           "(tdfd.dfd changed since training?): retrain the model")
        return ok

    @staticmethod
    def _paths(path: str | Path) -> tuple[Path, Path]:
        p = Path(path)
        stem = p.with_suffix("") if p.suffix in (".safetensors", ".json") else p
        return stem.with_name(stem.name + ".safetensors"), stem.with_name(stem.name + ".json")

    def save(self, path: str | Path, extra: dict[str, Any] | None = None) -> tuple[Path, Path]:
        """Write ``<stem>.safetensors`` (weights) and ``<stem>.json`` (config); no pickle.

        Each file is written atomically (:mod:`tdfd.atomic_io`: temporary file, fsync,
        ``os.replace``); temporary files of an interrupted save are removed first.

        Args:
            path: ``<stem>``, ``<stem>.safetensors`` or ``<stem>.json``.
            extra: additional JSON-serialisable metadata stored under ``"extra"``.

        Returns:
            The two paths written.
        """
        from safetensors.torch import save

        weights, meta = self._paths(path)
        remove_orphans(weights.parent)  # temporary files of an interrupted save
        state = {k: v.detach().to("cpu").contiguous() for k, v in self.state_dict().items()}
        cfg = self.config()
        cfg["analytic_fingerprint"] = self.analytic_fingerprint()
        if extra:
            cfg["extra"] = extra
        atomic_write_bytes(weights, save(state, metadata={"format": MODEL_FORMAT}))
        atomic_write_text(meta, json.dumps(cfg, indent=2, sort_keys=True) + "\n")
        return weights, meta

    @classmethod
    def from_config(cls, cfg: dict[str, Any]) -> "DFDModel":
        """Build an (untrained) model from :meth:`config` output."""
        if cfg.get("format") != MODEL_FORMAT:
            raise ModelError(f"not a tdfd DFD model description (format {cfg.get('format')!r}, expected {MODEL_FORMAT!r})")
        if cfg.get("coarse"):
            raise ModelError(f"the model uses coarse fits {cfg['coarse']}, an experimental option that was never shipped "
                             "and has been removed (docs/ARCHITECTURE.md)")
        try:
            camera = Camera.from_dict(cfg["camera"], name=cfg.get("camera_name", "custom"))
            return cls(camera, tile=cfg["tile"], stride=cfg["stride"], analytic=cfg.get("analytic") or {},
                       confidence_scale=cfg["confidence_scale"], correction_scale=cfg["correction_scale"],
                       context=cfg.get("context", 1), magnification_per_dpt=cfg.get("magnification_per_dpt", 0.0),
                       psf_family_input=cfg.get("psf_family_input", False), psf_family=cfg.get("psf_family"),
                       scale_calibration=cfg.get("scale_calibration"),
                       structure_pooling=cfg.get("structure_pooling"),
                       pooled_scale_calibration=cfg.get("pooled_scale_calibration"),
                       **cfg["refine"])
        except (KeyError, TypeError, ValueError) as exc:
            raise ModelError(f"invalid model description: {exc!r}") from exc

    @classmethod
    def read_description(cls, path: str | Path) -> dict[str, Any]:
        """The JSON description :meth:`save` wrote (``<stem>.json``), e.g. its ``extra``.

        Raises:
            ModelError: the file is missing or not valid JSON.
        """
        meta = cls._paths(path)[1]
        try:
            return json.loads(meta.read_text())
        except OSError as exc:
            raise ModelError(f"cannot read model description {meta}: {exc}") from exc
        except json.JSONDecodeError as exc:
            raise ModelError(f"{meta} is not valid JSON: {exc}") from exc

    @classmethod
    def load(cls, path: str | Path, map_location: str | torch.device = "cpu") -> "DFDModel":
        """Load a model written by :meth:`save` (safetensors + JSON).

        Raises:
            ModelError: a missing, corrupt or mismatching file.
        """
        from safetensors import SafetensorError
        from safetensors.torch import load_file

        weights, meta = cls._paths(path)
        if not weights.is_file() or not meta.is_file():
            raise ModelError(f"model files {weights} and {meta} must both exist")
        cfg = cls.read_description(path)
        model = cls.from_config(cfg)
        try:
            state = load_file(str(weights), device=str(map_location))
        except (SafetensorError, OSError, ValueError) as exc:
            raise ModelError(f"cannot read weights {weights}: {exc}") from exc
        try:
            model.load_state_dict(state, strict=True)
        except RuntimeError as exc:
            raise ModelError(f"weights {weights} do not match {meta}: {exc}") from exc
        model.analytic_matches = model.check_analytic(cfg["analytic_fingerprint"]) if "analytic_fingerprint" in cfg else None
        return model.to(map_location)
