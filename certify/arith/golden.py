"""Golden-section search of a scalar function over an interval (the rate scans of the error
bound's design and certificate)."""

from __future__ import annotations

import math
from collections.abc import Callable

__all__ = ["golden_section"]


def golden_section(fun: Callable[[float], float], a: float, b: float, steps: int) -> None:
    """Golden-section steps minimising `fun` over [a, b]: `steps` + 2 evaluations, each new
    point inside the bracket that holds the smallest value seen. Returns nothing: callers
    record the values `fun` computes (their candidates carry more than the value)."""
    g = (math.sqrt(5.0) - 1.0) / 2.0
    c, d = b - g * (b - a), a + g * (b - a)
    fc, fd = fun(c), fun(d)
    for _ in range(steps):
        if fc <= fd:
            b, d, fd = d, c, fc
            c = b - g * (b - a)
            fc = fun(c)
        else:
            a, c, fc = c, d, fd
            d = a + g * (b - a)
            fd = fun(d)
