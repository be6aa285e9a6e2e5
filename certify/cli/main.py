"""The `certify` command line: the parser, the exit codes and the one-line error handling.

Exit codes of `certify run`: 0 certified, 1 not certified, 2 bad input or usage, 3
inconclusive (a required check UNKNOWN, not run, or in ERROR), 4 internal error (an
exception escaped: one line on stderr naming the step, `--debug` for the traceback).
A crash never exits 0 or 1. Every command: 130 when interrupted (Ctrl-C, at any point: one
line, no traceback, no report half-written), 141 when the reader of its output went away
(`certify systems | head -1`: quietly, as a Unix tool killed by SIGPIPE). This module
imports only the standard library at start-up, so `certify --help`, `--version` and
`certify systems` answer at once; each command imports what it needs (`certify.cli.commands`).
Python warnings raised while a command runs (a numpy overflow, a torch notice) go to the
debug log (`--debug` shows them), never onto the output a user or a CI log reads.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
import warnings
from typing import Any

from certify.certificate import EXIT_BAD_INPUT, EXIT_INTERNAL_ERROR
from certify.cli.interrupts import EXIT_INTERRUPTED, INTERRUPTS
from certify.cli.parser import build_parser
from certify.errors import CertifyError

#: exit status when stdout's reader went away (128 + SIGPIPE)
EXIT_CLOSED_PIPE = 141


def _command_of(argv: list[str]) -> str | None:
    """The sub-command named in argv (the first word that is not an option)."""
    return next((a for a in argv if not a.startswith("-")), None)


def main(argv: list[str] | None = None) -> int:
    """Run one command; returns its exit code (see the module docstring)."""
    with INTERRUPTS.active():
        try:
            code = _main(argv)
            INTERRUPTS.check()  # one Python dropped inside a finaliser
            for stream in (sys.stdout, sys.stderr):  # a closed pipe shows here, not at exit
                stream.flush()
            return code
        except KeyboardInterrupt:
            with INTERRUPTS.deferred(), contextlib.suppress(OSError, ValueError):
                print("certify: interrupted", file=sys.stderr, flush=True)
            return EXIT_INTERRUPTED
        except BrokenPipeError:  # only where stdout or stderr itself is closed (`_main`)
            return _closed_pipe()


def _main(argv: list[str] | None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser(with_train=_command_of(argv) == "train")
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # usage errors (exit 2), --help and --version (exit 0)
        return int(exc.code or 0) if not isinstance(exc.code, str) else EXIT_BAD_INPUT
    if args.debug:
        import logging

        logging.basicConfig(stream=sys.stderr, level=logging.WARNING,
                            format="certify: debug: %(message)s")
        logging.getLogger("certify").setLevel(logging.DEBUG)
    try:
        from certify.cli import commands  # imported when a command runs, not for --help

        with warnings.catch_warnings():  # restored after the command (in-process callers)
            warnings.showwarning = _to_debug_log
            return int(getattr(commands, f"cmd_{args.command}")(args))
    except CertifyError as exc:
        print(f"certify: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except BrokenPipeError as exc:
        if _stdio_closed():
            raise  # the reader went away: `main` exits quietly
        return _internal_error(exc, args)
    except Exception as exc:  # a crash: never a verdict
        return _internal_error(exc, args)


def _to_debug_log(message: Warning | str, category: type[Warning], filename: str, lineno: int,
                  file: Any = None, line: str | None = None) -> None:
    """`warnings.showwarning` while a command runs: the warning as one debug line."""
    import logging

    logging.getLogger("certify").debug("%s:%d: %s: %s", filename, lineno, category.__name__,
                                       message)


def _broken(stream: Any) -> bool:
    """Whether `stream` is a pipe or socket whose reader has gone (POSIX poll: POLLERR)."""
    try:
        fd = stream.fileno()
    except (AttributeError, OSError, ValueError):
        return False
    try:
        import select

        poller = select.poll()
    except (ImportError, AttributeError):  # pragma: no cover - no poll (Windows)
        return True
    poller.register(fd, select.POLLOUT)
    return any(events & (select.POLLERR | select.POLLHUP) for _, events in poller.poll(0))


def _stdio_closed() -> bool:
    return _broken(sys.stdout) or _broken(sys.stderr)


def _closed_pipe() -> int:
    """stdout or stderr lost its reader (`certify systems | head -1`): that is the reader's
    choice, not a failure of certify. Point the closed stream at /dev/null (so that nothing
    more is written to it, and Python's own flush at exit says nothing) and exit
    `EXIT_CLOSED_PIPE`, the status of a Unix tool killed by SIGPIPE."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
    except OSError:  # pragma: no cover
        return EXIT_CLOSED_PIPE
    for stream in (sys.stdout, sys.stderr):
        if _broken(stream):
            os.dup2(devnull, stream.fileno())
    os.close(devnull)
    return EXIT_CLOSED_PIPE


def _internal_error(exc: Exception, args: argparse.Namespace) -> int:
    """One line on stderr naming where it happened and the exception; exit 4."""
    from certify.checks.registry import internal_error_message

    if args.debug:
        import traceback

        traceback.print_exception(exc, file=sys.stderr)
    display = getattr(args, "display", None)
    step = getattr(display, "current_step", None)
    where = f"step '{step}'" if step else f"'certify {args.command}'"
    hint = "" if args.debug else " (re-run with --debug for the traceback)"
    print(f"certify: internal error in {where}: {internal_error_message(exc)}{hint}",
          file=sys.stderr)
    _junit_for_crash(args, step or f"certify {args.command}", exc)
    return EXIT_INTERNAL_ERROR


def _junit_for_crash(args: argparse.Namespace, where: str, exc: Exception) -> None:
    """Where a JUnit file was asked for, leave one <error> case in it, so that CI shows the
    crash in its test view instead of a missing file (best effort: stderr has the line)."""
    path = getattr(args, "junit", None)
    if not path or path == "-":
        return
    try:
        from certify.checks.registry import internal_error_message
        from certify.files import atomic_write_bytes
        from reports.junit import render_internal_error

        text = render_internal_error(where, internal_error_message(exc), type(exc).__name__)
        atomic_write_bytes(path, text.encode("utf-8"))
    except Exception:  # the crash itself may be the file system; the exit code says enough
        pass


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
