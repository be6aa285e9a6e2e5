"""softplus: f = log(1 + e^x) = max(x, 0) + log1p(e^-|x|), f' = s(x), f'' = s(x) s(-x).

Interval extensions: f from the stable form max(x, 0) + log1p(exp(-|x|)) (exp and log1p
widened by `LIBM_ULPS` ulps each, the sum rounded outward); f' = s(x) as in sigmoid; f'' as
s(x) s(-x). f and f' are increasing (no critical points); f'' has its maximum 1/4 at 0.
Slopes lie in (0, 1); |f'''| <= sqrt(3)/18. The point formula is the same stable form (torch's
nn.Softplus switches to x above a threshold, which is not exact, so it is not used).
"""

from __future__ import annotations

import numpy as np
import torch

from certify.arith.intervals import Interval
from certify.model.activations.base import Activation, Critical, dec, inc, sigmoid_iv


class Softplus(Activation):
    name = "softplus"
    slope_bounds = (0.0, 1.0)
    d3_bound = 0.0962250448649377
    critical = {0: (), 1: (), 2: (Critical.at("0", "0.25"),)}

    def f(self, x: torch.Tensor) -> torch.Tensor:
        return torch.clamp_min(x, 0.0) + torch.log1p(torch.exp(-x.abs()))

    def f_array(self, x: np.ndarray) -> np.ndarray:
        return np.maximum(x, 0.0) + np.log1p(np.exp(-np.abs(x)))

    def d1(self, x: torch.Tensor) -> torch.Tensor:
        return torch.sigmoid(x)

    def d2(self, x: torch.Tensor) -> torch.Tensor:
        return torch.sigmoid(x) * torch.sigmoid(-x)

    def f_and_d1(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.f(x), torch.sigmoid(x)

    def d2_given(self, x: torch.Tensor, f: torch.Tensor, d1: torch.Tensor) -> torch.Tensor:
        return d1 * (1.0 - d1)

    def _f_iv(self, a: Interval) -> Interval:
        pos = Interval(a.lo.clamp_min(0.0), a.hi.clamp_min(0.0))
        absx = Interval(a.mig(), a.mag())
        e = dec(lambda v: torch.exp(-v), absx)
        return pos + inc(torch.log1p, e)

    def _d1_iv(self, a: Interval) -> Interval:
        return sigmoid_iv(a)

    def _d2_iv(self, a: Interval) -> Interval:
        return sigmoid_iv(a) * sigmoid_iv(-a)


SOFTPLUS = Softplus()
