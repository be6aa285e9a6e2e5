"""Maximisation B&B with a tolerance that relaxes after a box budget (`coarse_after`)."""

from __future__ import annotations

import torch

from certify.search.bnb import Budget, ClosingRule, Output, Schedule, branch_and_bound
from certify.search.evaluation import BoxEval

F64 = torch.float64


def _evaluate(lo: torch.Tensor, hi: torch.Tensor) -> BoxEval:
    """f(x) = 1 - |x - a|^2 with a mean-value bound: f(c) + sum 2 (|c - a| + r) r (sound)."""
    a = torch.tensor([0.31415926, 0.71828182], dtype=F64)
    c = 0.5 * (lo + hi)
    r = 0.5 * (hi - lo)
    value = 1.0 - ((c - a) ** 2).sum(-1)
    upper = value + (2.0 * ((c - a).abs() + r) * r).sum(-1) * (1 + 1e-12) + 1e-15
    return BoxEval(upper=upper, centre_value=value, score=None)


def test_coarse_after_stops_at_the_coarse_tolerance_after_the_budget() -> None:
    lo, hi = torch.zeros(2, dtype=F64), torch.ones(2, dtype=F64)
    kw = dict(budget=Budget(200_000), schedule=Schedule(batch=16), output=Output(project=None))
    fine = branch_and_bound(lo, hi, _evaluate, ClosingRule(rel_tol=1e-9), **kw)
    relaxed = branch_and_bound(lo, hi, _evaluate,
                               ClosingRule(rel_tol=1e-9, coarse_after=(128, 1e-2)), **kw)
    coarse = branch_and_bound(lo, hi, _evaluate, ClosingRule(rel_tol=1e-2), **kw)
    for out in (fine, relaxed, coarse):
        assert out.complete and out.upper >= 1.0  # sound: the true max is 1, at a
    assert fine.upper <= 1.0 + 2e-9
    assert relaxed.upper <= 1.0 + 1e-2 + 1e-12  # the coarse tolerance, no more
    # the fine phase refines until 128 boxes, then the coarse rule closes the rest
    assert coarse.stats.boxes_processed < relaxed.stats.boxes_processed \
        < fine.stats.boxes_processed
    assert relaxed.stats.boxes_processed <= 128 + 4 * 2 * 16  # a few rounds in flight at most


def test_give_up_stops_only_while_the_bound_is_above_its_level() -> None:
    """`give_up = (N, level)`: a run whose bound after N boxes is above the level stops
    there as budget-spent, still with a sound bound (>= the true max 1); one whose bound is
    already below runs on to the same outcome as without it."""
    lo, hi = torch.zeros(2, dtype=F64), torch.ones(2, dtype=F64)
    kw = dict(budget=Budget(200_000), schedule=Schedule(batch=16), output=Output(project=None))
    plain = branch_and_bound(lo, hi, _evaluate, ClosingRule(rel_tol=1e-9), **kw)
    early = branch_and_bound(lo, hi, _evaluate,
                             ClosingRule(rel_tol=1e-9, give_up=(128, 1.0 + 1e-12)), **kw)
    late = branch_and_bound(lo, hi, _evaluate, ClosingRule(rel_tol=1e-9, give_up=(128, 2.0)),
                            **kw)
    assert plain.complete and not plain.stats.budget_exhausted
    assert early.stats.budget_exhausted and not early.complete
    assert 128 <= early.stats.boxes_processed <= 128 + 4 * 2 * 16
    assert early.upper >= 1.0  # sound
    assert late.complete and late.upper == plain.upper
    assert late.stats.boxes_processed == plain.stats.boxes_processed
