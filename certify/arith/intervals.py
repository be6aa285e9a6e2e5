"""Interval arithmetic on batched float64 tensors, sound under floating point.

An `Interval` is a pair of tensors (lo, hi) of the same shape ``[batch, ...]``. Every
operation rounds outward (the scheme is `ROUNDING`, quoted verbatim by the certificate), so
the true real-number result of the operation on any reals inside the operands lies inside
the computed interval. NaN anywhere means "undefined somewhere in the box": callers treat
it as UNKNOWN, never as proved.

This module holds the number type and its arithmetic: the rounding helpers (`down`, `up`,
the libm widening, Higham's `gamma`), +, -, *, powers and reciprocals, and products with
point or interval matrices in midpoint-radius form. The elementary-function rules and the
`certify.spec.expr.Algebra` over intervals are in `certify.spec.interval_rules`; the enclosures of a
system's f, h and their derivatives over boxes in `certify.spec.enclosures`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch

ROUNDING = (
    "outward rounding: every +, -, *, / and sqrt result is moved one ulp outward with "
    "torch.nextafter (round-to-nearest errs by at most half an ulp); libm functions (sin, "
    "cos, tan, exp, log, tanh, pow, hypot) are widened by 4 ulps relative plus 4 * 2^-1022 "
    "absolute (their documented error is <= 1 ulp); products with point matrices (BLAS) are "
    "done in midpoint-radius form with Higham's bound gamma_k |W| |c| added to the radius "
    "and the radius rounded up by (1 + 2 gamma_k); eigenvalues of point symmetric matrices "
    "come from closed forms with outward rounding (n <= 2) or LAPACK plus a margin of "
    "8 (n + 1) u ||A||_F; spectral radii of non-negative matrices are bounded by a "
    "Collatz-Wielandt quotient rounded up; first-order Taylor models absorb the float "
    "errors of their centre and coefficients into the remainder (gamma_k |.| bounds, "
    "rounded up). NaN or Inf in any bound makes the box UNKNOWN."
)

U = 2.0**-53  # unit roundoff of float64
EPS = 2.0**-52  # machine epsilon of float64 (2 U)
EPS = 2.0**-52
TINY = 2.0**-1022
LIBM_ULPS = 4
_POS_INF = float("inf")


def gamma(k: int) -> float:
    """Higham's gamma_k = k u / (1 - k u), slightly rounded up."""
    return (k * U / (1.0 - k * U)) * (1.0 + 1e-12)


_INFS: dict[tuple[torch.device, torch.dtype], tuple[torch.Tensor, torch.Tensor]] = {}


def _infs(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(-inf, +inf) as 0-d tensors on x's device and of its dtype, made once per device:
    `torch.nextafter` on a GPU takes no CPU scalar tensor."""
    key = (x.device, x.dtype)
    pair = _INFS.get(key)
    if pair is None:
        pair = _INFS[key] = (torch.tensor(-_POS_INF, dtype=x.dtype, device=x.device),
                             torch.tensor(_POS_INF, dtype=x.dtype, device=x.device))
    return pair


def down(x: torch.Tensor) -> torch.Tensor:
    """One ulp towards -inf (covers a round-to-nearest error)."""
    return torch.nextafter(x, _infs(x)[0])


def up(x: torch.Tensor) -> torch.Tensor:
    """One ulp towards +inf."""
    return torch.nextafter(x, _infs(x)[1])


def widen_down(x: torch.Tensor, ulps: int = LIBM_ULPS) -> torch.Tensor:
    """At least `ulps` ulps below x (for libm results)."""
    return down(x - (ulps * EPS) * x.abs() - ulps * TINY)


def widen_up(x: torch.Tensor, ulps: int = LIBM_ULPS) -> torch.Tensor:
    """At least `ulps` ulps above x."""
    return up(x + (ulps * EPS) * x.abs() + ulps * TINY)


@dataclass(frozen=True)
class Interval:
    """A batch of real intervals [lo, hi] (tensors of equal shape, float64)."""

    lo: torch.Tensor
    hi: torch.Tensor

    @staticmethod
    def point(x: torch.Tensor) -> Interval:
        return Interval(x, x)

    @property
    def shape(self) -> torch.Size:
        return self.lo.shape

    def mid(self) -> torch.Tensor:
        return 0.5 * (self.lo + self.hi)

    def midrad(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Centre c and a radius r (rounded up) with [lo, hi] inside [c - r, c + r]."""
        c = 0.5 * (self.lo + self.hi)
        r = up(torch.maximum(self.hi - c, c - self.lo))
        return c, r

    def mag(self) -> torch.Tensor:
        """max |x| over the interval."""
        return torch.maximum(self.lo.abs(), self.hi.abs())

    def mig(self) -> torch.Tensor:
        """min |x| over the interval (0 when it contains 0)."""
        zero = torch.zeros_like(self.lo)
        return torch.where(self.lo > 0, self.lo, torch.where(self.hi < 0, -self.hi, zero))

    def contains(self, x: torch.Tensor) -> torch.Tensor:
        return (self.lo <= x) & (x <= self.hi)

    def __getitem__(self, idx: Any) -> Interval:
        return Interval(self.lo[idx], self.hi[idx])

    def __neg__(self) -> Interval:
        return Interval(-self.hi, -self.lo)

    def __add__(self, other: Interval | float) -> Interval:
        o = _as_interval(other, self)
        return Interval(down(self.lo + o.lo), up(self.hi + o.hi))

    __radd__ = __add__

    def __sub__(self, other: Interval | float) -> Interval:
        return self + (-_as_interval(other, self))

    def __rsub__(self, other: Interval | float) -> Interval:
        return _as_interval(other, self) + (-self)

    def __mul__(self, other: Interval | float) -> Interval:
        return imul(self, _as_interval(other, self))

    __rmul__ = __mul__


def _as_interval(v: Interval | float | torch.Tensor, like: Interval) -> Interval:
    if isinstance(v, Interval):
        return v
    return const_interval(float(v), like.lo) if not torch.is_tensor(v) else Interval(v, v)


def const_interval(value: float, like: torch.Tensor) -> Interval:
    """A constant; decimal constants that are not exact doubles are widened one ulp."""
    t = torch.full_like(like, value)
    if math.isfinite(value) and float(value).is_integer() and abs(value) < 2.0**53:
        return Interval(t, t)
    return Interval(down(t), up(t))


def imul(a: Interval, b: Interval) -> Interval:
    """Interval product (min/max of the four endpoint products, rounded outward)."""
    p1, p2, p3, p4 = a.lo * b.lo, a.lo * b.hi, a.hi * b.lo, a.hi * b.hi
    lo = torch.minimum(torch.minimum(p1, p2), torch.minimum(p3, p4))
    hi = torch.maximum(torch.maximum(p1, p2), torch.maximum(p3, p4))
    return Interval(down(lo), up(hi))


def isqr(a: Interval) -> Interval:
    """a^2, hand-written (the product a*a would lose the dependency)."""
    lo2, hi2 = a.mig() ** 2, a.mag() ** 2
    return Interval(down(lo2).clamp_min(0.0), up(hi2))


def ipow_int(a: Interval, k: int) -> Interval:
    """a^k for an integer k (even powers hand-written; 1/0 gives an infinite bound)."""
    if k == 0:
        one = torch.ones_like(a.lo)
        return Interval(one, one)
    if k == 1:
        return a
    if k == 2:
        return isqr(a)
    if k < 0:
        return ireciprocal(ipow_int(a, -k))
    ulps = LIBM_ULPS + k
    if k % 2 == 0:
        lo, hi = a.mig() ** k, a.mag() ** k
    else:
        lo, hi = a.lo**k, a.hi**k
    lo = widen_down(lo, ulps)
    if k % 2 == 0:
        lo = lo.clamp_min(0.0)
    return Interval(lo, widen_up(hi, ulps))


def ireciprocal(a: Interval) -> Interval:
    """1/a; an interval touching 0 gives (-inf, inf) (UNKNOWN downstream)."""
    safe = (a.lo > 0) | (a.hi < 0)
    lo = torch.where(safe, down(1.0 / a.hi), torch.full_like(a.lo, -_POS_INF))
    hi = torch.where(safe, up(1.0 / a.lo), torch.full_like(a.lo, _POS_INF))
    return Interval(lo, hi)


def ipow_real(a: Interval, e: float) -> Interval:
    """a^e for a non-integer real e (NaN where a < 0: undefined in the box)."""
    nan = torch.full_like(a.lo, float("nan"))
    lo_ok = a.lo >= 0
    if e > 0:
        lo, hi = a.lo**e, a.hi**e
    else:
        lo, hi = a.hi**e, a.lo**e
    lo = torch.where(lo_ok, widen_down(lo).clamp_min(0.0), nan)
    hi = torch.where(lo_ok, widen_up(hi), nan)
    return Interval(lo, hi)


# ----- products with point matrices (midpoint-radius, Higham's bound) --------------------
def matmul_point_right(c: torch.Tensor, r: torch.Tensor, W: torch.Tensor
                       ) -> tuple[torch.Tensor, torch.Tensor]:
    """Enclosure of X @ W for X in [c - r, c + r] and a point matrix W [k, m].

    Returns (centre, radius) with radius rounded up; covers BLAS rounding of c @ W.
    """
    k = W.shape[-2]
    g = gamma(k + 2)
    absW = W.abs()
    cy = c @ W
    ry = (r + g * c.abs()) @ absW
    ry = up(ry * (1.0 + 2.0 * g) + k * TINY)
    return cy, ry


def midrad_to_interval(c: torch.Tensor, r: torch.Tensor) -> Interval:
    return Interval(down(c - r), up(c + r))


def imatmul(A: Interval, B: Interval) -> Interval:
    """Interval matrix product A @ B (batched, last two dims), midpoint-radius form."""
    ca, ra = A.midrad()
    cb, rb = B.midrad()
    k = ca.shape[-1]
    g = gamma(k + 3)
    cy = ca @ cb
    ry = ca.abs() @ rb + ra @ (cb.abs() + rb)
    ry = ry + g * (ca.abs() @ cb.abs())
    ry = up(ry * (1.0 + 2.0 * g) + k * TINY)
    return midrad_to_interval(cy, ry)
