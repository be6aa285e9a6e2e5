"""Progress reporting protocol: the core stays silent, callers inject a display."""

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
