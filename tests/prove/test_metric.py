"""The Riemannian path certificate with a metric that follows the state: enclosures that contain
every sampled value, the tube's exclusion, planted near-ties never proved, the metric's
constants, and the chain of stages never below what the inequality allows."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from certify.enclose.metric import (
    lam_max_upper,
    metric_congruence,
    metric_tm,
    path_metric_tm,
    point_matrix,
    tube_box_outside,
    tube_outside,
    tube_point,
)
from certify.model.kernels import lam_max
from certify.model.metric import PolyMetric, even_monomials
from certify.model.network import GainNetwork
from certify.prove import metric as pm
from certify.results import Status
from certify.spec.system import System

from ..conftest import SPEC_3X2, random_network
from ..planted import linear_system

A2 = np.array([[0.0, 1.0], [-2.0, -1.0]])
C2 = np.array([[1.0, 0.0]])
P2 = np.array([[3.0, 0.7], [0.7, 1.5]])


def _metric(seed: int, scale: float = 0.2) -> PolyMetric:
    rng = np.random.default_rng(seed)
    E = even_monomials(2, 2)
    C = rng.normal(size=(len(E), 2, 2)) * scale
    C = C + C.transpose(0, 2, 1)
    C[0] = P2
    return PolyMetric(E, C)


def _linear_gain(K: np.ndarray) -> GainNetwork:
    net = GainNetwork(2, 1, (4,), structure="structural").double()
    with torch.no_grad():
        net.layers[-1].weight.zero_()
        net.layers[-1].bias.zero_()
        net.K.copy_(torch.as_tensor(K))
    return net.requires_grad_(False)


def _boxes(system, rng, count: int, width: float):
    box = np.concatenate([system.X, system.Y])
    span = box[:, 1] - box[:, 0]
    lo = box[:, 0] + rng.random((count, len(box))) * span * (1 - width)
    return torch.as_tensor(lo), torch.as_tensor(lo + width * span)


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 10_000), structural=st.booleans(), width=st.floats(0.01, 0.6),
       alpha=st.floats(0.1, 3.0), mu=st.floats(0.5, 200.0), precondition=st.booleans())
def test_the_path_metric_enclosure_contains_every_sampled_value(seed, structural, width, alpha,
                                                                mu, precondition):
    """Over random boxes, lam_max of N (or of T N T^T) at sampled points never exceeds the
    box bound; M's own enclosure likewise."""
    s = linear_system(A2, C2, P=P2)
    net = random_network(2, 1, hidden=(5,), structure="structural" if structural else "direct",
                         seed=seed, scale=1.5)
    M = _metric(seed)
    rng = np.random.default_rng(seed)
    lo, hi = _boxes(s, rng, 5, width)
    T = metric_congruence(M, np.zeros(3), mu, 1) if precondition else None
    ub, _ = lam_max_upper(path_metric_tm(s, net, M, alpha, mu, lo, hi, congruence=T), lo, hi)
    u = torch.as_tensor(rng.random((5, 200, 3)))
    z = (lo[:, None] + u * (hi - lo)[:, None]).reshape(-1, 3)
    N = point_matrix(s, net, M, alpha, mu, z)
    if T is not None:
        N = T @ N @ T.T
    vals = lam_max(N).reshape(5, 200).max(1).values
    assert torch.all(torch.isnan(ub) | (vals <= ub))
    mub, _ = lam_max_upper(metric_tm(M, lo, hi), lo, hi)
    mv = lam_max(M.value(z[:, :2])).reshape(5, 200).max(1).values
    assert torch.all(mv <= mub)


CURVED = System.from_text("""
name = "curved"
states = ["x1", "x2"]
outputs = ["y"]
f = ["x2", "-x1 - x2 + 0.3*x1**2*x2"]
h = ["x1 + 0.3*sin(x2)"]
[box]
X = [[-1, 1], [-1.5, 1.5]]
Y = [[-1.5, 1.5]]
[design]
lam = 0.5
""", origin="test spec curved")


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 10_000), which=st.sampled_from(["curved", "three"]),
       structural=st.booleans(), width=st.floats(0.01, 0.6), tau=st.floats(0.05, 1.0),
       alpha=st.floats(0.1, 3.0), mu=st.floats(0.5, 200.0))
def test_the_enclosure_in_tube_coordinates_contains_every_sampled_value(
        seed, which, structural, width, tau, alpha, mu):
    """Over random boxes of u = (x, t), lam_max of N at z = (x, h(x) + t) for sampled u never
    exceeds the box bound (a nonlinear h; two outputs)."""
    s = CURVED if which == "curved" else System.from_text(SPEC_3X2, origin="three")
    n, p = s.n, s.p
    net = random_network(n, p, hidden=(5,), structure="structural" if structural else "direct",
                         seed=seed, scale=1.5)
    rng = np.random.default_rng(seed)
    E = even_monomials(n, 2)
    C = rng.normal(size=(len(E), n, n)) * 0.1
    C = C + C.transpose(0, 2, 1)
    C[0] = np.eye(n) * 2.0
    M = PolyMetric(E, C)
    box = np.concatenate([s.X, np.tile([[-tau, tau]], (p, 1))])
    span = box[:, 1] - box[:, 0]
    lo = box[:, 0] + rng.random((5, len(box))) * span * (1 - width)
    lo, hi = torch.as_tensor(lo), torch.as_tensor(lo + width * span)
    ub, _ = lam_max_upper(path_metric_tm(s, net, M, alpha, mu, lo, hi, tube=True), lo, hi)
    u = lo[:, None] + torch.as_tensor(rng.random((5, 200, n + p))) * (hi - lo)[:, None]
    N = point_matrix(s, net, M, alpha, mu, tube_point(s, u.reshape(-1, n + p)))
    vals = lam_max(N).reshape(5, 200).max(1).values
    assert torch.all(torch.isnan(ub) | (vals <= ub))


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 10_000), tau=st.floats(0.01, 1.0), width=st.floats(0.01, 0.5))
def test_a_tube_coordinate_box_with_a_point_of_the_tube_is_never_excluded(seed, tau, width):
    """Two outputs: the tube ||t|| <= tau is a ball inside the box [-tau, tau]^2; a box with
    a point of the ball is kept."""
    s = System.from_text(SPEC_3X2, origin="three")
    rng = np.random.default_rng(seed)
    box = np.concatenate([s.X, np.tile([[-1.5 * tau, 1.5 * tau]], (2, 1))])
    span = box[:, 1] - box[:, 0]
    lo = box[:, 0] + rng.random((40, 5)) * span * (1 - width)
    lo, hi = torch.as_tensor(lo), torch.as_tensor(lo + width * span)
    out = tube_box_outside(s, lo, hi, tau)
    u = lo[:, None] + torch.as_tensor(rng.random((40, 300, 5))) * (hi - lo)[:, None]
    inside = (u[..., 3:].norm(dim=-1) <= tau).any(1)
    assert not bool((out & inside).any())
    corner = torch.tensor([[0.0, 0.0, 0.0, 0.8 * tau, 0.8 * tau]])
    assert bool(tube_box_outside(s, corner, corner + 0.01 * tau, tau)[0])


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 10_000), tau=st.floats(0.01, 1.0), width=st.floats(0.01, 0.5))
def test_a_box_with_a_point_of_the_tube_is_never_excluded(seed, tau, width):
    s = linear_system(A2, C2, P=P2)
    rng = np.random.default_rng(seed)
    lo, hi = _boxes(s, rng, 40, width)
    out = tube_outside(s, lo, hi, tau)
    u = torch.as_tensor(rng.random((40, 300, 3)))
    z = lo[:, None] + u * (hi - lo)[:, None]
    gap = (z[..., 2] - z[..., 0]).abs()  # h = x1
    has_tube_point = (gap <= tau).any(1)
    assert not bool((out & has_tube_point).any())


def _exact_mu(K: np.ndarray, alpha: float) -> float:
    """The noise gain a constant metric P2 needs for the linear observer at rate alpha
    (the matrix (*) is constant on a linear system)."""
    Acl = A2 - K @ C2
    X = 0.5 * (P2 @ Acl + Acl.T @ P2) + 0.5 * alpha * P2
    MB = P2 @ K
    return float(np.linalg.eigvalsh(MB.T @ np.linalg.solve(-X, MB))[-1]) / 2


@pytest.mark.parametrize("factor,proved", [(1 - 1e-3, False), (1 + 1e-2, True)])
def test_a_noise_gain_a_hair_too_small_is_never_proved(factor, proved):
    """A constant metric (degree 0) on a linear plant and gain: (*) is the same at every
    point and its exact mu is known; 0.1% below it the prover refutes, 1% above it proves."""
    K = np.array([[1.0], [0.5]])
    s = linear_system(A2, C2, P=P2)
    M = PolyMetric.constant(P2)
    alpha = 0.8
    dom = pm.domain_for(s, None)
    out = pm.prove_inequality(s, _linear_gain(K), M, alpha, _exact_mu(K, alpha) * factor, dom,
                              max_boxes=5000)
    assert (out.status == Status.PROVED) == proved


def test_a_sampled_violation_is_never_proved():
    """A nonlinear metric on a nonlinear gain: mu below the largest sampled need is refuted
    (the sampled point itself violates (*))."""
    s = linear_system(A2, C2, P=P2)
    net = random_network(2, 1, hidden=(5,), structure="structural", seed=3)
    M = _metric(3, 0.05)
    dom = pm.domain_for(s, 0.3)
    terms = pm.PointTerms.at(s, net, M, pm.sample_domain(s, dom, 2000, 0))
    cands = pm.plan(terms, 0.15)
    assert cands
    alpha = cands[0]["alpha"]
    mu = pm.needed_mu(terms, alpha) * 0.98
    out = pm.prove_inequality(s, net, M, alpha, mu, dom, max_boxes=20_000)
    assert out.status != Status.PROVED


def test_the_metric_constants_hold_at_samples():
    """m_min, a (M <= a P), and the reaches are sound: never beaten at sampled states."""
    s = linear_system(A2, C2, P=P2)
    M = _metric(5, 0.05)
    X = np.asarray(s.X)
    c = pm.prove_constants(s, M, X, P2, boxes=20_000)
    assert not isinstance(c, str)
    x = torch.as_tensor(X[:, 0] + np.random.default_rng(0).random((5000, 2)) * (X[:, 1] - X[:, 0]))
    Mv = M.value(x).numpy()
    assert np.linalg.eigvalsh(Mv)[:, 0].min() >= c.m_min
    Li = np.linalg.inv(np.linalg.cholesky(P2))
    assert np.linalg.eigvalsh(Li @ Mv @ Li.T)[:, -1].max() <= c.a
    for i, g in enumerate(c.gamma):
        assert np.sqrt(np.linalg.inv(Mv)[:, i, i]).max() <= g
    assert np.sqrt(np.linalg.inv(Mv)[:, 0, 0]).max() <= c.gamma_h  # h = x1


@pytest.mark.slow
def test_the_chain_never_claims_below_the_constant_metrics_exact_bound():
    """A linear plant and gain with the constant metric as 'M(x)': the chain of stages proves
    a bound at least the exact optimum over alpha of sqrt(mu(alpha) / alpha) vbar /
    sqrt(m_min) (the same inequality on every tube), and within a few percent of it."""
    K = np.array([[1.0], [0.5]])
    s = linear_system(A2, C2, P=P2)
    M = PolyMetric.constant(P2)
    vbar = 0.15
    alphas = np.linspace(0.05, 2.5, 400)
    exact = min(math.sqrt(_exact_mu(K, a) / a) for a in alphas
                if np.linalg.eigvalsh(0.5 * (P2 @ (A2 - K @ C2) + (A2 - K @ C2).T @ P2)
                                      + 0.5 * a * P2)[-1] < 0)
    v1 = (exact * vbar) ** 2 * 1.05
    out = pm.prove_metric_chain(s, _linear_gain(K), M, vbar=vbar, P1=P2, V1_inf=v1)
    assert out.status == Status.PROVED
    m_min = out.constants.m_min
    proved = math.sqrt(out.stages[-1].v_inf / m_min)
    lower = exact * vbar / math.sqrt(np.linalg.eigvalsh(P2)[-1])  # m_min <= lam_min(P2)
    assert proved >= exact * vbar / math.sqrt(np.linalg.eigvalsh(P2)[0]) * (1 - 1e-9)
    assert proved >= lower
    assert proved <= exact * vbar / math.sqrt(m_min) * 1.06
