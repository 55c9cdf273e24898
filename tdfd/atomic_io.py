r"""Atomic file writes: a reader sees the old file or the new one, never a torn one.

Every file tdfd's tools write for later runs to read (data-set shards and manifests, model
weights, training checkpoints) goes through :func:`atomic_writer`: the bytes go to a
temporary file beside the target, named ``.<name>.<pid>.tdfd-tmp``, which is flushed,
``fsync``-ed and renamed over the target with :func:`os.replace` (atomic on POSIX and
Windows within one file system); then the folder is ``fsync``-ed so the rename itself
survives a power cut. A process killed mid-write leaves only its temporary file, which
:func:`remove_orphans` deletes on the next run (only those whose writer process is gone).

Example:
    >>> import tempfile, pathlib
    >>> d = pathlib.Path(tempfile.mkdtemp())
    >>> atomic_write_bytes(d / "x.bin", b"abc").read_bytes()
    b'abc'
    >>> sorted(p.name for p in d.iterdir())
    ['x.bin']
"""

from __future__ import annotations

import contextlib
import logging
import os
from pathlib import Path
from typing import IO, Iterator

__all__ = ["atomic_writer", "atomic_write_bytes", "atomic_write_text", "remove_orphans", "TEMP_SUFFIX"]

logger = logging.getLogger(__name__)

#: Suffix of the temporary files (``.<name>.<pid>.tdfd-tmp``).
TEMP_SUFFIX = ".tdfd-tmp"


def _temp_path(path: Path) -> Path:
    return path.with_name(f".{path.name}.{os.getpid()}{TEMP_SUFFIX}")


def _fsync_dir(folder: Path) -> None:
    if os.name != "posix":  # Windows cannot open a folder for fsync; its rename is durable enough
        return
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


@contextlib.contextmanager
def atomic_writer(path: str | os.PathLike) -> Iterator[IO[bytes]]:
    """A binary file object whose content replaces ``path`` atomically when the block ends.

    On an exception inside the block the temporary file is removed and ``path`` is left as
    it was. The folder is created if needed.

    Raises:
        OSError: the folder cannot be created or written (from the OS, unchanged).
    """
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = _temp_path(target)
    f = open(tmp, "wb")
    try:
        yield f
        f.flush()
        os.fsync(f.fileno())
        f.close()
        os.replace(tmp, target)
    except BaseException:
        f.close()
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise
    _fsync_dir(target.parent)


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically (see :func:`atomic_writer`); returns the path."""
    with atomic_writer(path) as f:
        f.write(data)
    return Path(path)


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    """Write UTF-8 ``text`` to ``path`` atomically; returns the path."""
    return atomic_write_bytes(path, text.encode("utf-8"))


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return False  # our own leftovers: this process is not writing them now
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OSError):
        return True  # exists (another user's), or we cannot tell: leave it
    return True


def remove_orphans(folder: str | os.PathLike) -> list[Path]:
    """Delete the temporary files of interrupted :func:`atomic_writer` calls in ``folder``.

    Only files named ``.<name>.<pid>.tdfd-tmp`` whose process ``pid`` no longer runs (or is
    this process) are removed, so a writer running concurrently keeps its file.

    Returns:
        The files removed (empty when the folder does not exist).
    """
    root = Path(folder)
    if not root.is_dir():
        return []
    removed = []
    for p in root.glob(f".*{TEMP_SUFFIX}"):
        stem = p.name[: -len(TEMP_SUFFIX)]
        pid_text = stem.rsplit(".", 1)[-1]
        if not pid_text.isdigit() or _alive(int(pid_text)):
            continue
        with contextlib.suppress(FileNotFoundError):
            p.unlink()
            removed.append(p)
            logger.info("removed %s, left by an interrupted write", p)
    return removed
