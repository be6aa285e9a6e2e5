"""Whole-box decisions beyond the vertex dimension (`certify.enclose.whole_box`): never a box
with a member above the level (members sampled at random and at adversarial vertices, with
remainders at random and adversarial signs), a spread family the hull cannot decide is
decided, and `tm_lam_upper` reports the level only for boxes the decision proved."""

from __future__ import annotations

import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from certify.arith.eigen import MAX_VERTEX_DIM
from certify.arith.taylor import TM
from certify.enclose.taylor import tm_lam_upper
from certify.enclose.whole_box import decide_whole_box, spectral_norm_upper

from ..soak import examples

F64 = torch.float64


def _family(gen: torch.Generator, B: int, n: int, d: int, top: float, spread: float,
            slope: float, rem: float) -> TM:
    """c = Q diag(top, top - spread u) Q^T (u in [1, 2]), random symmetric slopes whose sizes
    fall off with the coordinate (a few strong ones, many weak), remainder `rem`."""
    Q = torch.linalg.qr(torch.randn(B, n, n, generator=gen, dtype=F64))[0]
    ev = top - spread * (1 + torch.rand(B, n, generator=gen, dtype=F64))
    ev[:, 0] = top
    c = Q @ torch.diag_embed(ev) @ Q.transpose(-1, -2)
    c = 0.5 * (c + c.transpose(-1, -2))
    fall = 0.5 ** torch.arange(d, dtype=F64)
    g = torch.randn(B, n, n, d, generator=gen, dtype=F64) * slope * fall
    g = 0.5 * (g + g.transpose(1, 2))
    return TM(c, g, torch.full((B, n, n), rem, dtype=F64))


def _worst_members(A: TM, gen: torch.Generator, samples: int = 256) -> torch.Tensor:
    """The largest lam_max over sampled members [B]: random points and sign vectors of the
    cube, the first-order vertex towards the centre's top eigenvector, each with the
    remainder at random signs and at the signs of u u^T (u the member's top eigenvector)."""
    B, n, _, d = A.g.shape
    v = torch.rand(B, samples, d, generator=gen, dtype=F64) * 2 - 1
    v[:, samples // 2:] = torch.sign(v[:, samples // 2:])
    u0 = torch.linalg.eigh(A.c).eigenvectors[..., -1]
    v[:, 0] = torch.sign(torch.einsum("bi,bijd,bj->bd", u0, A.g, u0))
    Az = A.c[:, None] + torch.einsum("bijd,bsd->bsij", A.g, v)
    sgn = torch.randint(0, 2, Az.shape, generator=gen).to(F64) * 2 - 1
    sgn = torch.tril(sgn) + torch.tril(sgn, -1).transpose(-1, -2)
    u = torch.linalg.eigh(Az).eigenvectors[..., -1]
    adv = torch.sign(u[..., :, None] * u[..., None, :])
    e = A.e[:, None]
    lam = torch.maximum(torch.linalg.eigvalsh(Az + sgn * e)[..., -1],
                        torch.linalg.eigvalsh(Az + adv * e)[..., -1])
    return lam.amax(-1)


@settings(max_examples=examples(25), deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(2, 6), d=st.integers(1, 12),
       level=st.sampled_from([0.0, -0.3, 0.5]), spread=st.sampled_from([0.5, 5.0, 50.0]),
       slope=st.sampled_from([0.01, 0.1, 1.0]), rem=st.sampled_from([1e-4, 0.02]),
       keep=st.integers(0, 8))
def test_decided_boxes_have_no_member_above_the_level(seed, n, d, level, spread, slope, rem,
                                                      keep) -> None:
    gen = torch.Generator().manual_seed(seed)
    B = 24
    A = _family(gen, B, n, d, level - 0.2, spread, slope, rem)
    r = torch.ones(B, d, dtype=F64)
    rG = A.g.permute(0, 3, 1, 2)
    decided = decide_whole_box(A.c, rG, A.e, level, keep=keep)
    worst = _worst_members(A, gen)
    assert not bool((decided & (worst > level)).any())
    bound, _ = tm_lam_upper(A, r, level=level)
    assert not bool(((bound <= level) & (worst > level)).any())


def test_spread_family_is_decided_where_the_hull_is_not() -> None:
    """Twelve coordinates (beyond the vertex dimension), a centre with one eigenvalue just
    below the level and the rest far below, slopes that move D mostly in the roomy
    directions: the hull bound (every coordinate's entries in the remainder) stays above the
    level, the whole-box decision proves every box, and no sampled member is above it."""
    gen = torch.Generator().manual_seed(7)
    B, n, d = 16, 5, 12
    assert d > MAX_VERTEX_DIM
    A = _family(gen, B, n, d, -0.5, 20.0, 0.1, 1e-4)
    r = torch.ones(B, d, dtype=F64)
    hull, _ = tm_lam_upper(A, r)  # no level: the bound alone, the first-order part in rem
    assert bool((hull > 0).all())
    assert bool(decide_whole_box(A.c, A.g.permute(0, 3, 1, 2), A.e, 0.0).all())
    bound, _ = tm_lam_upper(A, r, level=0.0)
    assert bool((bound <= 0).all())
    assert bool((_worst_members(A, gen) <= 0).all())


def test_nan_and_a_centre_above_the_level_never_decide() -> None:
    gen = torch.Generator().manual_seed(1)
    A = _family(gen, 4, 3, 10, 0.5, 5.0, 1e-6, 1e-6)  # centre above the level 0
    rG = A.g.permute(0, 3, 1, 2)
    assert not bool(decide_whole_box(A.c, rG, A.e, 0.0).any())
    B = _family(gen, 4, 3, 10, -1.0, 5.0, 1e-6, 1e-6)
    c = B.c.clone()
    c[0, 1, 1] = float("nan")
    rem = B.e.clone()
    rem[1, 0, 0] = float("inf")
    out = decide_whole_box(c, B.g.permute(0, 3, 1, 2), rem, 0.0)
    assert out.tolist() == [False, False, True, True]


def test_spectral_norm_upper_bounds_the_norm() -> None:
    gen = torch.Generator().manual_seed(2)
    G = torch.randn(50, 4, 4, generator=gen, dtype=F64)
    S = torch.tril(G) + torch.tril(G, -1).transpose(-1, -2)
    exact = torch.linalg.matrix_norm(S, ord=2)
    assert bool((spectral_norm_upper(G) >= exact).all())
    assert bool((spectral_norm_upper(G) <= exact * (1 + 1e-12) + 1e-12).all())
