"""Interval enclosure rules of the elementary functions and the interval `Algebra`.

`RULES` is the one table: each whitelisted function name of `certify.spec.expr.FUNCTIONS` maps to
its torch point function and, beside it, its enclosure rule. Monotone functions share the
endpoint rule; `sin`, `cos`, `tan`, `abs`, `sqrt` and `log` are hand-written (even powers
and products are `certify.arith.intervals.ipow_int` / `imul`). libm results are widened by
`LIBM_ULPS` ulps (`certify.arith.intervals.widen_down` / `widen_up`), as `ROUNDING` states.
`INTERVAL` is the `certify.spec.expr.Algebra` that evaluates sympy trees over intervals, used for
the enclosures of f, h, their Jacobians and second derivatives (`certify.spec.enclosures`)
and of the domain's constraints.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch

from certify.arith.intervals import (
    Interval,
    const_interval,
    down,
    imul,
    ipow_int,
    ipow_real,
    up,
    widen_down,
    widen_up,
)
from certify.errors import SpecError
from certify.spec.expr import DERIVED_FUNCTIONS, FUNCTIONS

_POS_INF = float("inf")


def _monotone_increasing(point: Callable[[torch.Tensor], torch.Tensor]
                         ) -> Callable[[Interval], Interval]:
    """Endpoint rule for an increasing libm function (widened by LIBM_ULPS)."""

    def rule(a: Interval) -> Interval:
        return Interval(widen_down(point(a.lo)), widen_up(point(a.hi)))

    return rule


def contains_point(a: Interval, offset: float, period: float) -> torch.Tensor:
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
        has_max = trivial | contains_point(a, max_at, _TWO_PI)
        has_min = trivial | contains_point(a, min_at, _TWO_PI)
        one = torch.ones_like(lo)
        hi = torch.where(has_max, one, hi).clamp(max=1.0)
        lo = torch.where(has_min, -one, lo).clamp(min=-1.0)
        nan = torch.isnan(a.lo) | torch.isnan(a.hi)
        return Interval(torch.where(nan, a.lo + a.hi, lo), torch.where(nan, a.lo + a.hi, hi))

    return rule


def _tan_rule(a: Interval) -> Interval:
    pole = contains_point(a, math.pi / 2, math.pi) | ((a.hi - a.lo) >= math.pi) | (a.mag() > _BIG)
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
    """`certify.spec.expr.Algebra` over `Interval` values (for `certify.spec.expr.evaluate`)."""

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
