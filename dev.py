#!/usr/bin/env python3
"""One-file set-up and task runner for tdfd: needs only Python 3.10+.

    python3 dev.py autofocus   # the main job: simulated autofocus bench, default settings
    python3 dev.py test        # the whole test suite

Both create ``.venv`` beside this file on first use and install what they need into it.
torch is pinned *only here* (``torch==2.13.0`` resolves to a local CPU build on the
project's machines; an unpinned ``torch`` would pull several GB of CUDA wheels). The
package's own dependency range stays loose. Set ``TDFD_TORCH`` to install another spec.
"""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
import venv
from pathlib import Path

ROOT = Path(__file__).resolve().parent
VENV = ROOT / ".venv"
BIN = VENV / ("Scripts" if os.name == "nt" else "bin")
PY = BIN / ("python.exe" if os.name == "nt" else "python")
TORCH_SPEC = os.environ.get("TDFD_TORCH", "torch==2.13.0")
STAMP = VENV / ".tdfd-installed"


def _run(cmd: list[str], **kw) -> int:
    return subprocess.call([str(c) for c in cmd], cwd=ROOT, **kw)


def _fingerprint() -> str:
    return hashlib.sha256((ROOT / "pyproject.toml").read_bytes() + TORCH_SPEC.encode()).hexdigest()


def ensure_env() -> None:
    """Create the virtual environment and install tdfd (editable) with its test extras."""
    if not PY.exists():
        print(f"[dev] creating {VENV}", flush=True)
        venv.EnvBuilder(with_pip=True).create(VENV)
    if STAMP.exists() and STAMP.read_text() == _fingerprint():
        return
    pip = [PY, "-m", "pip", "install", "--disable-pip-version-check", "-q"]
    print(f"[dev] installing {TORCH_SPEC} (CPU build) and tdfd[test]", flush=True)
    if _run(pip + [TORCH_SPEC]) != 0:
        sys.exit("dev.py: installing torch failed")
    if _run(pip + ["-e", ".[test]"]) != 0:
        sys.exit("dev.py: installing tdfd failed")
    STAMP.write_text(_fingerprint())


def main(argv: list[str]) -> int:
    if not argv or argv[0] in {"-h", "--help"}:
        print(__doc__)
        return 0
    task, rest = argv[0], argv[1:]
    ensure_env()
    if task == "test":
        return _run([PY, "-m", "pytest", "-q", *rest])
    if task == "autofocus":
        return _run([BIN / "tdfd", "autofocus", "--sim", *rest])
    if task == "tdfd":
        return _run([BIN / "tdfd", *rest])
    if task == "python":
        return _run([PY, *rest])
    print(f"dev.py: unknown task {task!r} (use autofocus, test, tdfd or python)", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
