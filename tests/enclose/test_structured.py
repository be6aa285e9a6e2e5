"""The last hidden layer's relaxation errors as a matrix (`certify.enclose.structured`): the
enclosure with those errors apart plus He{C eps} holds at sampled points, the Loewner upper
model bounds v^T D v for every sampled v (the eigenvectors of D included), and it decides
boxes the entrywise remainder cannot."""

from __future__ import annotations

import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from certify.enclose.crown import forward_bounds
from certify.enclose.mixed import contraction_tm_mixed, mixed_jacobian_crown
from certify.enclose.preconditioner import diagonal_preconditioner
from certify.enclose.structured import entrywise, loewner_upper
from certify.enclose.taylor import tm_lam_upper
from certify.model import activations

from ..soak import examples
from .test_crown import _boxes, _net, _points
from .test_mixed_rows import mixed_case, sampled_D
from .test_preconditioner_choice import _problem

F64 = torch.float64


@settings(max_examples=examples(4), deadline=None)
@given(seed=st.integers(0, 10_000), act=st.sampled_from(activations.names()),
       depth=st.integers(1, 3), scale=st.sampled_from([1e-3, 0.05, 0.5]), m=st.integers(1, 4))
def test_errors_apart_plus_C_eps_contain_sampled_rows(seed: int, act: str, depth: int,
                                                      scale: float, m: int) -> None:
    """With top_apart, R dN/dz - (linear lines) = C eps + (what the lines still carry): for
    every sampled point and every row, the distance to the lines' band is at most
    sum_k |C_ik| w_jk (the errors apart cannot exceed their bound)."""
    d = 4
    net = _net(seed, d, depth, 6, 2.0, act)
    gen = torch.Generator().manual_seed(seed + 5)
    R = torch.randn(m, d - 1, generator=gen, dtype=F64) * 3.0
    lo, hi = _boxes(seed, 8, d, scale)
    cols = list(range(d - 1))
    z = _points(lo, hi, 100, seed)
    B, S, _ = z.shape
    _, jac = net.forward_with_jacobian(z.reshape(-1, d))
    want = torch.einsum("mo,soj->smj", R, jac[..., cols]).reshape(B, S, m, len(cols))
    dz = z - 0.5 * (lo + hi)[:, None]
    fb = forward_bounds(net, lo, hi, cols=cols)
    le, top = mixed_jacobian_crown(net, lo, hi, cols, R, fb, top_apart=True)
    low = torch.einsum("bmjd,bsd->bsmj", le.gl, dz) + le.cl[:, None]
    upp = torch.einsum("bmjd,bsd->bsmj", le.gu, dz) + le.cu[:, None]
    outside = torch.maximum(low - want, want - upp).clamp_min(0.0)
    allowed = torch.einsum("mk,bjk->bmj", top.C.abs(), top.w)
    if top.rank is not None and top.rank.lower is not None:  # the first layer's, apart too
        allowed = allowed + top.rank.lower.full
    allowed = allowed[:, None]
    assert bool((outside <= allowed + 1e-13 * (1 + want.abs())).all())
    full, none = mixed_jacobian_crown(net, lo, hi, cols, R, fb)
    assert none is None
    assert bool((le.cu - le.cl <= full.cu - full.cl + 1e-12).all())  # the lines are narrower


@settings(max_examples=examples(10), deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(2, 4), cond=st.sampled_from([2.0, 30.0]),
       scale=st.sampled_from([0.0, 1e-3, 0.05, 0.3]))
def test_loewner_model_bounds_every_sampled_quadratic_form(seed: int, n: int, cond: float,
                                                           scale: float) -> None:
    """For sampled points z and vectors v (random, and the eigenvectors of D(z)):
    v^T D(z) v <= v^T (c + g . dz) v + |v|^T e |v| for the upper model (c + W, g, e); the
    entrywise form of the same errors contains D(z) entry by entry."""
    prob, pc, lo, hi, r, D, dz = mixed_case(seed, n, cond, scale, 80)
    gen = torch.Generator().manual_seed(seed + 4)
    A, top = contraction_tm_mixed(prob, pc, lo, hi, r, prob.lam, top_apart=True)
    U = loewner_upper(A, top)
    M = U.c[:, None] + torch.einsum("bijd,bsd->bsij", U.g, dz)
    v = torch.cat([torch.randn(5, D.shape[1], 16, n, generator=gen, dtype=F64),
                   torch.linalg.eigh(D).eigenvectors.transpose(-1, -2),
                   torch.linalg.eigh(D - M).eigenvectors.transpose(-1, -2)], 2)
    # the same errors entry by entry: an entrywise enclosure of D again
    E = entrywise(A, top)
    lin = E.c[:, None] + torch.einsum("bijd,bsd->bsij", E.g, dz)
    assert bool(((D - lin).abs() <= E.e[:, None] + 1e-13 * (1 + D.abs())).all())
    lhs = torch.einsum("bsvi,bsij,bsvj->bsv", v, D, v)
    rhs = torch.einsum("bsvi,bsij,bsvj->bsv", v, M, v) \
        + torch.einsum("bsvi,bij,bsvj->bsv", v.abs(), U.e, v.abs())
    assert bool((lhs <= rhs + 1e-12 * (1 + lhs.abs())).all())


def test_matrix_errors_decide_boxes_the_entrywise_remainder_cannot() -> None:
    """A 4-state chain with a 6x5 tanh network (gain 2) and a metric of condition 30, boxes
    of radius 0.1, a level between the boxes' sampled maxima: the upper model decides
    strictly more boxes than the entrywise remainder, and none whose
    sampled lam_max exceeds the level."""
    from certify.enclose.mpdi import mpdi_box_bounds
    from certify.enclose.options import box_bound_options

    prob = _problem(3, 4, 30.0)
    pc, lo, hi, r, sampled, level = boxes_and_level(prob, 0.8, 0.1, 0.8)
    A, top = contraction_tm_mixed(prob, pc, lo, hi, r, prob.lam, top_apart=True)
    A0, _ = contraction_tm_mixed(prob, pc, lo, hi, r, prob.lam)
    plain = decided(A0, r, level)
    structured = decided(loewner_upper(A, top, level), r, level)
    assert int(structured.sum()) > int(plain.sum()), (int(plain.sum()), int(structured.sum()))
    assert bool((sampled[structured] <= level).all())
    assert bool((sampled > level).any())
    # the prover's mixed-row stage uses the matrix form: it decides more than the entrywise
    # remainder too, and no box above the level
    opts = box_bound_options(prob, prob.lam, pc=pc, screen=level, decide=True,
                             plain_screen=False)
    stage = mpdi_box_bounds(opts, lo, hi).upper <= level
    assert int(stage.sum()) > int(plain.sum()), (int(plain.sum()), int(stage.sum()))
    assert bool((sampled[stage] <= level).all())


def boxes_and_level(prob, spread: float, radius: float, quantile: float) -> tuple:
    """For a chain problem with the congruence M = I: 256 boxes of `radius` with centres in
    [-spread, spread]^d, their sampled max of lam_max(D) (64 points each) and a level
    between those maxima (their `quantile` + 0.05), so that some boxes must not be decided:
    (pc, lo, hi, r, sampled, level)."""
    n = prob.n
    pc = diagonal_preconditioner(prob.P_t, torch.ones(n, dtype=F64), "none")
    gen = torch.Generator().manual_seed(0)
    c = 2 * spread * torch.rand(256, n + 1, generator=gen, dtype=F64) - spread
    lo, hi = c - radius, c + radius
    r = torch.full_like(lo, radius)
    D = sampled_D(prob, _points(lo, hi, 64, 1).reshape(-1, n + 1))
    sampled = torch.linalg.eigvalsh(D)[:, -1].reshape(256, -1).amax(1)
    return pc, lo, hi, r, sampled, float(sampled.quantile(quantile)) + 0.05


def decided(model, r: torch.Tensor, level: float) -> torch.Tensor:
    """Which boxes the model's bound decides against `level` (the decision reports just
    below the level)."""
    bound, _ = tm_lam_upper(model, r, level=level)
    return bound == level - 1e-12 * (1 + abs(level))
