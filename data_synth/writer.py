"""Writing (and reading back) synthesised data sets: shards, manifest, contact sheet, PNG pairs.

Layout of an output directory::

    manifest.json            format, tdfd version, seed, count, size, camera, config, shard list
    camera.json              the camera in the tdfd contract JSON (for ``tdfd depth --camera``)
    shard_00000.safetensors  samples [0, K), shard_00001 ... (safe format, no pickle)
    contact_sheet.png        image_f1 | image_f2 | depth of the first samples, for people
    png16/pair_00000_f1.png  with --png16: 16-bit PNGs, value = round(intensity * 65535)
    png16/pair_00000_f2.png
    png16/pair_00000_depth.npy  float32 depth map in metres

A shard holds ``image_f1``, ``image_f2`` (``(N, 1, H, W)``; ``uint16`` raw codes plus
``white_level`` ``(N,)`` when the sensor quantised them, which is exact, else ``float32``),
``depth`` ``(N, 1, H, W)`` and ``tile_depth`` ``(N, 1, h, w)`` float32 metres, ``index``
``(N,)`` int64; its metadata (one key, ``tdfd``, a JSON object) holds the format tag, the
image encoding and the samples' ``params``. :func:`load_shard` and
:class:`ShardDataset` read them back as float32 tensors.

Crash safety: every file is written atomically (:mod:`tdfd.atomic_io`: temporary file,
fsync, ``os.replace``), a :class:`ShardWriter` removes the old ``manifest.json`` *before*
it writes its first shard (:func:`invalidate_manifest`) and the new one is written last
(:func:`write_manifest`), so a run killed midway leaves a directory without a manifest,
which :class:`ShardDataset` refuses, rather than an old manifest over new shards. The next
run removes the temporary files a killed one left. :class:`ShardDataset` checks each
shard's SHA-256 against the manifest the first time it reads it.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch

import tdfd
from tdfd import Camera
from tdfd.atomic_io import atomic_write_bytes, atomic_write_text, remove_orphans
from tdfd.errors import InputError

__all__ = ["FORMAT", "MANIFEST_NAME", "ShardWriter", "load_shard", "ShardDataset", "write_png16_pair",
           "contact_sheet", "sha256_file", "invalidate_manifest", "write_manifest", "ShardIntegrityError"]

logger = logging.getLogger(__name__)

#: Manifest format tag.
FORMAT = "tdfd-synth/1"
SHARD_FORMAT = "tdfd-synth-shard/1"
#: The manifest's file name in an output directory.
MANIFEST_NAME = "manifest.json"


class ShardIntegrityError(InputError):
    """A data set on disk that does not match its manifest (missing, changed or torn shard)."""


def invalidate_manifest(out_dir: str | os.PathLike) -> bool:
    """Remove ``manifest.json`` from ``out_dir`` (before any shard is rewritten).

    Returns:
        Whether there was one.
    """
    try:
        (Path(out_dir) / MANIFEST_NAME).unlink()
    except FileNotFoundError:
        return False
    logger.info("removed the old %s of %s before writing new shards", MANIFEST_NAME, out_dir)
    return True


def write_manifest(out_dir: str | os.PathLike, content: dict[str, Any]) -> Path:
    """Write ``manifest.json`` atomically (the last file of a run)."""
    return atomic_write_text(Path(out_dir) / MANIFEST_NAME, json.dumps(content, indent=2, sort_keys=True) + "\n")


def sha256_file(path: str | os.PathLike) -> str:
    """Hex SHA-256 of a file."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _codes(images: torch.Tensor, white: torch.Tensor) -> np.ndarray | None:
    """``uint16`` codes if ``images * white`` are exactly integers, else ``None``."""
    scaled = images.double() * white.double().reshape(-1, 1, 1, 1)
    codes = torch.round(scaled)
    if float((scaled - codes).abs().max()) > 1e-3 or float(codes.max()) > 65535 or float(codes.min()) < 0:
        return None
    back = (codes / white.double().reshape(-1, 1, 1, 1)).float()
    if not torch.equal(back, images.float()):
        return None
    return codes.numpy().astype(np.uint16)


class ShardWriter:
    """Accumulates samples and writes a shard every ``shard_size`` samples.

    Creating one removes the directory's old ``manifest.json`` (it will no longer describe
    the shards) and the temporary files an interrupted run left. Shards are written
    atomically; write the new manifest with :func:`write_manifest` when all are done.

    Args:
        out_dir: output directory (created).
        shard_size: samples per shard.
    """

    def __init__(self, out_dir: str | os.PathLike, shard_size: int = 256) -> None:
        if int(shard_size) < 1:
            raise InputError(f"shard size must be >= 1, got {shard_size}")
        self.out = Path(out_dir)
        self.out.mkdir(parents=True, exist_ok=True)
        invalidate_manifest(self.out)
        remove_orphans(self.out)
        self.shard_size = int(shard_size)
        self.buffer: list[dict[str, Any]] = []
        self.shards: list[dict[str, Any]] = []

    def add(self, sample: dict[str, Any]) -> None:
        self.buffer.append(sample)
        if len(self.buffer) >= self.shard_size:
            self.flush()

    def flush(self) -> None:
        """Write the buffered samples as one shard (no-op if empty)."""
        if not self.buffer:
            return
        from safetensors.numpy import save

        items, self.buffer = self.buffer, []
        name = f"shard_{len(self.shards):05d}.safetensors"
        params = [it["params"] for it in items]
        tensors: dict[str, np.ndarray] = {
            "depth": torch.stack([it["depth"] for it in items]).float().numpy(),
            "tile_depth": torch.stack([it["tile_depth"] for it in items]).float().numpy(),
            "index": np.asarray([int(p["index"]) for p in params], dtype=np.int64),
        }
        f1 = torch.stack([it["image_f1"] for it in items])
        f2 = torch.stack([it["image_f2"] for it in items])
        encoding = "float32"
        if all(bool(p.get("noise")) and "bits" in p for p in params):
            white = torch.tensor([2.0 ** int(p["bits"]) - 1 for p in params], dtype=torch.float64)
            c1, c2 = _codes(f1, white), _codes(f2, white)
            if c1 is not None and c2 is not None:
                tensors.update(image_f1=c1, image_f2=c2, white_level=white.float().numpy())
                encoding = "raw_uint16"
        if encoding == "float32":
            tensors.update(image_f1=f1.float().numpy(), image_f2=f2.float().numpy())
        # one metadata key: safetensors writes its metadata map in hash order, so several keys
        # would make the bytes differ between processes
        meta = {"tdfd": json.dumps({"format": SHARD_FORMAT, "image_encoding": encoding, "params": params},
                                   sort_keys=True)}
        path = self.out / name
        data = save({k: np.ascontiguousarray(v) for k, v in tensors.items()}, metadata=meta)
        atomic_write_bytes(path, data)
        self.shards.append({"file": name, "first_index": int(params[0]["index"]), "count": len(items),
                            "image_encoding": encoding, "sha256": hashlib.sha256(data).hexdigest()})
        logger.info("wrote %s (%d samples)", path, len(items))


def load_shard(path: str | os.PathLike) -> dict[str, Any]:
    """Read a shard: float32 tensors ``image_f1``, ``image_f2`` (in [0, 1]), ``depth``,
    ``tile_depth``, int64 ``index`` and the list ``params``."""
    from safetensors import safe_open

    with safe_open(str(path), framework="np") as f:
        raw = (f.metadata() or {}).get("tdfd", "{}")
        arrays = {k: f.get_tensor(k) for k in f.keys()}
    try:
        meta = json.loads(raw)
    except json.JSONDecodeError:
        meta = {}
    if meta.get("format") != SHARD_FORMAT:
        raise InputError(f"{path} is not a tdfd synthesis shard")
    out: dict[str, Any] = {k: torch.from_numpy(np.array(arrays[k])) for k in ("depth", "tile_depth", "index")}
    if meta.get("image_encoding") == "raw_uint16":
        white = torch.from_numpy(np.array(arrays["white_level"])).double().reshape(-1, 1, 1, 1)
        for k in ("image_f1", "image_f2"):
            out[k] = (torch.from_numpy(arrays[k].astype(np.float64)) / white).float()
    else:
        for k in ("image_f1", "image_f2"):
            out[k] = torch.from_numpy(np.array(arrays[k]))
    out["params"] = meta["params"]
    return out


class ShardDataset(torch.utils.data.Dataset):
    """The samples of a directory written by the CLI, in index order (items like
    :class:`~data_synth.DefocusPairDataset`'s).

    Args:
        out_dir: the directory.
        verify: check each shard's SHA-256 against the manifest the first time it is read
            (default; costs about one read of the file).

    Raises:
        InputError: no readable manifest (none, or a run was interrupted before writing it).
        ShardIntegrityError: (when an item is read) a shard that is missing or whose bytes
            differ from the manifest's SHA-256; the message names the shard.
    """

    def __init__(self, out_dir: str | os.PathLike, verify: bool = True) -> None:
        self.root = Path(out_dir)
        path = self.root / MANIFEST_NAME
        if not path.is_file():
            raise InputError(f"{self.root} has no {MANIFEST_NAME}: not a data set, or its writing was interrupted "
                             f"(run python -m data_synth again)")
        try:
            self.manifest = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise InputError(f"cannot read {path}: {exc}") from exc
        if not isinstance(self.manifest, dict) or self.manifest.get("format") != FORMAT:
            raise InputError(f"{self.root} is not a {FORMAT} data set")
        self.shards = self.manifest["shards"]
        self.offsets = np.cumsum([0] + [s["count"] for s in self.shards])
        self.verify = bool(verify)
        self._verified: set[int] = set()
        self._cache: tuple[int, dict[str, Any]] | None = None

    def check_shard(self, k: int) -> Path:
        """Path of shard ``k`` after checking it exists and matches the manifest's SHA-256.

        Raises:
            ShardIntegrityError: missing, or different bytes.
        """
        entry = self.shards[k]
        path = self.root / entry["file"]
        if not path.is_file():
            raise ShardIntegrityError(f"shard {entry['file']} of {self.root} is missing")
        want = entry.get("sha256")
        if want is None:
            raise ShardIntegrityError(f"the manifest of {self.root} gives no sha256 for shard {entry['file']}")
        got = sha256_file(path)
        if got != want:
            raise ShardIntegrityError(f"shard {entry['file']} of {self.root} does not match its manifest (sha256 "
                                      f"{got[:12]}..., manifest {want[:12]}...): the data set was rewritten or damaged; "
                                      f"generate it again")
        return path

    def __len__(self) -> int:
        return int(self.offsets[-1])

    def __getitem__(self, i: int) -> dict[str, Any]:
        if i < 0:
            i += len(self)
        if not 0 <= i < len(self):
            raise IndexError(i)
        k = int(np.searchsorted(self.offsets, i, side="right") - 1)
        if self._cache is None or self._cache[0] != k:
            if self.verify and k not in self._verified:
                self.check_shard(k)
                self._verified.add(k)
            self._cache = (k, load_shard(self.root / self.shards[k]["file"]))
        data, j = self._cache[1], i - int(self.offsets[k])
        item = {key: data[key][j] for key in ("image_f1", "image_f2", "depth", "tile_depth")}
        item["params"] = data["params"][j]
        return item


def write_png16_pair(out_dir: str | os.PathLike, index: int, sample: dict[str, Any]) -> list[Path]:
    """Write ``pair_XXXXX_f1.png`` / ``_f2.png`` (16-bit, ``round(intensity * 65535)``) and
    ``pair_XXXXX_depth.npy`` (float32 metres) for the ``tdfd depth`` CLI."""
    import cv2

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for key, suffix in (("image_f1", "f1"), ("image_f2", "f2")):
        arr = np.round(sample[key][0].double().clamp(0, 1).numpy() * 65535.0).astype(np.uint16)
        p = out / f"pair_{index:05d}_{suffix}.png"
        if not cv2.imwrite(str(p), arr):
            raise OSError(f"could not write {p}")
        paths.append(p)
    p = out / f"pair_{index:05d}_depth.npy"
    np.save(p, sample["depth"][0].float().numpy())
    paths.append(p)
    return paths


def contact_sheet(samples: Sequence[dict[str, Any]], path: str | os.PathLike, camera: Camera | None = None) -> Path:
    """A PNG grid of ``image_f1 | image_f2 | depth`` per sample (matplotlib, Agg)."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    n = len(samples)
    if n == 0:
        raise InputError("contact sheet needs at least one sample")
    cols = 3
    fig, axes = plt.subplots(n, cols, figsize=(3 * cols, 2.9 * n), squeeze=False)
    near, far = camera.depth_range_m if camera is not None else (None, None)
    for r, s in enumerate(samples):
        p = s["params"]
        f1, f2 = s["image_f1"][0].numpy(), s["image_f2"][0].numpy()
        vmax = float(max(f1.max(), f2.max(), 1e-6))
        axes[r, 0].imshow(f1, cmap="gray", vmin=0, vmax=vmax)
        axes[r, 1].imshow(f2, cmap="gray", vmin=0, vmax=vmax)
        im = axes[r, 2].imshow(s["depth"][0].numpy(), cmap="viridis_r", vmin=near, vmax=far)
        fig.colorbar(im, ax=axes[r, 2], fraction=0.046, pad=0.04, label="m")
        axes[r, 0].set_title(f"#{p['index']} f1  {p['layout']}, {p['illumination']}", fontsize=7)
        axes[r, 1].set_title(f"f2  psf {p['psf_shape']}, {p['bits']} bit", fontsize=7)
        axes[r, 2].set_title(f"depth {p['depth_min_m']:.2f}-{p['depth_max_m']:.2f} m", fontsize=7)
        for a in axes[r]:
            a.set_xticks([])
            a.set_yticks([])
    fig.tight_layout()
    out = Path(path)
    fig.savefig(out, dpi=80, metadata={"Software": None})
    plt.close(fig)
    return out


def manifest(seed: int, count: int, size: tuple[int, int], camera: Camera, config: dict, shards: list[dict],
             png16: bool, sheet: str | None) -> dict[str, Any]:
    """The ``manifest.json`` content."""
    return {
        "format": FORMAT,
        "tdfd_version": tdfd.__version__,
        "seed": int(seed),
        "count": int(count),
        "size": list(size),
        "camera": {"name": camera.name, **camera.to_dict()},
        "config": config,
        "shards": shards,
        "png16": bool(png16),
        "contact_sheet": sheet,
    }
