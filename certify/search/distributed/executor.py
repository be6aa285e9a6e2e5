"""Where chunks of work run: in this process, or on a Dask cluster (local or remote).

Branch and bound, the MPDI grid sweep and the residual/rate proofs cut their work into chunks
and call `executor.map(fn, items)` (or `map_chunks(fn, payload, items)`); results come back
in the order of `items`, so what the caller merges is identical whichever executor ran it.
`submit_chunks(fn, payload, items)` is `map_chunks` without the wait: it returns a handle whose
`result()` gives the same list later, so a caller can keep several rounds in flight (branch and
bound's pipeline, `certify.search.rounds`) and still merge them in the order it dispatched them.

- `SerialExecutor()`: the default; runs `fn(item)` here, in order.
- `DaskExecutor(workers=N)`: starts a `dask.distributed.LocalCluster` of N worker processes
  with one thread each (torch single-threaded inside, see `certify.search.threads`).
- `DaskExecutor(scheduler="tcp://host:port")`: connects to a running Dask scheduler (a
  dask-jobqueue cluster on SLURM/PBS, Kubernetes, `dask scheduler` by hand). The connection
  times out after `connect_timeout` seconds with a `SettingsError` (one line, exit 2).

A worker that dies mid-task loses nothing: Dask re-runs the tasks it held on the other
workers (and a LocalCluster's nanny restarts the process). Tasks are pure functions of their
arguments, so a re-run returns the same result. `fn` must be picklable: a module-level
function; the data it needs travels as plain data (`payload`), sent to each worker once
(`map_chunks` scatters it), and a worker builds its evaluator from it once per process
(`worker_cache`). Dask is imported only when a `DaskExecutor` is made.
"""

from __future__ import annotations

import hashlib
import logging
import pickle
from collections import OrderedDict
from collections.abc import Callable, Sequence
from typing import Any, Protocol, runtime_checkable

from certify.errors import SettingsError
from certify.search.distributed.wire import WireArray, from_wire, to_wire  # noqa: F401 - re-exported

_log = logging.getLogger(__name__)

#: seconds to wait for a scheduler given by address before giving up (exit 2)
CONNECT_TIMEOUT = 5.0

#: evaluators each worker process keeps (keyed by payload digest), least recently used dropped
CACHE_SIZE = 4
LOST_WORKER_RETRIES = 3  # re-scatter and re-run a round this many times when workers vanish


@runtime_checkable
class Executor(Protocol):
    """Runs `fn` over `items`, results in the order of `items`."""

    workers: int
    remote: bool  # True: chunks go to other processes (worth chunking even for 1 worker)

    def map(self, fn: Callable[[Any], Any], items: Sequence[Any]) -> list[Any]: ...

    def close(self) -> None: ...


class SerialExecutor:
    """Everything in this process, in order (the default; no dependency)."""

    workers = 1
    remote = False  # chunks run in this process
    description = "serial (this process)"

    def map(self, fn: Callable[[Any], Any], items: Sequence[Any]) -> list[Any]:
        return [fn(item) for item in items]

    def map_chunks(self, fn: Callable[..., Any], payload: Any,
                   items: Sequence[tuple]) -> list[Any]:
        return [fn(payload, *item) for item in items]

    def submit_chunks(self, fn: Callable[..., Any], payload: Any,
                      items: Sequence[tuple]) -> LazyChunks:
        """`map_chunks` run when its `result()` is asked for (in this process, in order)."""
        return LazyChunks(lambda: self.map_chunks(fn, payload, items))

    def close(self) -> None:
        pass

    def __enter__(self) -> SerialExecutor:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class LazyChunks:
    """A round of chunks computed in this process when `result()` is first called."""

    def __init__(self, compute: Callable[[], list[Any]]) -> None:
        self._compute: Callable[[], list[Any]] | None = compute
        self._value: list[Any] = []

    def result(self) -> list[Any]:
        if self._compute is not None:
            self._value, self._compute = self._compute(), None
        return self._value

    def cancel(self) -> None:
        self._compute = None


class PendingChunks:
    """A round of chunks on a Dask cluster: `result()` waits for all of them and returns them
    in the order submitted (whatever order they finish in). When workers vanish (a lost
    worker's tasks that Dask could not re-run itself, or the scattered payload lost with
    every worker that held it) the round is scattered and submitted again, up to
    `LOST_WORKER_RETRIES` times; a task's result depends only on its inputs, so a re-run
    gives the same answer."""

    def __init__(self, executor: DaskExecutor, fn: Callable[..., Any], payload: Any,
                 items: Sequence[tuple]) -> None:
        self._executor, self._fn, self._payload = executor, fn, payload
        self._wired = [to_wire(tuple(it)) for it in items]
        self._futures: list[Any] | None = None
        self._failures = 0
        try:
            self._submit()
        except _lost_work_errors() as exc:  # a worker died during the scatter: retry later
            self._lost(exc)

    def _submit(self) -> None:
        ex, n = self._executor, len(self._wired)
        shared = ex._shared(self._payload)
        self._futures = ex.client.map(_call_with_payload, [self._fn] * n, [shared] * n,
                                      self._wired, pure=False)

    def _lost(self, exc: BaseException) -> None:
        self._futures = None
        self._executor._forget(self._payload)
        self._failures += 1
        if self._failures > LOST_WORKER_RETRIES:
            raise RuntimeError(f"Dask lost workers {self._failures} times in one round: "
                               f"{type(exc).__name__}: {exc}") from exc
        self._executor.client.wait_for_workers(1, timeout=60)

    def result(self) -> list[Any]:
        while True:
            try:
                if self._futures is None:
                    self._submit()
                return from_wire(self._executor.client.gather(self._futures))
            except _lost_work_errors() as exc:
                self._lost(exc)

    def wait(self, seconds: float) -> bool:
        """Whether every chunk is back within `seconds` (a round to be submitted again
        after lost workers counts as back: `result()` handles it)."""
        if self._futures is None:
            return True
        from distributed import wait

        try:
            with self._executor.client.as_current():  # `wait` looks for a default client
                wait(self._futures, timeout=seconds)
        except TimeoutError:
            return False
        except _lost_work_errors() + (_cancelled_group(),):
            return True  # `result()` submits the round again
        return True

    def cancel(self) -> None:
        if self._futures:
            self._executor.client.cancel(self._futures)
        self._futures = None


def _close_failed_client(client: Any) -> None:
    """Close a `Client` whose constructor raised, quietly and at once (best effort)."""
    try:
        client.close(timeout=2)
    except Exception:  # it never connected: nothing to report
        pass
    client.status = "closed"  # its __del__ then has nothing left to do


def _call_with_payload(fn: Callable[..., Any], payload: Any, item: tuple) -> Any:
    """Task body of `DaskExecutor.map_chunks` (module level: picklable): arguments and
    result cross the wire as numpy arrays (`to_wire`)."""
    return to_wire(fn(payload, *from_wire(item)))


class DaskExecutor:
    """Chunks on a Dask cluster: a LocalCluster of `workers` processes, or `scheduler`."""

    def __init__(self, workers: int | None = None, scheduler: str | None = None, *,
                 connect_timeout: float = CONNECT_TIMEOUT) -> None:
        if (workers is None) == (scheduler is None):
            raise ValueError("DaskExecutor needs exactly one of workers= or scheduler=")
        try:
            from dask.distributed import Client, LocalCluster
        except ImportError:  # pragma: no cover - dask is a declared extra
            raise SettingsError("--workers/--scheduler need dask.distributed: pip install "
                                "'certify[dask]'") from None
        self._cluster = None
        self._scattered: dict[str, Any] = {}
        self.remote = True
        if scheduler is not None:
            address = str(scheduler).strip()
            if not address:
                raise SettingsError("--scheduler must be an address like tcp://host:8786")
            # made in two steps, so that a client whose connection failed can be closed
            # here: left to its __del__, it would try again at exit, time out and print an
            # ignored traceback after the one-line error
            client = Client.__new__(Client)
            try:
                client.__init__(address, timeout=f"{connect_timeout}s", set_as_default=False)
            except (OSError, TimeoutError, ValueError, TypeError) as exc:
                _close_failed_client(client)
                reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
                raise SettingsError(f"--scheduler {address}: cannot connect to a Dask "
                                    f"scheduler within {connect_timeout:g} s ({reason})"
                                    ) from None
            self.client = client
            self.workers = max(1, len(self.client.scheduler_info().get("workers", {})))
            self.description = f"dask scheduler {address} ({self.workers} workers)"
        else:
            if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
                raise SettingsError(f"--workers must be an int >= 1; got {workers!r}")
            with _worker_environment():
                self._cluster = LocalCluster(n_workers=workers, threads_per_worker=1,
                                             processes=True, dashboard_address=None,
                                             silence_logs=logging.ERROR)
            self.client = Client(self._cluster, set_as_default=False)
            self.client.wait_for_workers(workers, timeout=120)
            self.workers = workers
            self.description = f"dask LocalCluster ({workers} processes x 1 thread)"

    def map(self, fn: Callable[[Any], Any], items: Sequence[Any]) -> list[Any]:
        if not len(items):
            return []
        futures = self.client.map(fn, list(items), pure=False)
        return self.client.gather(futures)

    def map_chunks(self, fn: Callable[..., Any], payload: Any,
                   items: Sequence[tuple]) -> list[Any]:
        """`[fn(payload, *item) for item in items]` on the cluster; `payload` is sent to the
        workers once (scattered), not once per task."""
        if not len(items):
            return []
        return self.submit_chunks(fn, payload, items).result()

    def submit_chunks(self, fn: Callable[..., Any], payload: Any,
                      items: Sequence[tuple]) -> PendingChunks:
        """`map_chunks` without waiting: the tasks start now, `result()` gathers them."""
        return PendingChunks(self, fn, payload, items)

    def _forget(self, payload: Any) -> None:
        """Drop the cached scatter of `payload` (its copies may have died with a worker)."""
        key = payload.get("key") if isinstance(payload, dict) else None
        if key is not None:
            self._scattered.pop(key, None)

    def _shared(self, payload: Any) -> Any:
        """`payload` on every worker: scattered once per payload "key" (a digest) when it has
        one (branch and bound sends the same payload every round), else every call."""
        key = payload.get("key") if isinstance(payload, dict) else None
        if key is not None and key in self._scattered:
            return self._scattered[key]
        # a list, not the dict itself: Dask scatters a dict's values under its keys as names
        [shared] = self.client.scatter([payload], broadcast=True, hash=False)
        if key is not None:
            while len(self._scattered) >= CACHE_SIZE:
                self._scattered.pop(next(iter(self._scattered)))
            self._scattered[key] = shared
        return shared

    def worker_pids(self) -> dict[str, int]:
        """Worker address -> process id (for tests that kill one)."""
        import os

        return self.client.run(os.getpid)

    def close(self) -> None:
        """Close the client and, for a local cluster, the cluster.

        Every result has been gathered by then, so a failure inside Dask's own teardown
        (after a worker died, its cluster's status watcher can meet a worker address it
        never recorded and raise KeyError) changes no result: it is logged, not raised.
        """
        self._scattered.clear()
        try:
            self.client.close()
        finally:
            if self._cluster is not None:
                try:
                    self._cluster.close()
                except Exception as exc:  # noqa: BLE001 - Dask's teardown, results are in
                    _log.warning("closing the local Dask cluster: %s: %s",
                                 type(exc).__name__, exc)

    def __enter__(self) -> DaskExecutor:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _lost_work_errors() -> tuple[type[BaseException], ...]:
    """What Dask raises on the client when workers vanish mid-call (not errors of the task).

    KeyError: the scheduler's broadcast scatter names a worker that has just been removed;
    cancelled futures: a scattered payload lost with every worker that held it; KilledWorker:
    Dask gave up re-running a task after repeated worker deaths; closed comms: the same, seen
    from the connection.
    """
    from asyncio import CancelledError

    from distributed import CancelledError as DaskCancelled
    from distributed.comm.core import CommClosedError
    from distributed.scheduler import KilledWorker

    return (KeyError, CancelledError, DaskCancelled, CommClosedError, KilledWorker)


def _cancelled_group() -> type[BaseException]:
    """What `distributed.wait` raises for futures cancelled under it (a lost payload)."""
    try:
        from distributed.client import FuturesCancelledError
    except ImportError:  # older Dask: cancelled futures raise CancelledError there
        from distributed import CancelledError as FuturesCancelledError
    return FuturesCancelledError


def _worker_environment() -> Any:
    """Dask's worker environment without MALLOC_TRIM_THRESHOLD_: Dask sets it (to return
    memory to the OS sooner), which also turns off glibc's adaptive mmap threshold, so every
    large torch temporary becomes an mmap + page faults + munmap, and the box bounds run
    several times slower on a worker than in-process (`bench/scale.py`). One thread per
    library stays, and the workers' profiler is off."""
    import dask

    env = dict(dask.config.get("distributed.nanny.pre-spawn-environ", default={}) or {})
    env.pop("MALLOC_TRIM_THRESHOLD_", None)
    env.update(OMP_NUM_THREADS=1, MKL_NUM_THREADS=1, OPENBLAS_NUM_THREADS=1)
    # the worker's statistical profiler samples the task thread every 10 ms (for the
    # dashboard, which a LocalCluster here does not serve): CPU taken from the evaluation
    return dask.config.set({"distributed.nanny.pre-spawn-environ": env,
                            "distributed.worker.profile.enabled": False})


def executor_from_settings(settings: Any) -> SerialExecutor | DaskExecutor:
    """The executor `settings.workers` / `settings.scheduler` ask for (serial by default).

    A scheduler address wins over `workers`; `workers = 1` without a scheduler is serial
    (no cluster is started for one process)."""
    scheduler = getattr(settings, "scheduler", "") or None
    workers = int(getattr(settings, "workers", 1) or 1)
    if scheduler is not None:
        return DaskExecutor(scheduler=scheduler)
    if workers > 1:
        return DaskExecutor(workers=workers)
    return SerialExecutor()


# ----- the executor of the running verification ------------------------------------------

_current: list[Any] = []


def current_executor() -> Any:
    """The executor of the verification in progress (`using`), else a SerialExecutor."""
    return _current[-1] if _current else SerialExecutor()


class using:  # noqa: N801 - used as a context manager, like a function
    """`with using(executor): ...` makes it `current_executor()` for the block."""

    def __init__(self, executor: Any) -> None:
        self.executor = executor

    def __enter__(self) -> Any:
        _current.append(self.executor)
        return self.executor

    def __exit__(self, *exc: object) -> None:
        _current.remove(self.executor)


# ----- worker side: build once per process -----------------------------------------------

_cache: OrderedDict[str, Any] = OrderedDict()


def payload_key(payload: Any) -> str:
    """A digest of plain-data `payload` (pickled), to cache what a worker builds from it."""
    return hashlib.sha256(pickle.dumps(payload, protocol=4)).hexdigest()


def worker_cache(key: str, build: Callable[[], Any]) -> Any:
    """`build()` once per process per key (the last `CACHE_SIZE` kept)."""
    if key in _cache:
        _cache.move_to_end(key)
        return _cache[key]
    value = build()
    _cache[key] = value
    while len(_cache) > CACHE_SIZE:
        _cache.popitem(last=False)
    return value


#: children (evaluated boxes) each worker gets per branch-and-bound round from 3 workers on:
#: enough that the per-task overhead and the driver's share of a round stay small at 64
#: workers (bench/scale.py, scale_paper: E(64) from measured costs)
BOXES_PER_WORKER = 2048

#: up to this many workers the rounds are the serial ones (the default batch), so a run on
#: this 2-core machine is identical to the default serial run, not only to one with its batch
SERIAL_ROUNDS_UP_TO = 2


def round_batch(executor: Any, batch: int) -> int:
    """Boxes split per branch-and-bound round on `executor`: `batch` for a serial executor
    and for up to SERIAL_ROUNDS_UP_TO workers; beyond, raised to `workers *
    BOXES_PER_WORKER / 2` (each split gives 2 children). The verdict and bounds are those of
    a serial run with the returned batch and the same box budget."""
    workers = int(getattr(executor, "workers", 1))
    if not getattr(executor, "remote", False) or workers <= SERIAL_ROUNDS_UP_TO:
        return batch
    return max(batch, -(-workers * BOXES_PER_WORKER // 2))


def chunk_ranges(total: int, pieces: int, align: int = 1) -> list[tuple[int, int]]:
    """[0, total) cut into at most `pieces` contiguous (start, stop) ranges of near-equal size
    (boundaries multiples of `align` except the last), in order."""
    if total <= 0:
        return []
    pieces = max(1, min(pieces, -(-total // max(align, 1))))
    step = -(-total // pieces)
    step = -(-step // align) * align
    return [(s, min(total, s + step)) for s in range(0, total, step)]
