"""tdfd.atomic_io: a killed writer leaves the old file whole and an orphan the next run removes."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tdfd.atomic_io import TEMP_SUFFIX, atomic_write_bytes, atomic_writer, remove_orphans

ROOT = Path(__file__).resolve().parents[1]


def test_replace_and_failure_inside_the_block(tmp_path):
    target = tmp_path / "sub" / "w.bin"
    atomic_write_bytes(target, b"old")
    with pytest.raises(RuntimeError):
        with atomic_writer(target) as f:
            f.write(b"new but broken")
            raise RuntimeError("writer failed")
    assert target.read_bytes() == b"old"
    assert sorted(p.name for p in target.parent.iterdir()) == ["w.bin"]
    with atomic_writer(target) as f:
        f.write(b"new")
    assert target.read_bytes() == b"new"


def test_killed_writer_keeps_the_old_file_and_its_orphan_is_removed(tmp_path):
    target = tmp_path / "weights.bin"
    target.write_bytes(b"old weights")
    code = ("import sys, time\nfrom tdfd.atomic_io import atomic_writer\n"
            f"with atomic_writer({str(target)!r}) as f:\n"
            "    f.write(b'x' * 100000); f.flush(); print('writing', flush=True); time.sleep(60)\n")
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, env=env)
    try:
        assert proc.stdout.readline().strip() == b"writing"
        orphans = list(tmp_path.glob(f".*{TEMP_SUFFIX}"))
        assert [p.name for p in orphans] == [f".weights.bin.{proc.pid}{TEMP_SUFFIX}"]
        assert remove_orphans(tmp_path) == []  # its writer still runs
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
        proc.stdout.close()
    assert target.read_bytes() == b"old weights"
    deadline = time.monotonic() + 10
    while True:  # the pid is reaped by wait(); allow the OS a moment
        removed = remove_orphans(tmp_path)
        if removed or time.monotonic() > deadline:
            break
        time.sleep(0.05)
    assert [p.name for p in removed] == [orphans[0].name]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["weights.bin"]
    assert remove_orphans(tmp_path / "missing") == []


def test_model_save_is_atomic_and_cleans_up(tmp_path):
    """DFDModel.save writes through atomic_writer and removes a killed save's leftovers."""
    import torch

    from tdfd import Camera
    from tdfd.model import DFDModel

    torch.manual_seed(0)
    model = DFDModel(Camera.preset("reference"), tile=32, stride=16, hidden=4, blocks=1)
    orphan = tmp_path / f".m.safetensors.999999999{TEMP_SUFFIX}"
    orphan.write_bytes(b"torn weights")
    weights, meta = model.save(tmp_path / "m")
    assert not orphan.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.json", "m.safetensors"]
    back = DFDModel.load(tmp_path / "m")
    for k, v in model.state_dict().items():
        assert torch.equal(back.state_dict()[k], v), k


def test_checkpoint_is_atomic_and_cleans_up(tmp_path):
    import torch

    from training.config import load_config
    from training.data import build_model
    from training.loop import load_checkpoint, save_checkpoint

    cfg = load_config(None, ["model.tile=32", "model.stride=16", "model.hidden=4", "model.blocks=1"])
    model = build_model(cfg.model)
    opt = torch.optim.AdamW(model.refine.parameters())
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: 1.0)
    orphan = tmp_path / f".checkpoint.pt.999999999{TEMP_SUFFIX}"
    orphan.write_bytes(b"torn")
    save_checkpoint(tmp_path / "checkpoint.pt", model, opt, sched, 7, cfg)
    assert not orphan.exists() and sorted(p.name for p in tmp_path.iterdir()) == ["checkpoint.pt"]
    assert load_checkpoint(tmp_path / "checkpoint.pt", model, opt, sched)["step"] == 7
