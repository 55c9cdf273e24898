r"""Torch intra-op threads for a block of code (the bench's renderer and the analytic estimator)."""

from __future__ import annotations

import contextlib
from typing import Iterator

__all__ = ["torch_threads"]


@contextlib.contextmanager
def torch_threads(n: int | None) -> Iterator[None]:
    """Run the block with ``n`` torch intra-op threads (``None``: unchanged), then restore.

    The bench's frames are small: one thread is as fast as two, and on a busy machine two
    threads can be many times slower (the pool waits on a preempted worker).
    """
    import torch

    before = torch.get_num_threads()
    if n is None or n == before:
        yield
        return
    torch.set_num_threads(int(n))
    try:
        yield
    finally:
        torch.set_num_threads(before)
