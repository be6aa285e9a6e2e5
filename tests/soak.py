"""How many examples each property-based test draws: its own count times CERTIFY_SOAK
(default 1). `CERTIFY_SOAK=20 pytest tests/` is a soundness soak: every enclosure and
relaxation property is checked on 20x as many random networks, boxes and points, with new
draws (hypothesis' database and seeds aside) each run."""

from __future__ import annotations

import os


def examples(count: int) -> int:
    """`count` times the soak factor (a positive integer; a bad value is refused)."""
    raw = os.environ.get("CERTIFY_SOAK", "1")
    try:
        factor = int(raw)
    except ValueError:
        raise ValueError(f"CERTIFY_SOAK must be a positive integer, not {raw!r}") from None
    if factor < 1:
        raise ValueError(f"CERTIFY_SOAK must be a positive integer, not {raw!r}")
    return count * factor
