"""Thread policy for batched torch work on small CPUs.

Most of certify's kernels are many small matrix products and elementwise passes. On a 2-core
machine torch's own intra-op threads barely help them (and stall badly when the other core is
busy); independent chunks on worker threads, each running single-threaded torch, scale better.
`verify()` runs single-threaded (`torch_threads(1)`); grid sweeps use `parallel_chunks()`.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor

import torch


def worker_count() -> int:
    """Worker threads for chunked sweeps: the usable CPUs, at most 4 (env CERTIFY_WORKERS)."""
    env = os.environ.get("CERTIFY_WORKERS")
    if env and env.isdigit() and int(env) >= 1:
        return int(env)
    try:
        cpus = len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not on Linux
        cpus = os.cpu_count() or 1
    return max(1, min(4, cpus))


@contextlib.contextmanager
def torch_threads(n: int) -> Iterator[None]:
    """Run the block with torch's intra-op thread count set to n, then restore it."""
    before = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)


@contextlib.contextmanager
def parallel_chunks() -> Iterator[ThreadPoolExecutor]:
    """A pool of `worker_count()` threads with single-threaded torch inside; `map` keeps order,
    so results are merged deterministically."""
    with torch_threads(1), ThreadPoolExecutor(worker_count()) as pool:
        yield pool
