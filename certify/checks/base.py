"""The check protocol: one object per check, with its report presenter beside it.

Every check of `verify()` is an instance of a `Check` subclass, defined at the end of its own
module (`certify/checks/<name>.py`, as `CHECK`) next to the computation it runs. It states

- `name`, `title`: what the check is called in settings, JSON and reports;
- `reads`: the `VerifySettings` fields it reads (echoed by its presenter);
- `needs`: checks whose results it cannot run without (missing or failed: the check is
  reported as not applicable, with the reason, and is not run);
- `uses`: checks whose results it reads when they exist (a missing one is `None`);
- `run(context) -> result`: the computation; it may raise, the runner isolates it;
- `present(result, certificate) -> Presentation`: what the reports show, as pure data
  (labels, numbers, reasons); `reports/` formats and lays it out, and imports this module,
  never the reverse.

`certify.checks.registry` orders the registered checks by their dependencies and runs them;
adding a check is its module (with `CHECK`) plus its name in `settings.CHECK_NAMES`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, ClassVar

from certify.results import CheckFailure, Status

if TYPE_CHECKING:  # pragma: no cover
    from certify.certificate import Certificate
    from certify.figuredata import FigureData
    from certify.model.problem import Problem
    from certify.progress import Progress
    from certify.settings import VerifySettings


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


@dataclass
class Context:
    """What a check receives: the problem, the settings and the results before it."""

    problem: Problem
    settings: VerifySettings
    progress: Progress
    figures: FigureData
    #: every result so far, by check name (a failed check's `CheckFailure` included)
    results: dict[str, Any] = field(default_factory=dict)
    #: checks whose failure means the gate fails (grows if a check says so)
    required: list[str] = field(default_factory=list)

    def result(self, name: str) -> Any:
        """The result of check `name`, or None when it was not run or did not produce one."""
        r = self.results.get(name)
        return None if r is None or isinstance(r, CheckFailure) else r


class Check:
    """Base class of every check; subclasses set the class attributes and `run`/`present`."""

    name: ClassVar[str] = ""
    title: ClassVar[str] = ""
    result_type: ClassVar[type] = object
    reads: ClassVar[tuple[str, ...]] = ()
    needs: ClassVar[tuple[str, ...]] = ()
    uses: ClassVar[tuple[str, ...]] = ()

    def run(self, context: Context) -> Any:  # pragma: no cover - abstract
        raise NotImplementedError(f"check {self.name!r} has no run()")

    def present(self, result: Any, certificate: Certificate) -> Presentation:
        """Default presentation: no numbers (a check should override this)."""
        return Presentation(NOTHING, NOTHING)

    def __repr__(self) -> str:
        return f"<check {self.name}>"


def present_failure(result: CheckFailure) -> Presentation:
    """A check that raised (ERROR) or could not run (not applicable): the reason only."""
    why = ("internal error" if result.status == Status.ERROR else "not applicable")
    side = Quantity("", None, why)
    facts = (Quantity("Status", result.status.value), Quantity("Reason", result.message))
    if result.error_type:
        facts += (Quantity("Exception", result.error_type),)
    return Presentation(side, side, (), facts, facts)
