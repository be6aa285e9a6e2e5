"""SiLU (swish): f = x s(x), f' = s(x) (1 + x s(-x)), f'' = s(x) s(-x) (2 - x tanh(x/2)).

(s is the logistic sigmoid; 1 - 2 s(x) = -tanh(x/2).) Interval extensions compose sigma
(1 / (1 + exp(-x)), exp widened by `LIBM_ULPS`), tanh (widened by `LIBM_ULPS`) and
outward-rounded +, * on the point x. Critical points (mpmath, 25 digits): f at
-1.2784645427610738 (min -0.27846454276107380); f' at -+2.3993572805154677 (min
-0.09983932012886692, max 1.0998393201288669); f'' at 0 (max 1/2) and -+3.4358409935351107
(min -0.03691437319989319). Slopes lie in [-0.0998, 1.0998]; |f'''| <= 0.31.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from certify.arith.intervals import Interval
from certify.model.activations.base import (
    Activation,
    Critical,
    inc,
    scale,
    sigmoid_array,
    sigmoid_iv,
)

_D1_MIN = "-0.09983932012886691695818492"
_D1_MAX = "1.099839320128866916958185"


class SiLU(Activation):
    name = "silu"
    slope_bounds = (float(_D1_MIN) - 1e-15, float(_D1_MAX) + 1e-15)
    d3_bound = 0.31
    critical = {
        0: (Critical.at("-1.278464542761073795109359", "-0.2784645427610737951093587"),),
        1: (Critical.at("-2.39935728051546766783274", _D1_MIN),
            Critical.at("2.39935728051546766783274", _D1_MAX)),
        2: (Critical.at("-3.435840993535110688951641", "-0.03691437319989318563829178"),
            Critical.at("0", "0.5"),
            Critical.at("3.435840993535110688951641", "-0.03691437319989318563829178")),
    }

    def f(self, x: torch.Tensor) -> torch.Tensor:
        return x * torch.sigmoid(x)

    def f_array(self, x: np.ndarray) -> np.ndarray:
        return x * sigmoid_array(x)

    def d1(self, x: torch.Tensor) -> torch.Tensor:
        return torch.sigmoid(x) * (1.0 + x * torch.sigmoid(-x))

    def d2(self, x: torch.Tensor) -> torch.Tensor:
        return torch.sigmoid(x) * torch.sigmoid(-x) * (2.0 - x * torch.tanh(0.5 * x))

    def f_and_d1(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        s = torch.sigmoid(x)
        xs = x * s
        return xs, s + xs * (1.0 - s)

    def torch_module(self) -> nn.Module:
        return nn.SiLU()

    def _f_iv(self, a: Interval) -> Interval:
        return a * sigmoid_iv(a)

    def _d1_iv(self, a: Interval) -> Interval:
        return sigmoid_iv(a) * (1.0 + a * sigmoid_iv(-a))

    def _d2_iv(self, a: Interval) -> Interval:
        s = sigmoid_iv(a) * sigmoid_iv(-a)
        return s * (2.0 - a * inc(torch.tanh, scale(a, 0.5)))


SILU = SiLU()
