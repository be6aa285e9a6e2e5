"""Raising the proved rate by MPDI decisions (`certify.prove.rate.raise_rate`, used by the rate
check when its maximisation runs out): it climbs to the closed-form lam_cert of a linear
observer and never past it, a violated target lowers the upper end, and on
examples/vdp2_lmi.ckpt the rate check proves more than the design rate within its budget."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import scipy.linalg

from certify.prove.rate import raise_rate

from ..planted import lam_cert_linear, linear_problem

A = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [-1.0, -2.0, -2.0]])
C = np.array([[1.0, 0.0, 0.0]])
K = np.array([[3.0], [4.0], [1.0]])
# a metric from the Lyapunov equation of A - K C (so that lam_cert > 0), rounded
P = np.round(scipy.linalg.solve_continuous_lyapunov((A - K @ C).T, -np.eye(3)), 3)


@pytest.mark.slow
def test_ladder_climbs_to_the_closed_form_and_never_past_it() -> None:
    true = lam_cert_linear(A, C, K, P)
    assert true > 0
    prob = linear_problem(A, C, K, lam=0.5 * true, P=P)
    out = raise_rate(prob, 0.5 * true, 1.001 * true, max_boxes=2_000_000, rel_tol=1e-4)
    assert out.lower <= true  # sound: never above the true rate
    assert out.lower >= true * (1 - 2e-3), (out.lower, true, out.attempts)
    # targets above the true rate are refuted by a witness, not proved
    assert out.violated and out.upper >= true
    assert all(t <= true for t, status, _ in out.attempts if status == "PROVED")


def test_ladder_stops_at_the_budget() -> None:
    true = lam_cert_linear(A, C, K, P)
    prob = linear_problem(A, C, K, lam=0.5 * true, P=P)
    out = raise_rate(prob, 0.5 * true, true, max_boxes=0)
    assert out.attempts == [] and out.lower == 0.5 * true
    # a budget of a few boxes: the decisions together stay within it, whatever they prove
    out = raise_rate(prob, 0.5 * true, true, max_boxes=8)
    assert out.attempts and len(out.stats) == len(out.attempts)
    assert sum(s.boxes_processed for s in out.stats) <= 8 and out.lower < true


@pytest.mark.slow
def test_rate_check_on_vdp2_lmi_proves_above_the_design_rate() -> None:
    """The maximisation alone ended at the design rate 1.0 after its whole 20 s budget; with
    the ladder the check proves more than 1.05 on a 6 s budget (sampled upper 1.119), with the
    MPDI's design rate as the floor and without it."""
    from certify.checks.rate import check_rate
    from certify.model import checkpoint
    from certify.results import MpdiResult, Status
    from certify.settings import VerifySettings

    path = Path(__file__).parents[2] / "examples" / "vdp2_lmi.ckpt"
    prob = checkpoint.load(str(path)).problem
    mpdi = MpdiResult(Status.PROVED, "proved at the design rate", -0.5, -0.39)
    for known in (mpdi, None):  # without a proved design rate the ladder starts from 0
        res = check_rate(prob, VerifySettings(), mpdi=known)
        assert res.status is Status.PROVED
        assert res.proved_lower > 1.05 and res.proved_lower <= res.sampled_upper


@pytest.mark.slow
def test_rate_proof_gives_up_below_a_rate_already_proved() -> None:
    """`prove_rate(give_up=(N, rate))` on examples/vdp2_lmi.ckpt (whose maximisation proves
    less than the design rate 1.0 in its first thousands of boxes): asked to beat 1.0 it
    stops after N boxes as budget-spent, with a proved rate below 1.0; asked to beat a
    rate every bound beats, it runs to its box budget as without the argument."""
    from certify.model import checkpoint
    from certify.prove.mpdi import prove_rate

    path = Path(__file__).parents[2] / "examples" / "vdp2_lmi.ckpt"
    prob = checkpoint.load(str(path)).problem
    kw = dict(max_boxes=8192, batch=512)
    stopped = prove_rate(prob, give_up=(2048, 1.0), **kw)
    assert stopped.stats.budget_exhausted
    assert 2048 <= stopped.stats.boxes_processed < 4096
    assert stopped.lower is not None and stopped.lower < 1.0
    assert stopped.lower <= stopped.upper_sampled
    went_on = prove_rate(prob, give_up=(2048, -1e6), **kw)
    assert went_on.stats.boxes_processed >= 8192


@pytest.mark.slow
def test_ladder_climbs_as_far_when_the_machine_slows_down(monkeypatch) -> None:
    """The ladder's caps are boxes, not seconds: on examples/vdp2_lmi.ckpt the same targets
    are tried with the same outcomes when the clock runs 5x faster from the end of the first
    decision on (a machine loaded mid-run: with caps of 4x the last proof's time, the second
    target was cut short and the ladder stopped at the first). Nothing is on the clock."""
    import time

    import certify.prove.rate as rate_ladder
    from certify.model import checkpoint

    path = Path(__file__).parents[2] / "examples" / "vdp2_lmi.ckpt"
    prob = checkpoint.load(str(path)).problem
    args = (prob, 1.10, 1.1188308628907166)
    kw = dict(rel_tol=2e-3, max_boxes=2_000_000)
    steady = raise_rate(*args, **kw)
    real = time.perf_counter
    since: list[float] = []  # real time when the load arrived

    def loaded() -> float:
        now = real()
        return now if not since else since[0] + 5.0 * (now - since[0])

    decide = rate_ladder.prove_mpdi

    def first_then_load(*a, **k):
        out = decide(*a, **k)
        if not since:
            since.append(real())
        return out

    monkeypatch.setattr(time, "perf_counter", loaded)
    monkeypatch.setattr(rate_ladder, "prove_mpdi", first_then_load)
    slowed = raise_rate(*args, **kw)
    monkeypatch.undo()
    assert [a[:2] for a in slowed.attempts] == [a[:2] for a in steady.attempts]
    assert slowed.lower == steady.lower > 1.11
    assert sum(a[1] == "PROVED" for a in steady.attempts) >= 3
