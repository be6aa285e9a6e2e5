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
  (labels, numbers, reasons; the types of `certify.presentation`); `reports/` formats and
  lays it out through the certificate, never importing the checks.

`certify.checks.registry` orders the registered checks by their dependencies and runs them;
adding a check is its module (with `CHECK`) plus its name in `settings.CHECK_NAMES`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, ClassVar

from certify.presentation import NOTHING, Presentation
from certify.results import CheckFailure

if TYPE_CHECKING:  # pragma: no cover
    from certify.figuredata import FigureData
    from certify.model.problem import Problem
    from certify.progress import Progress
    from certify.settings import VerifySettings


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

    def present(self, result: Any, certificate: Any) -> Presentation:
        """Default presentation: no numbers (a check should override this). `certificate`: the
        `certify.Certificate` the result belongs to (checks may read other results there)."""
        return Presentation(NOTHING, NOTHING)

    def __repr__(self) -> str:
        return f"<check {self.name}>"
