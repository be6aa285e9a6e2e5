"""The certified decision lam_max(A) <= level over a box (`certify.enclose.decide`): the box's
own congruence decides families the identity cannot (a spread spectrum, a remainder in the
roomy directions), never decides a family with a member above the level (members sampled at
vertices and inside, remainders at random and at adversarial signs), and the vertex tried first
changes no decision."""

from __future__ import annotations

import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from certify.arith.eigen import cube_vertices, lam_max_at_most, rho_upper
from certify.arith.taylor import TM
from certify.enclose.decide import decide_affine_family, vertex_test
from certify.enclose.taylor import tm_lam_upper

from ..soak import examples

F64 = torch.float64


def _spread_family(gen: torch.Generator, B: int, n: int, d: int, top: torch.Tensor,
                   spread: float, slope: float, rem: float, rotate: bool = True) -> TM:
    """c = Q diag(top, top - spread * u) Q^T with u in [1, 2] (one eigenvalue near the level,
    the others far below), Q a random rotation (else I: the top eigenvector is e_1),
    symmetric slopes of size `slope`, remainder `rem` in every entry."""
    Q = (torch.linalg.qr(torch.randn(B, n, n, generator=gen, dtype=F64))[0] if rotate
         else torch.eye(n, dtype=F64).expand(B, n, n))
    ev = top[:, None] - spread * (1 + torch.rand(B, n, generator=gen, dtype=F64))
    ev[:, 0] = top
    c = Q @ torch.diag_embed(ev) @ Q.transpose(-1, -2)
    c = 0.5 * (c + c.transpose(-1, -2))
    g = torch.randn(B, n, n, d, generator=gen, dtype=F64) * slope
    g = 0.5 * (g + g.transpose(1, 2))
    e = torch.full((B, n, n), rem, dtype=F64)
    return TM(c, g, e)


def _worst_members(A: TM, r: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
    """The largest lam_max over sampled members of each box's family [B]: every vertex and 32
    random points of the affine part, each with the remainder at random signs and at the
    signs of u u^T for u the member's top eigenvector (the remainder's worst case there)."""
    d = r.shape[1]
    V = torch.cat([cube_vertices(d), torch.rand(32, d, generator=gen, dtype=F64) * 2 - 1])
    z = V[None] * r[:, None]
    Az = A.c[:, None] + torch.einsum("bijd,bsd->bsij", A.g, z)
    e = A.e[:, None]
    sgn = torch.randint(0, 2, Az.shape, generator=gen).to(F64) * 2 - 1
    sgn = torch.tril(sgn) + torch.tril(sgn, -1).transpose(-1, -2)
    u = torch.linalg.eigh(Az).eigenvectors[..., -1]
    adv = torch.sign(u[..., :, None] * u[..., None, :])
    lam_rand = torch.linalg.eigvalsh(Az + sgn * e)[..., -1]
    lam_adv = torch.linalg.eigvalsh(Az + adv * e)[..., -1]
    return torch.maximum(lam_rand, lam_adv).amax(-1)


def test_congruence_decides_a_spread_family_the_identity_cannot() -> None:
    """lam_max(c) = -0.1 with eigenvector e_1, the other eigenvalues at -10 or below,
    remainder 0.05 in every entry: rho(rem) = 0.05 n > 0.1, so no test in the original
    coordinates can pass, while in the box's own metric the remainder is small against the
    room in every direction (e_1^T E e_1 <= 0.05 < 0.1: the families really are <= 0)."""
    gen = torch.Generator().manual_seed(3)
    B, n, d = 16, 4, 3
    A = _spread_family(gen, B, n, d, torch.full((B,), -0.1, dtype=F64), 10.0, 1e-4, 0.05,
                       rotate=False)
    r = torch.full((B, d), 0.5, dtype=F64)
    rG = (A.g * r[:, None, None, :]).permute(0, 3, 1, 2)
    rem = A.e + 1e-12
    rr = rho_upper(rem)
    plain, _ = decide_affine_family(A.c, rG, rem, rr, 0.0, congruence=False)
    both, _ = decide_affine_family(A.c, rG, rem, rr, 0.0)
    assert not bool(plain.any()) and bool(both.all())
    assert bool((_worst_members(A, r, gen) <= 0).all())  # and the families really are <= 0


@settings(max_examples=examples(25), deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(4, 6), d=st.integers(2, 5),
       level=st.sampled_from([0.0, -0.3, 0.5]), spread=st.sampled_from([0.5, 5.0, 50.0]),
       rem=st.sampled_from([1e-3, 0.02, 0.1]), rotate=st.booleans())
def test_decided_boxes_hold_every_sampled_member(seed: int, n: int, d: int, level: float,
                                                 spread: float, rem: float,
                                                 rotate: bool) -> None:
    """tm_lam_upper(level=...) with the congruence: every box reported at the level has no
    sampled member above it (adversarial remainders included); boxes span lam_max(c) from
    below the level to above it, so both outcomes occur across the examples."""
    gen = torch.Generator().manual_seed(seed)
    B = 48
    top = level + torch.linspace(-0.6, 0.05, B, dtype=F64)
    A = _spread_family(gen, B, n, d, top, spread, 0.02, rem, rotate)
    r = torch.rand(B, d, generator=gen, dtype=F64) + 0.1
    bound, _ = tm_lam_upper(A, r, level=level)
    lvl = level - 1e-12 * (1.0 + abs(level))
    decided = bound == lvl
    worst = _worst_members(A, r, gen)
    assert bool((worst[decided] <= lvl + 1e-12 * (1 + abs(lvl))).all())
    assert not bool(decided[top > level].any())  # the centre itself is above the level


def test_a_planted_vertex_above_the_level_is_never_decided() -> None:
    """One vertex of the affine part above the level, everything else far below: not decided,
    with or without the congruence, whichever vertex is tried first."""
    gen = torch.Generator().manual_seed(11)
    B, n, d = 8, 5, 4
    A = _spread_family(gen, B, n, d, torch.full((B,), -0.05, dtype=F64), 10.0, 0.0, 1e-6)
    g = torch.zeros(B, n, n, d, dtype=F64)
    Q = torch.linalg.eigh(A.c).eigenvectors[..., -1]  # top eigenvector of c
    for m in range(d):  # all d slopes push the top eigenvalue up at the vertex (1, ..., 1)
        g[..., m] = 0.02 * Q[:, :, None] * Q[:, None, :]
    r = torch.ones(B, d, dtype=F64)
    rG = (g * r[:, None, None, :]).permute(0, 3, 1, 2)
    rem = A.e + 1e-12
    for cong in (False, True):
        decided, _ = decide_affine_family(A.c, rG, rem, rho_upper(rem), 0.0, congruence=cong)
        assert not bool(decided.any())


def test_vertex_tried_first_changes_no_decision() -> None:
    """vertex_test with any first vertex equals testing all 2^d vertices."""
    gen = torch.Generator().manual_seed(5)
    B, n, d = 64, 4, 3
    A = _spread_family(gen, B, n, d, torch.linspace(-0.5, 0.1, B, dtype=F64), 1.0, 0.05, 0.0)
    rG = (A.g * 0.5).permute(0, 3, 1, 2)
    t = torch.zeros(B, dtype=F64)
    V = cube_vertices(d)
    S = A.c[:, None] + torch.einsum("vd,bdij->bvij", V, rG)
    every = lam_max_at_most(S, t[:, None].expand(B, len(V))).all(-1)
    assert bool(every.any()) and bool((~every).any())
    for first in (torch.ones(B, d, dtype=F64), -torch.ones(B, d, dtype=F64),
                  torch.randint(0, 2, (B, d), generator=gen).to(F64) * 2 - 1):
        assert torch.equal(vertex_test(A.c, rG, t, first), every)


def test_nan_boxes_are_never_decided() -> None:
    gen = torch.Generator().manual_seed(2)
    B, n, d = 4, 4, 2
    A = _spread_family(gen, B, n, d, torch.full((B,), -1.0, dtype=F64), 1.0, 0.0, 1e-6)
    c = A.c.clone()
    c[1, 2, 3] = c[1, 3, 2] = float("nan")
    c[2, 0, 0] = float("inf")
    rG = (A.g * 0.1).permute(0, 3, 1, 2)
    rem = A.e + 1e-12
    decided, _ = decide_affine_family(c, rG, rem, rho_upper(rem), 0.0)
    assert decided.tolist() == [True, False, False, True]
