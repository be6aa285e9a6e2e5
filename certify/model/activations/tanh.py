"""tanh: f = tanh x, f' = 1 - tanh^2 = sech^2, f'' = -2 tanh sech^2, f''' in [-2, 2/3].

The network's original activation; its enclosures are kept hand-written and fast (the prover
calls them in its inner loop):

- f is increasing: endpoint rule, libm tanh widened by `LIBM_ULPS` ulps (plus 4 * 2^-1022);
- f' = 1 - t^2 from t = tanh over [mig, mag] (f' is even, decreasing in |x|): the maximum 1
  at 0 is taken exactly when the interval contains 0; 1 - t^2 is rounded outward;
- f'' = g(t) with g(t) = -2 t (1 - t^2): non-monotone in t, so the critical values
  +-4 / (3 sqrt 3) at t = -+1/sqrt 3 are included when the enclosure of t reaches them
  (slack 1e-12), and the result is clamped to [-4/(3 sqrt 3), 4/(3 sqrt 3)] widened two ulps.

The interval extensions used by the relaxations compute f' as 1 / cosh(x)^2 (no cancellation
for large |x|). Critical points: f' at 0 (value 1); f'' at -+0.6584789484624083 (values
+-0.7698003589195010).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import nn

from certify.arith.intervals import Interval, down, isqr, up, widen_down, widen_up
from certify.model.activations.base import Activation, Critical, inc

_G_CRIT = 4.0 / (3.0 * math.sqrt(3.0))  # max of -2 t (1 - t^2), attained at t = -1/sqrt(3)
_T_CRIT = 1.0 / math.sqrt(3.0)


def tanh_enclosure(a: Interval) -> Interval:
    """tanh over [lo, hi] (increasing: endpoint rule, widened; |tanh| <= 1 never overflows,
    so the plain widening of `certify.arith.intervals` serves). A point interval (lo and hi the
    same tensor, as the relaxations pass them) costs one libm call."""
    if a.lo is a.hi:
        t = torch.tanh(a.lo)
        return Interval(widen_down(t), widen_up(t))
    return Interval(widen_down(torch.tanh(a.lo)), widen_up(torch.tanh(a.hi)))


def dtanh_enclosure(a: Interval) -> Interval:
    """tanh'(x) = 1 - tanh(x)^2 over [lo, hi]: maximum 1 at 0 when the interval contains 0."""
    if a.lo is a.hi:  # a point: mig = mag = |x|
        m = a.lo.abs()
        t = tanh_enclosure(Interval(m, m))
    else:
        t = tanh_enclosure(Interval(a.mig(), a.mag()))  # tanh over |x|, increasing
    lo = down(1.0 - up(t.hi * t.hi)).clamp_min(0.0)
    hi = up(1.0 - down(t.lo * t.lo)).clamp(max=1.0)
    return Interval(lo, hi)


def _g_point(t: torch.Tensor) -> Interval:
    """g(t) = -2 t (1 - t^2) at point t, as an outward-rounded interval."""
    ti = Interval(t, t)
    return Interval(-2.0 * t, -2.0 * t) * (1.0 - isqr(ti))


def d2tanh_enclosure(a: Interval) -> Interval:
    """tanh''(x) = -2 tanh (1 - tanh^2): non-monotone, so critical points are included."""
    t = tanh_enclosure(a)
    g1, g2 = _g_point(t.lo), _g_point(t.hi)
    lo = torch.minimum(g1.lo, g2.lo)
    hi = torch.maximum(g1.hi, g2.hi)
    slack = 1e-12
    has_max = (t.lo <= -_T_CRIT + slack) & (t.hi >= -_T_CRIT - slack)
    has_min = (t.lo <= _T_CRIT + slack) & (t.hi >= _T_CRIT - slack)
    gmax = math.nextafter(math.nextafter(_G_CRIT, 1.0), 1.0)
    hi = torch.where(has_max, torch.clamp(hi, min=gmax), hi)
    lo = torch.where(has_min, torch.clamp(lo, max=-gmax), lo)
    return Interval(lo.clamp(min=-gmax), hi.clamp(max=gmax))


def _sech2_iv(a: Interval) -> Interval:
    """sech^2 x = 1 / cosh^2 x (cosh increasing in |x|)."""
    c = inc(torch.cosh, Interval(a.mig(), a.mag()))
    c2 = isqr(c)
    return Interval(down(1.0 / c2.hi), up(1.0 / c2.lo))


class Tanh(Activation):
    name = "tanh"
    slope_bounds = (0.0, 1.0)
    value_bound = 1.0
    d3_bound = 2.0
    critical = {
        0: (),
        1: (Critical.at("0", "1"),),
        2: (Critical.at("-0.6584789484624083543125232", "0.7698003589195010193455317"),
            Critical.at("0.6584789484624083543125232", "-0.7698003589195010193455317")),
    }

    def f(self, x: torch.Tensor) -> torch.Tensor:
        return torch.tanh(x)

    def f_array(self, x: np.ndarray) -> np.ndarray:
        return np.tanh(x)

    def d1(self, x: torch.Tensor) -> torch.Tensor:
        t = torch.tanh(x)
        return 1.0 - t * t

    def d2(self, x: torch.Tensor) -> torch.Tensor:
        t = torch.tanh(x)
        return -2.0 * t * (1.0 - t * t)

    def f_and_d1(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        t = torch.tanh(x)
        s = t * t
        s.neg_().add_(1.0)  # 1 - t^2 without a second temporary
        return t, s

    def f_and_d1_into(self, x: torch.Tensor, f_out: torch.Tensor, d1_out: torch.Tensor
                      ) -> None:
        torch.tanh(x, out=f_out)
        one = torch.ones((), dtype=x.dtype, device=x.device)
        torch.addcmul(one, f_out, f_out, value=-1.0, out=d1_out)

    def d2_given(self, x: torch.Tensor, f: torch.Tensor, d1: torch.Tensor) -> torch.Tensor:
        return -2.0 * f * d1

    def chain_pre(self, g_f: torch.Tensor, g_d1: torch.Tensor, x: torch.Tensor,
                  f: torch.Tensor, d1: torch.Tensor, out: torch.Tensor) -> None:
        # f'' = -2 f f': out = (g_f - 2 f g_d1) f' (one fused multiply-add, then one product)
        C = g_d1.shape[0]
        g_f[:C].addcmul_(g_d1, f[:C], value=-2.0)
        torch.mul(g_f, d1, out=out)

    def torch_module(self) -> nn.Module:
        return nn.Tanh()

    def _f_iv(self, a: Interval) -> Interval:
        return tanh_enclosure(a)

    def _d1_iv(self, a: Interval) -> Interval:
        return _sech2_iv(a)

    def _d2_iv(self, a: Interval) -> Interval:
        return tanh_enclosure(a) * _sech2_iv(a) * -2.0

    def enclose_f(self, a: Interval) -> Interval:
        return tanh_enclosure(Interval(a.lo.to(torch.float64), a.hi.to(torch.float64)))

    def enclose_d1(self, a: Interval) -> Interval:
        return dtanh_enclosure(Interval(a.lo.to(torch.float64), a.hi.to(torch.float64)))

    def enclose_d2(self, a: Interval) -> Interval:
        return d2tanh_enclosure(Interval(a.lo.to(torch.float64), a.hi.to(torch.float64)))


TANH = Tanh()
