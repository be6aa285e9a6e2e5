"""The branch-and-bound driver as a class whose state is named (`certify.search.bnb`): the
closing rule's levels, the leaves kept for the report, a run's state after it stops, and the
box bound's stage counts summed over the merged rounds (the same on a chunked executor as
serially)."""

from __future__ import annotations

import math

import pytest
import torch

from certify.arith.boxes import Box
from certify.progress import NullProgress
from certify.prove.mpdi import prove_mpdi
from certify.search.bnb import (
    BranchAndBound,
    Budget,
    ClosingRule,
    Leaves,
    Output,
    Schedule,
    branch_and_bound,
)
from certify.search.distributed.executor import SerialExecutor
from certify.search.evaluation import BoxEval, add_counts, join

from .test_bnb_rounds import ChunkedSerial, _small_vdp

F64 = torch.float64


def test_closing_levels_of_decision_and_maximisation() -> None:
    decision = ClosingRule(threshold=0.0)
    assert decision.decision and decision.level(best=5.0, processed=0) == 0.0
    maxi = ClosingRule(tol=0.1, rel_tol=0.01, coarse_after=(100, 0.5))
    assert not maxi.decision
    assert maxi.level(best=-math.inf, processed=0) == -math.inf  # nothing found yet
    assert maxi.level(best=2.0, processed=99) == 2.0 + max(0.1, 0.02)
    assert maxi.level(best=2.0, processed=100) == 2.0 + 1.0  # relaxed to the coarse tolerance
    # a decision with a tolerance closes at the larger of the two levels
    assert ClosingRule(threshold=0.0, tol=0.5).level(best=1.0, processed=0) == 1.5


def test_leaves_keep_unknown_and_violated_before_the_smallest_closed() -> None:
    leaves = Leaves((0, 1), 3, keep=4)
    lo = torch.zeros(10, 3, dtype=F64)
    hi = torch.linspace(0.1, 1.0, 10, dtype=F64)[:, None].expand(10, 3).clone()
    leaves.record(lo, hi, 0)
    leaves.record(lo[:1], hi[:1] * 0.01, 2)  # a tiny unknown box
    leaves.record(lo[:1], lo[:1], 1)  # the violation point
    out = leaves.result()
    assert len(out["status"]) == 4
    assert sorted(out["status"]) == ["proved", "proved", "unknown", "violated"]
    widest = [h[0] for h, s in zip(out["hi"], out["status"]) if s == "proved"]
    assert sorted(widest) == [0.9, 1.0]
    assert Leaves(None, 3, 4).result() == {"lo": [], "hi": [], "status": []}
    assert Leaves((0, 1), 1, 4).px is None  # one dimension: nothing to project


def _width_bound(lo: torch.Tensor, hi: torch.Tensor) -> BoxEval:
    """Bound width - 1/4 (closes boxes of width <= 1/4), centre value -1, one stage count."""
    width = (hi - lo).amax(-1)
    return BoxEval(upper=width - 0.25, centre_value=-torch.ones_like(width),
                   counts={"width": {"boxes": len(lo), "closed": int((width <= 0.25).sum())}})


def test_a_run_leaves_its_state_readable() -> None:
    """The class run and the function agree; after the run the named state says what
    happened: nothing open, every box counted, the counts summed over the rounds."""
    root = (torch.zeros(2, dtype=F64), torch.ones(2, dtype=F64))
    schedule = Schedule(batch=64, first_round=4, max_depth=80, lag=2)
    run = BranchAndBound(*root, _width_bound, ClosingRule(threshold=0.0), Budget(10_000),
                         schedule, Output(progress=NullProgress(), task="t", keep_leaves=100))
    out = run.run()
    same = branch_and_bound(*root, _width_bound, ClosingRule(threshold=0.0), Budget(10_000),
                            Schedule(batch=64, first_round=4))
    assert out.complete and out.upper == same.upper and out.upper <= 0
    assert out.stats.boxes_processed == same.stats.boxes_processed == 28 == run.processed
    assert len(run.frontier) == 0 and not run.in_flight and not run.violated
    assert math.isclose(run.closed_vol, 1.0) and run.stuck == 0
    assert run.stages == {"width": {"boxes": 28, "closed": 16}} == out.stats.stages


def test_counts_are_joined_and_added_name_by_name() -> None:
    a = BoxEval(torch.zeros(2, dtype=F64), torch.zeros(2, dtype=F64),
                counts={"s": {"boxes": 2, "closed": 1}})
    b = BoxEval(torch.zeros(1, dtype=F64), torch.zeros(1, dtype=F64),
                counts={"s": {"boxes": 1, "closed": 0}, "t": {"boxes": 1, "closed": 1}})
    c = BoxEval(torch.zeros(1, dtype=F64), torch.zeros(1, dtype=F64))
    assert join([a, b, c]).counts == {"s": {"boxes": 3, "closed": 1},
                                      "t": {"boxes": 1, "closed": 1}}
    assert join([c, c]).counts is None
    assert add_counts({}, None) == {}


@pytest.mark.slow
def test_stage_counts_of_a_chunked_run_are_those_of_the_serial_run() -> None:
    """The box bound's counts travel with each chunk's evaluation and are summed as the
    rounds merge: a chunked executor reports what the serial run does."""
    prob = _small_vdp()
    serial = prove_mpdi(prob, max_boxes=3000, executor=SerialExecutor(), batch=16)
    chunked = prove_mpdi(prob, max_boxes=3000, executor=ChunkedSerial(),
                         batch=16)
    assert serial.stats.stages and serial.stats.stages == chunked.stats.stages
    assert serial.stats.boxes_processed == chunked.stats.boxes_processed


def test_seeds_are_evaluated_first_and_not_counted_as_processed() -> None:
    """A seed point above the threshold is a violation before any round is merged."""
    root = (torch.zeros(2, dtype=F64), torch.ones(2, dtype=F64))

    def evaluate(lo: torch.Tensor, hi: torch.Tensor) -> BoxEval:
        c = 0.5 * (lo + hi)
        return BoxEval(upper=torch.full((len(lo),), 2.0, dtype=F64), centre_value=c[:, 0] - 0.5)

    pt = torch.tensor([[0.9, 0.1]], dtype=F64)
    out = branch_and_bound(*root, evaluate, ClosingRule(threshold=0.0), Budget(10_000),
                           Schedule(batch=4),
                           seeds=Box(pt, pt.clone(), torch.zeros(1, dtype=torch.long)))
    assert out.violated and out.lower == 0.4
    assert torch.equal(out.best_point, pt[0])
    assert out.stats.boxes_processed == 4  # the first round only (merged before stopping)
