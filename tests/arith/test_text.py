"""certify.arith.text: a bound printed never claims more than was proved (upper rounded up,
lower rounded down, at any magnitude), and a report renders a Quantity marked as a bound so."""

from __future__ import annotations

from decimal import Decimal

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from certify.arith.text import bound_text, lower_text, upper_text
from certify.presentation import Quantity
from reports.content import side

FINITE = st.floats(allow_nan=False, allow_infinity=False, width=64)


@settings(max_examples=600, deadline=None)
@given(x=FINITE, sig=st.integers(1, 8))
def test_printed_bounds_are_on_their_side(x, sig):
    up, down = upper_text(x, sig), lower_text(x, sig)
    assert Decimal(up) >= Decimal(x) and Decimal(down) <= Decimal(x), (x, up, down)
    assert float(bound_text(x, "upper", sig)) >= x and float(bound_text(x, "lower", sig)) <= x


def test_known_texts():
    assert upper_text(2.2703) == "2.28" and lower_text(7.835454496216) == "7.83"
    assert upper_text(1.903, 2) == "2" and lower_text(-0.00026001, 4) == "-2.601e-4"
    assert upper_text(3.77e-5) == "3.78e-5" and upper_text(2.5e7) == "2.5e7"
    assert bound_text(0.5, "lower", 3, signed=True) == "+0.5"
    assert upper_text(float("inf")) == "\u221e" and lower_text(float("nan")) == "NaN"
    with pytest.raises(ValueError, match="side"):
        bound_text(1.0, "outer")


def test_a_quantity_marked_as_a_bound_is_rendered_outward():
    assert side(Quantity("L", 12.3301, bound="upper")).text == "12.34"
    assert side(Quantity("rate", 2.83549, bound="lower", signed=True)).text == "+2.835"
    assert side(Quantity("sampled", 12.3301)).text == "12.33"  # nearest, not a bound
    assert side(Quantity("L", None, "no sound bound", bound="upper")).text != "None"
