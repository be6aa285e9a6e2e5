"""A proof's time budget as a deadline: `check_clock` and `OutOfTime`.

A deadline is a `time.perf_counter()` value. The set-up steps of a proof that read the clock
between their pieces (choosing the congruence, probing the bounds: `certify.enclose.mpdi`)
call `check_clock(deadline)` and raise `OutOfTime` once it has passed; the prover turns that
into an UNKNOWN outcome (`certify.prove.mpdi`). A base module: any layer may import it.
"""

from __future__ import annotations

import time


class OutOfTime(Exception):
    """A proof's set-up (before its first round) ran past the deadline of its budget: the
    proof stops there, UNKNOWN (raised by the set-up steps that read the clock, e.g.
    `certify.enclose.mpdi.plain_screen_pays`)."""


def check_clock(deadline: float | None) -> None:
    """Raise `OutOfTime` when `deadline` (a `time.perf_counter()` value) has passed; None:
    no deadline."""
    if deadline is not None and time.perf_counter() > deadline:
        raise OutOfTime
