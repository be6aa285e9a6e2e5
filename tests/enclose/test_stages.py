"""The box bound built from stages (`certify.enclose.stages`, `certify.enclose.options`):
which stages each configuration runs, each stage's own bound sound on the boxes it selects,
the driver keeping the smaller sound bound, the constant term (with a shift Q) computed once,
and the stage counts a proof returns in its statistics."""

from __future__ import annotations

import dataclasses

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from certify.arith.interval_ops import nan_min
from certify.enclose.mpdi import mpdi_box_bounds
from certify.enclose.options import (
    BoxBoundOptions,
    Technique,
    box_bound_options,
    mixed_rows_apply,
)
from certify.enclose.preconditioner import (
    constant_term,
    diagonal_preconditioner,
    make_preconditioner,
    to_lam_max_D,
    with_shift,
)
from certify.enclose.stages import BoxState, select_stages
from certify.model.kernels import mpdi_lam_max
from certify.prove.mpdi import prove_mpdi
from certify.results import Status

from ..soak import examples
from .test_preconditioner_choice import _problem

F64 = torch.float64


def _names(opts: BoxBoundOptions) -> list[str]:
    return [s.name for s in select_stages(opts)]


def test_each_configuration_runs_the_stages_of_the_table() -> None:
    """`select_stages` follows the table of `certify.enclose.stages`' docstring."""
    prob = _problem(1, 3, 8.0)
    chol = make_preconditioner(prob.P_t)
    none = diagonal_preconditioner(prob.P_t, torch.ones(3, dtype=F64), "none")
    assert not mixed_rows_apply(prob, chol) and mixed_rows_apply(prob, none)
    cases = [
        (dict(technique=Technique.PLAIN, pc=none), ["plain interval"]),
        (dict(technique=Technique.MEAN_VALUE), ["plain interval", "mean-value form"]),
        (dict(crown=False, pc=none), ["plain interval", "Taylor models"]),
        (dict(pc=chol), ["plain interval", "Taylor models", "linear bounds"]),
        (dict(pc=none), ["plain interval", "mixed rows"]),
        (dict(pc=none, plain_screen=False), ["mixed rows"]),
        # the plain screen is only dropped where the mixed rows take the boxes
        (dict(pc=chol, plain_screen=False), ["plain interval", "Taylor models",
                                             "linear bounds"]),
    ]
    for kwargs, want in cases:
        assert _names(box_bound_options(prob, prob.lam, **kwargs)) == want, kwargs


def test_the_public_taylor_keyword_translates_once() -> None:
    assert Technique.of(True) is Technique.TAYLOR
    assert Technique.of(False) is Technique.PLAIN
    assert Technique.of("interval") is Technique.MEAN_VALUE
    assert Technique.of(Technique.MEAN_VALUE) is Technique.MEAN_VALUE
    with pytest.raises(ValueError, match="taylor must be"):
        Technique.of("intervals")
    prob = _problem(1, 2, 8.0)
    with pytest.raises(ValueError, match="split_rule"):
        box_bound_options(prob, prob.lam, split_rule="deepest")


def _sampled_max(prob, lo: torch.Tensor, hi: torch.Tensor, seed: int) -> torch.Tensor:
    """The largest float64 lam_max(D) over 200 random points and the corners of each box."""
    n, d = prob.n, lo.shape[1]
    g = torch.Generator().manual_seed(seed)
    t = torch.rand(len(lo), 200, d, generator=g, dtype=F64)
    t[:, :8] = (t[:, :8] > 0.5).to(F64)
    z = (lo[:, None] + (hi - lo)[:, None] * t).reshape(-1, d)
    v = mpdi_lam_max(prob.system, prob.network, prob.P_t, prob.lam, z[:, :n], z[:, n:],
                     prob.shift_t)
    return v.reshape(len(lo), -1).amax(1)


@settings(max_examples=examples(12), deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(2, 4),
       kind=st.sampled_from(["cholesky", "none"]), technique=st.sampled_from(list(Technique)),
       crown=st.booleans(), screen=st.sampled_from([None, 0.0]), decide=st.booleans(),
       scale=st.sampled_from([0.0, 1e-3, 0.05, 0.3]))
@pytest.mark.slow
def test_every_stage_bounds_the_boxes_it_selects(seed: int, n: int, kind: str,
                                                  technique: Technique, crown: bool,
                                                  screen: float | None, decide: bool,
                                                  scale: float) -> None:
    """Each stage run on its own (its `select` on the state the stages before it left, then
    its `bound`) gives, on every box it selects, a bound at or above the sampled lam_max of
    M D M^T (converted back to D), or NaN; the driver's bound is the smaller of the screen's
    and the later stages' (nan_min) and sound too."""
    prob = _problem(seed, n, 8.0)
    pc = (make_preconditioner(prob.P_t) if kind == "cholesky"
          else diagonal_preconditioner(prob.P_t, torch.ones(n, dtype=F64), "none"))
    opts = box_bound_options(prob, prob.lam, pc=pc, technique=technique, crown=crown,
                             screen=screen, decide=decide)
    gen = torch.Generator().manual_seed(seed + 1)
    c = 2 * torch.rand(12, n + 1, generator=gen, dtype=F64) - 1
    lo, hi = c - scale, c + scale
    vmax = _sampled_max(prob, lo, hi, seed)
    tol = 1e-12 * (1 + vmax.abs())
    state = BoxState(opts, lo, hi)
    for stage in select_stages(opts):
        mask = stage.select(opts, state)
        if not bool(mask.any()):
            continue
        res = stage.bound(state.boxes.take(mask), opts, state)
        ub = to_lam_max_D(res.bound, prob.P_t, pc)
        assert bool((torch.isnan(ub) | (vmax[mask] <= ub + tol[mask])).all()), stage.name
        assert res.score.shape == (int(mask.sum()), n + 1)
        state.keep(stage, mask, res)
    bb = mpdi_box_bounds(opts, lo, hi)
    assert torch.equal(torch.isnan(bb.upper), torch.isnan(bb.plain) | torch.isnan(bb.taylor))
    fin = ~torch.isnan(bb.upper)
    assert bool((bb.upper[fin] <= bb.plain[fin]).all())
    assert bool((bb.upper[fin] <= bb.taylor[fin]).all())
    # the driver ran the same stages on the same state: the same bounds
    same = nan_min(state.plain, state.bound)
    assert torch.equal(torch.isnan(same), torch.isnan(bb.upper))
    assert torch.equal(same[fin], bb.upper[fin])
    ub = to_lam_max_D(bb.upper, prob.P_t, pc)
    assert bool((torch.isnan(ub) | (vmax <= ub + tol)).all())
    assert list(bb.counts) == _names(opts)


def test_counts_say_which_boxes_each_stage_bounded_and_closed() -> None:
    """The screen bounds every box; the Taylor models exactly the boxes it left above the
    level; the linear bounds a subset of those; "closed" counts the bounds <= the level."""
    prob = _problem(4, 3, 8.0)
    opts = box_bound_options(prob, prob.lam, pc=make_preconditioner(prob.P_t), screen=0.0,
                             decide=True)
    gen = torch.Generator().manual_seed(2)
    c = 2 * torch.rand(64, 4, generator=gen, dtype=F64) - 1
    bb = mpdi_box_bounds(opts, c - 0.05, c + 0.05)
    k = bb.counts
    assert k["plain interval"] == {"boxes": 64, "closed": int((bb.plain <= 0).sum())}
    assert k["Taylor models"]["boxes"] == int((~(bb.plain <= 0)).sum())
    assert 0 <= k["linear bounds"]["boxes"] <= k["Taylor models"]["boxes"]
    closed_later = int((~(bb.plain <= 0) & (bb.taylor <= 0)).sum())
    assert closed_later <= k["Taylor models"]["closed"] + k["linear bounds"]["closed"]


def test_the_constant_term_with_a_shift_is_made_once_and_bounds_stay_sound() -> None:
    """A problem with a constant term Q: the options hold M (2 lam P + Q) M^T (the
    preconditioner carries M Q M^T), and the bounds of D + Q are sound over sampled points."""
    base = _problem(5, 3, 8.0)
    u = torch.tensor([1.0, -0.5, 0.25], dtype=F64)
    Q = 0.3 * torch.outer(u, u)
    prob = dataclasses.replace(base, shift=Q.numpy())
    opts = box_bound_options(prob, prob.lam)
    assert opts.pc.shift is not None
    ref = constant_term(with_shift(make_preconditioner(prob.P_t), prob.shift_t), prob.lam)
    assert torch.equal(opts.constant.lo, ref.lo) and torch.equal(opts.constant.hi, ref.hi)
    plain = constant_term(make_preconditioner(prob.P_t), prob.lam)
    assert not torch.equal(opts.constant.hi, plain.hi)  # Q is in it
    gen = torch.Generator().manual_seed(5)
    c = 2 * torch.rand(16, 4, generator=gen, dtype=F64) - 1
    lo, hi = c - 0.05, c + 0.05
    vmax = _sampled_max(prob, lo, hi, 5)
    ub = to_lam_max_D(mpdi_box_bounds(opts, lo, hi).upper, prob.P_t, opts.pc)
    assert bool((torch.isnan(ub) | (vmax <= ub + 1e-12 * (1 + vmax.abs()))).all())
    # the shift moves the sampled values, so a bound without it would be wrong somewhere
    assert not torch.allclose(vmax, _sampled_max(base, lo, hi, 5))


def test_a_proof_returns_its_stage_counts_in_its_statistics() -> None:
    """A completed decision proof: the screen bounded every box the proof evaluated (it runs
    on every box of every round), and the stages' counts are in `ProofStats.stages`."""
    prob = _problem(2, 2, 8.0)
    out = prove_mpdi(prob, max_boxes=4000)
    assert out.status in (Status.PROVED, Status.UNKNOWN, Status.VIOLATED)
    st = out.stats
    assert st.stages, st
    first = next(iter(st.stages.values()))
    total = sum(v["boxes"] for v in st.stages.values())
    assert total >= st.boxes_processed
    if "plain interval" in st.stages:
        assert st.stages["plain interval"]["boxes"] == st.boxes_processed
    else:  # the mixed rows without a screen bound every box instead
        assert st.stages["mixed rows"]["boxes"] == st.boxes_processed
    assert all(0 <= v["closed"] <= v["boxes"] for v in st.stages.values()), first
