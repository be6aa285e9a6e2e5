"""The top layer's product errors by their rank structure (`certify.enclose.top_rank`): the
Loewner upper model bounds v^T D v at sampled points for one and two hidden layers and every
activation (deeper networks keep the independent form), and on the 2x10 four-state chain it
decides boxes the independent form cannot."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch
from hypothesis import example, given, settings
from hypothesis import strategies as st

from certify.arith.intervals import up
from certify.arith.taylor import TM
from certify.enclose.crown import forward_bounds
from certify.enclose.mixed import TopLayerRemainder, contraction_tm_mixed, mixed_jacobian_crown
from certify.enclose.structured import loewner_upper
from certify.enclose.top_rank import rank_loewner_upper
from certify.model import activations
from certify.model.network import GainNetwork
from certify.model.problem import Problem

from ..planted import linear_system
from ..soak import examples
from .test_mixed_rows import mixed_case
from .test_preconditioner_choice import _metric
from .test_structured import boxes_and_level, decided

F64 = torch.float64


def _chain(seed: int, n: int, hidden: tuple[int, ...], act: str, gain: float = 2.0,
           cond: float = 8.0) -> Problem:
    A = -np.eye(n) + 0.4 * np.diag(np.ones(n - 1), 1)
    system = linear_system(A, np.eye(1, n), lam=0.1, P=_metric(seed, n, cond), name="chainr")
    gen = torch.Generator().manual_seed(seed)
    net = GainNetwork(n, 1, hidden, structure="direct", K=torch.randn(n, 1, generator=gen),
                      activation=act)
    with torch.no_grad():  # every parameter from `gen`: the case is the seed's alone
        for layer in net.layers:
            layer.weight.copy_(gain * torch.randn(layer.weight.shape, generator=gen)
                               / layer.weight.shape[1] ** 0.5)
            layer.bias.copy_(0.3 * torch.randn(layer.bias.shape, generator=gen))
    return Problem(system, net.double(), 0.1, system.P)


@settings(max_examples=examples(12), deadline=None)
# a case where the first layer's f' errors decide the bound (leaving out the W0 half of their
# rank-one pairs fails here)
@example(seed=0, act="elu", depth=2, n=2, scale=1e-3, level=0.0)
@given(seed=st.integers(0, 10_000), act=st.sampled_from(activations.names()),
       depth=st.integers(1, 3), n=st.integers(2, 4),
       scale=st.sampled_from([0.0, 1e-3, 0.05, 0.3]), level=st.sampled_from([0.0, 2.0]))
@pytest.mark.slow
def test_rank_model_bounds_every_sampled_quadratic_form(seed: int, act: str, depth: int,
                                                        n: int, scale: float,
                                                        level: float) -> None:
    """For sampled points z and vectors v (random, the eigenvectors of D(z) and of D(z)
    minus the model's affine part): v^T D(z) v <= v^T (c + g . dz) v + |v|^T e |v|. The
    rank structure is there for one and two hidden layers, not for three."""
    prob, pc, lo, hi, r, D, dz = mixed_case(seed, n, 8.0, scale, 60,
                                            prob=_chain(seed, n, (6, 5, 4)[:depth], act))
    gen = torch.Generator().manual_seed(seed + 3)
    A, top = contraction_tm_mixed(prob, pc, lo, hi, r, prob.lam, top_apart=True)
    assert (top.rank is not None) == (depth <= 2)
    assert (top.rank is not None and top.rank.lower is not None) == (depth == 2)
    models = [loewner_upper(A, top, level)]
    if top.rank is not None:  # each form alone, for every neuron: both must be sound
        models += [rank_loewner_upper(A, top.C, top.w, top.rank, level, force=f)
                   for f in ("rank", "independent")]
    rnd = torch.randn(5, D.shape[1], 16, n, generator=gen, dtype=F64)
    for U in models:
        M = U.c[:, None] + torch.einsum("bijd,bsd->bsij", U.g, dz)
        v = torch.cat([rnd, torch.linalg.eigh(D).eigenvectors.transpose(-1, -2),
                       torch.linalg.eigh(D - M).eigenvectors.transpose(-1, -2)], 2)
        lhs = torch.einsum("bsvi,bsij,bsvj->bsv", v, D, v)
        rhs = torch.einsum("bsvi,bsij,bsvj->bsv", v, M, v) \
            + torch.einsum("bsvi,bij,bsvj->bsv", v.abs(), U.e, v.abs())
        assert bool((lhs <= rhs + 1e-12 * (1 + lhs.abs())).all())


def assert_majorised(M: torch.Tensor, model: TM, gen: torch.Generator) -> None:
    """v^T M v <= v^T c' v + |v|^T e' |v| for the model (c', e'), M [B, n, n], for v the
    eigenvectors of M - c' (where a violation would show first) and 8 random ones per box."""
    B, n, _ = M.shape
    v = torch.cat([torch.linalg.eigh(M - model.c).eigenvectors.transpose(1, 2),
                   torch.randn(B, 8, n, generator=gen, dtype=F64)], 1)
    lhs = torch.einsum("bvi,bij,bvj->bv", v, M, v)
    rhs = torch.einsum("bvi,bij,bvj->bv", v, model.c, v) \
        + torch.einsum("bvi,bij,bvj->bv", v.abs(), model.e, v.abs())
    assert bool((lhs <= rhs + 1e-12 * (1 + lhs.abs())).all())


def with_lower_entrywise(A: TM, top: TopLayerRemainder) -> TM:
    """A with the first layer's f' errors (apart in `top.rank.lower`) back in its remainder,
    entry by entry, as the backward pass carried them before they were kept apart."""
    full = top.rank.lower.full
    return TM(A.c, A.g, up(A.e + up(0.5 * (full + full.transpose(1, 2)))))


def test_first_layer_rank_terms_decide_boxes_the_entrywise_errors_cannot() -> None:
    """The same chain and boxes: the first layer's f' errors as rank-one terms
    ws1_l |U_l . x| |W0_l . x| decide more boxes than the same errors entry by entry, and
    none whose sampled lam_max exceeds the level."""
    prob = _chain(5, 4, (10, 10), "tanh", cond=30.0)
    pc, lo, hi, r, sampled, level = boxes_and_level(prob, 0.9, 0.1, 0.7)
    A, top = contraction_tm_mixed(prob, pc, lo, hi, r, prob.lam, top_apart=True)
    assert top.rank.lower is not None
    no_lower = TopLayerRemainder(top.C, top.w, replace(top.rank, lower=None))
    old = decided(loewner_upper(with_lower_entrywise(A, top), no_lower, level), r, level)
    new = decided(loewner_upper(A, top, level), r, level)
    assert int(new.sum()) > int(old.sum()), (int(old.sum()), int(new.sum()))
    assert bool((sampled[new] <= level).all())


def test_rank_structure_decides_boxes_the_independent_form_cannot() -> None:
    """A four-state chain with a 2x10 tanh network (gain 2), boxes of radius 0.1 and a level
    between the boxes' sampled maxima: the rank form decides more boxes than the same errors
    taken independent per entry of eps (the form before), and none whose sampled lam_max
    exceeds the level."""
    prob = _chain(5, 4, (10, 10), "tanh", cond=30.0)
    pc, lo, hi, r, sampled, level = boxes_and_level(prob, 0.9, 0.1, 0.7)
    A, top = contraction_tm_mixed(prob, pc, lo, hi, r, prob.lam, top_apart=True)
    assert top.rank is not None
    independent = TopLayerRemainder(top.C, top.w)  # no rank structure: the old form
    old = decided(loewner_upper(with_lower_entrywise(A, top), independent, level), r, level)
    new = decided(loewner_upper(A, top, level), r, level)
    assert int(new.sum()) > int(old.sum()), (int(old.sum()), int(new.sum()))
    assert bool((sampled[new] <= level).all())
    assert bool((sampled > level).any())


@settings(max_examples=examples(10), deadline=None)
@given(seed=st.integers(0, 10_000), act=st.sampled_from(activations.names()),
       n=st.integers(2, 4), scale=st.sampled_from([0.05, 0.3]),
       level=st.sampled_from([0.0, 2.0]))
def test_first_layer_pairs_majorise_every_error_pattern(seed: int, act: str, n: int,
                                                        scale: float, level: float) -> None:
    """The first layer's f' errors alone, at the corners of their set (e1_l = +-ws1_l, the
    top layer's errors 0): v^T (c + E) v <= v^T c' v + |v|^T e' |v| for the model (c', e') that
    `rank_loewner_upper` makes from (c, no remainder) with the top layer's error bounds set to
    0 (so that nothing else pays for these), E = sym(sum_l e1_l U_l W0_l^T), for v the
    eigenvectors of c + E - c' and random ones. Leaving out either half of the pairs fails
    here (checked)."""
    prob, pc, lo, hi, r, D, dz = mixed_case(seed, n, 8.0, scale, 4,
                                            prob=_chain(seed, n, (6, 5), act))
    cols = list(range(n))
    fb = forward_bounds(prob.network, lo, hi, cols=cols, crown=True, taylor=False)
    _, top = mixed_jacobian_crown(prob.network, lo, hi, cols, prob.P_t, fb, top_apart=True)
    low = top.rank.lower
    assert low is not None
    W0 = fb.layers[0].W.to(F64)[:, :n]
    gen = torch.Generator().manual_seed(seed)
    B, h1 = low.ws1.shape
    c0 = 0.5 * torch.randn(B, n, n, generator=gen, dtype=F64)
    c0 = c0 + c0.transpose(1, 2)
    A = TM(c0, torch.zeros(B, n, n, n + 1, dtype=F64), torch.zeros(B, n, n, dtype=F64))
    z = torch.zeros_like
    only_first = replace(top.rank, rs=z(top.rank.rs), ws=z(top.rank.ws),
                         beta=z(top.rank.beta), entry=z(top.rank.entry))
    out = rank_loewner_upper(A, top.C, z(top.w), only_first, level, force="rank")
    for _ in range(16):
        s1 = torch.randint(0, 2, (B, h1), generator=gen).to(F64) * 2 - 1
        E = torch.einsum("bl,bil,lj->bij", s1 * low.ws1, low.U, W0)
        assert_majorised(c0 + 0.5 * (E + E.transpose(1, 2)), out, gen)


@settings(max_examples=examples(10), deadline=None)
@given(seed=st.integers(0, 10_000), act=st.sampled_from(activations.names()),
       n=st.integers(2, 4), scale=st.sampled_from([0.05, 0.3]),
       level=st.sampled_from([0.0, 2.0]), coupled=st.booleans())
def test_beta_terms_majorise_every_error_pattern(seed: int, act: str, n: int, scale: float,
                                                 level: float, coupled: bool) -> None:
    """The products of the two layers' tangent variations alone, at the corners of their set
    (sigma_k = +-rs_k, delta_l = +-rho1_l, every other error 0): v^T (c + E) v <= v^T c' v +
    |v|^T e' |v| for the model (c', e') `rank_loewner_upper` makes in the coupled form and in
    the pair form, E = sym(C diag(sigma) W1 diag(delta) W0), for v the eigenvectors of
    c + E - c' and random ones."""
    prob, pc, lo, hi, r, D, dz = mixed_case(seed, n, 8.0, scale, 4,
                                            prob=_chain(seed, n, (6, 5), act))
    cols = list(range(n))
    fb = forward_bounds(prob.network, lo, hi, cols=cols, crown=True, taylor=False)
    _, top = mixed_jacobian_crown(prob.network, lo, hi, cols, prob.P_t, fb, top_apart=True)
    rank = top.rank
    assert rank.W1 is not None
    gen = torch.Generator().manual_seed(seed)
    B, h = rank.rs.shape
    h1 = rank.rho1.shape[1]
    c0 = 0.5 * torch.randn(B, n, n, generator=gen, dtype=F64)
    c0 = c0 + c0.transpose(1, 2)
    A = TM(c0, torch.zeros(B, n, n, n + 1, dtype=F64), torch.zeros(B, n, n, dtype=F64))
    z = torch.zeros_like
    only_beta = replace(rank, ws=z(rank.ws), o=z(rank.o), tc=z(rank.tc),
                        entry=z(rank.entry), lower=None)
    out = rank_loewner_upper(A, top.C, z(top.w), only_beta, level, force="rank",
                             coupled=coupled)
    C = top.C.to(F64)
    for _ in range(16):
        sig = (torch.randint(0, 2, (B, h), generator=gen).to(F64) * 2 - 1) * rank.rs
        dl = (torch.randint(0, 2, (B, h1), generator=gen).to(F64) * 2 - 1) * rank.rho1
        E = torch.einsum("ik,bk,kl,bl,lj->bij", C, sig, rank.W1, dl, rank.W0)
        assert_majorised(c0 + 0.5 * (E + E.transpose(1, 2)), out, gen)


def test_coupled_beta_terms_decide_boxes_the_pair_form_cannot() -> None:
    """The 2x10 four-state chain of the tests above: the beta terms in the coupled form (the
    cancellations between the top neurons kept) decide more boxes than the pair form alone,
    and none whose sampled lam_max exceeds the level."""
    prob = _chain(5, 4, (10, 10), "tanh", cond=30.0)
    pc, lo, hi, r, sampled, level = boxes_and_level(prob, 0.9, 0.1, 0.7)
    A, top = contraction_tm_mixed(prob, pc, lo, hi, r, prob.lam, top_apart=True)
    old = decided(rank_loewner_upper(A, top.C, top.w, top.rank, level, coupled=False), r,
                  level)
    new = decided(rank_loewner_upper(A, top.C, top.w, top.rank, level), r, level)
    assert int(new.sum()) > int(old.sum()), (int(old.sum()), int(new.sum()))
    assert bool((sampled[new] <= level).all())


@settings(max_examples=examples(40), deadline=None)
@given(seed=st.integers(0, 10_000), h=st.integers(2, 12), h1=st.integers(2, 12),
       spread=st.sampled_from([1e-3, 1.0, 1e3]))
def test_scaled_majorant_dominates_delta_h_delta(seed: int, h: int, h1: int,
                                                 spread: float) -> None:
    """diag(F') >= Delta H Delta for every |delta| <= rho (corners and inside), F' the scaled
    diagonal majorant of the coupled beta terms, H = W1^T diag(y) W1 as `_coupled_beta`
    forms it; and F' <= F, the diagonal dominance bound it scales."""
    from certify.arith.intervals import gamma
    from certify.enclose.top_rank import _scaled_majorant, gram

    gen = torch.Generator().manual_seed(seed)
    B = 16
    W1 = torch.randn(h, h1, generator=gen, dtype=F64)
    y = torch.rand(B, h, generator=gen, dtype=F64) * spread
    rho = torch.rand(B, h1, generator=gen, dtype=F64)
    rho[0, 0] = 0.0  # a neuron without variation
    H = gram(W1, y)
    Herr = up(gamma(h + 2) * gram(W1.abs(), y) * (1.0 + 2.0 * gamma(h + 2)))
    F = up(rho * ((H.abs() + Herr) @ rho[..., None])[..., 0] * (1.0 + 2.0 * gamma(h1 + 2)))
    Fs = _scaled_majorant(H, Herr, rho, F)
    assert bool((Fs <= F).all()) and bool((Fs >= 0).all())
    for corner in (True, False):
        t = torch.rand(B, 32, h1, generator=gen, dtype=F64) * 2 - 1
        if corner:
            t = torch.sign(t)
        d = t * rho[:, None, :]  # [B, S, h1]
        M = torch.diag_embed(Fs)[:, None] - d[..., :, None] * H[:, None] * d[..., None, :]
        lo = torch.linalg.eigvalsh(M)[..., 0]
        assert bool((lo >= -1e-12 * (1.0 + Fs.abs().amax(-1))[:, None]).all())
