"""The branch-and-bound trees are pinned: on a few instances (decision proved, violated and
cut by its box budget with a lag of 1, maximisation with seeds and a coarse tolerance,
give_up, the depth limit, a far wall-clock cap) the boxes of every evaluation, in order, and
the outcome's numbers hash to the digests recorded before `branch_and_bound` took its
arguments as objects (`ClosingRule`, `Budget`, `Schedule`, `Output`). A change of the driver
that moves a single box, or a bound in its last bit, fails here.

The instance is a polynomial with its natural interval bound: additions, products and
min/max only, so its values are the same bit for bit on every machine."""

from __future__ import annotations

import hashlib

import pytest
import torch

from certify.arith.boxes import Box
from certify.search.bnb import Budget, ClosingRule, Output, Schedule, branch_and_bound
from certify.search.evaluation import BoxEval

F64 = torch.float64
ROOT = (torch.tensor([-1.0, -1.0], dtype=F64), torch.tensor([1.0, 1.0], dtype=F64))


def _square(lo: torch.Tensor, hi: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The interval of t^2 over [lo, hi], elementwise."""
    low = torch.where((lo <= 0) & (hi >= 0), torch.zeros_like(lo),
                      torch.minimum(lo * lo, hi * hi))
    return low, torch.maximum(lo * lo, hi * hi)


def ridge(shift: float):
    """f = x y / 5 - (x^2 + y^2 - 1/4)^2 - shift over boxes (its maximum 0.0275 - shift
    lies on two arcs of the circle, so the tree follows them), with its natural interval
    bound and a split score."""

    def evaluate(lo: torch.Tensor, hi: torch.Tensor) -> BoxEval:
        c = 0.5 * (lo + hi)
        x, y = c[:, 0], c[:, 1]
        s = x * x + y * y - 0.25
        value = 0.2 * x * y - s * s - shift
        x2, X2 = _square(lo[:, 0], hi[:, 0])
        y2, Y2 = _square(lo[:, 1], hi[:, 1])
        s2, _ = _square(x2 + y2 - 0.25, X2 + Y2 - 0.25)
        xy = torch.stack([lo[:, 0] * lo[:, 1], lo[:, 0] * hi[:, 1], hi[:, 0] * lo[:, 1],
                          hi[:, 0] * hi[:, 1]], 1).amax(1)
        score = (hi - lo) * torch.stack([y.abs() + 4 * x.abs(), x.abs() + 4 * y.abs()], 1)
        return BoxEval(upper=0.2 * xy - s2 - shift, centre_value=value, score=score)

    return evaluate


SEED = Box(torch.tensor([[0.3, 0.2]], dtype=F64), torch.tensor([[0.3, 0.2]], dtype=F64),
           torch.zeros(1, dtype=torch.long))

#: name: (shift, rule, budget, schedule, seeds, digest, boxes); the digests were recorded
#: with the driver before its arguments became objects
CASES = {
    "proved": (0.03, ClosingRule(threshold=0.0), Budget(20_000),
               Schedule(batch=64, first_round=16), None, "8fa48d972d9bbe80", 436),
    "capped far": (0.03, ClosingRule(threshold=0.0), Budget.capped(20_000, seconds=1e6),
                   Schedule(batch=64, first_round=16), None, "8fa48d972d9bbe80", 436),
    "violated": (0.0274, ClosingRule(threshold=0.0), Budget(20_000), Schedule(batch=64),
                 None, "b8b068c072646264", 388),
    "budget, lag 1": (0.028, ClosingRule(threshold=0.0), Budget(1001),
                      Schedule(batch=32, lag=1), None, "501ec5ae9807249e", 1000),
    "maximise": (0.0, ClosingRule(rel_tol=1e-4, tol=1e-12, coarse_after=(4000, 1e-2)),
                 Budget(20_000), Schedule(batch=128), SEED, "c27cf7b4dcfc4e11", 4096),
    "give up": (0.0, ClosingRule(rel_tol=1e-9, give_up=(512, 0.028)), Budget(20_000),
                Schedule(batch=64), None, "1737dfe95210cad7", 528),
    "depth limit": (0.0276, ClosingRule(threshold=0.0, stop_on_violation=False),
                    Budget(20_000), Schedule(batch=16, max_depth=12), None,
                    "6496786200653785", 372),
}


@pytest.mark.parametrize("name", list(CASES))
def test_the_tree_is_the_one_recorded(name: str) -> None:
    shift, rule, budget, schedule, seeds, digest, boxes = CASES[name]
    evaluate = ridge(shift)
    h = hashlib.sha256()

    def recording(lo: torch.Tensor, hi: torch.Tensor) -> BoxEval:
        h.update(lo.numpy().tobytes())
        h.update(hi.numpy().tobytes())
        return evaluate(lo, hi)

    out = branch_and_bound(*ROOT, recording, rule, budget, schedule, Output(), seeds=seeds)
    st = out.stats
    h.update(repr((out.upper, out.lower, out.violated, out.complete, out.stuck,
                   st.boxes_processed, st.max_depth, st.proved_volume_fraction,
                   st.budget_exhausted)).encode())
    assert st.boxes_processed == boxes
    assert h.hexdigest()[:16] == digest
