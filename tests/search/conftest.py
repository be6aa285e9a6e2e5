"""Fixtures of the search tests: a Dask cluster that a test may kill a worker of."""

from __future__ import annotations

import pytest

from certify.search.distributed.executor import DaskExecutor


def gone(pid: int) -> bool:
    """The process `pid` has died (no longer exists, or a zombie its parent has not reaped
    yet), read from /proc without asking Dask, which may still be restarting it."""
    try:
        with open(f"/proc/{pid}/stat") as stat:
            return stat.read().rsplit(")", 1)[1].split()[0] in ("Z", "X")
    except FileNotFoundError:
        return True


@pytest.fixture
def doomed2():
    """A 2-worker cluster of its own for a test that kills a worker, so that what Dask does
    after the kill never reaches another test. Its lost-worker timeout is 0 s: the dead
    worker's nanny is retired at once, never restarted, which is what a machine too busy to
    restart it within Dask's default timeout gets; the work must finish on the one left."""
    import dask

    with dask.config.set({"distributed.deploy.lost-worker-timeout": "0s"}):
        ex = DaskExecutor(workers=2)
        yield ex
        ex.close()
