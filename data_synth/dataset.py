"""Torch datasets of procedural DFD pairs.

:class:`DefocusPairDataset` synthesises on the fly (deterministic per ``(seed, index)``,
whatever the DataLoader worker count or order); :class:`ShardDataset` reads the shards the
CLI writes (:mod:`data_synth.writer`).
"""

from __future__ import annotations

from typing import Any, Sequence

import torch

from tdfd import Camera

from .params import SynthConfig
from .synth import SynthBatchGenerator

__all__ = ["DefocusPairDataset", "collate_pairs"]


class DefocusPairDataset(torch.utils.data.Dataset):
    """Procedural defocus pairs, synthesised on the fly.

    Args:
        size: image size, an int or ``(H, W)`` (px).
        camera: camera description (default the ``reference`` preset).
        seed: stream seed; sample ``i`` depends only on ``(seed, i)`` and the options.
        length: nominal length (any non-negative index works).
        families: texture families (default all of :data:`tdfd.textures.TEXTURE_FAMILIES`), or
            ``{family: relative weight}`` (:class:`SynthConfig`).
        psf_shapes: PSF shapes among ``"gaussian"``, ``"pillbox"``, ``"beta"`` (default all).
        tile, stride: tile grid of ``tile_depth``.
        noise: apply the sensor model.
        illumination_prob: probability of active illumination (default from the config).
        config: a full :class:`~data_synth.params.SynthConfig` (the arguments above override it).
        return_sharp: also return the sharp radiance as ``sharp``.
        **options: any other :class:`~data_synth.params.SynthConfig` field.

    Items are dicts: ``image_f1``, ``image_f2`` float32 ``(1, H, W)`` in [0, 1] (raw /
    white level, black level included); ``depth`` ``(1, H, W)`` metres; ``tile_depth``
    ``(1, h, w)`` metres (inverse of the window-weighted mean inverse depth of each tile,
    squared periodic Hann window by default); ``params`` a flat dict of plain values
    (:data:`data_synth.synth.PARAM_KEYS`), which ``default_collate`` batches.

    :meth:`batch` (alias :meth:`get_batch`) returns a whole batch in one call.

    Example:
        >>> ds = DefocusPairDataset(size=64, seed=1, length=4, tile=32, stride=16)
        >>> item = ds[2]
        >>> sorted(k for k in item if k != "params")
        ['depth', 'image_f1', 'image_f2', 'tile_depth']
        >>> bool(torch.equal(item["image_f1"], ds[2]["image_f1"]))
        True
    """

    def __init__(self, size: int | Sequence[int] = 256, camera: Camera | None = None, seed: int = 0,
                 length: int = 100_000, families: Sequence[str] | None = None,
                 psf_shapes: Sequence[str] | None = None, tile: int = 64, stride: int = 32, noise: bool = True,
                 illumination_prob: float | None = None, config: SynthConfig | None = None,
                 return_sharp: bool = False, **options: Any) -> None:
        base = (config or SynthConfig()).to_dict()
        base.update(tile=tile, stride=stride, noise=noise)
        if families is not None:
            base["families"] = dict(families) if isinstance(families, dict) else list(families)
        if psf_shapes is not None:
            base["psf_shapes"] = list(psf_shapes)
        if illumination_prob is not None:
            base["illumination_prob"] = illumination_prob
        base.update(options)
        self.generator = SynthBatchGenerator(size, camera, seed, SynthConfig.from_dict(base), return_sharp)
        self.length = int(length)

    @property
    def config(self) -> SynthConfig:
        return self.generator.config

    @property
    def camera(self) -> Camera:
        return self.generator.camera

    @property
    def seed(self) -> int:
        return self.generator.seed

    @property
    def size(self) -> tuple[int, int]:
        return self.generator.size

    def __len__(self) -> int:
        return self.length

    def __getitem__(self, index: int) -> dict[str, Any]:
        if index < 0:
            index += self.length
        if index < 0:
            raise IndexError(index)
        return self.generator.sample(int(index))

    def batch(self, indices: Sequence[int]) -> dict[str, Any]:
        """Samples ``indices`` stacked into ``(N, 1, ., .)`` tensors; ``params`` a list of dicts."""
        return self.generator.batch(indices)

    get_batch = sample_batch = batch


def collate_pairs(items: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Stack items into a batch, keeping ``params`` as a list of dicts (a ``collate_fn``)."""
    out: dict[str, Any] = {k: torch.stack([it[k] for it in items]) for k in items[0] if k != "params"}
    out["params"] = [it["params"] for it in items]
    return out
