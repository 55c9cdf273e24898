"""Command line: ``python -m training [--config FILE] [--set key=value ...] [--resume]``.

Examples::

    python -m training --config training/configs/reference.toml
    python -m training --set optim.steps=200 --set out_dir=runs/try --resume
    torchrun --nproc_per_node 2 -m training --config training/configs/reference.toml
    python -m training --evaluate models/reference --set eval.samples=128
"""

from __future__ import annotations

import argparse
import json
import logging
import sys

from .config import ConfigError, config_to_dict, load_config


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m training", description="Train the tdfd refinement CNN.")
    p.add_argument("--config", help="config file (.toml, .json, .yaml)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a config value, e.g. optim.lr=1e-3 (repeatable)")
    p.add_argument("--resume", action="store_true", help="continue from OUT_DIR/checkpoint_last.pt if present")
    p.add_argument("--stop-at-step", type=int, default=None, metavar="N",
                   help="stop with a checkpoint after N steps (continue later with --resume)")
    p.add_argument("--print-config", action="store_true", help="print the resolved config and exit")
    p.add_argument("--evaluate", metavar="MODEL", help="only evaluate a saved model (path stem) and write OUT_DIR/report.*")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s", stream=sys.stdout)
    try:
        cfg = load_config(args.config, args.overrides)
    except ConfigError as exc:
        p.error(str(exc))
    if args.print_config:
        print(json.dumps(config_to_dict(cfg), indent=2, sort_keys=True))
        return 0
    if args.evaluate:
        from pathlib import Path

        from tdfd.model import DFDModel

        from .evaluate import evaluate_planes, write_report

        model = DFDModel.load(args.evaluate)
        result = evaluate_planes(model, cfg)
        write_report(result, Path(cfg.out_dir) / "report", title=f"Refinement evaluation ({args.evaluate})")
        print(json.dumps(result["summary"], indent=2))
        return 0
    from .loop import train

    summary = train(cfg, resume=args.resume, stop_at_step=args.stop_at_step)
    print(json.dumps(summary, indent=2, sort_keys=True, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
