"""The gridded designs of a metric that follows the state (`certify.design.metric_poly`):
known answers on linear plants (the degree-0 metric step against an independent LMI solve,
the scalar noise gain and the optimal gain in closed form), and the designs' inequality at
their own points through the certificate's point matrix (a second assembly of (*))."""

from __future__ import annotations

import math

import cvxpy as cp
import numpy as np
import pytest
import torch

from certify.design import metric_poly as mp
from certify.enclose.metric import point_matrix
from certify.model.metric import PolyMetric
from certify.model.network import GainNetwork

from ..planted import linear_system

A2 = np.array([[0.0, 1.0], [-2.0, -1.0]])
C2 = np.array([[1.0, 0.0]])
K2 = np.array([[1.5], [0.7]])
ZERO2 = np.zeros((1, 2), dtype=np.int64)


def _lmi_mu(A: np.ndarray, C: np.ndarray, K: np.ndarray, alpha: float) -> float:
    """min mu s.t. [[P Acl + Acl^T P + alpha P, P K], [K^T P, -mu I]] <= 0, P >= I: the
    constant-metric noise gain of the linear observer, posed in cvxpy (independent code)."""
    n, p = K.shape
    Acl = A - K @ C
    P = cp.Variable((n, n), symmetric=True)
    mu = cp.Variable()
    top = P @ Acl + Acl.T @ P + alpha * P
    M = cp.bmat([[top, P @ K], [K.T @ P, -mu * np.eye(p)]])
    prob = cp.Problem(cp.Minimize(mu), [0.5 * (M + M.T) << 0, P >> np.eye(n)])
    prob.solve(solver=cp.CLARABEL)
    assert prob.status == "optimal"
    return float(mu.value)


@pytest.mark.parametrize("alpha", [0.3, 1.0, 1.6])
def test_the_degree_0_metric_step_matches_the_lmi_optimum(alpha):
    """On a linear plant with a linear gain the matrix (*) is the same at every point: the
    degree-0 design's mu equals the LMI optimum to solver tolerance."""
    s = linear_system(A2, C2)
    pts = mp.design_points(s, 0.3, per_axis=5, offsets=3)
    F, J, B = mp.linear_terms(pts, K2)
    out = mp.metric_step(pts, ZERO2, F, J, B, alpha)
    assert out is not None
    metric, mu = out
    want = _lmi_mu(A2, C2, K2, alpha)
    assert mu == pytest.approx(want, rel=1e-5, abs=1e-6)
    assert np.linalg.eigvalsh(metric.coefficients[0])[0] >= 1 - 1e-6


def test_the_constant_metric_design_takes_the_best_rate():
    """design_constant_metric's (P, alpha, mu) is feasible for the LMI and no rate of a fine
    scan does better than its mu / alpha by more than the scan's resolution."""
    s = linear_system(A2, C2)
    P, alpha, mu = mp.design_constant_metric(s, K2, per_axis=5)
    best = min(_lmi_mu(A2, C2, K2, a) / a for a in np.linspace(0.1, 2.0, 40))
    assert mu / alpha <= best * 1.02
    assert mu == pytest.approx(_lmi_mu(A2, C2, K2, alpha), rel=1e-4)


def test_the_scalar_gain_step_finds_the_closed_form_optimum():
    """x' = a x, y = x, metric 1: mu(k) = k^2 / (2 (k - a) - alpha), minimised at
    k = 2 a + alpha with mu = 2 a + alpha."""
    a, alpha = 1.0, 1.0
    s = linear_system(np.array([[a]]), np.array([[1.0]]), X=np.array([[-1.0, 1.0]]))
    pts = mp.design_points(s, 0.2, per_axis=7, offsets=3)
    got = mp.gain_step(pts, PolyMetric.constant(np.eye(1)), alpha)
    assert got is not None
    K, mu = got
    assert float(K[0, 0]) == pytest.approx(2 * a + alpha, rel=1e-4)
    assert mu == pytest.approx(2 * a + alpha, rel=1e-5)
    # and the metric step at that gain gives the same noise gain (metric 1 is optimal)
    F, J, B = mp.linear_terms(pts, K)
    metric, mu2 = mp.metric_step(pts, np.zeros((1, 1), dtype=np.int64), F, J, B, alpha)
    assert mu2 == pytest.approx(k_mu(float(K[0, 0]), a, alpha), rel=1e-5)


def k_mu(k: float, a: float, alpha: float) -> float:
    return k * k / (2 * (k - a) - alpha)


def _linear_net(K: np.ndarray) -> GainNetwork:
    n, p = K.shape
    net = GainNetwork(n, p, (3,), structure="structural").double()
    with torch.no_grad():
        net.layers[-1].weight.zero_()
        net.layers[-1].bias.zero_()
        net.K.copy_(torch.as_tensor(K))
    return net.requires_grad_(False)


@pytest.mark.slow
def test_a_designed_metric_satisfies_its_inequality_at_its_points():
    """The degree-2 design on the Van der Pol tube: the certificate's own point matrix
    (`certify.enclose.metric.point_matrix`, a second assembly of (*)) at the design's points
    is negative semidefinite up to solver tolerance, M >= I at the grid's states, and the
    designed bound is below the constant metric's on the same points."""
    from certify.spec.system import load_system

    s = load_system("vdp")
    K0 = np.array([[8.7], [20.8]])
    pts = mp.design_points(s, 0.6, per_axis=9, offsets=3)
    d = mp.design_metric(s, K0, degree=2, tau=0.6, rounds=1, pts=pts,
                         alphas=np.array([1.0, 2.0, 3.0]))
    assert d is not None and d.linear
    z = torch.as_tensor(np.concatenate([pts.x, pts.w], 1))
    N = point_matrix(s, _linear_net(d.K[0]), d.metric, d.alpha, d.mu, z)
    scale = float(torch.linalg.matrix_norm(N, ord=2).max())
    assert float(torch.linalg.eigvalsh(N)[:, -1].max()) <= 1e-6 * scale
    Mq = d.metric.value(torch.as_tensor(pts.states)).numpy()
    assert np.linalg.eigvalsh(Mq)[:, 0].min() >= 1 - 1e-6
    F, J, B = mp.linear_terms(pts, d.K[0])
    const = mp.metric_step(pts, ZERO2, F, J, B, d.alpha)
    assert const is not None
    assert d.per_unit_noise <= math.sqrt(const[1] / d.alpha) + 1e-9
