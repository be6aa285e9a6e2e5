"""The `certify` command line: the parser, the exit codes and the one-line error handling.

Exit codes of `certify run`: 0 certified, 1 not certified, 2 bad input or usage, 3
inconclusive (a required check UNKNOWN, not run, or in ERROR), 4 internal error (an
exception escaped: one line on stderr naming the step, `--debug` for the traceback).
A crash never exits 0 or 1. Every command: 130 when interrupted (Ctrl-C, at any point: one
line, no traceback, no report half-written), 141 when the reader of its output went away
(`certify systems | head -1`: quietly, as a Unix tool killed by SIGPIPE). This module
imports only the standard library at start-up, so `certify --help`, `--version` and
`certify systems` answer at once; each command imports what it needs (`certify.commands`).
"""

from __future__ import annotations

import argparse
import contextlib
import os
import signal
import sys
import threading
from collections.abc import Iterator
from typing import Any

from certify.certificate import EXIT_BAD_INPUT, EXIT_INTERNAL_ERROR
from certify.commands import builtin_system_names
from certify.errors import CertifyError
from certify.settings import CERTIFICATE_CHECK, CHECK_NAMES, WORKERS_PER_CPU

#: exit status after Ctrl-C (128 + SIGINT) and when stdout's reader went away (128 + SIGPIPE)
EXIT_INTERRUPTED = 130
EXIT_CLOSED_PIPE = 141

EXIT_CODES_TEXT = ("exit codes of run: 0 certified, 1 not certified, 2 bad input or usage, "
                   "3 inconclusive (a required check unknown or in ERROR), 4 internal error; "
                   "any command: 130 interrupted, 141 output pipe closed")

EXAMPLES = """\
examples:
  certify systems                                   list the built-in systems
  certify check vdp                                 pre-flight the spec as given
  certify train vdp --preset certified -o vdp.ckpt  train a gain network
  certify run vdp.ckpt --html r.html --junit r.xml  verify, write reports
  certify run vdp.ckpt --json - --quiet | jq .verdict
  certify run vdp.ckpt --require mpdi,rate --skip simulation
  certify run model.onnx --system spec.toml         verify a model trained elsewhere
  certify import model.onnx --system spec.toml -o model.ckpt
  certify report r.json --pdf r.pdf                 re-render without verifying
  eval "$(certify completion bash)"                 tab completion (bash, zsh, fish)

""" + EXIT_CODES_TEXT + "."


def version() -> str:
    """The installed distribution's version (the package's own when not installed)."""
    from importlib import metadata

    try:
        return metadata.version("certify")
    except metadata.PackageNotFoundError:  # pragma: no cover - running from a bare tree
        from certify import __version__

        return __version__


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


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # one line, exit 2
        self.exit(EXIT_BAD_INPUT, f"certify: error: {message} (see 'certify --help')\n")


def _dispatch(name: str) -> Any:
    """A command function, imported when the command runs (not when the parser is built)."""
    def run(args: argparse.Namespace) -> int:
        from certify import commands

        return getattr(commands, f"cmd_{name}")(args)

    return run


def _report_flags(p: argparse.ArgumentParser, json_help: str) -> None:
    p.add_argument("--html", metavar="PATH", help="write the HTML report")
    p.add_argument("--pdf", metavar="PATH", help="write the PDF report")
    p.add_argument("--json", metavar="PATH", help=json_help)
    p.add_argument("--junit", metavar="PATH",
                   help="write JUnit XML (a required check that fails is a <failure>, ERROR "
                        "an <error>; checks not required never fail the build)")
    p.add_argument("--trajectories", action="store_true",
                   help="also plot each simulated run's true and estimated states (HTML/PDF) and "
                        "store them in the JSON certificate")


def systems_text() -> str:
    """The built-in systems, as help text names them (read from the package's spec files)."""
    return ", ".join(builtin_system_names())


def _model_flags(p: argparse.ArgumentParser, system_help: str) -> None:
    """The flags that turn a model from elsewhere (ONNX, TorchScript, state_dict) into a
    verification problem (`certify import`, `certify run MODEL --system SPEC`)."""
    p.add_argument("--system", metavar="SPEC", help=system_help)
    p.add_argument("--lam", type=float, help="contraction rate (default: the spec's)")
    p.add_argument("--metric", help="metric P as [[a,b],[b,c]] (default: the spec's)")
    p.add_argument("--activation", metavar="NAME",
                   help="the activation of a state_dict (it carries none), e.g. tanh")
    p.add_argument("--structure", choices=("direct", "structural"),
                   help="gain structure when the output width does not decide it (p = 1)")


def build_parser(with_train: bool = True) -> argparse.ArgumentParser:
    """The full parser. `with_train=False` leaves out `train`'s own options (they import
    the training code); `main` builds them only when the command is `train`."""
    formatter = argparse.RawDescriptionHelpFormatter
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--debug", action="store_true",
                        help="on an internal error, print the traceback")
    parser = _Parser(prog="certify", formatter_class=formatter, epilog=EXAMPLES,
                     description="Train and certify learned contraction observers.")
    parser.add_argument("--version", action="version", version=f"certify {version()}")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser,
                                metavar="COMMAND")

    systems = systems_text()
    p = sub.add_parser("systems", parents=[common],
                       help=f"list the built-in systems ({systems}), or print one")
    p.add_argument("name", nargs="?", help=f"a built-in name ({systems}) or a spec path")
    p.set_defaults(func=_dispatch("systems"))

    p = sub.add_parser("check", parents=[common], formatter_class=formatter,
                       help="pre-flight a spec: necessary condition and metric synthesis",
                       epilog="exit codes: 0 the spec as given passes, 1 it fails (a metric "
                              "that fixes it is printed when one is found), 2 bad input, "
                              "3 undecided, 4 internal error.")
    p.add_argument("system", help=f"built-in name ({systems}) or spec path")
    p.add_argument("--lam", type=float, help="contraction rate (default: the spec's)")
    p.add_argument("--metric", help="metric P as [[a,b],[b,c]] (default: the spec's)")
    p.add_argument("--margin", type=float, default=0.05, help="SDP margin (default 0.05)")
    p.add_argument("--no-synthesis", action="store_true", help="do not search a metric")
    p.add_argument("--json", metavar="PATH", help="write the results as JSON ('-': stdout)")
    p.set_defaults(func=_dispatch("check"))

    p = sub.add_parser("train", parents=[common],
                       help="train a gain network and write a checkpoint")
    if with_train:
        from training.command import add_train_arguments

        add_train_arguments(p)
    p.set_defaults(func=_dispatch("train"))

    names = ", ".join(CHECK_NAMES)
    skippable = ", ".join(c for c in CHECK_NAMES if c != CERTIFICATE_CHECK)
    p = sub.add_parser("run", parents=[common], formatter_class=formatter,
                       help="verify a checkpoint and write the certificate",
                       epilog=f"checks: {names}.\n{EXIT_CODES_TEXT}.")
    p.add_argument("checkpoint", help="a checkpoint written by 'certify train' (.ckpt), or "
                   "a model from elsewhere (.onnx, TorchScript, state_dict) with --system")
    _model_flags(p, f"the system a model from elsewhere observes (built-in name: {systems}; "
                    "or a spec path)")
    _report_flags(p, "write the JSON certificate ('-': stdout, the rest goes to stderr)")
    p.add_argument("--grid-points", type=int, help="dense grid size over X x Y (default 1e6)")
    p.add_argument("--proof-seconds", type=float, help="prover time budget (default 60)")
    p.add_argument("--max-boxes", type=int, help="prover sub-box budget")
    p.add_argument("--adversarial-starts", type=int, help="gradient-ascent starts")
    p.add_argument("--noise", type=float, help="noise bound vbar (default 0.15)")
    p.add_argument("--sim-time", type=float, help="simulated seconds (default 10)")
    p.add_argument("--seed", type=int, help="random seed (default 0)")
    p.add_argument("--require", metavar="CHECKS",
                   help=f"comma-separated checks that must pass; {CERTIFICATE_CHECK} (the "
                        "certificate) is always one of them, and alone by default; from: "
                        f"{names}")
    p.add_argument("--skip", metavar="CHECKS",
                   help=f"comma-separated checks not to run (never {CERTIFICATE_CHECK}, the "
                        f"certificate); from: {skippable}")
    p.add_argument("--allow-unknown", action="store_true",
                   help="an UNKNOWN required check other than the MPDI does not fail the gate "
                        "(the MPDI must be PROVED to certify; ERROR always fails)")
    p.add_argument("--workers", type=int, metavar="N",
                   help="run the grid and the proofs on a local Dask cluster of N processes "
                        f"(default 1: in this process; at most {WORKERS_PER_CPU} per CPU)")
    p.add_argument("--scheduler", metavar="ADDRESS",
                   help="run them on a running Dask cluster, e.g. tcp://host:8786 "
                        "(dask-jobqueue on SLURM/PBS, Kubernetes)")
    p.add_argument("--device", metavar="DEVICE",
                   help="torch device: cpu (default), cuda or cuda:N. The MPDI grid, the "
                        "falsifier and the branch-and-bound proofs (MPDI, rate, residual, "
                        "dk/dy) run there; the simulation, LipSDP and the pre-flight stay on "
                        "the CPU")
    p.add_argument("--config", metavar="PATH", help="read [tool.certify] from this file")
    p.add_argument("--no-config", action="store_true", help="ignore pyproject.toml")
    p.add_argument("--quiet", "-q", action="store_true", help="only the verdict line")
    p.set_defaults(func=_dispatch("run"))

    p = sub.add_parser("import", parents=[common],
                       help="turn an ONNX, TorchScript or state_dict model into a checkpoint")
    p.add_argument("model", help="model.onnx, a TorchScript file, or a state_dict (.pt)")
    _model_flags(p, f"the system the model observes (built-in name: {systems}; or a spec "
                    "path; required)")
    p.add_argument("-o", "--output", required=True, metavar="PATH", help="checkpoint to write")
    p.set_defaults(func=_dispatch("import"))

    p = sub.add_parser("report", parents=[common],
                       help="re-render reports from a saved JSON certificate")
    p.add_argument("certificate", help="a JSON certificate written by 'certify run --json'")
    _report_flags(p, "write the JSON certificate again ('-': stdout)")
    p.add_argument("--quiet", "-q", action="store_true", help="only the verdict line")
    p.set_defaults(func=_dispatch("report"))

    p = sub.add_parser("completion", parents=[common], formatter_class=formatter,
                       help="print a shell completion script",
                       epilog='bash: eval "$(certify completion bash)"\n'
                              "zsh:  eval \"$(certify completion zsh)\"\n"
                              "fish: certify completion fish | source")
    p.add_argument("shell", choices=("bash", "zsh", "fish"))
    p.set_defaults(func=_dispatch("completion"))
    return parser


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
        return int(args.func(args))
    except CertifyError as exc:
        print(f"certify: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except BrokenPipeError as exc:
        if _stdio_closed():
            raise  # the reader went away: `main` exits quietly
        return _internal_error(exc, args)
    except Exception as exc:  # a crash: never a verdict
        return _internal_error(exc, args)


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
        from certify.checkpoint import atomic_write_bytes
        from certify.checks.registry import internal_error_message
        from reports.junit import render_internal_error

        text = render_internal_error(where, internal_error_message(exc), type(exc).__name__)
        atomic_write_bytes(path, text.encode("utf-8"))
    except Exception:  # the crash itself may be the file system; the exit code says enough
        pass


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
