"""The check runner: a check whose inputs are missing is NOT APPLICABLE (never SKIPPED, which
means the user skipped it), with the reason; the check itself is not run."""

from __future__ import annotations

from typing import Any

from certify.checks.base import Context
from certify.checks.registry import get_check, run_checks, run_one
from certify.figuredata import FigureData
from certify.progress import NullProgress
from certify.results import CheckFailure, Status
from certify.settings import VerifySettings


def _context(results: dict[str, Any] | None = None) -> Context:
    # problem=None: a check whose inputs are missing must not even look at the problem
    return Context(problem=None, settings=VerifySettings(), progress=NullProgress(),  # type: ignore[arg-type]
                   figures=FigureData(), results=dict(results or {}))


def test_missing_input_skipped_by_the_user_is_not_applicable():
    result, _ = run_one(get_check("simulation"), _context(), skip=("bounds",))
    assert isinstance(result, CheckFailure)
    assert result.status == Status.NOT_APPLICABLE
    assert result.message == "not applicable: needs bounds, which was skipped"
    assert result.error_type == ""


def test_failed_input_is_not_applicable_and_names_the_failure():
    failed = CheckFailure(Status.ERROR, "internal error: OverflowError", "OverflowError")
    result, _ = run_one(get_check("simulation"), _context({"bounds": failed}))
    assert result.status == Status.NOT_APPLICABLE
    assert result.message.startswith("not applicable: needs bounds, which ended in ERROR "
                                     "(internal error: OverflowError)")


def test_checks_the_user_skips_are_absent_and_their_dependents_not_applicable():
    context = _context()
    timings = run_checks(context, skip=("bounds",), names=("bounds", "simulation"))
    assert "bounds" not in context.results and "bounds" not in timings
    assert context.results["simulation"].status == Status.NOT_APPLICABLE
