"""Training pipeline of the tdfd refinement CNN (not part of the installed library).

Run from the repository root: ``python -m training --config FILE --set key=value``.
Modules: :mod:`training.config` (typed configuration), :mod:`training.data` (on-the-fly
procedural batches), :mod:`training.losses`, :mod:`training.loop` (seeds, DDP, exact
resume, logs), :mod:`training.evaluate` (the report), :mod:`training.calibrate_scale` (the last
stage: the predicted error scale's calibration, ``python -m training.calibrate_scale --model STEM``).
"""

from .config import ConfigError, TrainConfig, load_config

__all__ = ["ConfigError", "TrainConfig", "load_config", "train"]


def train(*args, **kwargs):
    """:func:`training.loop.train` (imported lazily)."""
    from .loop import train as _train

    return _train(*args, **kwargs)
