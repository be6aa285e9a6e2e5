"""What the command line shows: live progress while it works, then the summary.

`print_summary`: the table of checks, each check's one-line message, the table of
simulation runs, the verdict line (with its notes, e.g. a vacuous bound) and on the line
after it the error bound (`headline_line`: "‖e‖ ≤ B for noise ≤ v̄ after t ≥ T", per
component, "useful" or "vacuous"; or why there is none). A bound that does not rest on the
certificate says what it rests on after "error bound" (never "certified" under a verdict
that is not CERTIFIED). Where a plant region was proved forward invariant, a last line
"validity: ..." states the bound with conditions (a)-(b) proved for a set of starts.

On a terminal: `rich.progress` bars, one row per running step and one per task inside it
(a grid sweep counts points; a proof shows its closed volume and its boxes against the
budget it reports). Elsewhere (CI logs, pipes): plain timestamped lines, and while a step runs a
status line at least every `heartbeat` seconds, so a log never goes silent for long. The
seconds printed for a step are the ones `verify()` records in the certificate (and JUnit).
"""

from __future__ import annotations

import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, TextIO


@dataclass
class _Task:
    name: str
    total: float | None
    started: float = field(default_factory=time.monotonic)
    done: float = 0.0
    fields: dict[str, Any] = field(default_factory=dict)
    rich_id: Any = None


class ProgressDisplay:
    """A `certify.progress.Progress` with steps, drawn on `stream` (stderr by default).

    `interrupted`, when given, is called at every step and task update and raises to stop
    the work (the CLI passes `certify.cli.interrupts.INTERRUPTS.check`, so a Ctrl-C that Python
    dropped
    inside a finaliser still ends the run at the next update, not minutes later).
    """

    def __init__(self, stream: TextIO | None = None, *, quiet: bool = False,
                 rich: bool | None = None, heartbeat: float = 2.0,
                 interrupted: Callable[[], None] | None = None) -> None:
        self.stream = stream if stream is not None else sys.stderr
        self._interrupted = interrupted or (lambda: None)
        self.quiet = quiet
        isatty = getattr(self.stream, "isatty", lambda: False)()
        self.use_rich = (isatty if rich is None else rich) and not quiet
        self.heartbeat = heartbeat
        #: the step running now (None between steps); read by the CLI's error handler
        self.current_step: str | None = None
        #: seconds shown for each finished step, as printed
        self.shown: dict[str, float] = {}
        self._step_started = 0.0
        self._tasks: dict[str, _Task] = {}
        self._lock = threading.RLock()
        self._last_output = time.monotonic()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._rich: Any = None
        self._step_id: Any = None

    # ----- steps ---------------------------------------------------------------------
    def start_step(self, name: str) -> None:
        self._interrupted()
        with self._lock:
            self.current_step = name
            self._step_started = time.monotonic()
            for task in list(self._tasks):  # left over by a step that raised
                self.finish(task)
            if self.quiet:
                return
            if self.use_rich:
                bars = self._ensure_rich()
                self._step_id = bars.add_task(name, total=None, info="")
            else:
                self._ensure_heartbeat()
                self._line(f"{name} ...")

    def finish_step(self, name: str, status: str, seconds: float) -> None:
        with self._lock:
            self.shown[name] = seconds
            self.current_step = None
            tasks, self._tasks = list(self._tasks.values()), {}
            if self.quiet:
                return
            text = f"{name:<12} {status:<9} {seconds:8.2f} s"
            if self.use_rich and self._rich is not None:
                for task in tasks:
                    if task.rich_id is not None:
                        self._rich.remove_task(task.rich_id)
                if self._step_id is not None:
                    self._rich.remove_task(self._step_id)
                    self._step_id = None
                self._rich.console.print("  " + text, highlight=False, markup=False)
            else:
                self._line(text)

    def note(self, text: str) -> None:
        """One line the run established on the way (e.g. that the verdict is decided)."""
        with self._lock:
            if self.quiet:
                return
            if self.use_rich and self._rich is not None:
                self._rich.console.print("  " + text, highlight=False, markup=False)
            else:
                self._line(text)

    # ----- tasks inside a step (the Progress protocol) ---------------------------------
    def start(self, task: str, total: float | None = None) -> None:
        with self._lock:
            self.finish(task)  # a task started again replaces its row
            state = _Task(task, total)
            self._tasks[task] = state
            if self.use_rich and self._rich is not None:
                state.rich_id = self._rich.add_task(f"  {task}", total=total,
                                                    info=self._info(state))

    def update(self, task: str, advance: float = 1.0, **fields: object) -> None:
        self._interrupted()
        with self._lock:
            state = self._tasks.get(task)
            if state is None:
                return
            state.done += advance
            state.fields.update(fields)
            if state.rich_id is not None:
                volume = state.total == 1.0 and "proved" in state.fields
                completed = float(state.fields["proved"]) if volume else state.done
                self._rich.update(state.rich_id, completed=completed, info=self._info(state))

    def finish(self, task: str, message: str = "") -> None:
        with self._lock:
            state = self._tasks.pop(task, None)
            if state is not None and state.rich_id is not None:
                self._rich.remove_task(state.rich_id)

    def close(self) -> None:
        """Stop the live display and the status thread (idempotent)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=1.0)
            self._thread = None
        if self._rich is not None:
            self._rich.stop()
            self._rich = None

    # ----- drawing -----------------------------------------------------------------------
    def _info(self, state: _Task) -> str:
        """A task's status in words: points swept, or volume closed and boxes against the
        budget the proof reports."""
        f = state.fields
        if "proved" in f or state.total == 1.0:  # a proof: its total is the box's volume
            text = f"{100 * float(f.get('proved', 0.0)):.2f}% of the volume closed"
            budget = f.get("budget")
            text += f", {int(f.get('boxes', 0)):,}" + (f" / {int(budget):,}" if budget else "") \
                + " boxes"
            return text + f", {time.monotonic() - state.started:.0f} s"
        if state.total:
            return f"{state.done:,.0f} / {state.total:,.0f}"
        return ""

    def _status_line(self) -> str:
        elapsed = time.monotonic() - self._step_started
        parts = [f"{self.current_step}: running, {elapsed:.1f} s"]
        for state in self._tasks.values():
            info = self._info(state)
            parts.append(state.name + (f" {info}" if info else ""))
        return "; ".join(parts)

    def _line(self, text: str) -> None:
        stamp = time.strftime("%H:%M:%S")
        print(f"[{stamp}] {text}", file=self.stream, flush=True)
        self._last_output = time.monotonic()

    def _ensure_rich(self) -> Any:
        if self._rich is None:
            from rich.console import Console
            from rich.progress import (
                BarColumn,
                Progress,
                SpinnerColumn,
                TextColumn,
                TimeElapsedColumn,
            )

            self._rich = Progress(SpinnerColumn(), TextColumn("{task.description:<16}"),
                                  BarColumn(bar_width=30), TextColumn("{task.fields[info]}"),
                                  TimeElapsedColumn(), console=Console(file=self.stream),
                                  transient=True)
            self._rich.start()
        return self._rich

    def _ensure_heartbeat(self) -> None:
        if self._thread is None and self.heartbeat > 0:
            self._thread = threading.Thread(target=self._beat, name="certify-progress",
                                            daemon=True)
            self._thread.start()

    def _beat(self) -> None:
        while not self._stop.wait(min(0.25, self.heartbeat / 4)):
            with self._lock:
                quiet_for = time.monotonic() - self._last_output
                if self.current_step is not None and quiet_for >= self.heartbeat:
                    self._line("  " + self._status_line())


# ----- the summary after a run -----------------------------------------------------------
def _plain_table(header: list[str], rows: list[list[str]], out: TextIO,
                 indent: str = "") -> None:
    table = [header, *rows]
    widths = [max(len(line[i]) for line in table) for i in range(len(header))]
    for line in table:
        text = "  ".join(f"{cell:<{w}}" for cell, w in zip(line, widths)).rstrip()
        print(indent + text, file=out)


def run_table(cert: Any) -> tuple[list[str], list[list[str]]]:
    """The simulation runs, compact for a terminal: run, window, what ended it, e/b, breach."""
    from reports.content import fmt, result
    from reports.sections import exit_words

    r = result(cert, "simulation")
    if r is None or not r.runs:
        return [], []
    rows = []
    for run in r.runs:
        label = run.label if run.within_conditions else f"{run.label.split(' (')[0]}*"
        window = run.window if run.window is not None else run.exit_time
        rows.append([label, fmt(window, 3) + ("" if run.exit_time is not None else " (all)"),
                     exit_words(run), fmt(run.max_ratio, 3), fmt(run.peak_error, 3),
                     fmt(run.conservatism, 3), "BREACH" if run.breach else ""])
    return ["run", "valid window (s)", "what ended it", "max e/b", "peak after T", "bound/peak",
            "breach"], rows


def _unicode_ok(out: TextIO) -> bool:
    """Whether `out` can print the headline's symbols (‖ ≤ ≥ →): its encoding says so (a
    stream without one, e.g. an in-memory `io.StringIO`, takes any text)."""
    encoding = getattr(out, "encoding", None)
    if encoding is None:
        return True
    try:
        "\u2016\u2264\u2265\u2192\u221e".encode(encoding)
    except (LookupError, UnicodeEncodeError):
        return False
    return True


def headline_line(cert: Any, out: TextIO) -> str:
    """The error bound on one line, in Unicode where `out` can print it."""
    from reports.content import error_headline_text

    return error_headline_text(cert, unicode=_unicode_ok(out)).line


def print_verdict(cert: Any, out: TextIO) -> None:
    """The verdict line and, on the next line, the error bound (plain text: what `--quiet`
    prints)."""
    from reports.content import error_headline_text, verdict_line

    print(verdict_line(cert), file=out)
    print(headline_line(cert, out), file=out)
    validity = error_headline_text(cert, unicode=_unicode_ok(out)).validity
    if validity:
        print(f"validity: {validity}", file=out)


def print_summary(cert: Any, out: TextIO) -> None:
    """The checks table, messages, simulation runs, the verdict line and the error bound
    after it (rich on a terminal)."""
    from reports.content import check_rows, error_headline_text, verdict_summary

    rows = check_rows(cert)
    header, runs = run_table(cert)
    outside = any(r[0].endswith("*") for r in runs)
    if getattr(out, "isatty", lambda: False)():
        from rich.console import Console
        from rich.table import Table

        table = Table(title=f"certify: {cert.system.get('name', '')} (lam={cert.lam:g})")
        for col in ("check", "status", "sampled", "proved", "required"):
            table.add_column(col)
        colours = {"PROVED": "green", "PASSED": "green", "VIOLATED": "red",
                   "UNKNOWN": "yellow", "ERROR": "red", "QUALIFIED": "yellow"}
        for r in rows:
            table.add_row(r.title, f"[{colours.get(r.badge_key, 'white')}]{r.badge}[/]",
                          r.sampled.value, r.proved.value, "yes" if r.required else "")
        console = Console(file=out)
        console.print(table)
        for r in rows:
            console.print(f"  {r.name}: {r.message}", highlight=False, markup=False)
        if runs:
            sims = Table(title="simulation runs", title_justify="left")
            for col in header:
                sims.add_column(col)
            for row in runs:
                sims.add_row(*row)
            console.print(sims)
            if outside:
                console.print("  * outside the theorem's conditions (Gaussian noise)",
                              highlight=False, markup=False)
        colour = {"CERTIFIED": "green", "NOT CERTIFIED": "red"}.get(cert.verdict, "yellow")
        console.print(f"[bold {colour}]{cert.verdict}[/]: ", end="", highlight=False)
        console.print(verdict_summary(cert), highlight=False, markup=False)
        h = error_headline_text(cert, unicode=_unicode_ok(out))
        if h.proved:
            word = "green" if h.size_word == "useful" else "yellow"
            console.print(f"{h.label}: ", style="bold", end="", highlight=False, markup=False)
            console.print(h.sentence, end="", highlight=False, markup=False)
            console.print(f" [bold {word}]{h.size_word}[/]", highlight=False)
            if h.components:
                console.print(f"  per component: {h.components}", highlight=False,
                              markup=False)
            console.print(f"  {h.size}", highlight=False, markup=False)
            console.print(f"  {h.source}", style="dim", highlight=False, markup=False)
            if h.validity:
                console.print(f"validity: {h.validity}", highlight=False, markup=False)
        else:
            console.print(h.sentence, highlight=False, markup=False)
        return
    _plain_table(["check", "status", "sampled", "proved", "req"],
                 [[r.title, r.badge, r.sampled.value, r.proved.value,
                   "yes" if r.required else ""] for r in rows], out)
    for r in rows:
        print(f"  {r.name}: {r.message}", file=out)
    if runs:
        print("  simulation runs:", file=out)
        _plain_table(header, runs, out, indent="    ")
        if outside:
            print("    * outside the theorem's conditions (Gaussian noise)", file=out)
    print_verdict(cert, out)
