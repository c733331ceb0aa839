"""torch's thread count for the body of a ``with`` block (`torch_threads`)."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import torch

from ..parsing import positive_int

__all__ = ["torch_threads"]


@contextmanager
def torch_threads(threads: int) -> Iterator[int]:
    """Run the body with ``torch.set_num_threads(threads)``, then restore the old count
    (torch's default, one thread per core, makes wall times meaningless on a shared
    machine)."""
    threads = positive_int(threads, "threads")
    previous = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        yield threads
    finally:
        torch.set_num_threads(previous)
