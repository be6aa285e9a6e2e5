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

from certify.presentation import NOTHING, Presentation, Quantity
from certify.results import CheckFailure
from certify.settings import DECLARED, RETIRED, RETIRED_LABELS

if TYPE_CHECKING:  # pragma: no cover
    import torch

    from certify.figuredata import FigureData
    from certify.model.problem import Problem
    from certify.progress import Progress
    from certify.prove.weighted import Weighting
    from certify.settings import VerifySettings


@dataclass
class Context:
    """What a check receives: the problem, the settings, where to compute and the results
    before it.

    `device` and `executor` are resolved once per run (`certify.verify.verify`): the checks
    prove on `on_device(problem)` (copied there once per problem, or itself on the CPU) and
    hand `executor` to the proofs. `deadline`: the run's wall-clock cap as a `time.perf_counter()`
    value (None: no cap), handed to every proof."""

    problem: Problem
    settings: VerifySettings
    progress: Progress
    figures: FigureData
    #: every result so far, by check name (a failed check's `CheckFailure` included)
    results: dict[str, Any] = field(default_factory=dict)
    #: checks whose failure means the gate fails (grows if a check says so)
    required: list[str] = field(default_factory=list)
    device: torch.device | str = "cpu"
    executor: Any = None
    deadline: float | None = None
    #: the caller wants the verdict more than the numbers: no check runs once it is decided
    #: (`certify.checks.registry.run_checks`), and a check may look for a decisive result
    #: cheaply first (the MPDI's coarse search)
    fail_fast: bool = False
    _copies: dict[int, tuple[Problem, Problem]] = field(default_factory=dict, repr=False)
    _weighted: Weighting | None = field(default=None, repr=False)

    def result(self, name: str) -> Any:
        """The result of check `name`, or None when it was not run or did not produce one."""
        r = self.results.get(name)
        return None if r is None or isinstance(r, CheckFailure) else r

    def on_device(self, problem: Problem | None = None) -> Problem:
        """`problem` (default the run's) on `device`: copied there at the first call, then
        the same copy (itself where it is there already)."""
        problem = self.problem if problem is None else problem
        if id(problem) not in self._copies:  # the original is kept, so its id stays its own
            self._copies[id(problem)] = (problem, problem.on(self.device))
        return self._copies[id(problem)][1]

    def weighted(self) -> Weighting:
        """The metric-weighted gain of the problem (`certify.prove.weighted.weighting`, on the
        CPU; its proofs run on `on_device(w.problem)`): made at the first call, then shared
        by the residual and Lipschitz checks."""
        if self._weighted is None:
            from certify.prove.weighted import weighting

            self._weighted = weighting(self.problem)
        return self._weighted


def setting_quantity(name: str, settings: dict[str, Any]) -> Quantity:
    """A setting as a check's presenter shows it (`Presentation.setting`): the label and
    unit of its declaration (`certify.settings.DECLARED`), its value in `settings` (a
    certificate's). An older certificate that holds the retired setting `name` replaced
    (`certify.settings.RETIRED`, e.g. rate_seconds for rate_boxes) shows that one instead."""
    decl = DECLARED[name]
    if name not in settings:
        for old, new in RETIRED.items():
            if new == name and old in settings:
                label, unit = RETIRED_LABELS[old]
                return Quantity(label, settings[old], suffix=unit)
        return Quantity(decl.label, None, "not recorded")
    return Quantity(decl.label, settings[name], decl.none, suffix=decl.unit)


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
