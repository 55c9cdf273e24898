r"""Two depth estimates fused by inverse variance, each variance's scale fitted on training data.

The refinement CNN states its uncertainty as a confidence ``conf = 1 / (1 + (b / b0)^2)``
(:mod:`tdfd.model.combined`: ``b`` the Laplace scale of the relative error, ``b0`` the model's
``confidence_scale``), so its standard deviation is ``sqrt(2) b = sqrt(2) b0 sqrt(1/conf - 1)``;
the likelihood fit (:mod:`tdfd.dfd.seeded_fit`) states a standard deviation from its curvature.
Neither is exact (the fit's tapered bins are correlated, the CNN's scale is conservative on some
scenes), so each is multiplied by a factor that makes the median of ``|error| / sigma`` a normal
variable's, 0.674, on held-out training scenes (:func:`sigma_factor`; :class:`LikelihoodScales`
stores them). The fused inverse depth is the inverse-variance mean.

The fused sigma is stated as a Laplace scale on the model's confidence scale; since the two
errors are not independent (they share the scene) and the fit's curvature sigma is not
proportional to its error, that scale is mapped once more, ``log b' = log b + s(log b)``
(:func:`tdfd.knot_map.calibrate_log_scale`, fitted on the fused errors of the same training
scenes: :meth:`LikelihoodScales.fused_scale`), so that its median error is ``b' ln 2`` along ``b``;
since format 4 also along the tile's slope in the model's map, ``+ g(log max(slope, 1e-4))``:
the fit takes each tile for fronto-parallel, so the fused error grows with the slope at a given
``b`` (on the training scenes 0.5x the median factor on flat tiles, 1.3x on the steepest).

Example:
    >>> import torch
    >>> fuse(torch.tensor([1.0, 1.0]), torch.tensor([1.0, float("inf")]),
    ...      torch.tensor([2.0, 2.0]), torch.tensor([1.0, 1.0]))[0].tolist()
    [1.5, 2.0]
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import torch

from ..errors import InputError, ModelError
from ..knot_map import calibrate_log_scale, knot_pairs, piecewise_linear, validate_knots

__all__ = ["MEDIAN_ABS_NORMAL", "SCALES_FORMAT", "SCALES_PSF", "SLOPE_FLOOR", "model_sigma", "confidence_from_sigma",
           "sigma_factor", "fuse", "LikelihoodScales", "tile_slope"]

#: The median of ``|x|`` for a standard normal ``x``.
MEDIAN_ABS_NORMAL = 0.6744897501960817
#: The ``format`` of a scales file (versions 1, before ``shared_bias``, 2, before the fused
#: scale's map, 3, before its slope part, and 4, before ``registered``, still load: without them).
SCALES_FORMAT = "tdfd.likelihood_scales/5"
_FORMATS = ("tdfd.likelihood_scales/1", "tdfd.likelihood_scales/2", "tdfd.likelihood_scales/3",
            "tdfd.likelihood_scales/4", SCALES_FORMAT)
#: the slope below which the fused scale's slope part reads the slope as this (a flat map's slope is 0)
SLOPE_FLOOR = 1e-4
#: the PSFs a scales file can be fitted for (:attr:`LikelihoodScales.psf`); a file without the key: profiled
SCALES_PSF = ("profiled", "measured")
_TINY = 1e-150  # squares stay above float64's smallest normal


def model_sigma(confidence: torch.Tensor, confidence_scale: float) -> torch.Tensor:
    """The model's standard deviation of the relative error, ``sqrt(2) b0 sqrt(1/conf - 1)``
    (``inf`` where the confidence is 0).

    Example:
        >>> round(float(model_sigma(torch.tensor([0.5]), 0.01)[0]), 5)
        0.01414

    Raises:
        InputError: a confidence outside [0, 1] or a scale not > 0.
    """
    if not confidence_scale > 0:
        raise InputError(f"confidence_scale must be > 0, got {confidence_scale}")
    if not bool(((confidence >= 0) & (confidence <= 1)).all()):
        raise InputError("confidences must lie in [0, 1]")
    c = confidence.to(torch.float64)
    safe = torch.where(c > 0, c, torch.ones_like(c))
    return torch.where(c > 0, math.sqrt(2.0) * confidence_scale * (1.0 / safe - 1.0).clamp_min(0).sqrt(),
                       torch.full_like(c, math.inf))


def confidence_from_sigma(sigma: torch.Tensor, confidence_scale: float) -> torch.Tensor:
    """The inverse of :func:`model_sigma`: ``1 / (1 + sigma^2 / (2 b0^2))`` (0 for ``inf``).

    Example:
        >>> round(float(confidence_from_sigma(model_sigma(torch.tensor([0.3]), 0.01), 0.01)[0]), 6)
        0.3
    """
    if not confidence_scale > 0:
        raise InputError(f"confidence_scale must be > 0, got {confidence_scale}")
    return 1.0 / (1.0 + sigma.to(torch.float64) ** 2 / (2.0 * confidence_scale ** 2))


def sigma_factor(errors: torch.Tensor, sigmas: torch.Tensor) -> float:
    """The factor on ``sigmas`` that makes the median of ``|errors| / sigma`` 0.674 (a normal's),
    over the finite, positive sigmas.

    Example:
        >>> round(sigma_factor(torch.tensor([-2.0, 1.0, 4.0]), torch.tensor([1.0, 1.0, 2.0])), 4)
        2.9652

    Raises:
        InputError: no finite positive sigma.
    """
    ok = torch.isfinite(sigmas) & (sigmas > 0) & torch.isfinite(errors)
    if not bool(ok.any()):
        raise InputError("no finite positive sigma to calibrate")
    return float((errors[ok].abs() / sigmas[ok]).median()) / MEDIAN_ABS_NORMAL


def fuse(q_a: torch.Tensor, sigma_a: torch.Tensor, q_b: torch.Tensor, sigma_b: torch.Tensor
         ) -> tuple[torch.Tensor, torch.Tensor]:
    """Inverse-variance mean of two estimates and its standard deviation; an infinite sigma gives
    its estimate no weight (a zero sigma, all of it).

    Raises:
        InputError: shapes that differ, or a pair with no finite sigma.
    """
    if q_a.shape != sigma_a.shape or q_a.shape != q_b.shape or q_a.shape != sigma_b.shape:
        raise InputError(f"estimates and sigmas must share one shape, got {tuple(q_a.shape)}, {tuple(sigma_a.shape)}, "
                         f"{tuple(q_b.shape)}, {tuple(sigma_b.shape)}")
    wa = torch.where(torch.isfinite(sigma_a), 1.0 / sigma_a.clamp_min(_TINY) ** 2, torch.zeros_like(sigma_a))
    wb = torch.where(torch.isfinite(sigma_b), 1.0 / sigma_b.clamp_min(_TINY) ** 2, torch.zeros_like(sigma_b))
    if not bool((wa + wb > 0).all()):
        raise InputError("every pair needs at least one finite sigma")
    return (wa * q_a + wb * q_b) / (wa + wb), 1.0 / (wa + wb).sqrt()


@dataclass(frozen=True)
class LikelihoodScales:
    """The factors on the two sigmas a fusion uses (:func:`sigma_factor` on held-out training
    scenes; 1 each: the raw sigmas), one per band of the tile's slope.

    The likelihood fit takes each tile for a fronto-parallel plane, so its curvature sigma
    understates the error where the depth changes across the tile; the model's map says where:
    a tile's *slope* is the largest relative difference of the map's inverse depth to its eight
    neighbours (:func:`tile_slope`). ``slope_edges`` split the tiles into bands, each with its
    own pair of factors.

    Args:
        fit: factors on the likelihood fit's sigma, one per band (a float: one band).
        model: factors on the model's sigma from its confidence, one per band.
        slope_edges: the increasing inner edges of the bands (``len(fit) - 1`` of them).
        shared_bias: remove the model's bias, measured against the fit, before the fusion
            (:mod:`tdfd.dfd.shared_bias`); the ``model`` factors then belong to the map without it.
        bias_radius: with ``shared_bias``, the bias of each tile is measured on the fitted tiles
            within this many tiles of it (:func:`~tdfd.dfd.shared_bias.bias_map`); ``None``: one
            bias for the whole image.
        fused_log_b, fused_log_b_calibrated: knots of the map of the fused Laplace scale
            (:meth:`fused_scale`; :func:`~tdfd.knot_map.validate_knots`), both or neither; ``None``:
            the fused scale as the two factors make it.
        fused_log_slope, fused_slope_log_shift: knots of the map's slope part, ``g`` at
            ``log max(slope, SLOPE_FLOOR)`` (piecewise linear, constant beyond the ends), both or
            neither, and only with the map's scale part; ``None``: no slope part.
        psf: the PSF the stage was told while they were fitted: ``"profiled"`` (over the family's
            shapes, as shipped) or ``"measured"`` (each lens's own, from a focus sweep, as
            ``tdfd depth --psf-model`` tells it); the fit's errors, hence its factors, differ.
        registered: whether the stage fitted each pair's focus breathing and shift while they
            were fitted (:mod:`tdfd.dfd.pair_registration`, ``tdfd depth --likelihood-register``);
            the fit's sigma then holds what the registration leaves, so its factors differ.
        provenance: how they were fitted (command, data, counts); free-form, saved with them.

    Example:
        >>> s = LikelihoodScales(fit=(1.5, 3.0), model=(0.7, 0.6), slope_edges=(0.02,))
        >>> [t.tolist() for t in s.factors(torch.tensor([0.0, 0.05]))]
        [[1.5, 3.0], [0.7, 0.6]]
    """

    fit: float | tuple[float, ...] = 1.0
    model: float | tuple[float, ...] = 1.0
    slope_edges: tuple[float, ...] = ()
    provenance: dict[str, Any] = field(default_factory=dict, compare=False)
    shared_bias: bool = field(default=False, kw_only=True)
    bias_radius: int | None = field(default=None, kw_only=True)
    fused_log_b: tuple[float, ...] | None = field(default=None, kw_only=True)
    fused_log_b_calibrated: tuple[float, ...] | None = field(default=None, kw_only=True)
    fused_log_slope: tuple[float, ...] | None = field(default=None, kw_only=True)
    fused_slope_log_shift: tuple[float, ...] | None = field(default=None, kw_only=True)
    psf: str = field(default="profiled", kw_only=True)
    registered: bool = field(default=False, kw_only=True)

    def __post_init__(self) -> None:
        bands = len(self.slope_edges) + 1
        for name in ("fit", "model"):
            v = getattr(self, name)
            vals = tuple(v) if isinstance(v, (list, tuple)) else (v,)
            if len(vals) != bands or not all(isinstance(x, (int, float)) and math.isfinite(x) and x > 0 for x in vals):
                raise InputError(f"the {name} sigma factors must be {bands} finite values > 0 (one per slope band), "
                                 f"got {v!r}")
            object.__setattr__(self, name, tuple(float(x) for x in vals))
        edges = tuple(float(e) for e in self.slope_edges)
        if any(not (math.isfinite(e) and e > 0) for e in edges) or any(b <= a for a, b in zip(edges, edges[1:])):
            raise InputError(f"slope_edges must be finite, > 0 and increasing, got {self.slope_edges!r}")
        object.__setattr__(self, "slope_edges", edges)
        if self.psf not in SCALES_PSF:
            raise InputError(f"psf must be one of {SCALES_PSF}, got {self.psf!r}")
        if not isinstance(self.shared_bias, bool):
            raise InputError(f"shared_bias must be a bool, got {self.shared_bias!r}")
        if not isinstance(self.registered, bool):
            raise InputError(f"registered must be a bool, got {self.registered!r}")
        if self.bias_radius is not None and not (isinstance(self.bias_radius, int) and self.bias_radius >= 1):
            raise InputError(f"bias_radius must be an int >= 1 (tiles) or None, got {self.bias_radius!r}")
        if (self.fused_log_b is None) != (self.fused_log_b_calibrated is None):
            raise InputError("the fused scale's map needs both fused_log_b and fused_log_b_calibrated, or neither")
        if self.fused_log_b is not None:
            x, y = validate_knots(self.fused_log_b, self.fused_log_b_calibrated)  # type: ignore[arg-type]
            object.__setattr__(self, "fused_log_b", tuple(x))
            object.__setattr__(self, "fused_log_b_calibrated", tuple(y))
        if (self.fused_log_slope is None) != (self.fused_slope_log_shift is None):
            raise InputError("the fused scale's slope part needs both fused_log_slope and fused_slope_log_shift, "
                             "or neither")
        if self.fused_log_slope is not None:
            if self.fused_log_b is None:
                raise InputError("the fused scale's slope part needs its scale part (fused_log_b)")
            x, y = knot_pairs(self.fused_log_slope, self.fused_slope_log_shift, "fused_log_slope",
                              "fused_slope_log_shift")
            object.__setattr__(self, "fused_log_slope", tuple(x))
            object.__setattr__(self, "fused_slope_log_shift", tuple(y))

    def band(self, slope: torch.Tensor) -> torch.Tensor:
        """Each tile's band index for its slope (``(T,)``, long)."""
        return torch.bucketize(slope.to(torch.float64), torch.tensor(self.slope_edges, dtype=torch.float64),
                               right=True)

    def factors(self, slope: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(fit, model)`` factors ``(T,)`` float64 of tiles of these slopes."""
        k = self.band(slope)
        return (torch.tensor(self.fit, dtype=torch.float64)[k], torch.tensor(self.model, dtype=torch.float64)[k])

    def fused_scale(self, scale: torch.Tensor, slope: torch.Tensor | None = None) -> torch.Tensor:
        """The fused Laplace scale ``b`` (any shape, > 0) through the map,
        ``exp(log b + s(log b) + g(log max(slope, SLOPE_FLOOR)))``; ``b`` itself without one
        (``inf`` stays ``inf``).

        Args:
            scale: the fused scales before the map.
            slope: the tiles' slopes (:func:`tile_slope`), shaped as ``scale``; needed when the
                map has a slope part, ignored otherwise.

        Raises:
            InputError: a slope part and no slope, or one of another shape.

        Example:
            >>> s = LikelihoodScales(fused_log_b=(-5.0, -3.0), fused_log_b_calibrated=(-4.0, -3.0))
            >>> round(float(s.fused_scale(torch.tensor([math.exp(-4.0)]))[0].log()), 4)
            -3.5
            >>> s = LikelihoodScales(fused_log_b=(-5.0, -3.0), fused_log_b_calibrated=(-4.0, -3.0),
            ...                      fused_log_slope=(-6.0, -2.0), fused_slope_log_shift=(-0.5, 0.5))
            >>> round(float(s.fused_scale(torch.tensor([math.exp(-4.0)]), torch.tensor([0.0]))[0].log()), 4)
            -4.0
        """
        b = scale.to(torch.float64)
        if self.fused_log_b is None:
            return b
        out = calibrate_log_scale(b.log(), torch.tensor(self.fused_log_b, dtype=torch.float64),
                                  torch.tensor(self.fused_log_b_calibrated, dtype=torch.float64))
        if self.fused_log_slope is not None:
            if slope is None or slope.shape != scale.shape:
                raise InputError("these scales' fused map has a slope part: pass the tiles' slopes, shaped as the "
                                 f"scales {tuple(scale.shape)}, got "
                                 f"{None if slope is None else tuple(slope.shape)}")
            out = out + piecewise_linear(slope.to(torch.float64).clamp_min(SLOPE_FLOOR).log(),
                                         torch.tensor(self.fused_log_slope, dtype=torch.float64),
                                         torch.tensor(self.fused_slope_log_shift, dtype=torch.float64))
        return torch.where(torch.isfinite(b), out.exp(), b)

    def save(self, path: str | Path) -> None:
        """Write them as JSON (``format``: :data:`SCALES_FORMAT`)."""
        Path(path).write_text(json.dumps({"format": SCALES_FORMAT, **asdict(self)}, indent=2) + "\n")

    @classmethod
    def load(cls, path: str | Path) -> "LikelihoodScales":
        """Read a file :meth:`save` wrote.

        Raises:
            ModelError: a file that is not JSON, of another format, or with bad factors.
        """
        try:
            data = json.loads(Path(path).read_text())
        except (OSError, json.JSONDecodeError) as e:
            raise ModelError(f"cannot read likelihood scales from {path}: {e}") from e
        if not isinstance(data, dict) or data.get("format") not in _FORMATS:
            raise ModelError(f"{path} is not a {SCALES_FORMAT} file")
        try:
            return cls(fit=data["fit"], model=data["model"], slope_edges=tuple(data.get("slope_edges") or ()),
                       shared_bias=data.get("shared_bias", False), bias_radius=data.get("bias_radius"),
                       fused_log_b=data.get("fused_log_b"), fused_log_b_calibrated=data.get("fused_log_b_calibrated"),
                       fused_log_slope=data.get("fused_log_slope"),
                       fused_slope_log_shift=data.get("fused_slope_log_shift"),
                       psf=data.get("psf", "profiled"), registered=data.get("registered", False),
                       provenance=dict(data.get("provenance") or {}))
        except (KeyError, TypeError, InputError) as e:
            raise ModelError(f"{path}: bad likelihood scales ({e})") from e


def tile_slope(q_map: torch.Tensor) -> torch.Tensor:
    """Each tile's slope: the largest ``|q_n - q| / q`` over its (up to eight) neighbours ``n`` in
    the map ``(h, w)`` of inverse depths.

    Example:
        >>> tile_slope(torch.tensor([[1.0, 1.0], [1.0, 1.1]])).tolist()
        [[0.1, 0.1], [0.1, 0.1]]
    """
    if q_map.ndim != 2:
        raise InputError(f"need an (h, w) map, got {tuple(q_map.shape)}")
    q = q_map.to(torch.float64)
    pad = torch.nn.functional.pad(q[None, None], (1, 1, 1, 1), mode="replicate")[0, 0]
    h, w = q.shape
    out = torch.zeros_like(q)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            out = torch.maximum(out, (pad[1 + dy: 1 + dy + h, 1 + dx: 1 + dx + w] - q).abs() / q)
    return out
