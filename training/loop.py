"""The training loop: seeds, CPU/CUDA, DDP via ``torchrun``, exact resume, CSV logs, tqdm.

Run ``python -m training --config FILE --set key=value ...`` (see :mod:`training.__main__`).
Under ``torchrun`` (``WORLD_SIZE`` > 1 in the environment) the process group is
initialised (NCCL on CUDA, gloo on CPU), the CNN is wrapped in DistributedDataParallel,
each rank reads its own block of sample indices, and only rank 0 validates and writes.
"""

from __future__ import annotations

import csv
import json
import logging
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import nn

from tdfd.atomic_io import atomic_writer, remove_orphans
from tdfd.model import DFDModel

from .calibrate_scale import calibrate_model
from .config import ConfigError, OptimConfig, TrainConfig, config_to_dict
from .data import Featurizer, FeatureSet, StepBatches, build_model, featurize_dataset, fetch_batch, make_dataset
from .losses import depth_relative_error, family_loss, laplace_nll, pooled_loss, refinement_loss

__all__ = ["train", "training_loss", "DistInfo", "setup_distributed", "validate", "save_checkpoint", "load_checkpoint",
           "CHECKPOINT_NAME", "LOG_COLUMNS"]

logger = logging.getLogger("training")

CHECKPOINT_NAME = "checkpoint_last.pt"
LOG_COLUMNS = ["step", "time_s", "lr", "loss", "nll", "l1", "train_mre", "samples_per_s", "val_nll",
               "val_mre_refined", "val_mre_analytic", "val_mre_conf_top", "val_mre_conf_bottom", "val_conf_mean",
               "family_ce", "val_family_acc", "pooled", "val_mre_pooled"]


@dataclass
class DistInfo:
    """Process placement: ``rank``, ``world_size``, ``local_rank``, ``device``."""

    rank: int
    world_size: int
    local_rank: int
    device: torch.device

    @property
    def is_main(self) -> bool:
        return self.rank == 0


def setup_distributed(device: str = "auto") -> DistInfo:
    """Initialise ``torch.distributed`` when launched by ``torchrun`` and pick the device."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    rank = int(os.environ.get("RANK", "0"))
    local = int(os.environ.get("LOCAL_RANK", "0"))
    use_cuda = torch.cuda.is_available() if device == "auto" else device.startswith("cuda")
    if use_cuda:
        dev = torch.device(f"cuda:{local}" if device in ("auto", "cuda") else device)
        torch.cuda.set_device(dev)
    else:
        dev = torch.device("cpu")
    if world > 1 and not torch.distributed.is_initialized():
        torch.distributed.init_process_group(backend="nccl" if use_cuda else "gloo")
    return DistInfo(rank, world, local, dev)


class _Head(nn.Module):
    """The trainable stage as a module (what DistributedDataParallel wraps)."""

    def __init__(self, model: DFDModel) -> None:
        super().__init__()
        self.model = model

    def forward(self, features, inverse_depth, rel_error):
        """``head``'s four outputs, then the image family logits (``None`` without the inference)."""
        return self.model.head_with_family(features, inverse_depth, rel_error)


def _lr_lambda(cfg: TrainConfig):
    o = cfg.optim

    def f(step: int) -> float:
        if step < o.warmup_steps:
            return (step + 1) / (o.warmup_steps + 1)
        t = (step - o.warmup_steps) / max(1, o.steps - o.warmup_steps)
        return o.min_lr_ratio + (1.0 - o.min_lr_ratio) * 0.5 * (1.0 + math.cos(math.pi * min(1.0, t)))

    return f


# ----------------------------------------------------------------------------- checkpoints
def save_checkpoint(path: Path, model: DFDModel, opt: torch.optim.Optimizer, sched: Any, step: int,
                    cfg: TrainConfig, extra: dict[str, Any] | None = None) -> None:
    """Write model, optimiser, scheduler, RNG states and step atomically (``torch.save`` into
    :func:`tdfd.atomic_io.atomic_writer`: temporary file, fsync, ``os.replace``; read back with
    ``weights_only=True``)."""
    state = {
        "step": int(step),
        "model": model.state_dict(),
        "optimizer": opt.state_dict(),
        "scheduler": sched.state_dict(),
        "rng_torch": torch.get_rng_state(),
        "rng_cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else [],
        "config_json": json.dumps(config_to_dict(cfg), sort_keys=True),
        "extra_json": json.dumps(extra or {}, sort_keys=True),
    }
    remove_orphans(path.parent)  # temporary files of an interrupted save
    with atomic_writer(path) as f:
        torch.save(state, f)


def load_checkpoint(path: Path, model: DFDModel, opt: torch.optim.Optimizer, sched: Any) -> dict[str, Any]:
    """Restore a checkpoint written by :func:`save_checkpoint`; returns its metadata."""
    state = torch.load(path, map_location="cpu", weights_only=True)
    model.load_state_dict(state["model"])
    opt.load_state_dict(state["optimizer"])
    sched.load_state_dict(state["scheduler"])
    torch.set_rng_state(state["rng_torch"])
    if torch.cuda.is_available() and state["rng_cuda"]:
        torch.cuda.set_rng_state_all(state["rng_cuda"])
    return {"step": int(state["step"]), "config": json.loads(state["config_json"]), "extra": json.loads(state["extra_json"])}


# ----------------------------------------------------------------------------- the loss
def training_loss(model: DFDModel, optim: OptimConfig, q: torch.Tensor, log_b: torch.Tensor,
                  family_logits: torch.Tensor | None, batch: dict[str, torch.Tensor]
                  ) -> tuple[torch.Tensor, dict[str, float]]:
    """One step's loss on :meth:`DFDModel.head_with_family`'s outputs: the tiles' loss
    (:func:`refinement_loss`), the structure-pooled map's (:func:`pooled_loss`, with
    ``optim.pooled_weight``; through the scales alone with ``optim.pooled_scales_only``) and the
    image family's (:func:`family_loss`, with ``optim.family_weight``).

    Returns:
        ``(loss, parts)``: ``parts`` the detached ``nll`` and ``l1``, and ``pooled`` and
        ``family`` where those terms are on.
    """
    loss, parts = refinement_loss(q, log_b, batch["tile_depth"], optim.l1_weight)
    if optim.pooled_weight > 0:  # the map pooled along the depth structure, scored too
        q_in = q.detach() if optim.pooled_scales_only else q
        pooled = pooled_loss(model.pooled_inverse_depth(q_in, log_b), log_b, batch["tile_depth"])
        loss = loss + optim.pooled_weight * pooled
        parts["pooled"] = float(pooled.detach())
    if family_logits is not None and optim.family_weight > 0:
        fam = family_loss(family_logits, batch["family_class"])
        loss = loss + optim.family_weight * fam
        parts["family"] = float(fam.detach())
    return loss, parts


# ----------------------------------------------------------------------------- validation
@torch.no_grad()
def validate(model: DFDModel, data: FeatureSet, device: torch.device, chunk: int = 64) -> dict[str, float]:
    """Held-out metrics: Laplace NLL, median absolute relative depth error (refined and
    analytic), median error in the top and bottom confidence halves, mean confidence; the
    image family verdict's accuracy (with the family inference) and the pooled map's median
    error (with the structure pooling)."""
    was_training = model.training
    model.eval()
    errs_r, errs_a, errs_p, confs, nlls = [], [], [], [], []
    hits, labelled = 0, 0
    for b in data.chunks(chunk):
        b = {k: v.to(device) for k, v in b.items()}
        q, log_b, conf, q_a, family_logits = model.head_with_family(b["features"], b["inverse_depth"], b["rel_error"])
        if "family_class" in b:  # the image-wide family verdict against the truth
            known = b["family_class"] >= 0
            hits += int((family_logits.argmax(1) == b["family_class"])[known].sum())
            labelled += int(known.sum())
        nlls.append(laplace_nll(q, log_b, 1.0 / b["tile_depth"]) * q.numel())
        errs_r.append(depth_relative_error(1.0 / q, b["tile_depth"]).flatten().cpu())
        errs_a.append(depth_relative_error(1.0 / q_a, b["tile_depth"]).flatten().cpu())
        if model.structure_pooling is not None:
            q_p = model.pooled_inverse_depth(q, log_b)
            errs_p.append(depth_relative_error(1.0 / q_p, b["tile_depth"]).flatten().cpu())
        confs.append(conf.flatten().cpu())
    model.train(was_training)
    er, ea, c = torch.cat(errs_r), torch.cat(errs_a), torch.cat(confs)
    order = torch.argsort(c)
    half = len(order) // 2
    return {"val_nll": float(sum(nlls) / er.numel()), "val_mre_refined": float(er.median()),
            "val_mre_analytic": float(ea.median()), "val_mre_conf_top": float(er[order[half:]].median()),
            "val_mre_conf_bottom": float(er[order[:half]].median()) if half else float("nan"),
            "val_conf_mean": float(c.mean()), **({"val_family_acc": hits / labelled} if labelled else {}),
            **({"val_mre_pooled": float(torch.cat(errs_p).median())} if errs_p else {})}


# ----------------------------------------------------------------------------- helpers
class _CsvLog:
    """Append-only CSV log; on resume rows at or after the resume step are dropped."""

    def __init__(self, path: Path, resume_step: int | None) -> None:
        self.path = path
        rows: list[dict[str, str]] = []
        if resume_step is not None and path.exists():
            with path.open() as fh:
                rows = [r for r in csv.DictReader(fh) if int(r["step"]) <= resume_step]
        with path.open("w", newline="") as fh:
            w = csv.DictWriter(fh, LOG_COLUMNS)
            w.writeheader()
            w.writerows(rows)

    def write(self, row: dict[str, Any]) -> None:
        with self.path.open("a", newline="") as fh:
            csv.DictWriter(fh, LOG_COLUMNS).writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in row.items()})


def _setup_logging(out: Path, is_main: bool) -> logging.Handler | None:
    if not is_main:
        return None
    handler = logging.FileHandler(out / "train.log")
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    logger.addHandler(handler)
    logger.setLevel(logging.INFO)
    return handler


def _new_window() -> dict[str, float]:
    """Running sums of one logging window (losses, error, sample counts) and its start time."""
    return {"loss": 0.0, "nll": 0.0, "l1": 0.0, "mre": 0.0, "family": 0.0, "pooled": 0.0, "n": 0,
            "t": time.perf_counter(), "samples": 0, "fresh": 0}


@torch.no_grad()
def fit_normaliser(model: DFDModel, feats: torch.Tensor) -> None:
    """Per-channel mean/std of the features ``(N, C, h, w)`` into the CNN's standardisation."""
    x = feats.transpose(0, 1).reshape(feats.shape[1], -1).double()
    model.refine.set_normaliser(x.mean(1).float(), x.std(1).float())


# ----------------------------------------------------------------------------- train
def train(cfg: TrainConfig, resume: bool = False, stop_at_step: int | None = None) -> dict[str, Any]:
    """Train the refinement and write the run directory.

    Writes ``config.json``, ``train_log.csv``, ``train.log``, ``checkpoint_last.pt``,
    ``model.safetensors`` + ``model.json`` and (``final_eval``) ``report.{json,md,png}``
    into ``cfg.out_dir``.

    Args:
        cfg: the configuration.
        resume: continue from ``out_dir/checkpoint_last.pt`` if it exists (exactly: the
            result equals an uninterrupted run).
        stop_at_step: stop (with a checkpoint, without the final model) once this many
            steps are done; simulates an interruption, or splits a run into chunks.

    Returns:
        A summary dict (steps done, final validation metrics, wall time, paths).
    """
    t_start = time.perf_counter()
    dist = setup_distributed(cfg.device)
    if cfg.threads:
        # on a GPU too: the process gathers replay minibatches on the CPU beside the data
        # workers, and torch's default of one thread per core there slowed a CUDA run 5x
        torch.set_num_threads(cfg.threads)
    out = Path(cfg.out_dir)
    if dist.is_main:
        out.mkdir(parents=True, exist_ok=True)
    if dist.world_size > 1:
        torch.distributed.barrier()
    handler = _setup_logging(out, dist.is_main)
    try:
        return _train(cfg, resume, dist, out, t_start, stop_at_step)
    finally:
        if handler is not None:
            logger.removeHandler(handler)
            handler.close()
        if dist.world_size > 1 and torch.distributed.is_initialized():
            torch.distributed.barrier()
            torch.distributed.destroy_process_group()


def _train(cfg: TrainConfig, resume: bool, dist: DistInfo, out: Path, t_start: float,
           stop_at_step: int | None) -> dict[str, Any]:
    torch.manual_seed(cfg.seed)
    model = build_model(cfg.model)
    opt = torch.optim.AdamW(model.refine.parameters(), lr=cfg.optim.lr, weight_decay=cfg.optim.weight_decay)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, _lr_lambda(cfg))
    ckpt = out / CHECKPOINT_NAME
    start = 0
    featurizer_factory = lambda: Featurizer(cfg.model)  # noqa: E731
    train_factory = lambda: make_dataset(cfg.data, cfg.model, cfg.data.seed)  # noqa: E731
    if resume and ckpt.exists():
        meta = load_checkpoint(ckpt, model, opt, sched)
        start = meta["step"]
        logger.info("resumed from %s at step %d", ckpt, start)
    else:
        # feature standardisation from the first batches of the training stream (same on every rank)
        ds, fz = train_factory(), featurizer_factory()
        n = cfg.optim.normaliser_batches * cfg.data.batch_size
        fs = featurize_dataset(ds, fz, n, chunk=cfg.data.batch_size)
        fit_normaliser(model, fs.features)
    if dist.is_main:
        (out / "config.json").write_text(json.dumps(config_to_dict(cfg), indent=2, sort_keys=True) + "\n")
        n_params = sum(p.numel() for p in model.refine.parameters())
        logger.info("config %s", json.dumps(config_to_dict(cfg), sort_keys=True))
        logger.info("device %s, world size %d, %d trainable parameters, steps %d..%d",
                    dist.device, dist.world_size, n_params, start, cfg.optim.steps)
    model.to(dist.device)
    # optimiser state follows the parameters onto the device
    for st in opt.state.values():
        for k, v in st.items():
            if isinstance(v, torch.Tensor) and k != "step":
                st[k] = v.to(dist.device)
    head: nn.Module = _Head(model)
    if dist.world_size > 1:
        head = nn.parallel.DistributedDataParallel(head, device_ids=[dist.device.index] if dist.device.type == "cuda" else None)
    val: FeatureSet | None = None
    if dist.is_main:
        t0 = time.perf_counter()
        val_ds = make_dataset(cfg.data, cfg.model, cfg.data.val_seed)
        val = featurize_dataset(val_ds, featurizer_factory(), cfg.data.val_size, chunk=cfg.data.batch_size)
        logger.info("validation set: %d pairs (seed %d), %.1f s", len(val), cfg.data.val_seed, time.perf_counter() - t0)
    log = _CsvLog(out / "train_log.csv", start if resume else None) if dist.is_main else None

    steps, reuse, pool_size = cfg.optim.steps, cfg.data.reuse, cfg.data.pool_batches
    last_ckpt = start
    if start % reuse and start < steps:
        raise ConfigError(f"checkpoint step {start} is not a multiple of data.reuse={reuse}")
    n_batches = -(-steps // reuse)  # generated batches; batch k feeds steps k*reuse .. k*reuse + reuse - 1
    first_batch = start // reuse
    warm = max(0, first_batch - pool_size + 1)  # on resume, rebuild the replay pool first
    batches = StepBatches(train_factory, featurizer_factory, cfg.data.batch_size, dist.rank, dist.world_size, n_batches)
    loader_kw: dict[str, Any] = {"batch_size": None, "sampler": range(warm, n_batches), "num_workers": cfg.data.num_workers}
    if cfg.data.num_workers > 0:
        loader_kw.update(prefetch_factor=cfg.data.prefetch_factor, persistent_workers=False)
    loader = torch.utils.data.DataLoader(batches, **loader_kw)
    from tqdm import tqdm

    bar = tqdm(total=steps, initial=start, disable=not dist.is_main, desc="train", mininterval=5.0, dynamic_ncols=True)
    step, stopped_early, last_val = start, False, {}
    window = _new_window()
    pool: list[dict[str, torch.Tensor]] = []
    model.train()
    for bid, fresh in zip(range(warm, n_batches), loader):
        pool.append(fresh)
        del pool[:-pool_size]
        if bid < first_batch:
            continue
        window["fresh"] += cfg.data.batch_size * dist.world_size
        stacked = {k: torch.cat([p[k] for p in pool]) for k in fresh} if len(pool) > 1 else fresh
        for _ in range(min(reuse, steps - step)):
            if len(pool) == 1 and reuse == 1:
                mb = stacked
            else:  # a minibatch from the replay pool, drawn by (seed, step, rank)
                g = torch.Generator().manual_seed((cfg.seed * 1_000_003 + step) * 65_537 + dist.rank)
                idx = torch.randint(len(stacked["features"]), (cfg.data.batch_size,), generator=g)
                mb = {k: v[idx] for k, v in stacked.items()}
            b = {k: v.to(dist.device, non_blocking=True) for k, v in mb.items()}
            q, log_b, _conf, _qa, fam_logits = head(b["features"], b["inverse_depth"], b["rel_error"])
            loss, parts = training_loss(model, cfg.optim, q, log_b, fam_logits, b)
            window["pooled"] += parts.get("pooled", 0.0)
            window["family"] += parts.get("family", 0.0)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            if cfg.optim.grad_clip > 0:
                torch.nn.utils.clip_grad_norm_(model.refine.parameters(), cfg.optim.grad_clip)
            opt.step()
            sched.step()
            step += 1
            with torch.no_grad():
                mre = float(depth_relative_error(1.0 / q.detach(), b["tile_depth"]).median())
            window["loss"] += float(loss.detach())
            window["nll"] += parts["nll"]
            window["l1"] += parts["l1"]
            window["mre"] += mre
            window["n"] += 1
            window["samples"] += cfg.data.batch_size * dist.world_size
            bar.update(1)
            boundary = step % reuse == 0 or step == steps  # checkpoints and stops only between generated batches
            over_time = boundary and cfg.max_minutes > 0 and (time.perf_counter() - t_start) / 60.0 >= cfg.max_minutes
            if boundary and dist.world_size > 1 and cfg.max_minutes > 0:  # all ranks stop together
                flag = torch.tensor([float(over_time)], device=dist.device)
                torch.distributed.all_reduce(flag, op=torch.distributed.ReduceOp.MAX)
                over_time = bool(flag.item() > 0)
            interrupted = boundary and stop_at_step is not None and stop_at_step <= step < steps
            last = step == steps or over_time or interrupted
            if dist.is_main:
                row: dict[str, Any] = {}
                if step % cfg.log_every == 0 or last:
                    n = max(1, window["n"])
                    dt = max(time.perf_counter() - window["t"], 1e-9)
                    row.update(step=step, time_s=time.perf_counter() - t_start, lr=sched.get_last_lr()[0],
                               loss=window["loss"] / n, nll=window["nll"] / n, l1=window["l1"] / n,
                               train_mre=window["mre"] / n, samples_per_s=window["fresh"] / dt)
                    bar.set_postfix(loss=f"{row['loss']:.3f}", mre=f"{row['train_mre']:.4f}")
                    if model.refine.family is not None:
                        row["family_ce"] = window["family"] / n
                    if cfg.optim.pooled_weight > 0:
                        row["pooled"] = window["pooled"] / n
                    window = _new_window()
                if step % cfg.val_every == 0 or last:
                    last_val = validate(model, val, dist.device)
                    row.update(step=step, time_s=time.perf_counter() - t_start, **last_val)
                    logger.info("step %d: %s", step, ", ".join(f"{k} {v:.4g}" for k, v in last_val.items()))
                if row:
                    log.write(row)
                if (boundary and step // cfg.ckpt_every > last_ckpt // cfg.ckpt_every) or last:
                    save_checkpoint(out / CHECKPOINT_NAME, model, opt, sched, step, cfg)
                    last_ckpt = step
            if over_time and step < steps:
                stopped_early = True
                logger.warning("time budget of %.1f min reached at step %d of %d; stopping", cfg.max_minutes, step, steps)
            if interrupted or stopped_early:
                break
        if interrupted or stopped_early or step >= steps:
            break
    bar.close()
    wall = time.perf_counter() - t_start
    summary: dict[str, Any] = {"steps": step, "steps_planned": steps, "stopped_early": stopped_early,
                               "wall_time_s": round(wall, 1), "world_size": dist.world_size, **last_val}
    if step < steps and not stopped_early:  # interrupted on purpose: checkpoint only
        logger.info("stopped at step %d of %d (checkpoint %s)", step, steps, out / CHECKPOINT_NAME)
        return summary
    if dist.is_main:
        model.cpu().eval()
        extra = {"training": summary, "config": config_to_dict(cfg)}
        model.save(out / "model", extra=extra)
        summary["model"] = str(out / "model.safetensors")
        logger.info("trained %d steps in %.1f s; model written to %s", step, wall, out / "model.safetensors")
        # saved before the calibration too: a failing last stage must not lose the trained CNN
        if cfg.calibration.enabled:  # the last stage: the predicted error scale (before the report, which scores it)
            c = cfg.calibration
            extra["scale_calibration_fit"] = calibrate_model(model, c.planes, c.scenes, c.bins, c.smooth,
                                                             c.min_factor or None, c.depth_bins, c.border_levels,
                                                             pooled_planes=c.pooled_planes or None,
                                                             pooled_scenes=c.pooled_scenes or None)
            model.save(out / "model", extra=extra)
        if cfg.final_eval:
            from .evaluate import evaluate_planes, write_report

            t0 = time.perf_counter()
            result = evaluate_planes(model, cfg)
            write_report(result, out / "report", title=f"Refinement evaluation ({out.name})")
            summary["eval"] = result["summary"]
            logger.info("evaluation (%.1f s): %s", time.perf_counter() - t0, json.dumps(result["summary"]))
        (out / "summary.json").write_text(json.dumps(summary, indent=2, sort_keys=True) + "\n")
    return summary
