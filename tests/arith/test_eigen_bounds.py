"""Eigenvalue upper bounds: the certified 3x3 closed form is above the exact lam_max (mpmath
reference at 50 digits) and close to it; refused cases fall back to LAPACK."""

from __future__ import annotations

import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from certify.arith.eigen import (
    _lam3_certified,
    _pairs_lower,
    hertz_upper,
    lam_max_upper_interval,
    lam_max_upper_point,
)
from certify.arith.intervals import Interval
from tests.mp_reference import exact_lam_max

from ..soak import examples

F64 = torch.float64


def _sym_batch(seed: int, count: int, scale: float, cluster: bool) -> torch.Tensor:
    """Random symmetric 3x3 matrices; `cluster`: nearly repeated top eigenvalues."""
    gen = torch.Generator().manual_seed(seed)
    A = torch.randn(count, 3, 3, generator=gen, dtype=F64)
    if cluster:
        Q, _ = torch.linalg.qr(A)
        ev = torch.tensor([1.0, 1.0 + 1e-13, -0.5], dtype=F64)
        A = Q @ torch.diag(ev) @ Q.transpose(-1, -2)
    return scale * 0.5 * (A + A.transpose(-1, -2))


@settings(max_examples=examples(12), deadline=None)
@given(seed=st.integers(0, 10_000), scale=st.sampled_from([1e-6, 1.0, 37.0, 1e5]),
       cluster=st.booleans())
def test_lam3_bound_containsexact_lam_max(seed: int, scale: float, cluster: bool) -> None:
    S = _sym_batch(seed, 6, scale, cluster)
    ub = lam_max_upper_point(S)
    for k in range(len(S)):
        exact = exact_lam_max(S[k].numpy())
        assert float(ub[k]) >= exact
        # tight: within a relative 1e-7 of the matrix scale
        assert float(ub[k]) - exact <= 1e-7 * float(S[k].abs().sum()) + 1e-280


def test_lam3_certifies_generic_matrices_and_refuses_nan() -> None:
    S = _sym_batch(3, 200, 1.0, False)
    mu, ok = _lam3_certified(S)
    assert float(ok.double().mean()) > 0.95  # the fast path decides almost every matrix
    exact = torch.linalg.eigvalsh(S)[:, -1]
    assert bool((mu[ok] > exact[ok]).all())
    bad = S.clone()
    bad[0, 1, 0] = float("nan")
    _, ok_bad = _lam3_certified(bad)
    assert not bool(ok_bad[0])
    assert torch.isnan(lam_max_upper_point(bad)[0])


def test_lam3_zero_and_diagonal_matrices() -> None:
    Z = torch.zeros(1, 3, 3, dtype=F64)
    assert float(lam_max_upper_point(Z)[0]) >= 0.0
    D = torch.diag(torch.tensor([-1.0, 2.0, 0.5], dtype=F64))[None]
    ub = float(lam_max_upper_point(D)[0])
    assert 2.0 <= ub <= 2.0 + 1e-6


def test_hertz_3x3_above_sampled_members() -> None:
    gen = torch.Generator().manual_seed(5)
    C = _sym_batch(7, 20, 1.0, False)
    R = torch.rand(20, 3, 3, generator=gen, dtype=F64) * 0.3
    R = 0.5 * (R + R.transpose(-1, -2))
    ub = hertz_upper(C, R)
    for _ in range(30):
        E = (2 * torch.rand(20, 3, 3, generator=gen, dtype=F64) - 1) * R
        E = torch.tril(E) + torch.tril(E, -1).transpose(-1, -2)
        assert bool((torch.linalg.eigvalsh(C + E)[:, -1] <= ub).all())


@settings(max_examples=examples(10), deadline=None)
@given(seed=st.integers(0, 10_000), n=st.sampled_from([3, 4, 5, 7]),
       level=st.sampled_from([-0.5, 0.0, 0.5]))
def test_interval_bound_with_a_level_is_sound_and_decides_the_same(seed: int, n: int,
                                                                   level: float) -> None:
    """lam_max_upper_interval(A, level): above every sampled member of the family (also where
    the 2 x 2 sub-families say no bound decides and Gershgorin is returned); decides exactly
    the boxes the full bound decides, with the same value there; and a sub-family whose
    exact max exceeds the level is never decided."""
    gen = torch.Generator().manual_seed(seed)
    C = torch.randn(64, n, n, generator=gen, dtype=F64) * 0.3
    C = 0.5 * (C + C.transpose(-1, -2)) - torch.eye(n, dtype=F64) * (0.2 + n * 0.15)
    R = torch.rand(64, n, n, generator=gen, dtype=F64) * 0.3 * torch.rand(64, 1, 1, generator=gen,
                                                                          dtype=F64)
    R = 0.5 * (R + R.transpose(-1, -2))
    A = Interval(C - R, C + R)
    full = lam_max_upper_interval(A)
    lev = lam_max_upper_interval(A, level=level)
    # (LAPACK's eigenvalues of a sub-batch may differ from the whole batch's in the last
    # bits, inside the bound's margin: compare to 1e-12)
    edge = (full - level).abs() <= 1e-12
    assert bool(((lev <= level) == (full <= level))[~edge].all())
    decided = full <= level
    assert torch.allclose(lev[decided], full[decided], rtol=0, atol=1e-12)
    assert bool((lev >= full - 1e-12).all())  # never tighter than the full bound
    for _ in range(20):
        E = (2 * torch.rand(64, n, n, generator=gen, dtype=F64) - 1) * R
        E = torch.tril(E) + torch.tril(E, -1).transpose(-1, -2)
        assert bool((torch.linalg.eigvalsh(C + E)[:, -1] <= lev).all())
    # a 2 x 2 sub-family above the level: its members' lam_max is, so nothing may decide
    pair = _pairs_lower(A)
    assert not bool((lev[pair > level] <= level).any())
    assert 0 < int(decided.sum()) < 64 or level != 0.0  # the level splits the batch here
    assert bool((pair > level).any()) or level != -0.5  # and the shortcut is taken
