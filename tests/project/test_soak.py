"""The property tests' soak factor (`tests/soak.py`): counts scale by CERTIFY_SOAK; a value
that is not a positive integer is refused with its name, not read as 1."""

from __future__ import annotations

import pytest

from ..soak import examples


def test_examples_scale_by_the_soak_factor(monkeypatch) -> None:
    monkeypatch.delenv("CERTIFY_SOAK", raising=False)
    assert examples(12) == 12
    monkeypatch.setenv("CERTIFY_SOAK", "20")
    assert examples(12) == 240


@pytest.mark.parametrize("bad", ["0", "-2", "two", "1.5"])
def test_a_bad_soak_factor_is_refused(monkeypatch, bad: str) -> None:
    monkeypatch.setenv("CERTIFY_SOAK", bad)
    with pytest.raises(ValueError, match="CERTIFY_SOAK must be a positive integer"):
        examples(12)
