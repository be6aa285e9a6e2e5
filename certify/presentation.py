"""What a report shows of a check, as pure data: `Quantity` and `Presentation`.

Each check's presenter (`Check.present` in `certify.checks`) fills these; the certificate
hands them to the renderers (`Certificate.presentation`), so `reports/` formats them without
importing any check.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from certify.results import CheckFailure, Status

__all__ = ["Quantity", "Presentation", "NOTHING", "present_failure"]


@dataclass(frozen=True)
class Quantity:
    """One thing a report shows: a label, a value, and why the value may be missing.

    `value` is plain data: a number, a bool, a word, a point (list of floats) or a matrix
    (list of lists); `None` means "not established" and `missing` says why. `sig`, `signed`
    and `suffix` are formatting hints for the renderer (which does all formatting).
    """

    label: str
    value: Any = None
    missing: str = ""
    sig: int = 4
    signed: bool = False
    suffix: str = ""


@dataclass(frozen=True)
class Presentation:
    """A check in every report: its two sides, what it was checked with, every number.

    `sampled` is the falsification side (a value found at concrete points), `proved` the
    sound side; `setting` names the knobs it ran with; `numbers` lists every number (JUnit
    and the HTML table); `facts` are the key facts of the check's report section.
    """

    sampled: Quantity
    proved: Quantity
    setting: tuple[Quantity, ...] = ()
    numbers: tuple[Quantity, ...] = ()
    facts: tuple[Quantity, ...] = ()


NOTHING = Quantity("", None)


def present_failure(result: CheckFailure) -> Presentation:
    """A check that raised (ERROR) or could not run (not applicable): the reason only."""
    why = ("internal error" if result.status == Status.ERROR else "not applicable")
    side = Quantity("", None, why)
    facts = (Quantity("Status", result.status.value), Quantity("Reason", result.message))
    if result.error_type:
        facts += (Quantity("Exception", result.error_type),)
    return Presentation(side, side, (), facts, facts)
