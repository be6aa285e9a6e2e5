"""Branch and bound in deterministic rounds: a chunked executor gives the serial result."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from certify.model.network import GainNetwork
from certify.model.problem import Problem
from certify.prove.mpdi import prove_mpdi
from certify.results import Status
from certify.search.distributed.executor import SerialExecutor
from certify.spec.system import load_system
from tests.planted import planted_problem


class ChunkedSerial(SerialExecutor):
    """Serial, but claims 3 workers: branch and bound then cuts every round into chunks and
    goes through `map_chunks` with the picklable task, as it would on Dask."""

    workers = 3

    def __init__(self) -> None:
        self.calls = 0

    def map_chunks(self, fn, payload, items):  # type: ignore[override]
        self.calls += 1
        return super().map_chunks(fn, payload, items)


def _small_vdp() -> Problem:
    """vdp with an LMI metric and gain plus a small random network: needs many rounds."""
    torch.manual_seed(0)
    P = np.array([[69.5852, -6.6789], [-6.6789, 1.6504]])
    net = GainNetwork(2, 1, (6, 6), K=torch.tensor([[8.1278], [47.7998]]))
    with torch.no_grad():
        net.layers[-1].weight.mul_(0.3)
    return Problem(load_system("vdp"), net, 1.1, P)


@pytest.mark.slow
def test_chunked_rounds_match_the_serial_run() -> None:
    prob = _small_vdp()
    serial = prove_mpdi(prob, max_boxes=3000, executor=SerialExecutor(), batch=16)
    ex = ChunkedSerial()
    chunked = prove_mpdi(prob, max_boxes=3000, executor=ex, batch=16)
    assert serial.stats.boxes_processed > 100  # several rounds ran
    assert ex.calls > 3
    assert serial.status is chunked.status
    assert serial.stats.boxes_processed == chunked.stats.boxes_processed
    assert serial.upper == chunked.upper


def test_chunked_rounds_still_find_a_planted_violation() -> None:
    out = prove_mpdi(planted_problem("corner"), executor=ChunkedSerial())
    assert out.status is Status.VIOLATED


def test_budgeted_decision_rounds_close_the_easy_region() -> None:
    """A region that never closes (bound 1 > 0) must not starve the rest: half of every
    round goes to the boxes nearest to closing, so a budgeted run proves the easy half."""
    from certify.search.bnb import Budget, ClosingRule, Schedule, branch_and_bound
    from certify.search.evaluation import BoxEval

    def evaluate(lo: torch.Tensor, hi: torch.Tensor) -> BoxEval:
        width = (hi - lo)[:, 0]
        hard = lo[:, 0] < 0.5
        upper = torch.where(hard, torch.ones_like(width), width - 0.1)
        return BoxEval(upper=upper, centre_value=-torch.ones_like(width))

    out = branch_and_bound(torch.zeros(1, dtype=torch.float64), torch.ones(1, dtype=torch.float64),
                           evaluate, ClosingRule(threshold=0.0), Budget(400),
                           Schedule(batch=4, max_depth=200))
    assert not out.complete and not out.violated
    assert out.upper == 1.0
    assert 0.49 <= out.stats.proved_volume_fraction <= 0.5


def test_first_round_sets_the_coarsest_boxes() -> None:
    """A bound that closes boxes of width <= 1/4 on [0, 1]^2: a first round of 16 boxes closes
    at once (16 boxes), the default first round of `batch` boxes spends them all, and a first
    round of 4 refines each box once (4 + 8 + 16)."""
    from certify.search.bnb import Budget, ClosingRule, Schedule, branch_and_bound
    from certify.search.evaluation import BoxEval

    def evaluate(lo: torch.Tensor, hi: torch.Tensor) -> BoxEval:
        width = (hi - lo).amax(-1)
        return BoxEval(upper=width - 0.25, centre_value=-torch.ones_like(width))

    root = (torch.zeros(2, dtype=torch.float64), torch.ones(2, dtype=torch.float64))
    counts = {}
    for first in (None, 16, 4):
        out = branch_and_bound(*root, evaluate, ClosingRule(threshold=0.0), Budget(10_000),
                               Schedule(batch=64, first_round=first))
        assert out.complete and out.upper <= 0
        counts[first] = out.stats.boxes_processed
    assert counts == {None: 64, 16: 16, 4: 28}
