"""GELU (exact, erf-based): f = x Phi(x), f' = Phi(x) + x phi(x), f'' = phi(x) (2 - x^2).

Phi(x) = erfc(-x / sqrt 2) / 2 (erfc keeps the lower tail accurate, unlike 1 + erf) and
phi(x) = exp(-x^2 / 2) / sqrt(2 pi). Interval extensions: the constants 1/sqrt 2 and
1/sqrt(2 pi) are enclosed by [down, up] of their nearest doubles; erfc (decreasing) is widened
by `ERFC_ULPS` = 16 ulps (CPU and CUDA libm erfc err by a few ulps), exp by `LIBM_ULPS`;
+, *, x^2 are rounded outward. Critical points (mpmath, 25 digits): f at -0.7517915246935645
(min -0.16997120747990366); f' at -+sqrt 2 (min -0.12890414518515479, max 1.1289041451851548);
f'' at 0 (max 2 / sqrt(2 pi)) and -+2 (min -2 e^-2 / sqrt(2 pi)). Slopes lie in
[-0.129, 1.129]; |f'''| = |phi(x) x (x^2 - 4)| <= 0.8.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from certify.arith.intervals import Interval, isqr
from certify.model.activations.base import ERFC_ULPS, Activation, Critical, const, dec, inc

_INV_SQRT2 = 1.0 / math.sqrt(2.0)
_INV_SQRT_2PI = 1.0 / math.sqrt(2.0 * math.pi)
_D1_MIN = "-0.1289041451851547863407444"
_D1_MAX = "1.128904145185154786340744"


def _Phi_iv(a: Interval) -> Interval:
    arg = -(a * const(_INV_SQRT2, a.lo))
    e = dec(torch.special.erfc, arg, ERFC_ULPS)
    return e * 0.5


def _phi_iv(a: Interval) -> Interval:
    return inc(torch.exp, -(isqr(a) * 0.5)) * const(_INV_SQRT_2PI, a.lo)


class GELU(Activation):
    name = "gelu"
    slope_bounds = (float(_D1_MIN) - 1e-15, float(_D1_MAX) + 1e-15)
    d3_bound = 0.8
    critical = {
        0: (Critical.at("-0.7517915246935644574579049", "-0.1699712074799036616938685"),),
        1: (Critical.at("-1.414213562373095048801689", _D1_MIN),
            Critical.at("1.414213562373095048801689", _D1_MAX)),
        2: (Critical.at("-2", "-0.1079819330263761039011284"),
            Critical.at("0", "0.7978845608028653558798921"),
            Critical.at("2", "-0.1079819330263761039011284")),
    }

    @staticmethod
    def _Phi(x: torch.Tensor) -> torch.Tensor:
        return 0.5 * torch.special.erfc(-_INV_SQRT2 * x)

    @staticmethod
    def _phi(x: torch.Tensor) -> torch.Tensor:
        return torch.exp(-0.5 * x * x) * _INV_SQRT_2PI

    def f(self, x: torch.Tensor) -> torch.Tensor:
        return x * self._Phi(x)

    def d1(self, x: torch.Tensor) -> torch.Tensor:
        return self._Phi(x) + x * self._phi(x)

    def d2(self, x: torch.Tensor) -> torch.Tensor:
        return self._phi(x) * (2.0 - x * x)

    def f_and_d1(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        P = self._Phi(x)
        return x * P, P + x * self._phi(x)

    def torch_module(self) -> nn.Module:
        return nn.GELU(approximate="none")

    def _f_iv(self, a: Interval) -> Interval:
        return a * _Phi_iv(a)

    def _d1_iv(self, a: Interval) -> Interval:
        return _Phi_iv(a) + a * _phi_iv(a)

    def _d2_iv(self, a: Interval) -> Interval:
        return _phi_iv(a) * (2.0 - isqr(a))


GELU_ = GELU()
