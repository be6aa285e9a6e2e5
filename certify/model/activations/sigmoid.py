"""sigmoid (logistic): f = s(x) = 1 / (1 + e^-x), f' = s(x) s(-x), f'' = -s(x) s(-x) tanh(x/2).

Interval extensions: s via 1 / (1 + exp(-x)) (exp widened by `LIBM_ULPS`, sum and quotient
rounded outward), which is accurate in both tails; f' as s(x) s(-x) (no 1 - s cancellation);
f'' with tanh(x/2) widened by `LIBM_ULPS` (x/2 rounded outward). Critical points: f' at 0
(value 1/4); f'' at -+ln(2 + sqrt 3) = -+1.3169578969248167 (values +-sqrt(3)/18).
Slopes lie in (0, 1/4]; |f'''| <= 1/8.
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


class Sigmoid(Activation):
    name = "sigmoid"
    slope_bounds = (0.0, 0.25)
    value_bound = 1.0
    d3_bound = 0.125
    critical = {
        0: (),
        1: (Critical.at("0", "0.25"),),
        2: (Critical.at("-1.316957896924816708625046", "0.09622504486493762741819146"),
            Critical.at("1.316957896924816708625046", "-0.09622504486493762741819146")),
    }

    def f(self, x: torch.Tensor) -> torch.Tensor:
        return torch.sigmoid(x)

    def f_array(self, x: np.ndarray) -> np.ndarray:
        return sigmoid_array(x)

    def d1(self, x: torch.Tensor) -> torch.Tensor:
        return torch.sigmoid(x) * torch.sigmoid(-x)

    def d2(self, x: torch.Tensor) -> torch.Tensor:
        return -torch.sigmoid(x) * torch.sigmoid(-x) * torch.tanh(0.5 * x)

    def f_and_d1(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        s = torch.sigmoid(x)
        return s, s * (1.0 - s)

    def d2_given(self, x: torch.Tensor, f: torch.Tensor, d1: torch.Tensor) -> torch.Tensor:
        return d1 * (1.0 - 2.0 * f)

    def torch_module(self) -> nn.Module:
        return nn.Sigmoid()

    def _f_iv(self, a: Interval) -> Interval:
        return sigmoid_iv(a)

    def _d1_iv(self, a: Interval) -> Interval:
        return sigmoid_iv(a) * sigmoid_iv(-a)

    def _d2_iv(self, a: Interval) -> Interval:
        return -(self._d1_iv(a) * inc(torch.tanh, scale(a, 0.5)))


SIGMOID = Sigmoid()
