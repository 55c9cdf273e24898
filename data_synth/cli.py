"""``python -m data_synth``: write a synthetic DFD data set.

Example::

    python -m data_synth --out /tmp/synth --count 1000 --seed 0 --size 256
    python -m data_synth --out /tmp/pairs --count 20 --seed 7 --size 480x640 --camera paper \\
        --families fractal,dead_leaves --psf-shapes pillbox --png16

Writes shards, ``manifest.json`` (format, tdfd version, seed, config, camera, shard list with
SHA-256), ``camera.json``, ``contact_sheet.png`` and, with ``--png16``, 16-bit PNG pairs
for ``tdfd depth``. The same arguments give the same bytes. The old manifest goes before
the first shard is written and the new one is written last (atomically), so a run killed
midway leaves no manifest at all.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
from pathlib import Path
from typing import Sequence

import torch

from tdfd import Camera
from tdfd.atomic_io import atomic_write_text
from tdfd.errors import TdfdError

from .dataset import DefocusPairDataset
from .params import LAYOUTS, PSF_SHAPES, SynthConfig
from .writer import ShardWriter, contact_sheet, manifest, write_manifest, write_png16_pair

__all__ = ["main", "build_parser", "parse_size", "load_camera"]

logger = logging.getLogger("data_synth")


def parse_size(text: str) -> tuple[int, int]:
    """``"256"`` -> (256, 256); ``"480x640"`` -> (480, 640) (height x width)."""
    try:
        parts = [int(p) for p in str(text).lower().replace(",", "x").split("x")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must be N or HxW, got {text!r}") from None
    if len(parts) == 1:
        parts *= 2
    if len(parts) != 2 or min(parts) < 8:
        raise argparse.ArgumentTypeError(f"size must be N or HxW with sides >= 8, got {text!r}")
    return parts[0], parts[1]


def _list(text: str) -> list[str]:
    return [t for t in text.replace(",", " ").split() if t]


def _families(text: str) -> list[str] | dict[str, float]:
    """``a,b,c`` (drawn uniformly) or ``a:3,b:1.5,c:1`` (relative weights; every family named
    with one)."""
    items = _list(text)
    if not any(":" in t for t in items):
        return items
    weights: dict[str, float] = {}
    for t in items:
        name, sep, value = t.partition(":")
        try:
            weights[name] = float(value)
        except ValueError:
            weights[name] = math.nan
        if not sep or not math.isfinite(weights[name]) or weights[name] < 0:
            raise argparse.ArgumentTypeError(f"with weights every family needs NAME:WEIGHT (a number >= 0), got {t!r}")
    return weights


def load_camera(spec: str) -> Camera:
    """A preset name (``reference``, ``paper``) or a path to the contract camera JSON."""
    path = Path(spec)
    if path.suffix.lower() == ".json" or path.exists():
        try:
            text = path.read_text()
        except OSError as exc:
            raise TdfdError(f"cannot read camera file {spec}: {exc}") from exc
        return Camera.from_json(text, name=path.stem)
    return Camera.preset(spec)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m data_synth", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--count", required=True, type=int, help="number of samples")
    p.add_argument("--seed", type=int, default=0, help="stream seed (default 0)")
    p.add_argument("--start", type=int, default=0, help="first sample index (default 0)")
    p.add_argument("--size", type=parse_size, default=(256, 256), help="N or HxW pixels (default 256)")
    p.add_argument("--camera", default="reference", help="preset (reference, paper) or camera JSON path")
    p.add_argument("--families", type=_families, default=None,
                   help="texture families, comma separated (default all), or with relative weights: bandlimited:3,stripes:1")
    p.add_argument("--psf-shapes", type=_list, default=None, help=f"PSF shapes among {','.join(PSF_SHAPES)} (default all)")
    p.add_argument("--layouts", type=_list, default=None, help=f"depth layouts among {','.join(LAYOUTS)} (default the training mix)")
    p.add_argument("--illumination-prob", type=float, default=None, help="probability of active illumination")
    p.add_argument("--no-noise", action="store_true", help="ideal frames: no sensor noise, black level or quantisation")
    p.add_argument("--tile", type=int, default=64, help="tile size of tile_depth (default 64)")
    p.add_argument("--stride", type=int, default=32, help="tile stride of tile_depth (default 32)")
    p.add_argument("--config", default=None, help="JSON file of SynthConfig fields (the options above override it)")
    p.add_argument("--shard-size", type=int, default=256, help="samples per shard (default 256)")
    p.add_argument("--png16", action="store_true", help="also write 16-bit PNG pairs and depth .npy for `tdfd depth`")
    p.add_argument("--contact-sheet", type=int, default=12, help="samples in contact_sheet.png (0: none; default 12)")
    p.add_argument("--workers", type=int, default=0, help="DataLoader worker processes (default 0: in process)")
    p.add_argument("--threads", type=int, default=None, help="torch threads of this process")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.add_argument("-v", "--verbose", action="count", default=0, help="more logging")
    return p


def run(args: argparse.Namespace) -> dict:
    """Generate the data set described by parsed ``args``; returns the manifest."""
    from tqdm import tqdm

    if args.count < 1:
        raise TdfdError(f"--count must be >= 1, got {args.count}")
    if args.threads:
        torch.set_num_threads(int(args.threads))
    camera = load_camera(args.camera)
    base = SynthConfig()
    if args.config:
        try:
            base = SynthConfig.from_dict(json.loads(Path(args.config).read_text()))
        except (OSError, json.JSONDecodeError) as exc:
            raise TdfdError(f"cannot read config {args.config}: {exc}") from exc
    options = {}
    if args.layouts:
        options["layouts"] = {k: 1.0 for k in args.layouts}
    ds = DefocusPairDataset(size=args.size, camera=camera, seed=args.seed, length=args.start + args.count,
                            families=args.families, psf_shapes=args.psf_shapes, tile=args.tile, stride=args.stride,
                            noise=not args.no_noise, illumination_prob=args.illumination_prob, config=base, **options)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    writer = ShardWriter(out, args.shard_size)
    indices = list(range(args.start, args.start + args.count))
    subset = torch.utils.data.Subset(ds, indices)
    loader = torch.utils.data.DataLoader(subset, batch_size=None, num_workers=max(0, args.workers),
                                         persistent_workers=False)
    sheet: list = []
    for sample in tqdm(loader, total=len(indices), desc="synthesising", unit="pair", disable=args.quiet):
        idx = int(sample["params"]["index"])
        writer.add(sample)
        if args.png16:
            write_png16_pair(out / "png16", idx, sample)
        if len(sheet) < args.contact_sheet:
            sheet.append(sample)
    writer.flush()
    atomic_write_text(out / "camera.json", camera.to_json() + "\n")
    sheet_name = None
    if sheet:
        sheet_name = "contact_sheet.png"
        contact_sheet(sheet, out / sheet_name, camera)
    man = manifest(args.seed, args.count, ds.size, camera, {**ds.config.to_dict(), "start": args.start},
                   writer.shards, args.png16, sheet_name)
    write_manifest(out, man)  # last: the ShardWriter removed the old one before the first shard
    logger.info("wrote %d samples in %d shards to %s", args.count, len(writer.shards), out)
    return man


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    level = [logging.WARNING, logging.INFO, logging.DEBUG][min(args.verbose, 2)]
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")
    try:
        run(args)
    except TdfdError as exc:
        print(f"data_synth: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130
    return 0
