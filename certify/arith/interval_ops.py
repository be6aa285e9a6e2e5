"""Small batched interval helpers shared by the bound modules (outward rounded).

Sums carry Higham's gamma_k sum|x| summation error; every other result is moved one ulp
outward (`certify.arith.intervals.down` / `up`), as in `certify.arith.intervals.ROUNDING`.
"""

from __future__ import annotations

import torch

from certify.arith.intervals import TINY, Interval, down, gamma, up


def isum(a: Interval, dim: int) -> Interval:
    """Sum along `dim`, with the floating-point summation error bounded by gamma_k sum|x|."""
    k = a.lo.shape[dim]
    g = gamma(k + 1)
    slo = a.lo.sum(dim)
    shi = a.hi.sum(dim)
    elo = g * a.lo.abs().sum(dim) + k * TINY
    ehi = g * a.hi.abs().sum(dim) + k * TINY
    return Interval(down(slo - elo), up(shi + ehi))


def iadd(a: Interval, b: Interval) -> Interval:
    return Interval(down(a.lo + b.lo), up(a.hi + b.hi))


def isym(a: Interval) -> Interval:
    """He{A} = (A + A^T)/2 for an interval matrix [..., n, n]."""
    s = iadd(a, Interval(a.lo.transpose(-1, -2), a.hi.transpose(-1, -2)))
    return Interval(down(0.5 * s.lo), up(0.5 * s.hi))


def intersect(a: Interval, b: Interval) -> Interval:
    """a cap b (both contain the true value, so the intersection does too)."""
    return Interval(torch.maximum(a.lo, b.lo), torch.minimum(a.hi, b.hi))


def point(x: torch.Tensor) -> Interval:
    return Interval(x, x)



def const_lam(v: float, like: Interval) -> Interval:
    """The constant v as a one-ulp-wide interval shaped like `like`."""
    t = torch.full_like(like.lo, v)
    return Interval(down(t), up(t))


def bcast(a: Interval, B: int) -> Interval:
    """Expand an [n, n] interval matrix to [B, n, n]."""
    return Interval(a.lo.expand(B, *a.lo.shape[-2:]), a.hi.expand(B, *a.hi.shape[-2:]))


def nan_min(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Elementwise min that keeps NaN (unknown) when either side is NaN."""
    bad = torch.isnan(a) | torch.isnan(b)
    return torch.where(bad, torch.full_like(a, float("nan")), torch.minimum(a, b))
