"""The activation contract: point values, sound enclosures and linear relaxations.

An `Activation` carries everything the verifier needs beside the function itself: f, f', f''
at points (batched torch, any dtype and device), sound interval enclosures of all three over
intervals, and sound linear lower/upper bounds of f and f' over [lo, hi] (`LinearBounds`).

How enclosures are built (and why they are sound). Each activation writes f, f', f'' once
as an *interval extension* (`_f_iv`, `_d1_iv`, `_d2_iv`) composed of monotone libm
primitives (`inc`, `dec`: endpoint rule widened by the primitive's ulp margin) and the
outward-rounded operations of `certify.arith.intervals` (+, -, *, 1/x, x^2). Applied to a point
interval [x, x] this gives a rigorous enclosure of g(x) a few ulps wide. Over [lo, hi] the
generic `enclose_*` then returns the hull of g at both endpoints and of g's extremal values at
the critical points inside [lo, hi] (`Critical`: location and an outward-rounded value range,
computed with mpmath to 25 digits and re-checked by the tests). Between consecutive critical
points g is monotone (the list of critical points is complete: the zeros of g'), so the hull
is the exact range, up to rounding. A critical point counts as inside when it is within a
relative slack of 1e-12 of [lo, hi] (including one too many only loosens the bound).

Floating point: every primitive result is widened by its documented libm error bound with a
safety factor (`LIBM_ULPS` = 4 ulps relative plus 4 * 2^-1022 absolute for exp, expm1,
log1p, tanh, cosh; `ERFC_ULPS` = 16 for erfc), +inf from an overflow widens down to the
largest finite double (never NaN), and +, -, *, / are rounded outward by one ulp
(`certify.arith.intervals.ROUNDING`). NaN input gives NaN bounds (UNKNOWN downstream).

Relaxations (`relax`, `relax_d1`): a candidate line of slope s (the chord of g over [lo, hi],
or g' at lo when the interval is degenerate), then the residual r(x) = g(x) - s x is enclosed
over K = 8 sub-intervals [e_k, e_k+1] covering [lo, hi] exactly (e_0 = lo, e_K = hi, sorted),
each by the intersection of the mean-value form r(c_k) + (g'([e_k, e_k+1]) - s)(x - c_k) and
the plain form g([e_k, e_k+1]) - s [e_k, e_k+1], all in outward-rounded interval arithmetic.
The intercepts are the min/max of those enclosures, so for every real x in [lo, hi]:
    s x + lower_icpt <= g(x) <= s x + upper_icpt   (exact real arithmetic on the stored doubles;
a caller evaluating the lines in floating point rounds that evaluation itself).
For f' the mean-value form uses `enclose_d2`, which for ELU (f'' jumps at 0) is the hull of
both one-sided values: f' is Lipschitz, so the mean-value form holds with that hull.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from certify.arith.intervals import EPS, TINY, Interval, down, up

LIBM_ULPS = 4
ERFC_ULPS = 16
RELAX_PIECES = 8
_MAX = torch.finfo(torch.float64).max
_CRIT_SLACK = 1e-12


def sigmoid_array(x: np.ndarray) -> np.ndarray:
    """1 / (1 + e^-x) on a NumPy array, to a few ulps on the whole line (no overflow: e^-|x|
    only; the negative side as e^x / (1 + e^x), so the tail keeps its relative accuracy)."""
    e = np.exp(-np.abs(x))
    return np.where(x >= 0, 1.0, e) / (1.0 + e)


# ----- outward-rounded primitives ------------------------------------------------------------
def wdown(x: torch.Tensor, ulps: int = LIBM_ULPS) -> torch.Tensor:
    """At least `ulps` ulps below x (a libm result); +inf becomes the largest double."""
    y = down(x - (ulps * EPS) * x.abs() - ulps * TINY)
    return torch.where(x == math.inf, torch.full_like(x, _MAX), y)


def wup(x: torch.Tensor, ulps: int = LIBM_ULPS) -> torch.Tensor:
    """At least `ulps` ulps above x; -inf becomes the lowest double."""
    y = up(x + (ulps * EPS) * x.abs() + ulps * TINY)
    return torch.where(x == -math.inf, torch.full_like(x, -_MAX), y)


def inc(fn: Callable[[torch.Tensor], torch.Tensor], a: Interval, ulps: int = LIBM_ULPS
        ) -> Interval:
    """Enclosure of an increasing libm function over a (endpoint rule, widened)."""
    return Interval(wdown(fn(a.lo), ulps), wup(fn(a.hi), ulps))


def dec(fn: Callable[[torch.Tensor], torch.Tensor], a: Interval, ulps: int = LIBM_ULPS
        ) -> Interval:
    """Enclosure of a decreasing libm function over a."""
    return Interval(wdown(fn(a.hi), ulps), wup(fn(a.lo), ulps))


def const(value: float, like: torch.Tensor) -> Interval:
    """A real constant given by its nearest double: [down, up] of it contains the real."""
    t = torch.full_like(like, value)
    return Interval(down(t), up(t))


def scale(a: Interval, k: float) -> Interval:
    """k * a for an exact double k (rounded outward: exact unless under/overflow)."""
    lo, hi = (k * a.lo, k * a.hi) if k >= 0 else (k * a.hi, k * a.lo)
    return Interval(down(lo), up(hi))


def sigmoid_iv(a: Interval) -> Interval:
    """sigma(x) = 1 / (1 + exp(-x)), increasing; accurate in both tails (no cancellation)."""
    e = inc(torch.exp, -a)
    one_plus = Interval(down(1.0 + e.lo), up(1.0 + e.hi))
    return Interval(down(1.0 / one_plus.hi), up(1.0 / one_plus.lo))


def hull(a: Interval, b: Interval) -> Interval:
    return Interval(torch.minimum(a.lo, b.lo), torch.maximum(a.hi, b.hi))


# ----- the contract ---------------------------------------------------------------------
@dataclass(frozen=True)
class Critical:
    """A critical point x of g (g'(x) = 0, or a jump of g) and the range [lo, hi] of the
    values g takes there (outward-rounded from a 25-digit mpmath value)."""

    x: float
    lo: float
    hi: float

    @staticmethod
    def at(x: str, value: str, value_hi: str | None = None) -> Critical:
        v_lo = float(value)
        v_hi = float(value if value_hi is None else value_hi)
        return Critical(float(x), math.nextafter(math.nextafter(v_lo, -math.inf), -math.inf),
                        math.nextafter(math.nextafter(v_hi, math.inf), math.inf))


@dataclass
class LinearBounds:
    """Linear bounds on [lo, hi]: ls x + li <= g(x) <= us x + ui, tensors shaped like lo."""

    lower_slope: torch.Tensor
    lower_icpt: torch.Tensor
    upper_slope: torch.Tensor
    upper_icpt: torch.Tensor


class _Module(nn.Module):
    """An activation as an nn.Module (calls the activation's own point formula)."""

    def __init__(self, act: Activation) -> None:
        super().__init__()
        self.act = act

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.act.f(x)

    def extra_repr(self) -> str:
        return self.act.name


class Activation:
    """A C^1 activation function with its derivatives, enclosures and relaxations.

    Subclasses set `name`, `slope_bounds` (inf and sup of f' over the reals: the sector
    LipSDP needs), `value_bound` (sup |f|), `d3_bound` (sup |f'''|, math.inf when f'' is
    not continuous), the point formulas `f`, `d1`, `d2`, their interval extensions `_f_iv`,
    `_d1_iv`, `_d2_iv`, and `critical[k]`: every critical point of the k-th derivative
    (k = 0, 1, 2).
    """

    name: str = ""
    slope_bounds: tuple[float, float] = (0.0, 1.0)
    value_bound: float = math.inf  # sup |f| over the reals (inf: unbounded)
    d3_bound: float = math.inf
    critical: dict[int, tuple[Critical, ...]] = {0: (), 1: (), 2: ()}

    @property
    def lipschitz(self) -> float:
        """sup |f'| over the reals (the activation's Lipschitz constant)."""
        return max(abs(self.slope_bounds[0]), abs(self.slope_bounds[1]))

    # --- point values (torch, batched, any dtype/device) ---
    def f(self, x: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def d1(self, x: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def d2(self, x: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def f_array(self, x: np.ndarray) -> np.ndarray:
        """f on a float64 NumPy array: the simulation's right-hand side
        (`certify.simulate.integrate`),
        whose calls are a few rows each, where a NumPy ufunc costs a quarter of a torch call.
        This default runs `f` on a zero-copy torch view; subclasses with a NumPy form override
        it (equal to `f` up to the libraries' last-ulp differences; tested)."""
        return self.f(torch.from_numpy(x)).numpy()

    def f_and_d1(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """f(x) and f'(x) together (subclasses share work where they can)."""
        return self.f(x), self.d1(x)

    def f_and_d1_into(self, x: torch.Tensor, f_out: torch.Tensor, d1_out: torch.Tensor
                      ) -> None:
        """f(x) into f_out and f'(x) into d1_out (preallocated buffers, no autograd)."""
        f, d1 = self.f_and_d1(x)
        f_out.copy_(f)
        d1_out.copy_(d1)

    def d2_given(self, x: torch.Tensor, f: torch.Tensor, d1: torch.Tensor) -> torch.Tensor:
        """f''(x), given f(x) and f'(x) already computed (subclasses reuse them)."""
        return self.d2(x)

    def chain_pre(self, g_f: torch.Tensor, g_d1: torch.Tensor, x: torch.Tensor,
                  f: torch.Tensor, d1: torch.Tensor, out: torch.Tensor) -> None:
        """Reverse mode through (f(x), f'(x)): out = g_f f'(x), then out[:C] += g_d1 f''(x)
        for the first C = len(g_d1) rows (only those carry tangents). May overwrite g_f."""
        C = g_d1.shape[0]
        torch.mul(g_f, d1, out=out)
        out[:C].addcmul_(g_d1, self.d2_given(x[:C], f[:C], d1[:C]))

    def torch_module(self) -> nn.Module:
        return _Module(self)

    # --- interval extensions (sound for any interval, tight on points) ---
    def _f_iv(self, a: Interval) -> Interval:
        raise NotImplementedError

    def _d1_iv(self, a: Interval) -> Interval:
        raise NotImplementedError

    def _d2_iv(self, a: Interval) -> Interval:
        raise NotImplementedError

    def _iv(self, order: int) -> Callable[[Interval], Interval]:
        return (self._f_iv, self._d1_iv, self._d2_iv)[order]

    # --- enclosures over intervals ---
    def _enclose(self, order: int, a: Interval) -> Interval:
        """Hull of the order-th derivative at both endpoints and at critical points inside."""
        lo, hi = a.lo.to(torch.float64), a.hi.to(torch.float64)
        ends = torch.stack([lo, hi])
        v = self._iv(order)(Interval(ends, ends))
        out_lo = torch.minimum(v.lo[0], v.lo[1])
        out_hi = torch.maximum(v.hi[0], v.hi[1])
        for c in self.critical[order]:
            slack = _CRIT_SLACK * max(1.0, abs(c.x))
            inside = (lo <= c.x + slack) & (hi >= c.x - slack)
            out_lo = torch.where(inside, torch.clamp(out_lo, max=c.lo), out_lo)
            out_hi = torch.where(inside, torch.clamp(out_hi, min=c.hi), out_hi)
        return Interval(out_lo, out_hi)

    def enclose_f(self, a: Interval) -> Interval:
        """Contains f(x) for every x in a."""
        return self._enclose(0, a)

    def enclose_d1(self, a: Interval) -> Interval:
        """Contains f'(x) for every x in a."""
        return self._enclose(1, a)

    def enclose_d2(self, a: Interval) -> Interval:
        """Contains f''(x) for every x in a (for ELU: both one-sided values at 0)."""
        return self._enclose(2, a)

    def slope_range(self, a: Interval) -> tuple[torch.Tensor, torch.Tensor]:
        """Bounds (lo, hi) of f' over a (= enclose_d1)."""
        e = self.enclose_d1(a)
        return e.lo, e.hi

    # --- linear relaxations ---
    def relax(self, lo: torch.Tensor, hi: torch.Tensor) -> LinearBounds:
        """Sound linear lower/upper bounds of f on [lo, hi]."""
        return relax_generic(lo, hi, self._f_iv, self.enclose_f, self.enclose_d1)

    def relax_d1(self, lo: torch.Tensor, hi: torch.Tensor) -> LinearBounds:
        """Sound linear lower/upper bounds of f' on [lo, hi]."""
        return relax_generic(lo, hi, self._d1_iv, self.enclose_d1, self.enclose_d2)

    def __repr__(self) -> str:
        return f"Activation({self.name!r})"


def _pieces(lo: torch.Tensor, hi: torch.Tensor, k: int) -> torch.Tensor:
    """Sorted breakpoints [k + 1, *shape] with e_0 = lo, e_k = hi, all inside [lo, hi]."""
    t = torch.linspace(0.0, 1.0, k + 1, dtype=torch.float64, device=lo.device)
    t = t.reshape(-1, *([1] * lo.ndim))
    e = lo + (hi - lo) * t
    e = torch.minimum(torch.maximum(e, lo), hi)
    e[0], e[-1] = lo, hi
    return torch.cummax(e, dim=0).values


def relax_generic(lo: torch.Tensor, hi: torch.Tensor, g_iv: Callable[[Interval], Interval],
                  enclose_g: Callable[[Interval], Interval],
                  enclose_dg: Callable[[Interval], Interval],
                  pieces: int = RELAX_PIECES) -> LinearBounds:
    """Chord (or tangent) line + outward enclosure of the residual over `pieces` sub-intervals."""
    lo, hi = lo.to(torch.float64), hi.to(torch.float64)
    ends = torch.stack([lo, hi])
    g_ends = g_iv(Interval(ends, ends)).mid()
    w = hi - lo
    chord = (g_ends[1] - g_ends[0]) / torch.where(w > 0, w, torch.ones_like(w))
    tangent = enclose_dg(Interval(lo, lo)).mid()
    s = torch.where(w > 0, chord, tangent)
    s = torch.where(torch.isfinite(s), s, torch.zeros_like(s))
    e = _pieces(lo, hi, pieces)
    a, b = e[:-1], e[1:]
    c = 0.5 * (a + b)
    c = torch.minimum(torch.maximum(c, a), b)
    S = Interval(s.expand_as(a), s.expand_as(a))
    sub = Interval(a, b)
    # mean-value form: r(c) + (g'(sub) - s) (x - c)
    rc = g_iv(Interval(c, c)) - S * Interval(c, c)
    dev = Interval(down(a - c), up(b - c))
    mv = rc + (enclose_dg(sub) - S) * dev
    # plain form: g(sub) - s sub
    plain = enclose_g(sub) - S * sub
    r_lo = torch.maximum(mv.lo, plain.lo).amin(0)
    r_hi = torch.minimum(mv.hi, plain.hi).amax(0)
    return LinearBounds(lower_slope=s, lower_icpt=down(r_lo), upper_slope=s.clone(),
                        upper_icpt=up(r_hi))
