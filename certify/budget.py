"""The optional wall-clock cap of a proof: `cap_deadline`, `check_clock` and `OutOfTime`.

Proofs are budgeted in boxes (work), so that their outcome does not depend on the machine;
a run may add a wall-clock cap (`max_seconds`), handed to the proofs as a deadline: a
`time.perf_counter()` value, None for no cap. Without a cap nothing reads the clock to
decide anything. The set-up steps of a proof that read the clock between their pieces
(choosing the congruence, probing the bounds: `certify.enclose.mpdi`) call
`check_clock(deadline)` and raise `OutOfTime` once it has passed; the prover turns that
into an UNKNOWN outcome stopped by the cap (`certify.prove.mpdi`). A base module: any layer
may import it.
"""

from __future__ import annotations

import time


class OutOfTime(Exception):
    """A proof's set-up (before its first round) ran past the deadline of its wall-clock cap:
    the proof stops there, UNKNOWN (raised by the set-up steps that read the clock, e.g.
    `certify.enclose.mpdi.plain_screen_pays`)."""


def check_clock(deadline: float | None) -> None:
    """Raise `OutOfTime` when `deadline` (a `time.perf_counter()` value) has passed; None:
    no cap, and the clock is not read."""
    if deadline is not None and time.perf_counter() > deadline:
        raise OutOfTime


def cap_deadline(deadline: float | None, seconds: float | None,
                 started: float) -> float | None:
    """The earlier of `deadline` and `seconds` after `started` (None where neither is given)."""
    if seconds is not None:
        end = started + seconds
        deadline = end if deadline is None else min(deadline, end)
    return deadline


def passed(deadline: float | None) -> bool:
    """Whether `deadline` has passed (never, without one)."""
    return deadline is not None and time.perf_counter() > deadline
