"""Error bounds at the edges of the noise level: no noise (a limit reached only as t -> infinity,
never at a finite time) and a noise level so large that a bound overflows (no bound, never an
infinite one)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from certify.checks.bounds import check_bounds
from certify.model.network import GainNetwork
from certify.model.problem import Problem
from certify.presentation import error_headline
from certify.prove.error_bound import bound_curve, settle_time, worst_start
from certify.results import DissipationResult, Status

from ..planted import linear_system

A2 = np.array([[0.0, 1.0], [-2.0, -1.0]])
C2 = np.array([[1.0, 0.0]])
P2 = np.array([[3.0, 0.7], [0.7, 1.5]])


def _problem() -> Problem:
    net = GainNetwork(2, 1, (4,), structure="structural").double()
    with torch.no_grad():
        net.layers[-1].weight.zero_()
        net.layers[-1].bias.zero_()
    return Problem(system=linear_system(A2, C2, P=P2), network=net.requires_grad_(False),
                   lam=0.1, P=P2)


@pytest.mark.parametrize("with_dissipation", [False, True])
def test_no_noise_no_residual_is_a_limit_not_a_time(with_dissipation):
    """vbar = 0 and eps_bar = 0: the ultimate bound is 0, reached only as t -> infinity, so
    the headline names no time (it said 't >= 1500 s' where e^(-rate t) underflowed)."""
    d = DissipationResult(Status.PROVED, "test", alpha=1.0, mu=4.0) if with_dissipation else None
    r = check_bounds(_problem(), lam_cert=0.5, eps_bar=0.0, L=2.0, vbar=0.0, dissipation=d)
    assert r.status == Status.PROVED and r.ultimate == 0.0 and r.headline == 0.0
    assert r.settle_time is None
    assert "as t -> infinity" in r.message and "after t" not in r.message.split(";")[0]
    head = error_headline(r)
    assert head.sentence().endswith("as t \u2192 \u221e")
    # the curve itself never reaches 0 at a finite time (before underflow)
    assert settle_time(r, r.best, 1.0, 0.0) == math.inf
    assert float(bound_curve(r, r.best, 1.0, np.array([100.0]))[0]) > 0


def test_a_tiny_positive_headline_has_a_true_settle_time():
    """A tiny ultimate bound (far above the float range's bottom): its settle time is where
    the exact curve crosses the headline, not earlier."""
    r = check_bounds(_problem(), lam_cert=0.5, eps_bar=1e-160, L=0.0, vbar=0.0)
    assert r.status == Status.PROVED and r.settle_time is not None
    start = worst_start(getattr(r, r.best), P2, np.asarray(_problem().system.X))
    at = float(bound_curve(r, r.best, start, np.array([r.settle_time]))[0])
    assert at <= r.headline
    assert float(bound_curve(r, r.best, start, np.array([0.99 * r.settle_time]))[0]) > r.headline


@pytest.mark.parametrize("vbar", [1e150, 1e300, 1.7e308])
def test_huge_noise_gives_a_finite_bound_or_none(vbar):
    """Every applicable bound is a finite number; one that overflows is not applicable, with a
    reason; the headline is finite or absent, never inf or NaN."""
    d = DissipationResult(Status.PROVED, "test", alpha=1.0, mu=4.0)
    r = check_bounds(_problem(), lam_cert=0.5, eps_bar=0.0, L=2.0, vbar=vbar, dissipation=d)
    for b in r.bounds():
        if b.applicable:
            assert math.isfinite(b.bias) and math.isfinite(b.gain)
        else:
            assert b.reason
    if r.headline is not None:
        assert math.isfinite(r.headline) and r.vacuous
    else:
        assert r.status != Status.PROVED
    if vbar == 1.7e308:  # 2 vbar / (2 lam) overflows: no ISS bound at all
        assert not r.iss.applicable and "floating-point range" in r.iss.reason


def test_a_dissipation_inequality_is_planned_and_proved_at_any_noise():
    """The inequality V' <= -alpha V + mu |v|^2 does not depend on the noise level; only its
    bound does. At vbar = 1e308 the plan still ranks candidates (by the bound per unit noise)
    and proves one; the bound then overflows and is not given (never infinite)."""
    from certify.prove.dissipation import prove_dissipation

    K = np.array([[1.0], [0.5]])
    net = GainNetwork(2, 1, (4,), structure="structural").double()
    with torch.no_grad():
        net.layers[-1].weight.zero_()
        net.layers[-1].bias.zero_()
        net.K.copy_(torch.as_tensor(K))
    pb = Problem(system=linear_system(A2, C2, P=P2), network=net.requires_grad_(False),
                 lam=0.1, P=P2)
    small = prove_dissipation(pb, vbar=0.15)
    huge = prove_dissipation(pb, vbar=1e308)
    assert small.status == huge.status == Status.PROVED
    assert huge.mu / huge.alpha == pytest.approx(small.mu / small.alpha, rel=1e-6)
    d = DissipationResult(Status.PROVED, "test", alpha=huge.alpha, mu=huge.mu)
    r = check_bounds(pb, lam_cert=None, eps_bar=None, L=None, vbar=1e308, dissipation=d)
    assert r.headline is None and r.status != Status.PROVED
    assert "floating-point range" in r.message
