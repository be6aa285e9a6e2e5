"""Second-order Taylor models (`certify.bounds.taylor2`, `certify.gain.taylor2`): the models of
N, dN/dxhat and the contraction matrix contain every sampled float64 value, and the lam_max
bound of the quadratic matrix model is above every sampled lam_max(D)."""

from __future__ import annotations

import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from certify.bounds.preconditioner import diagonal_preconditioner
from certify.bounds.taylor2 import contraction_tm2_mixed, network_taylor2, tm2_lam_upper
from certify.kernels import closed_loop_jacobian

from .test_crown import _boxes, _net, _points
from .test_preconditioner_choice import _problem

F64 = torch.float64


def _poly(t, dz: torch.Tensor) -> torch.Tensor:
    """c + g . dz + dz^T H dz / 2 at the samples dz [B, S, d] -> [B, S, ...]."""
    lin = torch.einsum("b...d,bsd->bs...", t.g, dz)
    quad = torch.einsum("b...de,bsd,bse->bs...", t.H, dz, dz)
    return t.c[:, None] + lin + 0.5 * quad


@settings(max_examples=12, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(2, 6), arch=st.sampled_from([(2, 10), (3, 30)]),
       g=st.sampled_from([0.5, 2.0]), scale=st.sampled_from([1e-6, 1e-3, 0.03, 0.2]))
def test_network_models_contain_sampled_values(seed: int, n: int, arch: tuple[int, int],
                                               g: float, scale: float) -> None:
    d = n + 1
    net = _net(seed, d, arch[0], arch[1], g)
    lo, hi = _boxes(seed, 6, d, scale)
    val, jac, r = network_taylor2(net, lo, hi, n)
    assert bool((r >= 0.5 * (hi - lo)).all())
    z = _points(lo, hi, 100, seed)
    B, S, _ = z.shape
    v, J = net.forward_with_jacobian(z.reshape(-1, d))
    v, J = v.reshape(B, S, -1), J[..., :n].reshape(B, S, -1, n)
    dz = z - 0.5 * (lo + hi)[:, None]
    for want, tm in ((v, val), (J, jac)):
        assert bool((tm.e >= 0).all())
        err = (want - _poly(tm, dz)).abs()
        assert bool((err <= tm.e[:, None] + 1e-13 * (1 + want.abs())).all())


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(2, 5), cond=st.sampled_from([2.0, 30.0]),
       scale=st.sampled_from([0.0, 1e-3, 0.05, 0.2]))
def test_contraction_model_and_lam_bound_contain_sampled_D(seed: int, n: int, cond: float,
                                                           scale: float) -> None:
    prob = _problem(seed, n, cond)
    pc = diagonal_preconditioner(prob.P_t, torch.ones(n, dtype=F64), "none")
    d = n + 1
    gen = torch.Generator().manual_seed(seed + 3)
    c = 2 * torch.rand(5, d, generator=gen, dtype=F64) - 1
    lo, hi = c - scale, c + scale
    A, r = contraction_tm2_mixed(prob, pc, lo, hi, prob.lam)
    z = _points(lo, hi, 150, seed)
    J = closed_loop_jacobian(prob.system, prob.network, z.reshape(-1, d)[:, :n],
                             z.reshape(-1, d)[:, n:])
    P = prob.P_t
    D = 0.5 * (P @ J + (P @ J).transpose(1, 2)) + 2 * prob.lam * P
    D = D.reshape(5, -1, n, n)
    err = (D - _poly(A, z - c[:, None])).abs()
    assert bool((err <= A.e[:, None] + 1e-13 * (1 + D.abs())).all())
    lam = torch.linalg.eigvalsh(D)[..., -1].amax(-1)
    for level in (None, 0.0):
        bound = tm2_lam_upper(A, r, level=level)
        assert bool((lam <= bound + 1e-12 * (1 + lam.abs())).all())
