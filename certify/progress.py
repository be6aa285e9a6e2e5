"""Progress reporting protocol: the core stays silent, callers inject a display.

Two levels. A *step* is one unit of `verify()` (a check, the report maps) or of the command
line (writing the reports); its time is the one the certificate records. A *task* is work
inside a step (a grid sweep, a branch-and-bound proof) with optional totals and fields
(`proved` volume fraction, `boxes`). Steps and tasks have separate namespaces, so a check
named "lipschitz" and its inner task "lipschitz" never collide. A display that does not
implement the step methods gets them as `start`/`finish` (see `start_step`, `finish_step`).
"""

from __future__ import annotations

from typing import Protocol


class Progress(Protocol):
    """Receives progress events from long computations."""

    def start(self, task: str, total: float | None = None) -> None: ...

    def update(self, task: str, advance: float = 1.0, **fields: object) -> None: ...

    def finish(self, task: str, message: str = "") -> None: ...


class NullProgress:
    """Discards every event (the default: library calls never print)."""

    def start(self, task: str, total: float | None = None) -> None:
        pass

    def update(self, task: str, advance: float = 1.0, **fields: object) -> None:
        pass

    def finish(self, task: str, message: str = "") -> None:
        pass


def start_step(progress: Progress, name: str) -> None:
    """Tell `progress` that step `name` begins."""
    hook = getattr(progress, "start_step", None)
    if hook is not None:
        hook(name)
    else:
        progress.start(name)


def note(progress: Progress, text: str) -> None:
    """Tell `progress` something the run established on the way (one line; e.g. that the
    verdict is decided); a display without a `note` method ignores it."""
    hook = getattr(progress, "note", None)
    if hook is not None:
        hook(text)


def finish_step(progress: Progress, name: str, status: str, seconds: float) -> None:
    """Tell `progress` that step `name` ended with `status` after `seconds` (the recorded time)."""
    hook = getattr(progress, "finish_step", None)
    if hook is not None:
        hook(name, status, seconds)
    else:
        progress.finish(name, status)
