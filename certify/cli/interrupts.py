"""Ctrl-C while a command runs: recorded wherever it lands, raised again where it matters.

`INTERRUPTS` is the one instance: `certify.cli.main` activates it around a command, and the
commands call `INTERRUPTS.check()` at their steps and `INTERRUPTS.deferred()` around renames.
"""

from __future__ import annotations

import contextlib
import signal
import sys
import threading
from collections.abc import Iterator
from typing import Any

#: exit status after Ctrl-C (128 + SIGINT)
EXIT_INTERRUPTED = 130


class Interrupts:
    """Ctrl-C (SIGINT) while a command runs: exit 130 with one line, wherever it lands.

    Python turns SIGINT into `KeyboardInterrupt` wherever the main thread is; where that is a
    finaliser (`__del__`, a weakref callback: the figure libraries run many while the reports
    are drawn) Python prints it as "Exception ignored" and drops it, and the run would go on
    to exit 0. While `active()`, the handler also records the interrupt, such dropped ones
    are not printed, and `check()` raises it again where it matters: at every progress
    update and step, after the checks, before the reports are renamed into place and before
    the exit code is returned. `deferred()` holds an interrupt back (recorded, not raised)
    while files are renamed into place or cleaned up, so that no file is left half-done.
    """

    def __init__(self) -> None:
        self.received = False
        self._deferring = 0
        self._previous: Any = None
        self._hook: Any = None

    def _handle(self, signum: int, frame: Any) -> None:
        self.received = True
        if not self._deferring:
            raise KeyboardInterrupt

    def _unraisable(self, unraisable: Any) -> None:
        if isinstance(unraisable.exc_type, type) and issubclass(unraisable.exc_type,
                                                                KeyboardInterrupt):
            self.received = True  # dropped inside a finaliser: `check()` raises it again
            return
        self._hook(unraisable)

    @contextlib.contextmanager
    def active(self) -> Iterator[Interrupts]:
        """Handle SIGINT as above for the duration (in the main thread, and only where
        SIGINT has Python's default handler: an ignored SIGINT stays ignored)."""
        self.received = False
        install = (threading.current_thread() is threading.main_thread()
                   and signal.getsignal(signal.SIGINT) is signal.default_int_handler)
        if install:
            self._previous = signal.signal(signal.SIGINT, self._handle)
            self._hook, sys.unraisablehook = sys.unraisablehook, self._unraisable
        try:
            yield self
        finally:
            if install:
                signal.signal(signal.SIGINT, self._previous)
                sys.unraisablehook = self._hook

    def check(self) -> None:
        """Raise `KeyboardInterrupt` if an interrupt came (in the main thread only)."""
        if self.received and not self._deferring \
                and threading.current_thread() is threading.main_thread():
            raise KeyboardInterrupt

    @contextlib.contextmanager
    def deferred(self) -> Iterator[None]:
        """Hold interrupts back (recorded, raised by the next `check()`) for the duration."""
        self._deferring += 1
        try:
            yield
        finally:
            self._deferring -= 1


#: the one instance `main` activates; commands call `INTERRUPTS.check()`
INTERRUPTS = Interrupts()


