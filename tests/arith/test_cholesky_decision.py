"""The certified Cholesky test lam_max(S) <= t (`certify.arith.eigen.lam_max_at_most`) and its
use in the vertex bound (`tm_lam_upper(level=...)`): never True when the exact lam_max (mpmath,
50 digits) is above t, True wherever there is a little slack, False on NaN/Inf; a box the test
decides reports a level that is above every sampled lam_max of its Taylor model."""

from __future__ import annotations

import math

import mpmath
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from certify.arith.eigen import cube_vertices, lam_max_at_most
from certify.arith.taylor import TM
from certify.enclose.taylor import tm_lam_upper
from tests.mp_reference import exact_lam_max

from ..soak import examples

F64 = torch.float64


def _sym(gen: torch.Generator, count: int, n: int, scale: float, rank_def: bool
         ) -> torch.Tensor:
    A = torch.randn(count, n, n, generator=gen, dtype=F64) * scale
    if rank_def:  # a cluster of top eigenvalues (rank-deficient t I - S at t = lam_max)
        Q, _ = torch.linalg.qr(torch.randn(count, n, n, generator=gen, dtype=F64))
        ev = torch.randn(count, n, generator=gen, dtype=F64) * scale
        ev[:, : n // 2] = ev[:, :1]
        A = Q @ torch.diag_embed(ev) @ Q.transpose(-1, -2)
    return 0.5 * (A + A.transpose(-1, -2))


@settings(max_examples=examples(25), deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(2, 7),
       scale=st.sampled_from([1e-200, 1e-3, 1.0, 1e6, 1e200]), rank_def=st.booleans(),
       rel=st.sampled_from([-1e-6, -1e-12, -1e-15, 0.0, 1e-15, 1e-12, 1e-9, 1e-6]))
def test_cholesky_test_never_passes_above_theexact_lam_max(seed: int, n: int, scale: float,
                                                           rank_def: bool, rel: float) -> None:
    gen = torch.Generator().manual_seed(seed)
    S = _sym(gen, 6, n, scale, rank_def)
    lam = torch.linalg.eigvalsh(S)[:, -1]
    norm = torch.linalg.matrix_norm(S, ord=2)
    t = lam + rel * norm  # levels straddling lam_max within a few ulps to 1e-6 ||S||
    ok = lam_max_at_most(S, t)
    for b in range(len(S)):
        if bool(ok[b]):
            assert exact_lam_max(S[b].numpy()) <= mpmath.mpf(float(t[b]))


def test_cholesky_test_decides_with_slack_and_refuses_nan() -> None:
    gen = torch.Generator().manual_seed(0)
    for n in (2, 4, 6, 8):
        S = _sym(gen, 200, n, 1.0, False)
        lam = torch.linalg.eigvalsh(S)[:, -1]
        norm = torch.linalg.matrix_norm(S, ord=2)
        assert bool(lam_max_at_most(S, lam + 1e-9 * norm).all())  # slack: always decided
        assert not bool(lam_max_at_most(S, lam - 1e-9 * norm).any())  # false: never
    S = _sym(gen, 3, 4, 1.0, False)
    S[0, 1, 1] = float("nan")
    S[1, 2, 0] = S[1, 0, 2] = float("inf")
    t = torch.tensor([1e3, 1e3, float("nan")], dtype=F64)
    assert not bool(lam_max_at_most(S, t).any())
    assert lam_max_at_most(torch.zeros(0, 4, 4, dtype=F64), torch.zeros(0, dtype=F64)).shape \
        == (0,)


@settings(max_examples=examples(20), deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(4, 6), d=st.integers(2, 6),
       level=st.sampled_from([0.0, -0.5, 0.3]))
def test_vertex_bound_with_level_contains_sampled_lam_max(seed: int, n: int, d: int,
                                                           level: float) -> None:
    """tm_lam_upper(level=...): every box reports a bound above the sampled lam_max of its
    Taylor model's members (affine part plus any symmetric remainder within e), decided boxes
    at the level, the rest as without the level; both kinds occur."""
    gen = torch.Generator().manual_seed(seed)
    B = 64
    c = _sym(gen, B, n, 1.0, False)
    shift = level - torch.linalg.eigvalsh(c)[:, -1] + torch.linspace(-2.0, 0.5, B, dtype=F64)
    c = c + shift[:, None, None] * torch.eye(n, dtype=F64)  # lam_max(c) from level - 2 up
    g = torch.randn(B, n, n, d, generator=gen, dtype=F64) * 0.1
    g = 0.5 * (g + g.transpose(1, 2))
    e = torch.rand(B, n, n, generator=gen, dtype=F64) * 0.02
    e = 0.5 * (e + e.transpose(1, 2))
    r = torch.rand(B, d, generator=gen, dtype=F64) + 0.1
    A = TM(c, g, e)
    plain, _ = tm_lam_upper(A, r)
    decided, _ = tm_lam_upper(A, r, level=level)
    lvl = level - 1e-12 * (1.0 + abs(level))
    at_level = decided == lvl
    assert bool(at_level.any()) and bool((~at_level).any())
    # undecided boxes: vertices count at the first level of the ladder they pass (above
    # their eigenvalue bound but for its own margin), the rest at their eigenvalue bound
    und, pl = decided[~at_level], plain[~at_level]
    assert bool((und >= pl - 1e-12 * (1.0 + pl.abs())).all())
    # (a decided box's plain bound may exceed the level: the box's own congruence,
    # `certify.enclose.decide`, weighs the remainder against the room in each direction;
    # what must hold is that no member is above the level, sampled below)
    # samples: vertices and random points, remainders at random signs
    V = torch.cat([cube_vertices(d), torch.rand(32, d, generator=gen, dtype=F64) * 2 - 1])
    z = V[None] * r[:, None]  # [B, S, d]
    Az = c[:, None] + torch.einsum("bijd,bsd->bsij", g, z)
    sgn = torch.randint(0, 2, Az.shape, generator=gen).to(F64) * 2 - 1
    sgn = torch.tril(sgn) + torch.tril(sgn, -1).transpose(-1, -2)
    Az = Az + sgn * e[:, None]
    lam = torch.linalg.eigvalsh(Az)[..., -1].amax(-1)
    assert bool((lam <= decided + 1e-12 * (1 + lam.abs())).all())
    assert all(math.isfinite(float(v)) for v in decided)


def test_boxes_weyl_decides_skip_the_vertex_tests(monkeypatch) -> None:
    """tm_lam_upper(level=...): boxes whose Weyl bound of the affine part already passes get
    no vertex tests, and are reported decided like the vertex-tested ones."""
    import certify.enclose.decide as decide

    gen = torch.Generator().manual_seed(7)
    B, n, d = 32, 4, 3
    c = _sym(gen, B, n, 1.0, False)
    shift = -torch.linalg.eigvalsh(c)[:, -1] + torch.linspace(-3.0, 0.5, B, dtype=F64)
    c = c + shift[:, None, None] * torch.eye(n, dtype=F64)
    g = torch.randn(B, n, n, d, generator=gen, dtype=F64) * 0.1
    g = 0.5 * (g + g.transpose(1, 2))
    A = TM(c, g, torch.full((B, n, n), 1e-3, dtype=F64))
    r = torch.full((B, d), 0.5, dtype=F64)
    seen = []

    def counting(S, t):
        seen.append(S.shape[0])
        return lam_max_at_most(S, t)

    monkeypatch.setattr(decide, "lam_max_at_most", counting)
    bound, _ = tm_lam_upper(A, r, level=0.0)
    lvl = -1e-12
    assert 0 < sum(seen) < B  # Weyl decided some boxes, the vertices were tested on others
    assert bool((bound[:8] == lvl).all())
    assert not bool((bound[-4:] <= 0).any())  # lam_max(c) > 0 there: never decided
