"""Write one section of ``docs/BENCHMARKS.md`` without touching the others.

Each benchmark owns a section delimited by ``<!-- begin:NAME -->`` / ``<!-- end:NAME -->``
markers; :func:`update_section` replaces it (or appends it) and stamps the machine and
the command that reproduces it.
"""

from __future__ import annotations

import argparse
import os
import platform
import re
import statistics
import sys
import time
from pathlib import Path
from typing import Callable, Sequence

ROOT = Path(__file__).resolve().parents[1]
BENCHMARKS_MD = ROOT / "docs" / "BENCHMARKS.md"

HEADER = """# tdfd benchmarks

Every figure below was produced by the command named in its section, on the machine it
names; timings are medians of repeated runs. Regenerate all of them with
`python3 dev.py python -m benchmarks` (see `benchmarks/__main__.py`).
"""


def machine() -> str:
    """One line describing the machine: CPU count, CPU model, Python, torch/onnxruntime versions."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    parts = [f"{os.cpu_count()} cores ({cpu})", f"Python {platform.python_version()}"]
    for mod in ("torch", "onnxruntime"):
        m = sys.modules.get(mod)
        if m is not None:
            parts.append(f"{mod} {m.__version__}")
    return ", ".join(parts)


def median_time(fn: Callable[[], object], repeats: int = 20, warmup: int = 3) -> tuple[float, list[float]]:
    """Median wall time in seconds of ``fn()`` over ``repeats`` runs after ``warmup`` runs."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), times


def markdown_table(header: Sequence[str], rows: Sequence[Sequence[object]]) -> str:
    """A GitHub-flavoured Markdown table."""
    out = ["| " + " | ".join(map(str, header)) + " |", "|" + "---|" * len(header)]
    out += ["| " + " | ".join(map(str, r)) + " |" for r in rows]
    return "\n".join(out)


def comma_choices(parser: argparse.ArgumentParser, value: str, allowed: Sequence[str], option: str) -> list[str]:
    """The items of a comma-separated option, each one of ``allowed`` (at least one), or the
    parser's usage error naming the option."""
    items = [v.strip() for v in value.split(",") if v.strip()]
    if not items or any(v not in allowed for v in items):
        parser.error(f"{option} takes {' and/or '.join(allowed)}, got {value!r}")
    return items


def repo_path(path: str | Path) -> str:
    """``path`` relative to the repository where it lies in it, else as given (what the docs print)."""
    p = Path(path)
    return str(p.relative_to(ROOT)) if p.is_relative_to(ROOT) else str(path)


def given_options(args: argparse.Namespace, *names: str) -> str:
    """The command-line options ``names`` (attribute names of ``args``) that were given a value, as
    `` --the-name VALUE`` each, in order (what a section's Reproduce line echoes).

    Example:
        >>> given_options(argparse.Namespace(scales="s.json", bias_scales="", walk=4), "scales", "bias_scales", "walk")
        ' --scales s.json --walk 4'
    """
    return "".join(f" --{n.replace('_', '-')} {getattr(args, n)}" for n in names if getattr(args, n))


def with_model_option(command: str, model: str | Path) -> str:
    """``command`` plus ``--model MODEL`` unless ``model`` is the shipped ``models/reference``."""
    if Path(model).resolve() == (ROOT / "models" / "reference").resolve():
        return command
    return f"{command} --model {model}"


def update_section(name: str, title: str, body: str, command: str, path: Path = BENCHMARKS_MD) -> None:
    """Replace (or append) section ``name`` of ``docs/BENCHMARKS.md``.

    Args:
        name: stable identifier used in the markers.
        title: the section heading.
        body: Markdown content (tables, figure links, notes).
        command: the shell command that reproduces the section, run from the repo root.
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    text = path.read_text() if path.exists() else HEADER
    stamp = time.strftime("%Y-%m-%d")
    block = (f"<!-- begin:{name} -->\n## {title}\n\n"
             f"Reproduce: `{command}`  \nMachine: {machine()}; measured {stamp}.\n\n{body.strip()}\n"
             f"<!-- end:{name} -->")
    pattern = re.compile(rf"<!-- begin:{re.escape(name)} -->.*?<!-- end:{re.escape(name)} -->", re.S)
    if pattern.search(text):
        text = pattern.sub(lambda _m: block, text)
    else:
        text = text.rstrip() + "\n\n" + block + "\n"
    path.write_text(text)
