"""``python -m data_synth``: shards, manifest, contact sheet, 16-bit PNG pairs, reproducibility."""

import json
import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

import tdfd
from data_synth import DefocusPairDataset
from data_synth.cli import main
from data_synth.writer import ShardDataset, ShardIntegrityError, load_shard, sha256_file
from tdfd import Camera
from tdfd.errors import InputError

ARGS = ["--count", "5", "--size", "64", "--tile", "32", "--stride", "16", "--shard-size", "2", "-q"]


pytestmark = pytest.mark.usefixtures("one_torch_thread")  # tests/conftest.py


def _run(out: Path, *extra: str) -> dict:
    assert main(["--out", str(out), *ARGS, *extra]) == 0
    return json.loads((out / "manifest.json").read_text())


def test_cli_writes_manifest_shards_contact_sheet_and_png16(tmp_path):
    out = tmp_path / "a"
    man = _run(out, "--seed", "3", "--png16", "--contact-sheet", "3")
    assert man["format"] == "tdfd-synth/1" and man["tdfd_version"] == tdfd.__version__
    assert man["seed"] == 3 and man["count"] == 5 and man["size"] == [64, 64]
    assert man["camera"]["name"] == "reference" and man["config"]["tile"] == 32
    assert [s["count"] for s in man["shards"]] == [2, 2, 1]
    for s in man["shards"]:
        assert sha256_file(out / s["file"]) == s["sha256"]
    sheet = cv2.imread(str(out / "contact_sheet.png"))
    assert sheet is not None and sheet.shape[0] > 100
    assert Camera.from_json((out / "camera.json").read_text()) == Camera.preset("reference")
    # shards hold exactly what the dataset makes (raw codes are lossless)
    ds = DefocusPairDataset(size=64, seed=3, tile=32, stride=16)
    back = ShardDataset(out)
    assert len(back) == 5
    for i in range(5):
        a, b = back[i], ds[i]
        for k in ("image_f1", "image_f2", "depth", "tile_depth"):
            assert torch.equal(a[k], b[k]), k
        assert a["params"] == b["params"]
    shard = load_shard(out / man["shards"][0]["file"])
    assert shard["index"].tolist() == [0, 1] and shard["image_f1"].dtype == torch.float32
    # 16-bit PNG pairs for `tdfd depth`
    for i in range(5):
        for f in ("f1", "f2"):
            png = cv2.imread(str(out / "png16" / f"pair_{i:05d}_{f}.png"), cv2.IMREAD_UNCHANGED)
            assert png.dtype == np.uint16 and png.shape == (64, 64)
            expect = np.round(ds[i][f"image_{f}"][0].double().numpy() * 65535).astype(np.uint16)
            assert np.array_equal(png, expect)
        depth = np.load(out / "png16" / f"pair_{i:05d}_depth.npy")
        assert depth.dtype == np.float32 and np.array_equal(depth, ds[i]["depth"][0].numpy())


def test_cli_same_seed_same_bytes_different_seed_different_data(tmp_path):
    a = _run(tmp_path / "a", "--seed", "7", "--contact-sheet", "0")
    b = _run(tmp_path / "b", "--seed", "7", "--contact-sheet", "0", "--workers", "2")
    c = _run(tmp_path / "c", "--seed", "8", "--contact-sheet", "0")
    assert [s["sha256"] for s in a["shards"]] == [s["sha256"] for s in b["shards"]]
    assert a == b
    assert all(x["sha256"] != y["sha256"] for x, y in zip(a["shards"], c["shards"]))
    for s in a["shards"]:
        assert (tmp_path / "a" / s["file"]).read_bytes() == (tmp_path / "b" / s["file"]).read_bytes()


def test_cli_options_and_errors(tmp_path, capsys):
    cam = tmp_path / "cam.json"
    cam.write_text(Camera.preset("reference").replace(aperture_m=1.5e-3).to_json())
    man = _run(tmp_path / "p", "--camera", str(cam), "--families", "stripes,dots", "--psf-shapes", "pillbox",
               "--no-noise", "--layouts", "plane,slanted", "--size", "48x64", "--contact-sheet", "0")
    assert man["size"] == [48, 64] and man["camera"]["aperture_m"] == pytest.approx(1.5e-3)
    assert man["config"]["families"] == ["stripes", "dots"] and man["config"]["psf_shapes"] == ["pillbox"]
    shard = load_shard(tmp_path / "p" / man["shards"][0]["file"])
    assert man["shards"][0]["image_encoding"] == "float32"
    assert {p["layout"] for p in shard["params"]} <= {"plane", "slanted"}
    assert main(["--out", str(tmp_path / "x"), "--count", "2", "--camera", "nonexistent", "-q"]) == 1
    assert "error" in capsys.readouterr().err
    assert main(["--out", str(tmp_path / "y"), "--count", "2", "--families", "photos", "-q"]) == 1
    weighted = _run(tmp_path / "w", "--families", "stripes:3,dots:0", "--size", "48x64", "--contact-sheet", "0")
    assert weighted["config"]["families"] == {"stripes": 3.0, "dots": 0.0}
    drawn = {f for p in load_shard(tmp_path / "w" / weighted["shards"][0]["file"])["params"]
             for f in p["texture_families"].split(",")}
    assert "stripes" in drawn and drawn <= {"stripes", "flat"}  # "flat": an actively lit scene's texture-less target
    for bad in ("stripes:3,dots", "stripes:x", "stripes:-1", "stripes:nan"):
        with pytest.raises(SystemExit):
            main(["--out", str(tmp_path / "z"), "--count", "2", "--families", bad, "-q"])


def test_python_dash_m_entry_point(tmp_path):
    r = subprocess.run([sys.executable, "-m", "data_synth", "--help"], capture_output=True, text=True,
                       cwd=Path(__file__).resolve().parents[1])
    assert r.returncode == 0 and "--png16" in r.stdout and "--shard-size" in r.stdout


# ----------------------------------------------------------------- crash safety on disk
def test_rerun_killed_midway_leaves_no_stale_manifest(tmp_path):
    """A second run into the same folder, SIGKILLed after it rewrote a shard: the old manifest
    must not describe the new shards (before the fix it did, and ShardDataset loaded them)."""
    import signal
    import time

    out = tmp_path / "d"
    old = _run(out, "--seed", "1", "--contact-sheet", "0")
    first = out / old["shards"][0]["file"]
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1]))
    proc = subprocess.Popen([sys.executable, "-m", "data_synth", "--out", str(out), *ARGS, "--seed", "2",
                             "--count", "400", "--contact-sheet", "0", "--threads", "1"], env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 120
        while sha256_file(first) == old["shards"][0]["sha256"]:
            assert proc.poll() is None, proc.stderr.read().decode()
            assert time.monotonic() < deadline, "the second run never rewrote the first shard"
            time.sleep(0.01)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
        proc.stderr.close()
    assert proc.returncode == -signal.SIGKILL
    assert not (out / "manifest.json").exists()
    with pytest.raises(InputError, match="no manifest.json.*interrupted"):
        ShardDataset(out)
    # the next complete run works, and leaves no temporary files behind
    man = _run(out, "--seed", "2", "--contact-sheet", "0")
    assert not list(out.glob(".*tdfd-tmp"))
    assert len(ShardDataset(out)) == man["count"] == 5


def test_shard_dataset_checks_the_sha256(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    man = _run(a, "--seed", "1", "--contact-sheet", "0")
    _run(b, "--seed", "2", "--contact-sheet", "0")
    name = man["shards"][1]["file"]
    (a / name).write_bytes((b / name).read_bytes())  # a valid shard, but not the one the manifest lists
    ds = ShardDataset(a)
    assert ds[0]["params"]["index"] == 0  # shard 0 is intact
    with pytest.raises(ShardIntegrityError, match=f"shard {name} of .* does not match its manifest"):
        ds[2]
    assert torch.equal(ShardDataset(a, verify=False)[2]["image_f1"], ShardDataset(b)[2]["image_f1"])
    (a / name).unlink()
    with pytest.raises(ShardIntegrityError, match=f"shard {name} of .* is missing"):
        ShardDataset(a)[3]
    torn = man["shards"][0]["file"]
    data = (a / torn).read_bytes()
    (a / torn).write_bytes(data[: len(data) // 2])
    with pytest.raises(ShardIntegrityError, match=torn):
        ShardDataset(a)[0]


def test_orphaned_temporary_files_are_removed_on_the_next_run(tmp_path):
    out = tmp_path / "o"
    out.mkdir()
    dead = out / ".shard_00001.safetensors.999999999.tdfd-tmp"  # no such pid
    dead.write_bytes(b"half a shard")
    live = out / f".shard_00002.safetensors.{os.getppid()}.tdfd-tmp"  # a running process: not ours to delete
    live.write_bytes(b"being written")
    (out / "unrelated.tmp").write_bytes(b"keep")
    _run(out, "--contact-sheet", "0")
    assert not dead.exists() and live.exists() and (out / "unrelated.tmp").exists()
