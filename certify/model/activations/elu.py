"""ELU with alpha = 1: f = x (x > 0) or e^x - 1 (x <= 0); f' = 1 or e^x; f'' = 0 or e^x.

C^1 (f' is continuous at 0, with value 1), not C^2: f'' jumps from 1 (left) to 0 (right).
The point value f''(0) is taken as the left limit 1; `enclose_d2` of an interval that
contains 0 holds both one-sided values [0, 1] (the `Critical` entry at 0 with range [0, 1]),
which is what a mean-value form for f' needs (f' is Lipschitz with constant 1). There is no
third derivative at 0: `d3_bound` is inf.

Interval extensions: expm1 and exp widened by `LIBM_ULPS` ulps; the branch for x > 0 is exact.
Every function here is non-decreasing, so endpoints plus the jump at 0 give the range.
Slopes lie in (0, 1].
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import nn

from certify.arith.intervals import Interval
from certify.model.activations.base import Activation, Critical, inc


def _pieces(a: Interval, neg: Interval, pos: Interval) -> Interval:
    """Per endpoint: the x <= 0 enclosure where the endpoint is <= 0, else the x > 0 one."""
    return Interval(torch.where(a.lo > 0, pos.lo, neg.lo), torch.where(a.hi > 0, pos.hi, neg.hi))


class ELU(Activation):
    name = "elu"
    slope_bounds = (0.0, 1.0)
    d3_bound = math.inf
    critical = {0: (), 1: (), 2: (Critical(0.0, 0.0, 1.0),)}

    def f(self, x: torch.Tensor) -> torch.Tensor:
        return torch.where(x > 0, x, torch.expm1(torch.clamp_max(x, 0.0)))

    def f_array(self, x: np.ndarray) -> np.ndarray:
        return np.where(x > 0, x, np.expm1(np.minimum(x, 0.0)))

    def d1(self, x: torch.Tensor) -> torch.Tensor:
        return torch.where(x > 0, torch.ones_like(x), torch.exp(torch.clamp_max(x, 0.0)))

    def d2(self, x: torch.Tensor) -> torch.Tensor:
        return torch.where(x > 0, torch.zeros_like(x), torch.exp(torch.clamp_max(x, 0.0)))

    def torch_module(self) -> nn.Module:
        return nn.ELU(alpha=1.0)

    def _f_iv(self, a: Interval) -> Interval:
        neg = inc(torch.expm1, Interval(a.lo.clamp_max(0.0), a.hi.clamp_max(0.0)))
        return _pieces(a, neg, a)

    def _d1_iv(self, a: Interval) -> Interval:
        neg = inc(torch.exp, Interval(a.lo.clamp_max(0.0), a.hi.clamp_max(0.0)))
        one = torch.ones_like(a.lo)
        return _pieces(a, Interval(neg.lo, neg.hi.clamp_max(1.0)), Interval(one, one))

    def _d2_iv(self, a: Interval) -> Interval:
        neg = inc(torch.exp, Interval(a.lo.clamp_max(0.0), a.hi.clamp_max(0.0)))
        zero = torch.zeros_like(a.lo)
        return _pieces(a, Interval(neg.lo, neg.hi.clamp_max(1.0)), Interval(zero, zero))


ELU_ = ELU()
