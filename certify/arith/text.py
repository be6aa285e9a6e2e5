"""Sound bounds as text: rounded outward to a few significant digits.

A printed upper bound is never below the proved one and a printed lower bound never above it:
the float is read as the decimal it is (`decimal.Decimal(x)` is exact) and rounded toward
the side the bound is on, so that no report claims more than was proved.
"""

from __future__ import annotations

import math
from decimal import ROUND_CEILING, ROUND_FLOOR, Decimal

__all__ = ["upper_text", "lower_text", "bound_text", "special_text"]


def special_text(x: float, signed: bool = False) -> str | None:
    """'NaN', the infinities and zero spelled out; None for any other number."""
    if math.isnan(x):
        return "NaN"
    if math.isinf(x):
        return ("+\u221e" if signed else "\u221e") if x > 0 else "-\u221e"
    return "0" if x == 0 else None


def _directed(x: float, sig: int, rounding: str, signed: bool = False) -> str:
    """`x` rounded in the direction `rounding` (a `decimal` mode) to `sig` significant
    digits: plain decimals for 1e-3 <= |x| < 1e6, else mantissa and exponent ('1.25e-05').
    Exact: the float is read as the decimal it is, so the text is on the stated side."""
    special = special_text(x, signed)
    if special is not None:
        return special
    d = Decimal(x)
    q = d.quantize(Decimal(1).scaleb(d.adjusted() - sig + 1), rounding=rounding).normalize()
    sign = "+" if signed and x > 0 else ""
    if 1e-3 <= abs(x) < 1e6:
        return sign + format(q, "f")
    mantissa, exponent = f"{q:e}".split("e")
    return f"{sign}{mantissa}e{int(exponent)}"


def upper_text(x: float, sig: int = 3) -> str:
    """An upper bound as text, rounded UP to `sig` significant digits, so that the printed
    number is never below the proved one (1.2431 -> '1.25', 1240.2 -> '1250'); 'inf' and
    'NaN' spelled out."""
    return _directed(x, sig, ROUND_CEILING)


def lower_text(x: float, sig: int = 3) -> str:
    """A lower bound as text, rounded DOWN to `sig` significant digits (7.8354 -> '7.83'),
    so that the printed number is never above the proved one."""
    return _directed(x, sig, ROUND_FLOOR)


def bound_text(x: float, side: str, sig: int = 3, *, signed: bool = False) -> str:
    """`x` as a sound bound on `side` ("upper" or "lower"), rounded outward."""
    if side not in ("upper", "lower"):
        raise ValueError(f"side must be 'upper' or 'lower'; got {side!r}")
    return _directed(float(x), sig, ROUND_CEILING if side == "upper" else ROUND_FLOOR,
                     signed)
