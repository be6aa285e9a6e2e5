"""`certify.search.tree_estimate`'s random descents follow the proof's own tree: each point ends in
a leaf the decision proof itself closes, at the same depth, and the leaf estimate is near
the proof's leaf count; an UNKNOWN proof reports the estimate."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
import torch

from bench.instances import InstanceSpec, make_instance
from certify.prove.mpdi import mpdi_decision, prove_mpdi
from certify.results import ProofStats, Status
from certify.search.bnb import Budget, ClosingRule, Schedule, branch_and_bound
from certify.search.tree_estimate import leaf_depths, summarize


@pytest.mark.slow
def test_random_descents_end_in_the_proofs_own_leaves() -> None:
    problem, _ = make_instance(InstanceSpec(2, 10, 2.0, 2, 0.02, 0))
    setup = mpdi_decision(problem, float(problem.lam))
    closed: list[tuple[torch.Tensor, torch.Tensor]] = []

    def recording(lo: torch.Tensor, hi: torch.Tensor):
        out = setup.evaluate(lo, hi)
        shut = (out.upper <= 0.0) & torch.isfinite(out.upper)
        closed.append((lo[shut], hi[shut]))
        return out

    proof = branch_and_bound(setup.lo, setup.hi, recording, ClosingRule(threshold=0.0),
                             Budget(10**6), Schedule(first_round=setup.first_round))
    assert proof.complete
    leaf_lo = torch.cat([c[0] for c in closed])
    leaf_hi = torch.cat([c[1] for c in closed])
    root_volume = float((setup.hi - setup.lo).prod())
    leaf_depth = torch.round(torch.log2(root_volume / (leaf_hi - leaf_lo).prod(-1))).long()
    gen = torch.Generator().manual_seed(1)
    z = setup.lo + (setup.hi - setup.lo) * torch.rand(256, len(setup.lo), generator=gen,
                                                      dtype=torch.float64)
    depth, evaluations = leaf_depths(setup.evaluate, setup.lo, setup.hi, setup.first_round, z)
    assert bool((depth >= 0).all()) and evaluations >= len(z)
    inside = ((z[:, None] >= leaf_lo[None]) & (z[:, None] <= leaf_hi[None])).all(-1)
    same = (inside & (leaf_depth[None] == depth[:, None])).any(-1)
    assert bool(same.all()), int((~same).sum())
    est = summarize(depth, evaluations)
    assert 0.5 < est.leaves / len(leaf_lo) < 2.0, (est, len(leaf_lo))
    assert math.isfinite(est.rel_stderr) and est.stuck == 0


def test_stuck_points_are_left_out_of_the_estimate() -> None:
    est = summarize(torch.tensor([3, 5, -1, -1]), 10)
    assert est.stuck == 2 and est.leaves == (8 + 32) / 2 and est.boxes == 2 * est.leaves
    none = summarize(torch.tensor([-1, -1]), 4)
    assert none.stuck == 2 and math.isnan(none.boxes)


@pytest.mark.slow
def test_an_unknown_proof_reports_how_many_boxes_a_complete_one_takes() -> None:
    problem, _ = make_instance(InstanceSpec(2, 10, 2.0, 2, 0.02, 0))
    cut = prove_mpdi(problem, max_boxes=200)
    assert cut.status is Status.UNKNOWN
    whole = prove_mpdi(problem)
    assert whole.status is Status.PROVED and whole.stats.estimated_boxes is None
    est = cut.stats.estimated_boxes
    assert est is not None and 0.5 < est / whole.stats.boxes_processed < 2.0, (
        est, whole.stats.boxes_processed)
    assert "complete proof" in cut.message


@pytest.mark.slow
def test_the_mpdi_check_says_how_far_an_unfinished_proof_is() -> None:
    """The MPDI check with a box budget too small: UNKNOWN, and its message and reported
    numbers carry the estimate."""
    from certify.checks.mpdi import CHECK, check_mpdi
    from certify.settings import VerifySettings

    problem, _ = make_instance(InstanceSpec(2, 10, 2.0, 2, 0.02, 0))
    res = check_mpdi(problem, VerifySettings(max_boxes=200, grid_points=2000))
    assert res.status is Status.UNKNOWN
    assert "a complete proof would evaluate about" in res.message
    cert = SimpleNamespace(settings={})
    labels = {q.label: q.value for q in CHECK.present(res, cert).numbers}
    assert labels["boxes a complete proof needs (estimate)"] == res.proof.estimated_boxes > 256


@pytest.mark.slow
def test_more_descents_follow_until_the_target_or_a_budget_in_boxes() -> None:
    """Batches of descents follow while the standard error is above the target; the caps are
    in descents and box evaluations (never seconds), so the estimate is reproducible."""
    from certify.search.tree_estimate import estimate_tree

    problem, _ = make_instance(InstanceSpec(2, 10, 2.0, 2, 0.02, 0))
    s = mpdi_decision(problem, float(problem.lam))
    args = (s.evaluate, s.lo, s.hi, s.first_round, 64)
    one = estimate_tree(*args)
    assert one.points == 64
    capped = estimate_tree(*args, target_rel_stderr=0.0, max_points=192)
    assert capped.points == 192 and capped.rel_stderr < one.rel_stderr
    again = estimate_tree(*args, target_rel_stderr=0.0, max_points=192)
    assert again == capped
    boxes = estimate_tree(*args, target_rel_stderr=0.0, max_points=10**6,
                          max_evaluations=one.evaluations + 1)
    assert boxes.points == 64
    reached = estimate_tree(*args, target_rel_stderr=one.rel_stderr * 1.01, max_points=10**6)
    assert reached.points == 64


def test_the_report_shows_the_estimate_only_for_an_unfinished_proof() -> None:
    from reports.content import fmt_seconds
    from reports.sections import _estimate_rows

    done = ProofStats(estimated_boxes=None, estimate_rel_stderr=None,
                      boxes_per_second=1000.0, boxes_processed=500)
    assert _estimate_rows(done) == []
    cut = ProofStats(estimated_boxes=4500.0, estimate_rel_stderr=0.1,
                     boxes_per_second=1000.0, boxes_processed=500)
    rows = dict(_estimate_rows(cut))
    assert rows["Boxes a complete proof needs (estimate)"].startswith("4.5e+03")
    assert rows["Time it needs at this speed (estimate)"] == fmt_seconds(4.0)  # 4000 at 1000/s


def test_the_forecast_names_the_budget_and_warns_only_far_above_it() -> None:
    from certify.search.tree_estimate import FAR_ABOVE, forecast_text

    far = forecast_text(3.2e7, 0.31, 200_000)
    assert far.startswith("tree estimate: a complete proof evaluates about 3.2e+07 boxes")
    assert "+-31%" in far and "the budget is 200,000 boxes" in far
    assert "far above the budget" in far and "will likely be INCONCLUSIVE" in far
    near = forecast_text(FAR_ABOVE * 200_000 * 0.99, 0.2, 200_000)
    assert "budget is 200,000 boxes" in near and "INCONCLUSIVE" not in near
    for none in (None, math.nan, math.inf, 0.0):
        assert forecast_text(none, 0.1, 1000) == ""


@pytest.mark.slow
def test_the_mpdi_check_forecasts_the_tree_before_the_proof() -> None:
    """The MPDI check notes the estimate against the budget before its proof: far above a
    budget of 20 boxes (INCONCLUSIVE expected, and it is UNKNOWN), not far above 10^6 (and
    the proof finishes)."""
    from certify.checks.mpdi import check_mpdi
    from certify.progress import NullProgress
    from certify.settings import VerifySettings

    class Notes(NullProgress):
        def __init__(self) -> None:
            self.lines: list[str] = []

        def note(self, text: str) -> None:
            self.lines.append(text)

    problem, _ = make_instance(InstanceSpec(2, 10, 2.0, 2, 0.02, 0))
    small = Notes()
    res = check_mpdi(problem, VerifySettings(max_boxes=20, grid_points=2000), progress=small)
    assert res.status is Status.UNKNOWN
    (line,) = [t for t in small.lines if t.startswith("MPDI tree estimate")]
    assert "the budget is 20 boxes" in line and "INCONCLUSIVE" in line
    large = Notes()
    res = check_mpdi(problem, VerifySettings(max_boxes=10**6, grid_points=2000),
                     progress=large)
    assert res.status is Status.PROVED
    (line,) = [t for t in large.lines if t.startswith("MPDI tree estimate")]
    assert "the budget is 1,000,000 boxes" in line and "INCONCLUSIVE" not in line
