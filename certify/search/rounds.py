"""Branch and bound's rounds in flight: dispatched in order, merged in the same order.

A synchronous round leaves the workers idle while the driver merges the last round's
results and picks the next batch, and the driver idle while they compute. Branch and bound
(`certify.search.bnb`) therefore keeps up to `lag` (`certify.search.bnb.PIPELINE_LAG`) rounds in
flight:
round k+1 is chosen and dispatched before round k's results are merged, so the workers find
the next round queued when they finish one. The schedule is a function of the merged
results only, never of timing: the batch chosen at a step depends on the rounds merged so
far, and a round is merged when `lag` rounds are in flight (or the frontier cannot fill a
batch, or the run stops), always the oldest round first, never in completion order. The
serial path runs the SAME schedule (its rounds are evaluated in this process when merged),
so serial, one and many workers give the same boxes, bounds and verdict bit for bit.

`RoundPipeline` is the transport: `dispatch(lo, hi)` starts a round (in this process: lazily,
on an executor: its chunks are submitted at once, `Executor.submit_chunks`), `collect()`
waits for the oldest round and returns its `BoxEval` (chunks concatenated in order);
`collect(deadline)` waits for an executor's round only until then (None: not back in time,
cancelled; a round in this process honours the deadline through its `evaluate`,
`certify.search.bnb.RoundClock`).
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import torch

if TYPE_CHECKING:
    from certify.search.evaluation import BoxEval

CHUNKS_PER_WORKER = 1  # one task per worker per round: fewest round trips


def evaluate_in_halves_on_oom(evaluate: Callable[[torch.Tensor, torch.Tensor], BoxEval],
                              lo: torch.Tensor, hi: torch.Tensor) -> list[BoxEval]:
    """[evaluate(lo, hi)], or, where the GPU runs out of memory on the round, its halves in
    turn (halved again as needed, down to one box): the same boxes in the same order, so the
    same bounds, from smaller pieces. A round of many boxes on a GPU with little memory (a
    laptop's, a wide network) then runs slower instead of ending the check in ERROR."""
    try:
        return [evaluate(lo, hi)]
    except torch.cuda.OutOfMemoryError:
        if len(lo) < 2:
            raise
        torch.cuda.empty_cache()  # what the failed attempt cached goes back to the device
        m = len(lo) // 2
        return (evaluate_in_halves_on_oom(evaluate, lo[:m], hi[:m])
                + evaluate_in_halves_on_oom(evaluate, lo[m:], hi[m:]))


class _LocalRound:
    """A round evaluated in this process when collected (the serial path)."""

    def __init__(self, evaluate: Callable[[torch.Tensor, torch.Tensor], BoxEval],
                 lo: torch.Tensor, hi: torch.Tensor) -> None:
        self._args: tuple | None = (evaluate, lo, hi)

    def result(self) -> list[BoxEval]:
        assert self._args is not None, "collected twice"
        evaluate, lo, hi = self._args
        self._args = None
        return evaluate_in_halves_on_oom(evaluate, lo, hi)

    def cancel(self) -> None:
        self._args = None


class RoundPipeline:
    """Rounds of box evaluations in flight, collected oldest first.

    With an `executor` whose work runs elsewhere (`remote` or more than one worker) and a
    picklable `remote = (chunk_fn, payload)`, a round's boxes are cut into
    `executor.workers * CHUNKS_PER_WORKER` contiguous chunks and submitted; else the round
    is `evaluate(lo, hi)` in this process."""

    def __init__(self, evaluate: Callable[[torch.Tensor, torch.Tensor], BoxEval],
                 executor: Any = None, remote: tuple[Callable[..., BoxEval], Any] | None = None
                 ) -> None:
        self.evaluate = evaluate
        self.executor = executor
        self.remote = remote
        self.chunked = (executor is not None and remote is not None
                        and (bool(getattr(executor, "remote", False))
                             or int(getattr(executor, "workers", 1)) > 1))
        self._rounds: deque[Any] = deque()

    def __len__(self) -> int:
        return len(self._rounds)

    def dispatch(self, lo: torch.Tensor, hi: torch.Tensor) -> None:
        """Start evaluating the boxes lo, hi [N, d] (a new round, behind those in flight)."""
        if not self.chunked or len(lo) < 2:
            self._rounds.append(_LocalRound(self.evaluate, lo, hi))
            return
        from certify.search.distributed.executor import LazyChunks, chunk_ranges

        chunk_fn, payload = self.remote  # type: ignore[misc]
        ex = self.executor
        ranges = chunk_ranges(len(lo), int(ex.workers) * CHUNKS_PER_WORKER)
        items = [(lo[a:b], hi[a:b]) for a, b in ranges]
        submit = getattr(ex, "submit_chunks", None)
        if submit is None:  # an executor with map_chunks only: synchronous when collected
            self._rounds.append(LazyChunks(lambda: ex.map_chunks(chunk_fn, payload, items)))
        else:
            self._rounds.append(submit(chunk_fn, payload, items))

    def collect(self, deadline: float | None = None) -> BoxEval | None:
        """Wait for the oldest round in flight; its evaluation, chunks in order. With a
        `deadline` (a `time.perf_counter()` value), a round on an executor that can be waited
        for with a timeout (`wait(seconds) -> bool`) and is not back by then is cancelled
        and None returned."""
        from certify.search.evaluation import join

        pending = self._rounds.popleft()
        wait = getattr(pending, "wait", None)
        if deadline is not None and wait is not None:
            if not wait(max(0.0, deadline - time.perf_counter())):
                pending.cancel()
                return None
        return join(list(pending.result()))

    def cancel(self) -> None:
        """Drop every round in flight (an error ends the run)."""
        while self._rounds:
            self._rounds.popleft().cancel()
