"""Intra-op thread counts for a block of work.

The tracker's frame loop is thousands of small tensor operations and Warp launches per
frame: torch runs an operation above its grain size on all its intra-op threads, and
every such operation ends at an OpenMP barrier. On a machine whose other cores are busy
(another worker, another job), a thread that is descheduled stalls every barrier for a
time slice: one process tracking one hand with 2 threads took 887 ms per frame where 1
thread took 47 ms, at a load of 3 on 2 cores (docs/benchmarks.md, "Threads"). Warp runs
its CPU kernels on the calling thread, so it has no count to set. What uses a second
core is a second process (``--workers``).
"""

from __future__ import annotations

import contextlib
from typing import Iterator, Optional

import torch

__all__ = ["intra_op_threads"]


@contextlib.contextmanager
def intra_op_threads(n: Optional[int]) -> Iterator[None]:
    """Run the block with ``n`` torch intra-op threads (at most the current count) and
    restore the count after it; None leaves it as it is."""
    old = torch.get_num_threads()
    if n is None or n >= old:
        yield
        return
    torch.set_num_threads(max(1, int(n)))
    try:
        yield
    finally:
        torch.set_num_threads(old)
