"""Procedural defocus-pair synthesis for training tdfd's CNN (issue 3).

Composes the library's physics (:mod:`tdfd.textures`, :mod:`tdfd.illumination`,
:mod:`tdfd.optics.render`, :mod:`tdfd.sensor`) into training scenes:

* :class:`DefocusPairDataset`: a torch ``Dataset`` that synthesises on the fly,
  deterministic per ``(seed, index)``; ``batch(indices)`` for a whole batch.
* :class:`SynthBatchGenerator`: the same without the Dataset wrapper.
* :class:`SynthConfig`: every knob (scene mix, PSF shapes, sensor ranges, breathing, ...).
* ``python -m data_synth --out DIR --count N --seed S --size 256``: shards, manifest,
  contact sheet, optional 16-bit PNG pairs (:mod:`data_synth.cli`).
"""

from __future__ import annotations

from .dataset import DefocusPairDataset, collate_pairs
from .params import LAYOUTS, PSF_SHAPES, SynthConfig, sample_generator, sample_seed
from .psf import PSFModel
from .synth import PARAM_KEYS, SynthBatchGenerator, render_frames, warp_pair

__all__ = ["DefocusPairDataset", "SynthBatchGenerator", "SynthConfig", "PSFModel", "PARAM_KEYS", "LAYOUTS",
           "PSF_SHAPES", "collate_pairs", "render_frames", "warp_pair", "sample_generator", "sample_seed"]
