"""The optional wall-clock cap (`seconds`, `deadline`) holds however slow a box is: the rounds
are evaluated against the clock (`certify.search.bnb.RoundClock`), a round cut short leaves its
unevaluated boxes open with their parent's bound (never closed, not counted), an executor's
round not back by the deadline is cancelled, the set-up of a proof counts in its cap, and the
tree estimate keeps to its own time limit. A run its cap does not bind evaluates the same
calls as with no clock.

The assertions on time are upper bounds with a generous margin (the machine is shared); the
slow evaluations sleep, so they cost the same under any load."""

from __future__ import annotations

import math
import time
from concurrent.futures import ThreadPoolExecutor
from concurrent.futures import wait as futures_wait

import numpy as np
import pytest
import torch

from certify.model.network import GainNetwork
from certify.model.problem import Problem
from certify.prove.mpdi import prove_mpdi
from certify.results import Status
from certify.search.bnb import Budget, ClosingRule, RoundClock, Schedule, branch_and_bound
from certify.search.distributed.executor import SerialExecutor
from certify.search.evaluation import BoxEval
from tests.planted import linear_system

MARGIN = 20.0  # seconds allowed past a budget (the rounds themselves overrun by < 1 s)


def width_eval(lo: torch.Tensor, hi: torch.Tensor) -> BoxEval:
    """A 'bound' that never closes at threshold 0: the box's widest side (f = -1 everywhere,
    so any positive number is a sound upper bound of it)."""
    w = (hi - lo).amax(-1)
    return BoxEval(upper=w, centre_value=-torch.ones_like(w), score=hi - lo)


def sleepy(per_box: float, calls: list[int] | None = None):
    def evaluate(lo: torch.Tensor, hi: torch.Tensor) -> BoxEval:
        if calls is not None:
            calls.append(len(lo))
        time.sleep(per_box * len(lo))
        return width_eval(lo, hi)

    return evaluate


def _boxes(n: int, d: int = 2) -> tuple[torch.Tensor, torch.Tensor]:
    lo = torch.rand(n, d, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    return lo, lo + 0.1


def test_a_round_that_fits_is_one_call_as_without_a_clock() -> None:
    calls: list[int] = []
    lo, hi = _boxes(500)
    clock = RoundClock(sleepy(0.0, calls), time.perf_counter() + 3600.0, box_seconds=1e-6)
    out = clock(lo, hi)
    assert calls == [500] and out.done is None and not clock.expired
    # no measurement yet and a budget no box cost could overrun: no timing probes either
    calls.clear()
    clock = RoundClock(sleepy(0.0, calls), time.perf_counter() + 1e9)
    clock(lo, hi)
    assert calls == [500]


def test_a_slow_round_is_cut_at_the_deadline() -> None:
    """500 boxes at 20 ms: 10 s; with 1 s left, chunks sized to the time left, then the rest
    unevaluated (NaN bounds and centre values, `done` False)."""
    calls: list[int] = []
    lo, hi = _boxes(500)
    t = time.perf_counter()
    clock = RoundClock(sleepy(0.02, calls), t + 1.0)
    out = clock(lo, hi)
    assert time.perf_counter() - t < 1.0 + MARGIN
    assert clock.expired and out.done is not None
    done = int(out.done.sum())
    assert 0 < done < 500 and bool(out.done[:done].all()) and not bool(out.done[done:].any())
    assert torch.equal(out.upper[:done], width_eval(lo[:done], hi[:done]).upper)
    assert bool(out.upper[done:].isnan().all()) and bool(out.centre_value[done:].isnan().all())
    assert len(calls) > 3 and max(calls) < 500  # the two probes, then chunks


def test_a_slow_first_round_keeps_the_budget() -> None:
    """A first round of 1024 boxes at 20 ms each (20 s) under a 2 s budget: the run stops
    near the deadline with the first round unfinished: no box closed, the bound unknown."""
    t = time.perf_counter()
    out = branch_and_bound(torch.zeros(2, dtype=torch.float64), torch.ones(2, dtype=torch.float64),
                           sleepy(0.02), ClosingRule(threshold=0.0),
                           Budget.capped(10**6, seconds=2.0), Schedule(batch=1024))
    assert time.perf_counter() - t < 2.0 + MARGIN
    assert not out.complete and out.stats.budget_exhausted
    assert out.upper == math.inf  # first-round boxes not evaluated have no bound at all
    assert 0 < out.stats.boxes_processed < 1024


def test_boxes_a_round_did_not_evaluate_keep_their_parents_bound() -> None:
    """An evaluation that leaves boxes undone (as a round cut by the clock does): they stay
    open with the bound of the box they were split from, are not counted as processed, and
    the run stops there, UNKNOWN."""
    rounds: list[int] = []

    def partial(lo: torch.Tensor, hi: torch.Tensor) -> BoxEval:
        area = (hi - lo).prod(-1)  # a sound bound of f = -1 that halves with each split
        rounds.append(len(lo))
        done = torch.arange(len(lo)) < (10 if len(rounds) == 2 else len(lo))
        nan = torch.full_like(area, math.nan)
        return BoxEval(upper=torch.where(done, area, nan),
                       centre_value=torch.where(done, -1.0, nan), score=hi - lo,
                       done=None if bool(done.all()) else done)

    out = branch_and_bound(torch.zeros(2, dtype=torch.float64), torch.ones(2, dtype=torch.float64),
                           partial, ClosingRule(threshold=0.0), Budget(10**6), Schedule(batch=16))
    assert rounds == [16, 32]  # nothing dispatched after the cut round
    assert out.stats.boxes_processed == 16 + 10
    assert not out.complete and out.stats.budget_exhausted
    # first-round boxes of area 1/16, children 1/32: the 22 children not evaluated carry
    # their parent's 1/16 (an unknown bound would make it inf)
    assert out.upper == 1 / 16
    assert out.leaves["status"] == ["unknown"] * 32  # nothing closed, all 32 children open


def test_an_executors_round_not_back_by_the_deadline_is_cancelled() -> None:
    """On an executor (chunks in threads, as on Dask) a round is waited for until the
    deadline (a first round at least a few seconds), then cancelled and left unevaluated."""
    pool = ThreadPoolExecutor(2)

    class Handle:
        def __init__(self, futures) -> None:
            self.futures = futures
            self.cancelled = False

        def wait(self, seconds: float) -> bool:
            return not futures_wait(self.futures, timeout=seconds).not_done

        def result(self):
            return [f.result() for f in self.futures]

        def cancel(self) -> None:
            self.cancelled = True
            for f in self.futures:
                f.cancel()

    class Threaded(SerialExecutor):
        remote = True
        workers = 2

        def submit_chunks(self, fn, payload, items):  # type: ignore[override]
            return Handle([pool.submit(fn, payload, *it) for it in items])

    def chunk(payload, lo, hi):
        time.sleep(0.02 * len(lo))  # 10 s a chunk of the first round
        return width_eval(lo, hi)

    t = time.perf_counter()
    out = branch_and_bound(torch.zeros(2, dtype=torch.float64), torch.ones(2, dtype=torch.float64),
                           width_eval, ClosingRule(threshold=0.0),
                           Budget.capped(10**6, seconds=0.5), Schedule(batch=1024),
                           executor=Threaded(), remote=(chunk, {}))
    assert time.perf_counter() - t < 0.5 + MARGIN
    assert out.stats.boxes_processed == 0 and out.upper == math.inf and not out.complete
    pool.shutdown(wait=False, cancel_futures=True)


@pytest.mark.slow
def test_a_run_the_budget_does_not_bind_is_the_run_without_a_clock() -> None:
    """The same boxes, bounds and verdict bit for bit as with an unlimited budget."""
    from tests.search.test_bnb_rounds import _small_vdp

    prob = _small_vdp()
    budgeted = prove_mpdi(prob, seconds=120.0, max_boxes=3000, batch=16)
    unlimited = prove_mpdi(prob, seconds=1e9, max_boxes=3000, batch=16)
    assert budgeted.stats.boxes_processed == unlimited.stats.boxes_processed > 100
    assert budgeted.status is unlimited.status
    assert budgeted.upper == unlimited.upper and budgeted.lower == unlimited.lower
    assert budgeted.boxes == unlimited.boxes


@pytest.mark.slow
def test_a_tiny_budget_on_a_cheap_problem_still_bounds_its_first_round() -> None:
    """The set-up and a first round of at most a few seconds run whatever the budget: a
    budget of a millisecond gives the first round's bound, not none."""
    from certify.prove.side import bound_dk_dy
    from tests.search.test_bnb_rounds import _small_vdp

    prob = _small_vdp()
    out = prove_mpdi(prob, seconds=1e-3)
    assert math.isfinite(out.upper) and out.stats.boxes_processed > 0
    assert out.status is not Status.VIOLATED
    assert bound_dk_dy(prob, seconds=1e-3)[0] is not None


def slow_problem() -> Problem:
    """A 4-state observer with a deep, wide gelu gain: a box costs tens of milliseconds, so the
    first round of 1024 boxes alone takes far longer than the budget below (and the set-up of
    its bounds several seconds)."""
    n = 4
    A = -np.eye(n) + 0.3 * np.diag(np.ones(n - 1), 1) - 0.3 * np.diag(np.ones(n - 1), -1)
    C = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]])
    system = linear_system(A, C, lam=0.25)
    torch.manual_seed(0)
    net = GainNetwork(n, 2, (128,) * 6, activation="gelu").double().requires_grad_(False)
    return Problem(system, net, 0.25, np.eye(n))


def test_a_three_second_proof_budget_holds_on_a_slow_network() -> None:
    prob = slow_problem()
    t = time.perf_counter()
    out = prove_mpdi(prob, seconds=3.0)
    took = time.perf_counter() - t
    # 3 s, the estimate's own limit (2 s) and the margin
    assert took < 3.0 + 2.0 + 15.0, took
    assert out.status is Status.UNKNOWN and out.stats.budget_exhausted
    assert out.stats.stopped_by_cap and "wall-clock cap" in out.message


def test_the_tree_estimate_keeps_its_time_limit() -> None:
    from certify.prove.mpdi import mpdi_decision
    from certify.search.tree_estimate import estimate_tree
    from tests.search.test_bnb_rounds import _small_vdp

    problem = _small_vdp()
    s = mpdi_decision(problem, float(problem.lam))
    slow = sleepy_wrap(s.evaluate, 0.01)  # 10 ms a box: a batch of 64 descents takes seconds
    t = time.perf_counter()
    est = estimate_tree(slow, s.lo, s.hi, s.first_round, 64, seconds=0.5)
    assert time.perf_counter() - t < 0.5 + MARGIN
    assert est.points == 0 and math.isnan(est.boxes)  # no batch finished: no estimate
    # sized to the limit: fewer descents per batch, and an estimate
    est = estimate_tree(s.evaluate, s.lo, s.hi, s.first_round, 256, seconds=60.0,
                        box_seconds=1.0, levels=10)
    assert est.points == 16 and math.isfinite(est.boxes)


def sleepy_wrap(evaluate, per_box: float):
    def slow(lo: torch.Tensor, hi: torch.Tensor) -> BoxEval:
        time.sleep(per_box * len(lo))
        return evaluate(lo, hi)

    return slow
