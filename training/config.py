"""Typed training configuration: dataclasses, a file (JSON, TOML, YAML) and ``key=value`` overrides.

Example:
    >>> cfg = load_config(None, ["optim.lr=0.001", "data.batch_size=8", "model.hidden=16"])
    >>> cfg.optim.lr, cfg.data.batch_size, cfg.model.hidden
    (0.001, 8, 16)
    >>> load_config(None, ["optim.lr=fast"])
    Traceback (most recent call last):
    ...
    training.config.ConfigError: optim.lr: expected float, got 'fast'
"""

from __future__ import annotations

import dataclasses
import json
import math
import tomllib
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable

from tdfd.camera_file import resolve_camera
from tdfd.errors import CameraError, InputError

__all__ = ["TEXTURED_FAMILIES", "ConfigError", "DataConfig", "ModelConfig", "OptimConfig", "EvalConfig",
           "CalibrationConfig", "TrainConfig", "load_config", "apply_overrides", "config_to_dict", "config_from_dict"]


class ConfigError(InputError):
    """An unknown configuration key, a value of the wrong type, or an unreadable file."""


@dataclass
class DataConfig:
    """Where training pairs come from.

    Attributes:
        dataset: ``module:Class`` of the procedural dataset (deterministic per
            ``(seed, index)``; a ``batch(indices)`` method is used when present).
        options: keyword arguments for the dataset (image size, scene mix, ...).
        height, width: training image size in pixels (passed as ``size=(height, width)``).
        batch_size: pairs per optimisation step (per process under DDP).
        seed: seed of the training stream.
        val_seed: seed of the held-out validation set (must differ from ``seed``).
        val_size: pairs in the validation set.
        num_workers: DataLoader worker processes generating batches ahead of the loop.
        prefetch_factor: batches each worker prepares ahead.
        reuse: optimisation steps per freshly generated batch (1 = every step sees new
            pairs). Synthesis is the bottleneck on a small CPU; reusing each batch a few
            times, mixed with earlier ones, trains more per generated pair.
        pool_batches: the replay pool: each step draws its minibatch from the last
            ``pool_batches`` generated batches (by a generator seeded with the step, so
            resuming is still exact).
    """

    dataset: str = "data_synth:DefocusPairDataset"
    options: dict = field(default_factory=dict)
    height: int = 128
    width: int = 128
    batch_size: int = 32
    seed: int = 0
    val_seed: int = 1_000_003
    val_size: int = 256
    num_workers: int = 1
    prefetch_factor: int = 4
    reuse: int = 1
    pool_batches: int = 1


@dataclass
class ModelConfig:
    """The combined model (see :class:`tdfd.model.DFDModel`).

    ``camera``: a preset name (``reference``, ``paper``) or the path of a camera JSON file
    (the ``tdfd.camera`` object, :mod:`tdfd.camera_file`), e.g.
    ``python -m training --set model.camera=mycam.json``.
    """

    camera: str = "reference"
    tile: int = 64
    stride: int = 32
    hidden: int = 32
    blocks: int = 2
    kernel_size: int = 3
    dilation_base: int = 1
    confidence_scale: float = 0.01
    correction_scale: float = 1.0
    #: sides (odd, in tiles) of the neighbourhoods whose pooled fits are extra features
    #: (a number or a list; [] or 1: none)
    context: list[int] = field(default_factory=list)
    #: the CNN also sees the lens's PSF family (:mod:`tdfd.model.psf_family_code`)
    psf_family_input: bool = False
    #: with ``psf_family_input``: the share of Gaussian and pillbox samples told their family
    #: (the rest, and every power-exponential PSF, are unknown)
    psf_family_told_share: float = 0.5
    #: with ``psf_family_input``: an unknown family is inferred from the whole image
    #: (:mod:`tdfd.model.family_inference`), supervised by ``optim.family_weight``
    family_inference: bool = False
    #: options of the last stage that pools the tiles along the depth structure
    #: (:class:`tdfd.model.structure_pooling.StructurePooling`; {} = none); training sees it only
    #: through ``optim.pooled_weight``, the calibration stage fits its output's scale
    structure_pooling: dict = field(default_factory=dict)


@dataclass
class OptimConfig:
    """Optimiser, schedule and loss.

    Attributes:
        steps: optimisation steps in total.
        lr: peak AdamW learning rate (cosine decay after a linear warm-up).
        min_lr_ratio: final learning rate as a fraction of ``lr``.
        warmup_steps: linear warm-up steps.
        weight_decay: AdamW weight decay.
        grad_clip: gradient-norm clip (0 = off).
        l1_weight: weight of a plain mean absolute relative error term added to the Laplace
            NLL (stabilises the start; the NLL alone calibrates the confidence).
        normaliser_batches: batches used to fit the feature standardisation before step 0.
        family_weight: with ``model.family_inference``, weight of the cross-entropy of the
            image-wide PSF family logits against each sample's true family.
        pooled_weight: with ``model.structure_pooling``, weight of the pooled map's error in
            units of the tiles' scales (:func:`training.losses.pooled_loss`) beside the tiles'
            loss; 0 = training does not see the pooling.
        pooled_scales_only: with ``pooled_weight``, the pooled loss reaches the CNN only through
            the tiles' scales (the pooling's weights), not through their depths, so the tiles'
            depths answer to their own loss alone.
    """

    steps: int = 2000
    lr: float = 3e-3
    min_lr_ratio: float = 0.02
    warmup_steps: int = 50
    weight_decay: float = 1e-4
    grad_clip: float = 1.0
    l1_weight: float = 0.2
    normaliser_batches: int = 4
    family_weight: float = 0.1
    pooled_weight: float = 0.0
    pooled_scales_only: bool = False


@dataclass
class CalibrationConfig:
    """The run's last stage: calibrating the predicted error scale (:mod:`training.calibrate_scale`).

    Attributes:
        enabled: fit the calibration after training (before the final evaluation) and save
            the model with it.
        planes: textured planes (256x256) of the calibration scenes.
        scenes: scenes per depth-structure layout (480x640).
        bins: equal-count bands of the predicted scale (knots).
        smooth: odd moving-average width over the bands' factors.
        min_factor: smallest factor ``b' / b`` at a knot of the scale part (1: only widen); 0 = no bound.
        depth_bins: bands of the refined inverse depth (the depth part's knots); 0 = no depth part.
        border_levels: distances to the grid's edge with their own factor; 0 = no edge part.
        pooled_planes, pooled_scenes: the structure-pooled map's planes and scenes per layout
            (a model with ``model.structure_pooling``); 0 = ``planes``, ``scenes``.
    """

    enabled: bool = False
    planes: int = 2048
    scenes: int = 64
    bins: int = 40
    smooth: int = 3
    min_factor: float = 0.0
    depth_bins: int = 20
    border_levels: int = 5
    pooled_planes: int = 0
    pooled_scenes: int = 0


#: Textured texture families (every registered family but the near-uniform ``gradient`` and ``flat``).
TEXTURED_FAMILIES = ["fractal", "bandlimited", "voronoi", "dead_leaves", "stripes", "checkers", "dots", "line_art",
                     "glyphs"]


@dataclass
class EvalConfig:
    """The final evaluation report: held-out planes, binned by distance.

    Attributes:
        samples: textured-plane pairs.
        textureless_samples: texture-less plane pairs (for the confidence check).
        bins: distance bins, equally spaced in depth over the working range.
        seed: seed of the evaluation scenes (distinct from training and validation).
        height, width: evaluation image size.
        options: dataset options of the textured planes (``data.options`` are not used).
        textureless_options: dataset options of the texture-less planes.
        min_contrast: also report the subset of planes whose texture contrast is at least
            this (read from the dataset's ``params``; 0 = off).
        min_signal_e: and the subset of those with at least this many mean photo-electrons
            per pixel (0 = off).
    """

    samples: int = 64
    textureless_samples: int = 16
    bins: int = 7
    seed: int = 2_000_003
    height: int = 192
    width: int = 192
    options: dict = field(default_factory=lambda: {"layouts": {"plane": 1.0}, "families": list(TEXTURED_FAMILIES),
                                                   "illumination_prob": 0.0})
    textureless_options: dict = field(default_factory=lambda: {"layouts": {"plane": 1.0}, "families": ["flat"],
                                                               "illumination_prob": 0.0})
    min_contrast: float = 0.1
    min_signal_e: float = 0.0


@dataclass
class TrainConfig:
    """Everything one training run needs.

    Attributes:
        out_dir: run directory (checkpoints, ``train_log.csv``, report, final model).
        seed: seed of the model initialisation.
        device: ``auto`` (CUDA when available), ``cpu`` or ``cuda``/``cuda:N``.
        threads: torch intra-op threads of the training process on any device (0 = leave torch's
            default, one per core, which contends with busy data workers).
        log_every: steps between CSV log rows.
        val_every: steps between validations.
        ckpt_every: steps between checkpoints (the last step always writes one).
        max_minutes: stop early (with a checkpoint) after this wall time; 0 = no limit.
        final_eval: write the evaluation report at the end.
        calibration: the predicted error scale's calibration after training (:class:`CalibrationConfig`).
    """

    out_dir: str = "runs/default"
    seed: int = 0
    device: str = "auto"
    threads: int = 0
    log_every: int = 10
    val_every: int = 200
    ckpt_every: int = 100
    max_minutes: float = 0.0
    final_eval: bool = True
    data: DataConfig = field(default_factory=DataConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    calibration: CalibrationConfig = field(default_factory=CalibrationConfig)


# ----------------------------------------------------------------------------- parsing
def _hints(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def _coerce(path: str, tp: Any, value: Any) -> Any:
    """Convert ``value`` (a parsed file value or an override string) to type ``tp``."""
    origin = typing.get_origin(tp) or tp
    if origin is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.lower() in ("true", "1", "yes", "on", "false", "0", "no", "off"):
            return value.lower() in ("true", "1", "yes", "on")
        raise ConfigError(f"{path}: expected bool, got {value!r}")
    if origin is int:
        if isinstance(value, bool):
            raise ConfigError(f"{path}: expected int, got {value!r}")
        if isinstance(value, int):
            return value
        if isinstance(value, float) and value.is_integer():
            return int(value)
        if isinstance(value, str):
            try:
                return int(value.replace("_", ""))
            except ValueError:
                pass
        raise ConfigError(f"{path}: expected int, got {value!r}")
    if origin is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return float(value)
        if isinstance(value, str):
            try:
                return float(value)
            except ValueError:
                pass
        raise ConfigError(f"{path}: expected float, got {value!r}")
    if origin is str:
        if isinstance(value, str):
            return value
        raise ConfigError(f"{path}: expected str, got {value!r}")
    if origin is list:
        (item,) = typing.get_args(tp) or (Any,)
        if isinstance(value, str):
            text = value.strip()
            try:
                value = json.loads(text if text.startswith("[") else f"[{text}]")
            except json.JSONDecodeError as exc:
                raise ConfigError(f"{path}: expected a list such as [3, 7], got {value!r}") from exc
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            value = [value]
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{path}: expected a list, got {value!r}")
        return [v if item is Any else _coerce(f"{path}[{i}]", item, v) for i, v in enumerate(value)]
    if origin is dict:
        if isinstance(value, str):
            try:
                value = json.loads(value)
            except json.JSONDecodeError as exc:
                raise ConfigError(f"{path}: expected a JSON object, got {value!r}") from exc
        if not isinstance(value, dict):
            raise ConfigError(f"{path}: expected a mapping, got {value!r}")
        return dict(value)
    raise ConfigError(f"{path}: unsupported field type {tp!r}")


def config_from_dict(data: dict[str, Any], cls: type = TrainConfig, prefix: str = "") -> Any:
    """Build a config dataclass from nested dicts, checking keys and value types."""
    if not isinstance(data, dict):
        raise ConfigError(f"{prefix or 'config'}: expected a mapping, got {type(data).__name__}")
    hints = _hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise ConfigError(f"unknown config key(s) {[prefix + k for k in unknown]}; valid: {sorted(prefix + n for n in names)}")
    kwargs = {}
    for name, value in data.items():
        tp = hints[name]
        if dataclasses.is_dataclass(tp):
            kwargs[name] = config_from_dict(value, tp, prefix + name + ".")
        else:
            kwargs[name] = _coerce(prefix + name, tp, value)
    return cls(**kwargs)


def config_to_dict(cfg: Any) -> dict[str, Any]:
    """The config as nested plain dicts (JSON-serialisable)."""
    return dataclasses.asdict(cfg)


def apply_overrides(cfg: TrainConfig, overrides: Iterable[str]) -> TrainConfig:
    """Apply ``section.key=value`` overrides (values parsed by the field's type).

    ``data.options.KEY=VALUE`` sets one dataset option (the value parsed as JSON when it
    can be, else kept as a string).

    Raises:
        ConfigError: a malformed override, an unknown key or a value of the wrong type.
    """
    cfg = config_from_dict(config_to_dict(cfg))  # a deep copy, validated
    for item in overrides:
        if "=" not in item:
            raise ConfigError(f"override {item!r} must look like key=value")
        key, raw = item.split("=", 1)
        parts = key.strip().split(".")
        target: Any = cfg
        for i, part in enumerate(parts[:-1]):
            if isinstance(target, dict):
                raise ConfigError(f"override {key!r}: cannot index into option {'.'.join(parts[:i])!r}")
            if not dataclasses.is_dataclass(target) or part not in {f.name for f in dataclasses.fields(target)}:
                raise ConfigError(f"unknown config key {key!r}")
            target = getattr(target, part)
        last = parts[-1]
        if isinstance(target, dict):  # data.options.KEY
            try:
                target[last] = json.loads(raw)
            except json.JSONDecodeError:
                target[last] = raw
            continue
        fields = {f.name for f in dataclasses.fields(target)}
        if last not in fields:
            raise ConfigError(f"unknown config key {key!r}; valid in this section: {sorted(fields)}")
        tp = _hints(type(target))[last]
        if dataclasses.is_dataclass(tp):
            raise ConfigError(f"{key!r} is a section; set one of its keys")
        setattr(target, last, _coerce(key, tp, raw))
    return cfg


def _read_file(path: Path) -> dict[str, Any]:
    try:
        text = path.read_text()
    except OSError as exc:
        raise ConfigError(f"cannot read config file {path}: {exc}") from exc
    suffix = path.suffix.lower()
    try:
        if suffix == ".json":
            return json.loads(text)
        if suffix == ".toml":
            return tomllib.loads(text)
        if suffix in (".yaml", ".yml"):
            try:
                import yaml  # type: ignore[import-not-found]
            except ImportError as exc:
                raise ConfigError("YAML configs need PyYAML; use JSON or TOML") from exc
            return yaml.safe_load(text) or {}
    except (json.JSONDecodeError, tomllib.TOMLDecodeError) as exc:
        raise ConfigError(f"cannot parse config file {path}: {exc}") from exc
    raise ConfigError(f"config file {path} must be .json, .toml or .yaml")


def load_config(path: str | Path | None = None, overrides: Iterable[str] = ()) -> TrainConfig:
    """Defaults, then the file (if any), then the overrides; validated.

    Raises:
        ConfigError: unreadable file, unknown key, wrong type or an invalid value.
    """
    cfg = config_from_dict(_read_file(Path(path))) if path else TrainConfig()
    cfg = apply_overrides(cfg, overrides)
    validate_config(cfg)
    return cfg


def validate_config(cfg: TrainConfig) -> None:
    """Check value ranges; raise :class:`ConfigError` naming the first bad one."""
    checks = [
        (cfg.data.batch_size >= 1, "data.batch_size must be >= 1"),
        (cfg.data.val_size >= 1, "data.val_size must be >= 1"),
        (cfg.data.num_workers >= 0, "data.num_workers must be >= 0"),
        (cfg.data.prefetch_factor >= 1, "data.prefetch_factor must be >= 1"),
        (cfg.data.reuse >= 1 and cfg.data.pool_batches >= 1, "data.reuse and data.pool_batches must be >= 1"),
        (cfg.data.seed != cfg.data.val_seed, "data.val_seed must differ from data.seed (held-out set)"),
        (":" in cfg.data.dataset, "data.dataset must be 'module:Class'"),
        (min(cfg.data.height, cfg.data.width) >= cfg.model.tile, "data.height/width must be >= model.tile"),
        (min(cfg.eval.height, cfg.eval.width) >= cfg.model.tile, "eval.height/width must be >= model.tile"),
        (cfg.optim.steps >= 1, "optim.steps must be >= 1"),
        (cfg.optim.lr > 0, "optim.lr must be > 0"),
        (0 <= cfg.optim.min_lr_ratio <= 1, "optim.min_lr_ratio must be in [0, 1]"),
        (cfg.optim.warmup_steps >= 0, "optim.warmup_steps must be >= 0"),
        (cfg.optim.grad_clip >= 0, "optim.grad_clip must be >= 0"),
        (cfg.optim.l1_weight >= 0, "optim.l1_weight must be >= 0"),
        (cfg.optim.normaliser_batches >= 1, "optim.normaliser_batches must be >= 1"),
        (cfg.log_every >= 1 and cfg.val_every >= 1 and cfg.ckpt_every >= 1, "log_every, val_every, ckpt_every must be >= 1"),
        (cfg.max_minutes >= 0, "max_minutes must be >= 0"),
        (cfg.threads >= 0, "threads must be >= 0"),
        (cfg.device == "auto" or cfg.device == "cpu" or cfg.device.startswith("cuda"), "device must be auto, cpu or cuda[:N]"),
        (cfg.eval.bins >= 1 and cfg.eval.samples >= 1 and cfg.eval.textureless_samples >= 0,
         "eval.bins and eval.samples must be >= 1, eval.textureless_samples >= 0"),
        (cfg.model.confidence_scale > 0 and cfg.model.correction_scale > 0, "model scales must be > 0"),
        (0.0 <= cfg.model.psf_family_told_share <= 1.0, "model.psf_family_told_share must be in [0, 1]"),
        (cfg.model.psf_family_input or not cfg.model.family_inference,
         "model.family_inference needs model.psf_family_input = true"),
        (cfg.optim.family_weight >= 0, "optim.family_weight must be >= 0"),
        (math.isfinite(cfg.optim.pooled_weight) and cfg.optim.pooled_weight >= 0, "optim.pooled_weight must be >= 0"),
        (cfg.optim.pooled_weight == 0 or bool(cfg.model.structure_pooling),
         "optim.pooled_weight > 0 needs model.structure_pooling (the pooled map it trains)"),
        (cfg.calibration.planes >= 1 and cfg.calibration.scenes >= 1, "calibration.planes and scenes must be >= 1"),
        (cfg.calibration.pooled_planes >= 0 and cfg.calibration.pooled_scenes >= 0,
         "calibration.pooled_planes and pooled_scenes must be >= 0 (0: planes, scenes)"),
        (cfg.calibration.bins >= 2, "calibration.bins must be >= 2"),
        (cfg.calibration.smooth >= 1 and cfg.calibration.smooth % 2 == 1, "calibration.smooth must be an odd width >= 1"),
        (math.isfinite(cfg.calibration.min_factor) and cfg.calibration.min_factor >= 0,
         "calibration.min_factor must be >= 0 (0: no bound)"),
        (cfg.calibration.depth_bins == 0 or cfg.calibration.depth_bins >= 2,
         "calibration.depth_bins must be 0 (no depth part) or >= 2"),
        (cfg.calibration.border_levels == 0 or cfg.calibration.border_levels >= 2,
         "calibration.border_levels must be 0 (no edge part) or >= 2"),
    ]
    for ok, msg in checks:
        if not ok:
            raise ConfigError(msg)
    from tdfd.model import context_sizes  # the model's own rule for its sides

    try:
        resolve_camera(cfg.model.camera)
    except CameraError as exc:
        raise ConfigError(f"model.camera: {exc}") from exc

    try:
        context_sizes(cfg.model.context)
    except InputError as exc:
        raise ConfigError(f"model.context: {exc}") from exc
