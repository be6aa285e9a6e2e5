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


def _erf_gelu_constants(expr: tuple) -> tuple[float, float, float] | None:
    """(c1, c2, c3) of c1 * u * (c2 + erf(c3 * u)), factors in any order; None if not so."""
    scale, factors = _factors(expr)
    if len(factors) != 2 or U not in factors:
        return None
    other = factors[1] if factors[0] == U else factors[0]
    if other[0] != "add":
        return None
    terms = [other[1], other[2]]
    one = [t for t in terms if t[0] == "c"]
    erf = [t for t in terms if t[0] == "erf"]
    if len(one) != 1 or len(erf) != 1:
        return None
    inner_scale, inner = _factors(erf[0][1])
    return (scale, one[0][1], inner_scale) if inner == [U] else None


_GELU_EXACT = (0.5, 1.0, 1.0 / math.sqrt(2.0))


def _is_erf_gelu(expr: tuple) -> bool:
    """0.5 * u * (1 + erf(u / sqrt 2)), any order, constants up to float32 rounding."""
    found = _erf_gelu_constants(expr)
    return found is not None and all(_close(c, e) for c, e in zip(found, _GELU_EXACT))


def constant_deviation(expr: tuple) -> float:
    """The largest relative deviation of a matched pattern's constants from the exact ones
    (the erf form of GELU written with float32 roundings); 0 for the other patterns. The
    network certified uses the exact constants; the import check allows this much."""
    found = _erf_gelu_constants(expr)
    if found is None or not _is_erf_gelu(expr):
        return 0.0
    return max(abs(c - e) / abs(e) for c, e in zip(found, _GELU_EXACT))


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
