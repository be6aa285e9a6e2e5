"""Gain network Jacobians and the contraction kernel against references."""

from __future__ import annotations

import pytest
import torch

from certify.model.kernels import (
    contraction_matrix,
    gain_terms,
    generalized_lam_max,
    lam_max,
    mpdi_lam_max,
    pointwise_rate,
)
from certify.model.network import GainNetwork

from ..conftest import random_network


def _points(system, m=9, seed=0):
    g = torch.Generator().manual_seed(seed)
    lo = torch.as_tensor(system.X[:, 0])
    hi = torch.as_tensor(system.X[:, 1])
    ylo = torch.as_tensor(system.Y[:, 0])
    yhi = torch.as_tensor(system.Y[:, 1])
    x = lo + (hi - lo) * torch.rand(m, system.n, generator=g, dtype=torch.float64)
    y = ylo + (yhi - ylo) * torch.rand(m, system.p, generator=g, dtype=torch.float64)
    return x, y


def _k(system, net, x, y):
    return gain_terms(system, net, x, y, with_dy=False).k


@pytest.mark.parametrize("structure", ["direct", "structural"])
def test_jacobians_match_autograd_and_central_differences(system3, structure):
    net = random_network(3, 2, structure=structure, seed=3)
    x, y = _points(system3)
    terms = gain_terms(system3, net, x, y)
    for i in range(len(x)):
        xi, yi = x[i:i + 1], y[i:i + 1]
        jx = torch.autograd.functional.jacobian(lambda v, yi=yi: _k(system3, net, v[None], yi)[0],
                                                x[i])
        jy = torch.autograd.functional.jacobian(lambda v, xi=xi: _k(system3, net, xi, v[None])[0],
                                                y[i])
        torch.testing.assert_close(terms.dk_dx[i], jx, rtol=1e-10, atol=1e-12)
        torch.testing.assert_close(terms.dk_dy[i], jy, rtol=1e-10, atol=1e-12)
    h = 1e-6
    for j in range(3):
        e = torch.zeros(3, dtype=torch.float64)
        e[j] = h
        fd = (_k(system3, net, x + e, y) - _k(system3, net, x - e, y)) / (2 * h)
        torch.testing.assert_close(terms.dk_dx[:, :, j], fd, rtol=1e-6, atol=1e-7)


def test_structural_network_vanishes_on_manifold(system3):
    net = random_network(3, 2, structure="structural", seed=5)
    x, _ = _points(system3)
    k = _k(system3, net, x, system3.h(x))
    assert torch.max(torch.abs(k)) < 1e-14


def test_D_on_linear_system_matches_hand_computation(linear_system):
    # f = (x2, -2 x1 - 3 x2), linear gain K = [1, 0]^T on y - x1, zero network.
    net = GainNetwork(2, 1, hidden=(4,)).double()
    with torch.no_grad():
        for prm in net.parameters():
            prm.zero_()
        net.K.copy_(torch.tensor([[1.0], [0.0]]))
    x, y = _points(linear_system, m=5)
    P = torch.tensor([[2.0, 0.5], [0.5, 1.0]], dtype=torch.float64)
    lam = 0.3
    terms = gain_terms(linear_system, net, x, y)
    D = contraction_matrix(linear_system.jac_f(x), terms.dk_dx, P, lam)
    A = torch.tensor([[-1.0, 1.0], [-2.0, -3.0]], dtype=torch.float64)  # Jf - K C
    M = P @ A
    D_hand = 0.5 * (M + M.T) + 2 * lam * P
    torch.testing.assert_close(D, D_hand.expand(5, 2, 2))
    lm = mpdi_lam_max(linear_system, net, P, lam, x, y)
    torch.testing.assert_close(lm, torch.linalg.eigvalsh(D_hand)[-1].expand(5))
    # the pointwise rate is the largest lam making D <= 0
    rate = pointwise_rate(linear_system, net, P, x, y)[0]
    D_at_rate = 0.5 * (M + M.T) + 2 * rate * P
    assert abs(torch.linalg.eigvalsh(D_at_rate)[-1].item()) < 1e-12


def test_lam_max_closed_forms_match_eigvalsh():
    torch.manual_seed(0)
    for n in (1, 2, 3, 4):
        A = torch.randn(20, n, n, dtype=torch.float64)
        S = A + A.transpose(1, 2)
        torch.testing.assert_close(lam_max(S), torch.linalg.eigvalsh(S)[:, -1])
    P = torch.tensor([[3.0, 1.0], [1.0, 2.0]], dtype=torch.float64)
    S = torch.randn(10, 2, 2, dtype=torch.float64)
    S = S + S.transpose(1, 2)
    import scipy.linalg

    ref = [scipy.linalg.eigh(s.numpy(), P.numpy(), eigvals_only=True)[-1] for s in S]
    torch.testing.assert_close(generalized_lam_max(S, P), torch.tensor(ref, dtype=torch.float64))
