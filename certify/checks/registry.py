"""The registered checks: lookup, dependency order, the fault-isolating runner, presenters.

`settings.CHECK_NAMES` lists the checks `verify()` runs; each is `CHECK` in
`certify/checks/<name>.py`. `PRESENTED_ONLY` are checks whose results can appear in a
certificate but that `verify()` does not run (the metric SDP of `certify check`).

Fault isolation: a check that raises becomes that check's ERROR result (`CheckFailure`, with
the exception's type and message); a check whose `needs` are missing or failed is not run
and is reported as NOT APPLICABLE (`Status.NOT_APPLICABLE`, never SKIPPED, which means the
user skipped it), with the reason; every other check still runs. Bad input
(`CertifyError`) and interrupts are not isolated: they stop the run as they should.

Deciding early: once a required check is VIOLATED (a sound counterexample) the verdict is
NOT CERTIFIED whatever the rest find; `run_checks` says so through the progress at once and,
with `fail_fast`, runs no other check (each is NOT RUN, saying why). The wall-clock cap
(`Context.deadline`, the `max_seconds` setting): a check not started when it has passed is
not run (UNKNOWN, saying so), and a check one of whose proofs it stopped
(`ProofStats.stopped_by_cap` in the result's `proof`) is UNKNOWN, never PROVED from a cut
proof, with the cap named in its message.
"""

from __future__ import annotations

import importlib
import logging
import time
from typing import Any

from certify.budget import passed
from certify.checks.base import Check, Context
from certify.errors import CertifyError
from certify.presentation import Presentation, present_failure
from certify.progress import finish_step, note, start_step
from certify.results import CheckFailure, Status
from certify.settings import CHECK_NAMES

PRESENTED_ONLY = ("metric",)

_log = logging.getLogger("certify")


def get_check(name: str) -> Check:
    """The check object registered as `name` (imports its module)."""
    if name not in CHECK_NAMES and name not in PRESENTED_ONLY:
        raise KeyError(f"no check named {name!r} (known: {', '.join(CHECK_NAMES)})")
    check = importlib.import_module(f"certify.checks.{name}").CHECK
    if check.name != name:  # pragma: no cover - a registration mistake
        raise RuntimeError(f"certify/checks/{name}.py registers {check.name!r}")
    return check


def run_order(names: tuple[str, ...] | list[str] = CHECK_NAMES) -> list[Check]:
    """The checks `names` in dependency order (`needs` and `uses` first), else as listed."""
    checks = {n: get_check(n) for n in names}
    done: list[str] = []
    visiting: set[str] = set()

    def visit(name: str) -> None:
        if name in done:
            return
        if name in visiting:
            raise RuntimeError(f"checks depend on each other in a cycle through {name!r}")
        visiting.add(name)
        for dep in (*checks[name].needs, *checks[name].uses):
            if dep in checks:
                visit(dep)
        visiting.discard(name)
        done.append(name)

    for name in names:
        visit(name)
    return [checks[n] for n in done]


def internal_error_message(exc: BaseException) -> str:
    """One line naming an exception: its type and the first line of its message."""
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
    if len(text) > 200:
        text = text[:197] + "..."
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def _missing_inputs(check: Check, context: Context, skip: tuple[str, ...]) -> list[str]:
    """Why `check` cannot run: each of its `needs` that is absent or failed, in words."""
    reasons = []
    for dep in check.needs:
        result = context.results.get(dep)
        if result is None:
            how = "was skipped" if dep in skip else "was not run"
            reasons.append(f"needs {dep}, which {how}")
        elif isinstance(result, CheckFailure):
            reasons.append(f"needs {dep}, which ended in {result.status.value} "
                           f"({result.message})")
    return reasons


def run_one(check: Check, context: Context, skip: tuple[str, ...] = ()) -> tuple[Any, float]:
    """Run one check with its faults isolated; returns (result or CheckFailure, seconds)."""
    t0 = time.perf_counter()
    missing = _missing_inputs(check, context, skip)
    if missing:
        result: Any = CheckFailure(Status.NOT_APPLICABLE,
                                   "not applicable: " + "; ".join(missing))
    else:
        try:
            result = check.run(context)
        except CertifyError:
            raise  # the user's input: one line and exit 2, not a check failure
        except Exception as exc:  # isolating the check is the point
            _log.debug("check %s raised", check.name, exc_info=True)
            result = CheckFailure(
                Status.ERROR, f"internal error: {internal_error_message(exc)}; the other "
                "checks still ran (re-run with --debug for the traceback)",
                error_type=type(exc).__name__)
        failed_inputs = [f"{d} ({context.results[d].status.value})" for d in check.uses
                         if isinstance(context.results.get(d), CheckFailure)]
        if failed_inputs and not isinstance(result, CheckFailure):
            result.message += f" [inputs unavailable: {', '.join(failed_inputs)}]"
    seconds = time.perf_counter() - t0
    if hasattr(result, "seconds"):
        result.seconds = seconds  # one time per check: the step's, as progress showed it
    return result, seconds


def run_checks(context: Context, skip: tuple[str, ...] = (),
               names: tuple[str, ...] | list[str] = CHECK_NAMES) -> dict[str, float]:
    """Run every registered check not in `skip`, in dependency order; fills
    `context.results` and returns the seconds each took (shown by `context.progress`).
    With `context.fail_fast`, once a required check is VIOLATED no more run (module
    docstring)."""
    fail_fast = context.fail_fast
    timings: dict[str, float] = {}
    decided: str | None = None  # the required check whose violation decided the verdict
    for check in run_order(names):
        if check.name in skip:
            continue
        if decided is not None and fail_fast:
            context.results[check.name] = CheckFailure(
                Status.NOT_RUN, f"not run: the verdict was already decided ({decided} is "
                "VIOLATED: a sound counterexample) and no report asked for its numbers")
            continue
        if passed(context.deadline):
            context.results[check.name] = CheckFailure(
                Status.UNKNOWN, f"not run: the wall-clock cap {cap_words(context)} was "
                "reached before it started")
            continue
        start_step(context.progress, check.name)
        result, seconds = run_one(check, context, skip)
        cut_by_cap(result, context)
        context.results[check.name] = result
        timings[check.name] = seconds
        finish_step(context.progress, check.name, result.status.value, seconds)
        if decided is None and check.name in context.required \
                and result.status == Status.VIOLATED:
            decided = check.name
            rest = ("the other checks are not run" if fail_fast
                    else "the other checks still run for the reports")
            note(context.progress, f"verdict decided: NOT CERTIFIED, {check.name} is VIOLATED "
                 f"({result.message}); {rest}")
    return timings


def cap_words(context: Context) -> str:
    """The wall-clock cap as the user set it: '--max-seconds 30' (a caller's own deadline
    without the setting: 'of the run')."""
    cap = context.settings.max_seconds
    return "of the run" if cap is None else f"--max-seconds {cap:g}"


def cut_by_cap(result: Any, context: Context) -> None:
    """A result one of whose proofs the wall-clock cap stopped (`ProofStats.stopped_by_cap`
    in its `proof`) is UNKNOWN, unless VIOLATED (a sound counterexample needs no finished
    proof) or not a result of its own; its message then begins by naming the cap."""
    proof = getattr(result, "proof", None)
    if proof is None or not proof.stopped_by_cap or isinstance(result, CheckFailure) \
            or result.status in (Status.VIOLATED, Status.ERROR, Status.NOT_APPLICABLE):
        return
    result.status = Status.UNKNOWN
    result.message = f"stopped by the wall-clock cap {cap_words(context)}: {result.message}"


def presentation(name: str, result: Any, certificate: Any) -> Presentation | None:
    """What the reports show for check `name` (None for a check this certify does not know)."""
    if isinstance(result, CheckFailure):
        return present_failure(result)
    try:
        check = get_check(name)
    except KeyError:
        return None
    return check.present(result, certificate)
