"""Activation patterns: which activation an elementwise expression tree of u is.

Trees are tuples: ("u",) the layer output, ("c", value) a scalar constant, (op, *children)
for op in tanh, sigmoid, softplus, elu, gelu, silu, erf, add, sub, mul, div. Matching is
structural (never by evaluating): tanh(u) and the other single ops, u * sigmoid(u) (SiLU), and
0.5 * u * (1 + erf(u / sqrt 2)) with its factors in any order and its constants equal to 0.5, 1
and 1/sqrt 2 up to a few float32 roundings (exporters store them in float32; the network
certified is the exact GELU).
"""

from __future__ import annotations

import math

U: tuple = ("u",)
#: relative tolerance on the constants of the erf form of GELU: a few float32 roundings
GELU_CONSTANT_RTOL = 4 * 2.0 ** -24


def _factors(expr: tuple) -> tuple[float, list[tuple]]:
    """A product flattened: (constant factor, other factors); a / c counts as a * (1/c)."""
    if expr[0] == "mul":
        c1, f1 = _factors(expr[1])
        c2, f2 = _factors(expr[2])
        return c1 * c2, f1 + f2
    if expr[0] == "div" and expr[2][0] == "c" and expr[2][1] != 0.0:
        c, f = _factors(expr[1])
        return c / expr[2][1], f
    if expr[0] == "c":
        return expr[1], []
    return 1.0, [expr]


def _close(value: float, exact: float) -> bool:
    return abs(value - exact) <= GELU_CONSTANT_RTOL * abs(exact)


def _is_erf_gelu(expr: tuple) -> bool:
    """0.5 * u * (1 + erf(u / sqrt 2)), any order, constants up to float32 rounding."""
    scale, factors = _factors(expr)
    if not _close(scale, 0.5) or len(factors) != 2 or U not in factors:
        return False
    other = factors[1] if factors[0] == U else factors[0]
    if other[0] != "add":
        return False
    terms = [other[1], other[2]]
    one = [t for t in terms if t[0] == "c" and _close(t[1], 1.0)]
    erf = [t for t in terms if t[0] == "erf"]
    if len(one) != 1 or len(erf) != 1:
        return False
    inner_scale, inner = _factors(erf[0][1])
    return inner == [U] and _close(inner_scale, 1.0 / math.sqrt(2.0))


def match_activation(expr: tuple) -> str | None:
    """The activation name an expression tree of u is, or None."""
    if len(expr) == 2 and expr[1] == U and expr[0] in ("tanh", "sigmoid", "softplus", "elu",
                                                       "gelu", "silu"):
        return expr[0]
    if expr[0] == "mul" and {expr[1], expr[2]} == {U, ("sigmoid", U)}:
        return "silu"
    if _is_erf_gelu(expr):
        return "gelu"
    return None
