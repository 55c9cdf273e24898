"""Procedural defocus-pair synthesis for training tdfd's CNN (issue 3).

Composes the library's physics (:mod:`tdfd.textures`, :mod:`tdfd.illumination`,
:mod:`tdfd.optics.render`, :mod:`tdfd.sensor`) into training scenes:

* :class:`DefocusPairDataset`: a torch ``Dataset`` that synthesises on the fly,
  deterministic per ``(seed, index)`` (whatever the worker count or request order);
  ``batch(indices)`` returns a whole batch in one call.
* :class:`SynthBatchGenerator`: the same without the Dataset wrapper.
* :class:`SynthConfig`: every knob (scene mix, texture families, illumination, PSF shapes,
  sensor ranges, breathing, misregistration, tile grid).
* ``python -m data_synth --out DIR --count N --seed S --size 256``: shards, manifest,
  contact sheet, optional 16-bit PNG pairs (:mod:`data_synth.cli`);
  :class:`~data_synth.writer.ShardDataset` reads a written set back.

Throughput: a sample costs about 25 ms of one core at 256 x 256 (``docs/BENCHMARKS.md``,
section *synthesis*). Use a ``DataLoader`` with ``num_workers=2`` on the 2-core machine (each
worker renders with one torch thread); avoid two intra-op threads per process when other
work shares the cores (many small ops: OpenMP threads then wait on each other).

Example:
    >>> ds = DefocusPairDataset(size=64, seed=0, tile=32, stride=16)
    >>> s = ds[0]
    >>> s["image_f1"].shape, s["tile_depth"].shape, s["params"]["layout"] in LAYOUTS
    (torch.Size([1, 64, 64]), torch.Size([1, 3, 3]), True)
"""

from __future__ import annotations

from .dataset import DefocusPairDataset, collate_pairs
from .params import LAYOUTS, PSF_SHAPES, SynthConfig, sample_generator, sample_seed
from .psf import PSFModel
from .synth import PARAM_KEYS, SynthBatchGenerator, render_frames, warp_pair
from .writer import ShardDataset, load_shard

__all__ = ["DefocusPairDataset", "SynthBatchGenerator", "SynthConfig", "PSFModel", "PARAM_KEYS", "LAYOUTS",
           "PSF_SHAPES", "collate_pairs", "render_frames", "warp_pair", "sample_generator", "sample_seed",
           "ShardDataset", "load_shard"]
