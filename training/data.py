"""On-the-fly training data: procedural pairs from ``data_synth``, featurised per step.

Every optimisation step ``s`` reads a fixed block of sample indices,
``[s * G + rank * B, s * G + rank * B + B)`` with ``B`` the per-process batch and ``G = B *
world_size``, from a dataset that is deterministic per ``(seed, index)``. So the data of a
step depends only on the step (exact resume, no sampler state) and DDP ranks see disjoint
samples. :class:`StepBatches` is a map-style dataset of whole batches (one per step) for a
``DataLoader`` whose workers synthesise the pairs *and* run the analytic stage (it has no
trainable parameters), so the main process only runs the small CNN.
"""

from __future__ import annotations

import importlib
import inspect
import logging
from dataclasses import dataclass
from typing import Any, Callable

import torch

from data_synth import DefocusPairDataset
from tdfd.camera import Camera
from tdfd.camera_file import resolve_camera
from tdfd.model import DFDModel, family_classes, training_codes

from .config import TEXTURED_FAMILIES, ConfigError, DataConfig, ModelConfig

__all__ = ["import_object", "make_dataset", "build_model", "Featurizer", "StepBatches", "FeatureSet",
           "featurize_dataset", "fetch_batch", "STRUCTURE_LAYOUTS", "textured_scenes"]

#: data_synth depth layouts with depth structure (the structure benchmark's and the scale calibration's)
STRUCTURE_LAYOUTS = ("slanted", "layout", "smooth")

logger = logging.getLogger(__name__)


def import_object(spec: str) -> Any:
    """Import ``module:attribute`` (raises :class:`ConfigError` if it cannot)."""
    module, _, attr = spec.partition(":")
    try:
        obj = importlib.import_module(module)
        for part in attr.split("."):
            obj = getattr(obj, part)
    except (ImportError, AttributeError) as exc:
        raise ConfigError(f"cannot import {spec!r}: {exc}") from exc
    return obj


def textured_scenes(camera: Camera, tile: int, stride: int, layout: str, size: tuple[int, int], seed: int,
                    **options: Any) -> DefocusPairDataset:
    """Held-out scenes of one ``data_synth`` layout: every textured family, no assist light,
    on ``camera`` and the ``tile``/``stride`` grid; ``options`` go to the dataset (e.g.
    ``return_sharp``)."""
    return DefocusPairDataset(size=size, camera=camera, seed=seed, tile=tile, stride=stride, layouts={layout: 1.0},
                              families=list(TEXTURED_FAMILIES), illumination_prob=0.0, **options)


def build_model(mcfg: ModelConfig) -> DFDModel:
    """A fresh :class:`~tdfd.model.DFDModel` from the model section."""
    camera = resolve_camera(mcfg.camera)
    return DFDModel(camera, tile=mcfg.tile, stride=mcfg.stride, confidence_scale=mcfg.confidence_scale,
                    correction_scale=mcfg.correction_scale, hidden=mcfg.hidden, blocks=mcfg.blocks,
                    kernel_size=mcfg.kernel_size, dilation_base=mcfg.dilation_base, context=mcfg.context,
                    psf_family_input=mcfg.psf_family_input, structure_pooling=mcfg.structure_pooling or None,
                    **({"family_inference": True} if mcfg.family_inference else {}))


def make_dataset(dcfg: DataConfig, mcfg: ModelConfig, seed: int, height: int | None = None,
                 width: int | None = None, **extra: Any) -> Any:
    """Instantiate the configured dataset with ``seed``, the camera, the grid and the size.

    Only the keyword arguments the dataset's constructor accepts are passed (``seed``,
    ``camera``, ``tile``, ``stride``, ``size`` or ``height``/``width``), then
    ``dcfg.options`` and ``extra``.
    """
    cls = import_object(dcfg.dataset)
    h, w = height or dcfg.height, width or dcfg.width
    try:
        params = inspect.signature(cls).parameters
    except (TypeError, ValueError):
        params = {}
    var_kw = any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values())
    offer: dict[str, Any] = {"seed": seed, "camera": resolve_camera(mcfg.camera), "tile": mcfg.tile,
                             "stride": mcfg.stride}
    if "size" in params:
        offer["size"] = (h, w)
    else:
        offer.update(height=h, width=w)
    kwargs = {k: v for k, v in offer.items() if k in params or (var_kw and k in ("seed", "camera", "tile", "stride"))}
    kwargs.update(dcfg.options)
    kwargs.update(extra)
    try:
        return cls(**kwargs)
    except TypeError as exc:
        raise ConfigError(f"cannot build {dcfg.dataset} with {sorted(kwargs)}: {exc}") from exc


def fetch_batch(dataset: Any, indices: list[int]) -> dict[str, Any]:
    """Samples ``indices`` as a batch dict (the dataset's ``batch`` fast path if it has one)."""
    fast = getattr(dataset, "batch", None) or getattr(dataset, "get_batch", None)
    if callable(fast):
        return fast(indices)
    items = [dataset[i] for i in indices]
    out = {k: torch.stack([it[k] for it in items]) for k in ("image_f1", "image_f2", "tile_depth")}
    out["params"] = [it.get("params") for it in items]
    return out


class Featurizer:
    """The model's analytic stage: image pair -> CNN features and what the head needs.

    With ``model.psf_family_input`` each sample is told its own PSF family or not
    (:func:`tdfd.model.training_codes`, ``model.psf_family_told_share``)."""

    def __init__(self, mcfg: ModelConfig) -> None:
        self.model = build_model(mcfg).eval().set_validate(False)
        self.told_share = float(mcfg.psf_family_told_share)

    @torch.no_grad()
    def __call__(self, batch: dict[str, Any]) -> dict[str, torch.Tensor]:
        i1 = batch["image_f1"].float()
        i2 = batch["image_f2"].float()
        params = batch.get("params")
        if not isinstance(params, list):  # a dataset that records no per-sample parameters
            params = [None] * i1.shape[0]
        codes = None
        if self.model.psf_family_input:  # each sample's own PSF family, told or unknown
            codes = training_codes(params, self.told_share)
        feats, r = self.model.features(i1, i2, codes)
        target = batch["tile_depth"].float()
        if target.shape[-2:] != feats.shape[-2:]:
            raise ConfigError(f"dataset tile_depth {tuple(target.shape)} does not match the model grid {tuple(feats.shape)}")
        out = {"features": feats, "inverse_depth": r.inverse_depth.float(), "rel_error": r.rel_error.float(),
               "tile_depth": target}
        if self.model.refine.family is not None:  # each sample's true family: the inference's label
            out["family_class"] = family_classes(params)
        return out


class StepBatches(torch.utils.data.Dataset):
    """Map-style dataset whose item ``s`` is the featurised batch of optimisation step ``s``.

    Args:
        dataset_factory: builds the pair dataset (called lazily, once per worker).
        featurizer_factory: builds the :class:`Featurizer` (once per worker).
        batch_size: per-process batch.
        rank, world_size: DDP position (indices are offset per rank).
        num_steps: length.
    """

    def __init__(self, dataset_factory: Callable[[], Any], featurizer_factory: Callable[[], Featurizer],
                 batch_size: int, rank: int = 0, world_size: int = 1, num_steps: int = 1) -> None:
        self.dataset_factory, self.featurizer_factory = dataset_factory, featurizer_factory
        self.batch_size, self.rank, self.world_size, self.num_steps = batch_size, rank, world_size, num_steps
        self._ds = None
        self._fz = None

    def __len__(self) -> int:
        return self.num_steps

    def indices(self, step: int) -> list[int]:
        start = step * self.batch_size * self.world_size + self.rank * self.batch_size
        return list(range(start, start + self.batch_size))

    def __getitem__(self, step: int) -> dict[str, torch.Tensor]:
        if self._ds is None:
            self._ds, self._fz = self.dataset_factory(), self.featurizer_factory()
        return self._fz(fetch_batch(self._ds, self.indices(int(step))))


@dataclass
class FeatureSet:
    """A featurised fixed set (validation): tensors ``(N, ., h, w)`` and per-sample params."""

    features: torch.Tensor
    inverse_depth: torch.Tensor
    rel_error: torch.Tensor
    tile_depth: torch.Tensor
    params: list
    #: with the family inference: each sample's true class (:func:`~tdfd.model.family_inference.family_classes`)
    family_class: torch.Tensor | None = None

    def __len__(self) -> int:
        return int(self.features.shape[0])

    def chunks(self, size: int):
        for i in range(0, len(self), size):
            keys = ("features", "inverse_depth", "rel_error", "tile_depth") + (("family_class",) if self.family_class is not None else ())
            yield {k: getattr(self, k)[i : i + size] for k in keys}


def featurize_dataset(dataset: Any, featurizer: Featurizer, count: int, chunk: int = 32) -> FeatureSet:
    """Featurise samples ``0 .. count-1`` of ``dataset`` into a :class:`FeatureSet`."""
    parts: list[dict[str, torch.Tensor]] = []
    params: list = []
    for start in range(0, count, chunk):
        batch = fetch_batch(dataset, list(range(start, min(count, start + chunk))))
        parts.append(featurizer(batch))
        p = batch.get("params")
        params.extend(p if isinstance(p, list) else [p] * len(parts[-1]["features"]))
    cat = {k: torch.cat([p[k] for p in parts]) for k in parts[0]}
    return FeatureSet(params=params, **cat)
