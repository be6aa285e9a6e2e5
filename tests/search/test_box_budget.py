"""The box budget is work, honoured exactly: a run evaluates at most `max_boxes` boxes (its
first round and its last clipped to what is left), and without a wall-clock cap nothing
reads the clock: the same boxes and bounds however slow the machine."""

from __future__ import annotations

import math
import time

import pytest
import torch

from certify.prove.mpdi import prove_mpdi
from certify.results import Status
from certify.search.bnb import Budget, ClosingRule, Schedule, branch_and_bound
from certify.search.evaluation import BoxEval


def _never_closes(lo: torch.Tensor, hi: torch.Tensor) -> BoxEval:
    """A sound bound of f = -1 that never reaches the threshold 0: the box's widest side."""
    w = (hi - lo).amax(-1)
    return BoxEval(upper=w, centre_value=-torch.ones_like(w), score=hi - lo)


@pytest.mark.parametrize("budget", [1, 3, 4, 5, 100, 1000, 1025, 5000])
def test_a_run_never_evaluates_more_than_its_box_budget(budget):
    root = (torch.zeros(3, dtype=torch.float64), torch.ones(3, dtype=torch.float64))
    out = branch_and_bound(*root, _never_closes, ClosingRule(threshold=0.0), Budget(budget),
                           Schedule(batch=1024))
    assert 0 < out.stats.boxes_processed <= budget
    assert out.stats.budget_exhausted and not out.stats.stopped_by_cap and not out.complete
    # it stops only when no round of two children fits
    assert budget - out.stats.boxes_processed < 2 or out.stats.boxes_processed == budget


def test_a_small_budget_is_honoured_by_the_prover():
    """`--max-boxes 4`: four boxes evaluated, not a first round of 256 or 1024."""
    from tests.search.test_bnb_rounds import _small_vdp

    out = prove_mpdi(_small_vdp(), max_boxes=4)
    assert out.stats.boxes_processed <= 4
    assert out.status is Status.UNKNOWN and "max_boxes=4" in out.message


def test_without_a_cap_the_clock_decides_nothing(monkeypatch):
    """A clock that jumps an hour at every reading changes neither the boxes nor the bound."""
    from tests.search.test_bnb_rounds import _small_vdp

    problem = _small_vdp()
    steady = prove_mpdi(problem, max_boxes=3000, batch=16, estimate_points=0)
    real = time.perf_counter
    jumps = [0.0]

    def racing() -> float:
        jumps[0] += 3600.0
        return real() + jumps[0]

    monkeypatch.setattr(time, "perf_counter", racing)
    raced = prove_mpdi(problem, max_boxes=3000, batch=16, estimate_points=0)
    monkeypatch.undo()
    assert raced.stats.boxes_processed == steady.stats.boxes_processed
    assert raced.status is steady.status and raced.upper == steady.upper
    assert raced.boxes == steady.boxes and not raced.stats.stopped_by_cap


def test_a_cap_that_passed_stops_the_run_and_says_so():
    root = (torch.zeros(2, dtype=torch.float64), torch.ones(2, dtype=torch.float64))
    out = branch_and_bound(*root, _never_closes, ClosingRule(threshold=0.0),
                           Budget(10**6, deadline=time.perf_counter() - 1.0), Schedule(batch=64))
    assert out.stats.stopped_by_cap and out.stats.budget_exhausted
    assert out.stats.boxes_processed < 10**6 and not out.complete
    assert math.isfinite(out.upper)  # the first round is evaluated anyway (cheap): a bound
