"""Pipelined branch and bound (certify.search.rounds, certify.search.frontier): rounds in flight
are merged
in dispatch order, so the outcome depends on the lag and the budget only, never on which
executor ran the rounds or when their chunks finished; the lag does not change which boxes a
closing decision proof evaluates; a stopped run merges what it dispatched."""

from __future__ import annotations

import math
import random
import threading
import time
from concurrent.futures import ThreadPoolExecutor

import pytest
import torch

from certify.search import frontier as frontier_module
from certify.search.bnb import PIPELINE_LAG, Budget, ClosingRule, Schedule, branch_and_bound
from certify.search.distributed.executor import SerialExecutor
from certify.search.evaluation import BoxEval
from certify.search.frontier import Frontier

LIP = 3.0  # Lipschitz constant of sin(3 x) in each coordinate


def sine_eval(offset: float, lo: torch.Tensor, hi: torch.Tensor) -> BoxEval:
    """f(x) = sum_i sin(3 x_i) - offset: a sound upper bound over each box from the value at
    its centre plus LIP times the half widths (outward by 1e-12 for the float error)."""
    c = 0.5 * (lo + hi)
    val = torch.sin(3.0 * c).sum(-1) - offset
    upper = val + LIP * (0.5 * (hi - lo)).sum(-1) + 1e-12
    return BoxEval(upper=upper, centre_value=val, score=(hi - lo) * LIP)


def sine_chunk(payload: dict, lo: torch.Tensor, hi: torch.Tensor) -> BoxEval:
    """Chunk task of the threaded executor: a random delay, so chunks finish out of order."""
    time.sleep(random.random() * payload["jitter"])
    return sine_eval(payload["offset"], lo, hi)


class ThreadedExecutor(SerialExecutor):
    """Chunks on a thread pool: they run concurrently and finish in any order, like Dask's."""

    remote = True

    def __init__(self, workers: int = 2) -> None:
        self.workers = workers
        self.pool = ThreadPoolExecutor(workers)
        self.in_flight = 0
        self.max_in_flight = 0
        self.lock = threading.Lock()

    def submit_chunks(self, fn, payload, items):  # type: ignore[override]
        futures = [self.pool.submit(fn, payload, *it) for it in items]
        with self.lock:
            self.in_flight += 1
            self.max_in_flight = max(self.max_in_flight, self.in_flight)
        outer = self

        class Handle:
            def result(self):
                out = [f.result() for f in futures]
                with outer.lock:
                    outer.in_flight -= 1
                return out

            def cancel(self):
                for f in futures:
                    f.cancel()

        return Handle()

    def close(self) -> None:
        self.pool.shutdown()


DIM = 3  # f <= DIM - offset, with its max DIM - offset at x_i = pi/6
ROOT = (-torch.ones(DIM, dtype=torch.float64), torch.ones(DIM, dtype=torch.float64))


def _sine_bnb(offset: float, executor=None, jitter: float = 0.0, max_boxes: int = 2_000_000,
              lag: int = PIPELINE_LAG):
    evaluate = lambda lo, hi: sine_eval(offset, lo, hi)  # noqa: E731
    remote = (sine_chunk, {"offset": offset, "jitter": jitter})
    return branch_and_bound(*ROOT, evaluate, ClosingRule(threshold=0.0), Budget(max_boxes),
                            Schedule(batch=32, lag=lag), executor=executor,
                            remote=remote if executor is not None else None)


def _same(a, b) -> None:
    assert (a.upper, a.lower, a.violated, a.complete) == (b.upper, b.lower, b.violated,
                                                          b.complete)
    assert a.stats.boxes_processed == b.stats.boxes_processed
    assert a.stats.proved_volume_fraction == b.stats.proved_volume_fraction
    assert a.leaves == b.leaves and a.stuck == b.stuck
    assert (a.best_point is None) == (b.best_point is None)
    if a.best_point is not None:
        assert torch.equal(a.best_point, b.best_point)


def test_frontier_takes_worst_and_nearest_like_a_sort():
    """Frontier.take against a plain list model through adds, takes, closes and compactions:
    the same boxes (ids) leave, the worst (k+1)//2 then the k//2 nearest to closing."""
    gen = torch.Generator().manual_seed(0)
    fr = Frontier(1, capacity=8)
    fr.COMPACT_MIN = 64  # compact often
    compactions = 0
    original = fr._compact

    def counting() -> None:
        nonlocal compactions
        compactions += 1
        original()

    fr._compact = counting  # type: ignore[method-assign]
    model: dict[int, float] = {}
    next_id = 0
    for step in range(120):
        m = int(torch.randint(0, 120, (1,), generator=gen))
        ub = torch.randn(m, generator=gen, dtype=torch.float64)
        ub[torch.rand(m, generator=gen) < 0.05] = math.nan
        ids = torch.arange(next_id, next_id + m, dtype=torch.float64)[:, None]
        next_id += m
        fr.add(ids, ids, torch.zeros(m, dtype=torch.long), ub, ids)
        model.update({int(i): float(u) for i, u in zip(ids[:, 0], ub)})
        assert len(fr) == len(model)
        k = int(torch.randint(1, 100, (1,), generator=gen))
        nearest = step % 2 == 0
        lo, _, _, score = fr.take(k, nearest)
        taken = [int(v) for v in lo[:, 0]]
        assert torch.equal(score, lo) and len(set(taken)) == len(taken) == min(k, len(model))
        keyed = sorted(model, key=lambda i: -math.inf if math.isnan(model[i]) else -model[i])
        if nearest and len(model) > k:
            kw = (k + 1) // 2
            worst_vals = sorted((model[i] for i in taken[:kw]), key=lambda v: -math.inf
                                if math.isnan(v) else -v)
            ref_worst = [model[i] for i in keyed[:kw]]
            assert [str(v) for v in worst_vals] == [str(v) for v in ref_worst]
            rest = [model[i] for i in keyed[kw:]]
            near_ref = sorted(rest, key=lambda v: math.inf if math.isnan(v) else v)[:k - kw]
            near = sorted((model[i] for i in taken[kw:]), key=lambda v: math.inf
                          if math.isnan(v) else v)
            assert [str(v) for v in near] == [str(v) for v in near_ref]
        else:
            ref = [model[i] for i in keyed[:k]]
            assert [str(model[i]) for i in taken] == [str(v) for v in ref]
        for i in taken:
            del model[i]
        if step % 7 == 0:
            shut = fr.close(-1.0)
            gone = [] if shut is None else [int(v) for v in shut[0][:, 0]]
            assert sorted(gone) == sorted(i for i, v in model.items() if v <= -1.0)
            assert shut is None or bool((shut[2] <= -1.0).all())
            for i in gone:
                del model[i]
        finite = [v for v in model.values()]
        ref_max = max((math.inf if math.isnan(v) else v for v in finite), default=-math.inf)
        assert fr.open_max() == ref_max
        assert sorted(int(v) for v in fr.boxes()[0][:, 0]) == sorted(model)
    assert compactions > 5


@pytest.mark.parametrize("nearest", [True, False])
def test_frontier_pools_take_what_a_full_scan_takes(nearest: bool, monkeypatch):
    """Past POOL_MIN boxes `take` chooses within candidate pools: fed the same adds, takes
    and closes (children bounded near their parent, so the top pool is drained and refilled;
    ties and NaN bounds among them), a pooled frontier takes boxes of the same bounds in the
    same order as one that always scans; the pools are rebuilt several times and serve most
    takes."""
    gen = torch.Generator().manual_seed(1)
    pooled, scanned = Frontier(1, capacity=8), Frontier(1, capacity=8)
    pooled.POOL_MIN, scanned.POOL_MIN = 200, 10**9
    pooled.COMPACT_MIN = scanned.COMPACT_MIN = 256
    builds = []
    original = frontier_module._Pools.build

    def counting(fr: Frontier, k: int, near: bool):
        builds.append(fr is pooled)
        return original(fr, k, near)

    monkeypatch.setattr(frontier_module._Pools, "build", staticmethod(counting))
    bound: dict[int, float] = {}
    ub = torch.randn(3000, generator=gen, dtype=torch.float64).round(decimals=2)
    next_id, pooled_takes = 0, 0
    for step in range(200):
        m = len(ub)
        ub[torch.rand(m, generator=gen) < 0.01] = math.nan
        ids = torch.arange(next_id, next_id + m, dtype=torch.float64)[:, None]
        next_id += m
        bound.update({int(i): float(u) for i, u in zip(ids[:, 0], ub)})
        for fr in (pooled, scanned):
            fr.add(ids, ids, torch.zeros(m, dtype=torch.long), ub, None)
        k = int(torch.randint(1, 60, (1,), generator=gen))
        pooled_takes += len(pooled) > max(pooled.POOL_MIN, 8 * k)
        taken = [[bound[int(i)] for i in fr.take(k, nearest)[0][:, 0]]
                 for fr in (pooled, scanned)]
        assert [str(v) for v in taken[0]] == [str(v) for v in taken[1]]
        if step % 9 == 0:
            shut_pooled, shut_scanned = pooled.close(-2.0), scanned.close(-2.0)
            assert (shut_pooled is None) == (shut_scanned is None)
            if shut_pooled is not None:
                assert sorted(shut_pooled[2].tolist()) == sorted(shut_scanned[2].tolist())
        assert len(pooled) == len(scanned)
        parents = torch.tensor(taken[0], dtype=torch.float64).repeat(2)
        ub = (torch.nan_to_num(parents, nan=3.0)
              - 0.05 * torch.rand(len(parents), generator=gen, dtype=torch.float64)
              ).round(decimals=2)
    assert sum(builds) > 3 and not any(not b for b in builds) and pooled_takes > 150


def test_lag_does_not_change_the_boxes_of_a_closing_proof():
    """Each box is split or closed on its own bound against the fixed threshold, so the
    synchronous rounds (lag 1) and the pipelined ones evaluate the same boxes."""
    runs = [_sine_bnb(3.05, lag=lag) for lag in (1, 2, 3)]
    for out in runs:
        assert out.complete and not out.violated and out.upper <= 0
        assert out.stats.boxes_processed > 5000  # many rounds
    assert runs[0].stats.boxes_processed == runs[1].stats.boxes_processed \
        == runs[2].stats.boxes_processed
    assert runs[0].upper == runs[1].upper == runs[2].upper


@pytest.mark.parametrize("offset,budget", [(3.05, 10**9), (3.05, 1500), (2.95, 10**9)])
def test_out_of_order_chunks_give_the_serial_outcome(offset, budget):
    """Chunks on a thread pool finish in random order and two rounds are in flight; the
    outcome (bound, boxes, leaves, counterexample) is the serial one bit for bit: a closing
    proof, a budget-ended one and a violation."""
    serial = _sine_bnb(offset, max_boxes=budget)
    ex = ThreadedExecutor(2)
    try:
        threaded = _sine_bnb(offset, ex, jitter=0.002, max_boxes=budget)
    finally:
        ex.close()
    assert ex.max_in_flight == 2  # the pipeline was on
    _same(serial, threaded)
    assert serial.violated == (offset < DIM)


def test_a_stopped_run_merges_what_it_dispatched():
    """A budget-ended run and a violation: the rounds in flight are merged before the
    outcome, so the bound covers the whole domain (>= the true max 3 - offset) and the box
    budget is overrun by at most the two rounds dispatched before it was reached."""
    for lag in (1, 2, 3):
        out = _sine_bnb(3.05, max_boxes=700, lag=lag)
        assert not out.complete and out.stats.budget_exhausted
        assert out.upper >= DIM - 3.05
        assert 700 <= out.stats.boxes_processed < 700 + 2 * 2 * 32
        hit = _sine_bnb(2.9, lag=lag)
        assert hit.violated and not hit.complete and hit.lower > 0
        assert hit.upper >= DIM - 2.9 and hit.upper >= hit.lower
        assert hit.leaves["status"].count("violated") == 1


@pytest.mark.parametrize("offset", [3.05, 2.95])
def test_rounds_too_large_for_the_gpu_run_in_halves_with_the_same_outcome(offset):
    """A round the device has no memory for (simulated: more than 12 boxes at once) is
    evaluated in halves, in order: the outcome is the one of a run that never ran out."""
    refused, done = [], []

    def small_gpu(lo: torch.Tensor, hi: torch.Tensor) -> BoxEval:
        if len(lo) > 12:
            refused.append(len(lo))
            raise torch.cuda.OutOfMemoryError("CUDA out of memory (simulated)")
        done.append(len(lo))
        return sine_eval(offset, lo, hi)

    plain = _sine_bnb(offset, max_boxes=3000)
    halved = branch_and_bound(*ROOT, small_gpu, ClosingRule(threshold=0.0), Budget(3000),
                              Schedule(batch=32))
    _same(plain, halved)
    assert max(refused) == 64 and max(done) <= 12  # rounds of 2 x 32 children, halved
    assert sum(done) == halved.stats.boxes_processed


def test_one_box_the_gpu_cannot_hold_is_an_error_not_a_verdict():
    def no_memory(lo: torch.Tensor, hi: torch.Tensor) -> BoxEval:
        raise torch.cuda.OutOfMemoryError("CUDA out of memory (simulated)")

    with pytest.raises(torch.cuda.OutOfMemoryError):
        branch_and_bound(*ROOT, no_memory, ClosingRule(threshold=0.0), Budget(3000),
                         Schedule(batch=32))
