"""Interval arithmetic on batched float64 tensors, sound under floating point.

An `Interval` is a pair of tensors (lo, hi) of the same shape ``[batch, ...]``. Every
operation rounds outward (the scheme is `ROUNDING`, quoted verbatim by the certificate), so
the true real-number result of the operation on any reals inside the operands lies inside
the computed interval. NaN anywhere means "undefined somewhere in the box": callers treat
it as UNKNOWN, never as proved.

`RULES` is the one table: each whitelisted function name of `certify.expr.FUNCTIONS` maps to
its torch point function and, beside it, its enclosure rule. Monotone functions share the
endpoint rule; `sin`, `cos`, `tan`, `abs`, even powers and products are hand-written.
`INTERVAL` is the `certify.expr.Algebra` that evaluates sympy trees over intervals, used
for the enclosures of f, h, their Jacobians and second derivatives.
"""

from __future__ import annotations

import math
import weakref
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import sympy
import torch

from certify.errors import SpecError
from certify.expr import DERIVED_FUNCTIONS, FUNCTIONS, evaluate

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
EPS = 2.0**-52
TINY = 2.0**-1022
LIBM_ULPS = 4
_POS_INF = float("inf")


def gamma(k: int) -> float:
    """Higham's gamma_k = k u / (1 - k u), slightly rounded up."""
    return (k * U / (1.0 - k * U)) * (1.0 + 1e-12)


_NEG_INF_T = torch.tensor(-_POS_INF, dtype=torch.float64)
_POS_INF_T = torch.tensor(_POS_INF, dtype=torch.float64)


def down(x: torch.Tensor) -> torch.Tensor:
    """One ulp towards -inf (covers a round-to-nearest error)."""
    return torch.nextafter(x, _NEG_INF_T)


def up(x: torch.Tensor) -> torch.Tensor:
    """One ulp towards +inf."""
    return torch.nextafter(x, _POS_INF_T)


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


# ----- function rules --------------------------------------------------------------------
def _monotone_increasing(point: Callable[[torch.Tensor], torch.Tensor]
                         ) -> Callable[[Interval], Interval]:
    """Endpoint rule for an increasing libm function (widened by LIBM_ULPS)."""

    def rule(a: Interval) -> Interval:
        return Interval(widen_down(point(a.lo)), widen_up(point(a.hi)))

    return rule


def _contains_point(a: Interval, offset: float, period: float) -> torch.Tensor:
    """Whether [lo, hi] may contain offset + k * period for an integer k (errs towards yes)."""
    s = 1e-7
    k_lo = torch.ceil((a.lo - offset) / period - s)
    k_hi = torch.floor((a.hi - offset) / period + s)
    return k_lo <= k_hi


_TWO_PI = 2.0 * math.pi
_BIG = 1e6  # beyond this |x|, trigonometric rules give the trivial enclosure


def _sin_cos_rule(point: Callable[[torch.Tensor], torch.Tensor], max_at: float, min_at: float
                  ) -> Callable[[Interval], Interval]:
    def rule(a: Interval) -> Interval:
        v1, v2 = point(a.lo), point(a.hi)
        lo = widen_down(torch.minimum(v1, v2))
        hi = widen_up(torch.maximum(v1, v2))
        trivial = ((a.hi - a.lo) >= _TWO_PI) | (a.mag() > _BIG)
        has_max = trivial | _contains_point(a, max_at, _TWO_PI)
        has_min = trivial | _contains_point(a, min_at, _TWO_PI)
        one = torch.ones_like(lo)
        hi = torch.where(has_max, one, hi).clamp(max=1.0)
        lo = torch.where(has_min, -one, lo).clamp(min=-1.0)
        nan = torch.isnan(a.lo) | torch.isnan(a.hi)
        return Interval(torch.where(nan, a.lo + a.hi, lo), torch.where(nan, a.lo + a.hi, hi))

    return rule


def _tan_rule(a: Interval) -> Interval:
    pole = _contains_point(a, math.pi / 2, math.pi) | ((a.hi - a.lo) >= math.pi) | (a.mag() > _BIG)
    lo = torch.where(pole, torch.full_like(a.lo, -_POS_INF), widen_down(torch.tan(a.lo)))
    hi = torch.where(pole, torch.full_like(a.lo, _POS_INF), widen_up(torch.tan(a.hi)))
    return Interval(lo, hi)


def _abs_rule(a: Interval) -> Interval:
    return Interval(a.mig(), a.mag())


def _sqrt_rule(a: Interval) -> Interval:
    nan = torch.full_like(a.lo, float("nan"))
    ok = a.lo >= 0
    return Interval(torch.where(ok, down(torch.sqrt(a.lo)).clamp_min(0.0), nan),
                    torch.where(ok, up(torch.sqrt(a.hi)), nan))


def _log_rule(a: Interval) -> Interval:
    # log(x < 0) is NaN (undefined in the box); log(0) = -inf: both UNKNOWN downstream.
    return Interval(widen_down(torch.log(a.lo)), widen_up(torch.log(a.hi)))


@dataclass(frozen=True)
class Rule:
    """A whitelisted function: its torch point function and its interval enclosure."""

    point: Callable[[torch.Tensor], torch.Tensor]
    enclose: Callable[[Interval], Interval]


#: name -> (point function, enclosure rule), side by side.
RULES: dict[str, Rule] = {
    "sin": Rule(torch.sin, _sin_cos_rule(torch.sin, math.pi / 2, -math.pi / 2)),
    "cos": Rule(torch.cos, _sin_cos_rule(torch.cos, 0.0, math.pi)),
    "tan": Rule(torch.tan, _tan_rule),
    "exp": Rule(torch.exp, _monotone_increasing(torch.exp)),
    "log": Rule(torch.log, _log_rule),
    "sqrt": Rule(torch.sqrt, _sqrt_rule),
    "tanh": Rule(torch.tanh, _monotone_increasing(torch.tanh)),
    "abs": Rule(torch.abs, _abs_rule),
    "sign": Rule(torch.sign, lambda a: Interval(torch.sign(a.lo), torch.sign(a.hi))),  # exact
}


def enclose_function(name: str, a: Interval) -> Interval:
    """Apply the rule of `name`; a function without a rule stops with an error naming it."""
    rule = RULES.get(name)
    if rule is None:
        raise SpecError(f"no interval enclosure rule for function '{name}' "
                        f"(rules exist for: {', '.join(sorted(RULES))})")
    return rule.enclose(a)


class IntervalAlgebra:
    """`certify.expr.Algebra` over `Interval` values (for `certify.expr.evaluate`)."""

    def const(self, value: float, like: Interval) -> Interval:
        return const_interval(value, like.lo)

    def add(self, a: Interval, b: Interval) -> Interval:
        return a + b

    def mul(self, a: Interval, b: Interval) -> Interval:
        return imul(a, b)

    def pow_int(self, a: Interval, k: int) -> Interval:
        return ipow_int(a, k)

    def pow_real(self, a: Interval, e: float) -> Interval:
        return ipow_real(a, e)

    def func(self, name: str, a: Interval) -> Interval:
        return enclose_function(name, a)


INTERVAL = IntervalAlgebra()

assert set(RULES) == set(FUNCTIONS) | set(DERIVED_FUNCTIONS), \
    "every whitelisted function needs an enclosure rule"


# ----- tanh and its derivatives: moved to certify.activations.tanh -----------------------
# Thin re-exports (imported at call time: certify.activations imports this module).
def tanh_enclosure(a: Interval) -> Interval:
    """tanh over [lo, hi]; see `certify.activations.tanh`."""
    from certify.activations.tanh import tanh_enclosure as rule

    return rule(a)


def dtanh_enclosure(a: Interval) -> Interval:
    """tanh' over [lo, hi]; see `certify.activations.tanh`."""
    from certify.activations.tanh import dtanh_enclosure as rule

    return rule(a)


def d2tanh_enclosure(a: Interval) -> Interval:
    """tanh'' over [lo, hi]; see `certify.activations.tanh`."""
    from certify.activations.tanh import d2tanh_enclosure as rule

    return rule(a)


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


# ----- enclosures of f, h and their derivatives over boxes --------------------------------
_DERIV_CACHE: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _derivatives(system: Any) -> dict[str, list[sympy.Expr]]:
    """Sympy second derivatives of f and h, cached per system."""
    cached = _DERIV_CACHE.get(system)
    if cached is None:
        xs = system.symbols
        cached = {
            "hf": [sympy.diff(e, a, b) for e in system.f_expr for a in xs for b in xs],
            "hh": [sympy.diff(e, a, b) for e in system.h_expr for a in xs for b in xs],
        }
        _DERIV_CACHE[system] = cached
    return cached


def _enclose_list(system: Any, exprs: list[sympy.Expr], lo: torch.Tensor, hi: torch.Tensor
                  ) -> tuple[torch.Tensor, torch.Tensor]:
    if lo.ndim != 2 or lo.shape[1] != system.n or lo.shape != hi.shape:
        raise ValueError(f"expected boxes lo, hi of shape [batch, {system.n}]; got "
                         f"{list(lo.shape)} and {list(hi.shape)}")
    lo, hi = lo.to(torch.float64), hi.to(torch.float64)
    env = {s: Interval(lo[:, i], hi[:, i]) for i, s in enumerate(system.symbols)}
    like = Interval(lo[:, 0], hi[:, 0])
    outs = [evaluate(e, env, INTERVAL, like) for e in exprs]
    return torch.stack([o.lo for o in outs], -1), torch.stack([o.hi for o in outs], -1)


def f_enclosure(system: Any, lo: torch.Tensor, hi: torch.Tensor
                ) -> tuple[torch.Tensor, torch.Tensor]:
    """f over boxes: lo, hi [B, n] -> [B, n] each."""
    return _enclose_list(system, system.f_expr, lo, hi)


def h_enclosure(system: Any, lo: torch.Tensor, hi: torch.Tensor
                ) -> tuple[torch.Tensor, torch.Tensor]:
    """h over boxes: lo, hi [B, n] -> [B, p] each."""
    return _enclose_list(system, system.h_expr, lo, hi)


def jacobian_f_enclosure(system: Any, lo: torch.Tensor, hi: torch.Tensor
                         ) -> tuple[torch.Tensor, torch.Tensor]:
    """Symbolic Jf over boxes: lo, hi [B, n] -> Jlo, Jhi [B, n, n]."""
    a, b = _enclose_list(system, list(system.jf_expr), lo, hi)
    n = system.n
    return a.reshape(-1, n, n), b.reshape(-1, n, n)


def jacobian_h_enclosure(system: Any, lo: torch.Tensor, hi: torch.Tensor
                         ) -> tuple[torch.Tensor, torch.Tensor]:
    """Symbolic dh/dx over boxes -> [B, p, n] each."""
    a, b = _enclose_list(system, list(system.jh_expr), lo, hi)
    return a.reshape(-1, system.p, system.n), b.reshape(-1, system.p, system.n)


def hessian_f_enclosure(system: Any, lo: torch.Tensor, hi: torch.Tensor
                        ) -> tuple[torch.Tensor, torch.Tensor]:
    """d^2 f_i / dx_j dx_k over boxes -> [B, n, n, n] (index order i, j, k)."""
    a, b = _enclose_list(system, _derivatives(system)["hf"], lo, hi)
    n = system.n
    return a.reshape(-1, n, n, n), b.reshape(-1, n, n, n)


def hessian_h_enclosure(system: Any, lo: torch.Tensor, hi: torch.Tensor
                        ) -> tuple[torch.Tensor, torch.Tensor]:
    """d^2 h_l / dx_j dx_k over boxes -> [B, p, n, n]."""
    a, b = _enclose_list(system, _derivatives(system)["hh"], lo, hi)
    n = system.n
    return a.reshape(-1, system.p, n, n), b.reshape(-1, system.p, n, n)


def hessian_f_point(system: Any, x: torch.Tensor) -> torch.Tensor:
    """Point second derivatives of f at x [B, n] -> [B, n, n, n] (for tests)."""
    from certify.expr import TORCH

    env = {s: x[:, i] for i, s in enumerate(system.symbols)}
    vals = [evaluate(e, env, TORCH, x[:, 0]) for e in _derivatives(system)["hf"]]
    n = system.n
    return torch.stack(vals, -1).reshape(-1, n, n, n)
