"""Training loop: a tiny end-to-end run, exact resume, DDP on CPU (gloo)."""

from __future__ import annotations

import csv
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file

from tests.tiny_training import TINY
from training.config import ConfigError, load_config
from training.loop import CHECKPOINT_NAME, train

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent


@pytest.fixture(autouse=True)
def _standin_on_path(monkeypatch):
    monkeypatch.syspath_prepend(str(HERE))


def _cfg(tmp_path, name, *extra):
    return load_config(None, TINY + [f"out_dir={tmp_path / name}", *extra])


def test_end_to_end_writes_logs_checkpoint_model_report(tmp_path):
    cfg = _cfg(tmp_path, "run", "data.num_workers=1")
    summary = train(cfg)
    out = Path(cfg.out_dir)
    for name in ("config.json", "train_log.csv", "train.log", CHECKPOINT_NAME, "model.safetensors", "model.json",
                 "report.json", "report.md", "report.png", "summary.json"):
        assert (out / name).is_file(), name
    rows = list(csv.DictReader((out / "train_log.csv").open()))
    assert [int(r["step"]) for r in rows] == [2, 3, 4, 6]
    assert rows[-1]["val_mre_refined"] and rows[0]["loss"]
    assert summary["steps"] == 6 and "mre_refined" in summary["eval"]
    report = json.loads((out / "report.json").read_text())
    assert len(report["per_distance"]) == 2 and report["textureless"]["tiles"] == 2 * 9
    from tdfd.model import DFDModel

    model = DFDModel.load(out / "model")
    assert model.tile == 32 and model.refine.hidden == 8
    ckpt = torch.load(out / CHECKPOINT_NAME, weights_only=True)
    assert ckpt["step"] == 6


@pytest.mark.parametrize("reuse,pool", [(1, 1), (2, 3)])
def test_resume_is_exact(tmp_path, reuse, pool):
    extra = ("final_eval=false", f"data.reuse={reuse}", f"data.pool_batches={pool}")
    straight = _cfg(tmp_path, "straight", *extra)
    train(straight)
    split = _cfg(tmp_path, "split", *extra)
    first = train(split, stop_at_step=3)
    assert first["steps"] == (3 if reuse == 1 else 4)  # stops between generated batches
    assert not (Path(split.out_dir) / "model.safetensors").exists()
    train(split, resume=True)
    a = load_file(str(Path(straight.out_dir) / "model.safetensors"))
    b = load_file(str(Path(split.out_dir) / "model.safetensors"))
    assert a.keys() == b.keys()
    for k in a:
        assert torch.equal(a[k], b[k]), k
    assert float(a["refine.head.weight"].abs().sum()) > 0  # it did train
    rows = [int(r["step"]) for r in csv.DictReader((Path(split.out_dir) / "train_log.csv").open())]
    straight_rows = [int(r["step"]) for r in csv.DictReader((Path(straight.out_dir) / "train_log.csv").open())]
    assert rows == straight_rows  # the interrupted run's log continues without duplicates


@pytest.mark.slow
def test_ddp_two_processes_cpu(tmp_path):
    """Two gloo processes through torchrun: both ranks step in sync, rank 0 writes."""
    out = tmp_path / "ddp"
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), str(HERE)]), OMP_NUM_THREADS="1")
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2", "-m", "training",
           *[a for s in TINY + [f"out_dir={out}", "optim.steps=2", "final_eval=false", "val_every=2"] for a in ("--set", s)]]
    proc = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=240)
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["world_size"] == 2 and summary["steps"] == 2
    assert (out / "model.safetensors").is_file()


def test_training_lowers_the_validation_loss(tmp_path):
    """40 steps on the stand-in data lower the held-out Laplace NLL (measured on the
    forward-model stand-in: -1.955 -> best -2.104 after 11 steps, -1.983 at the end); gradient
    ascent (``(-loss).backward()``) raises it above +30 within 10 steps."""
    cfg = _cfg(tmp_path, "learn", "optim.steps=40", "optim.lr=0.003", "val_every=1", "log_every=1",
               "data.val_size=16", "final_eval=false")
    train(cfg)
    rows = list(csv.DictReader((Path(cfg.out_dir) / "train_log.csv").open()))
    nll = [float(r["val_nll"]) for r in rows]
    mre = [float(r["val_mre_refined"]) for r in rows]
    assert len(nll) == 40
    assert min(nll) < nll[0] - 0.1 and nll[-1] < nll[0], (nll[0], min(nll), nll[-1])
    assert max(nll) < nll[0] + 0.5 and max(mre) < 2 * mre[0], (max(nll), max(mre))


def test_calibration_stage_runs_after_training_when_enabled(tmp_path):
    """``calibration.enabled``: the run's model is saved with a fitted scale calibration and its
    fit record; without it (the default) the saved model has none."""
    from tdfd.model import DFDModel

    cfg = _cfg(tmp_path, "cal", "calibration.enabled=true", "calibration.planes=4", "calibration.scenes=1",
               "calibration.bins=2", "calibration.smooth=1", "final_eval=false")
    train(cfg)
    meta = json.loads((Path(cfg.out_dir) / "model.json").read_text())
    assert len(meta["scale_calibration"]["log_b"]) == 2
    assert meta["extra"]["scale_calibration_fit"]["planes"] == 4 and meta["extra"]["training"]["steps"] == 6
    assert DFDModel.load(Path(cfg.out_dir) / "model").scale_calibration.to_config() == meta["scale_calibration"]
    plain = _cfg(tmp_path, "plain", "final_eval=false")
    train(plain)
    assert json.loads((Path(plain.out_dir) / "model.json").read_text())["scale_calibration"] is None


@pytest.mark.parametrize("setting, match", [("calibration.bins=1", "bins"), ("calibration.smooth=2", "odd"),
                                            ("calibration.min_factor=-1", "min_factor"),
                                            ("calibration.planes=0", "planes")])
def test_calibration_config_is_checked(tmp_path, setting, match):
    with pytest.raises(ConfigError, match=match):
        _cfg(tmp_path, "bad", setting)


@pytest.mark.parametrize("device", ["cpu", "cuda:0"])
def test_threads_setting_applies_on_every_device(tmp_path, monkeypatch, device):
    """``threads`` limits the training process on a GPU too: there it gathers the replay
    minibatches beside busy data workers, and torch's default (a thread per core) made a CUDA
    run 5x slower on a 16-core machine (models/README.md, the GPU runs of 2026-11-27)."""
    import training.loop as loop

    calls: list[int] = []
    monkeypatch.setattr(loop, "setup_distributed", lambda _dev: loop.DistInfo(0, 1, 0, torch.device(device)))
    monkeypatch.setattr(loop.torch, "set_num_threads", calls.append)
    monkeypatch.setattr(loop, "_train", lambda *args: {"stub": True})
    assert train(_cfg(tmp_path, "threads", "threads=3")) == {"stub": True}
    assert calls == [3]
    calls.clear()
    train(_cfg(tmp_path, "default_threads", "threads=0"))
    assert calls == []


def test_pooled_loss_trains_the_tiles_through_the_structure_pooling(tmp_path):
    """``optim.pooled_weight``: the pooled map's error joins the loss and the log; with weight 0
    the stage is invisible to training (bitwise the same weights as a model without it)."""
    pooling = 'model.structure_pooling={"radius": 1, "curvature_test": 1.0}'
    extra = ("final_eval=false", "data.reuse=1")
    plain = _cfg(tmp_path, "plain", *extra)
    unseen = _cfg(tmp_path, "unseen", pooling, *extra)
    seen = _cfg(tmp_path, "seen", pooling, "optim.pooled_weight=1.0", *extra)
    for cfg in (plain, unseen, seen):
        train(cfg)
    a, b, c = (load_file(str(Path(cfg.out_dir) / "model.safetensors")) for cfg in (plain, unseen, seen))
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert not all(torch.equal(a[k], c[k]) for k in a)
    rows = list(csv.DictReader((Path(seen.out_dir) / "train_log.csv").open()))
    assert all(float(r["pooled"]) > 0 for r in rows if r["loss"])
    assert float(rows[-1]["val_mre_pooled"]) > 0
    unseen_rows = list(csv.DictReader((Path(unseen.out_dir) / "train_log.csv").open()))
    assert not any(r["pooled"] for r in unseen_rows) and unseen_rows[-1]["val_mre_pooled"]
    plain_rows = list(csv.DictReader((Path(plain.out_dir) / "train_log.csv").open()))
    assert not plain_rows[-1]["val_mre_pooled"]


def test_pooled_loss_on_the_scales_only_leaves_the_depths_to_the_tiles_loss():
    """``optim.pooled_scales_only``: the loss's gradient in the tiles' depths is the tiles' loss's
    alone, its gradient in their scales is not; without the option both carry the pooled term."""
    from tdfd import Camera
    from tdfd.model import DFDModel
    from training.config import OptimConfig
    from training.loop import training_loss

    model = DFDModel(Camera.preset("reference"), hidden=8, blocks=1, structure_pooling={"radius": 1})
    gen = torch.Generator().manual_seed(3)
    truth = 0.4 + 0.4 * torch.rand(2, 1, 5, 6, generator=gen)
    q0 = (1 / truth) * (1 + 0.03 * torch.randn(truth.shape, generator=gen))
    lb0 = math.log(0.02) + 0.5 * torch.randn(truth.shape, generator=gen)
    batch = {"tile_depth": truth}

    def grads(**kw):
        q, lb = q0.clone().requires_grad_(True), lb0.clone().requires_grad_(True)
        loss, parts = training_loss(model, OptimConfig(family_weight=0.0, **kw), q, lb, None, batch)
        loss.backward()
        return q.grad, lb.grad, parts

    q_alone, lb_alone, parts = grads()
    q_scales, lb_scales, parts_scales = grads(pooled_weight=1.0, pooled_scales_only=True)
    q_both, lb_both, _ = grads(pooled_weight=1.0)
    assert "pooled" not in parts and parts_scales["pooled"] > 0
    assert torch.equal(q_scales, q_alone) and not torch.allclose(lb_scales, lb_alone)
    assert not torch.allclose(q_both, q_alone) and torch.allclose(lb_both, lb_scales)


@pytest.mark.parametrize("settings, match", [
    (["optim.pooled_weight=-0.5", 'model.structure_pooling={"radius": 1}'], "pooled_weight must be >= 0"),
    (["optim.pooled_weight=nan", 'model.structure_pooling={"radius": 1}'], "pooled_weight must be >= 0"),
    (["optim.pooled_weight=0.5"], "needs model.structure_pooling"),
])
def test_pooled_weight_is_checked(tmp_path, settings, match):
    with pytest.raises(ConfigError, match=match):
        _cfg(tmp_path, "bad", *settings)
