"""Linear bounds of mixed Jacobian rows R dN/dz (`certify.enclose.mixed`): the enclosures
contain every sampled float64 value, and they are tighter than |R| times the unmixed ones."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from certify.arith.eigen import rho_upper
from certify.enclose.crown import forward_bounds, network_crown_tms
from certify.enclose.mixed import (
    contraction_rest,
    contraction_tm_mixed,
    mixed_jacobian_crown,
    network_crown_mixed_jacobian,
)
from certify.enclose.preconditioner import diagonal_preconditioner
from certify.model import activations
from certify.model.kernels import closed_loop_jacobian
from certify.spec.system import load_system

from ..soak import examples
from .test_crown import _boxes, _net, _points
from .test_preconditioner_choice import _problem

F64 = torch.float64


@pytest.mark.parametrize("act", activations.names())
@settings(max_examples=examples(3), deadline=None)
@given(seed=st.integers(0, 10_000), depth=st.integers(1, 3), g=st.sampled_from([0.5, 2.0]),
       scale=st.sampled_from([1e-7, 1e-3, 0.05, 0.5]), d=st.integers(2, 5),
       m=st.integers(1, 4))
def test_mixed_rows_contain_sampled_values(act: str, seed: int, depth: int, g: float,
                                           scale: float, d: int, m: int) -> None:
    net = _net(seed, d, depth, 6, g, act)
    out = d - 1
    gen = torch.Generator().manual_seed(seed + 5)
    R = torch.randn(m, out, generator=gen, dtype=F64) * 3.0
    lo, hi = _boxes(seed, 10, d, scale)
    cols = list(range(out))
    z = _points(lo, hi, 120, seed)
    B, S, _ = z.shape
    _, jac = net.forward_with_jacobian(z.reshape(-1, d))
    want = torch.einsum("mo,soj->smj", R, jac[..., cols]).reshape(B, S, m, len(cols))
    dz = z - 0.5 * (lo + hi)[:, None]
    tol = 1e-13 * (1 + want.abs())
    fb = forward_bounds(net, lo, hi, cols=cols)
    le, _ = mixed_jacobian_crown(net, lo, hi, cols, R, fb)
    low = torch.einsum("bmjd,bsd->bsmj", le.gl, dz) + le.cl[:, None]
    upp = torch.einsum("bmjd,bsd->bsmj", le.gu, dz) + le.cu[:, None]
    assert bool((low <= want + tol).all()) and bool((want <= upp + tol).all())
    tm, _ = network_crown_mixed_jacobian(net, lo, hi, cols, R)
    lin = tm.c[:, None] + torch.einsum("bmjd,bsd->bsmj", tm.g, dz)
    assert bool(((want - lin).abs() <= tm.e[:, None] + tol).all())


def sampled_D(prob, z: torch.Tensor) -> torch.Tensor:
    """He{P J} + 2 lam P (He{X} = (X + X^T) / 2, as the bounds) at points z [S, d]."""
    n = prob.n
    J = closed_loop_jacobian(prob.system, prob.network, z[:, :n], z[:, n:])
    P = prob.P_t
    return 0.5 * (P @ J + (P @ J).transpose(1, 2)) + 2 * prob.lam * P


def mixed_case(seed: int, n: int, cond: float, scale: float, points: int,
               prob=None) -> tuple:
    """A chain problem (`_problem`, or `prob`) with the congruence M = I, 5 boxes of radius
    `scale` around random centres c, and D sampled at `points` points per box: (prob, pc, lo,
    hi, r, D [5, S, n, n], dz [5, S, d] the points less their box centre)."""
    prob = _problem(seed, n, cond) if prob is None else prob
    pc = diagonal_preconditioner(prob.P_t, torch.ones(n, dtype=F64), "none")
    d = n + 1
    gen = torch.Generator().manual_seed(seed + 3)
    c = 2 * torch.rand(5, d, generator=gen, dtype=F64) - 1
    lo, hi = c - scale, c + scale
    r = torch.maximum(hi - c, c - lo)
    z = _points(lo, hi, points, seed).reshape(-1, d)
    D = sampled_D(prob, z).reshape(5, -1, n, n)
    dz = z.reshape(5, -1, d) - c[:, None]
    return prob, pc, lo, hi, r, D, dz


@settings(max_examples=examples(8), deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(2, 4), cond=st.sampled_from([2.0, 30.0]),
       scale=st.sampled_from([0.0, 1e-3, 0.05, 0.3]))
def test_contraction_tm_contains_He_PJ(seed: int, n: int, cond: float, scale: float) -> None:
    prob, pc, lo, hi, r, D, dz = mixed_case(seed, n, cond, scale, 150)
    A, _ = contraction_tm_mixed(prob, pc, lo, hi, r, prob.lam)
    lin = A.c[:, None] + torch.einsum("bijd,bsd->bsij", A.g, dz)
    assert bool(((D - lin).abs() <= A.e[:, None] + 1e-13 * (1 + D.abs())).all())


def test_mixing_before_bounding_is_tighter_than_after() -> None:
    """On a 2x10 tanh network (weight gain 2), R dN/dz bounded directly has a remainder whose
    spectral radius is below that of |R| times the entrywise remainders of dN/dz."""
    net = _net(4, 5, 2, 10, 2.0)
    rng = np.random.default_rng(0)
    Qm, _ = np.linalg.qr(rng.normal(size=(4, 4)))
    R = torch.as_tensor(Qm @ np.diag([1.0, 2.0, 8.0, 8.0]) @ Qm.T)
    lo, hi = _boxes(4, 64, 5, 0.0)
    lo, hi = (lo - 0.12).clamp_min(-1), (hi + 0.12).clamp_max(1)
    cols = [0, 1, 2, 3]
    _, jt, _ = network_crown_tms(net, lo, hi, cols)
    after = R.abs() @ jt.e[..., cols]
    mixed = network_crown_mixed_jacobian(net, lo, hi, cols, R)[0].e
    ra = rho_upper(0.5 * (after + after.transpose(1, 2)))
    rm = rho_upper(0.5 * (mixed + mixed.transpose(1, 2)))
    assert float((rm / ra).median()) < 0.95


def test_a_constant_rest_is_made_once_and_serves_every_box() -> None:
    """For a linear plant and output (the chains) He{P (Jf - K dh/dx)} + 2 lam P is constant:
    the batch's model has no first-order part and its centre lies within the remainders of
    each box's own model (single boxes take the general path); Van der Pol's is not."""
    prob, pc, lo, hi, r, _, _ = mixed_case(3, 4, 8.0, 0.05, 2)
    assert prob.system.jacobians_constant
    assert not load_system("vdp").jacobians_constant
    fast = contraction_rest(prob, pc, lo, hi, r, prob.lam)
    assert bool((fast.g == 0).all()) and bool((fast.e < 1e-12).all())
    for i in range(lo.shape[0]):
        own = contraction_rest(prob, pc, lo[i:i + 1], hi[i:i + 1], r[i:i + 1], prob.lam)
        assert bool(((fast.c[i] - own.c[0]).abs() <= fast.e[i] + own.e[0]).all())
