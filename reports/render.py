"""Write every requested report, atomically: all or nothing per file, never half-written.

Everything is rendered in memory first (figures drawn once, shared by HTML and PDF); only
then is each file written through a temporary file in its own directory and `os.replace`.
An exception or KeyboardInterrupt while rendering writes nothing; one while writing leaves
each target either as it was or complete.
"""

from __future__ import annotations

import gc
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from certify.certificate import Certificate
from certify.files import atomic_write_bytes
from reports.junit import render_junit

PathLike = str | Path


@contextmanager
def _no_cycle_collection() -> Iterator[None]:
    """The cyclic garbage collector paused (as it was before, after): drawing allocates
    many objects, and each full collection would walk the whole heap of the process (in a
    run, torch's too) several times over. Cycles made meanwhile are collected afterwards."""
    was = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was:
            gc.enable()


def render_reports(certificate: Certificate, *, html: bool = False, pdf: bool = False,
                   junit: bool = False, json: bool = False, unknown: str = "failure",
                   trajectories: bool = False) -> dict[str, bytes]:
    """The requested reports as bytes, keyed 'html' / 'pdf' / 'junit' / 'json'.

    `trajectories`: also draw each simulated run's true and estimated states, and write them
    into the JSON (which leaves them out otherwise).
    """
    out: dict[str, bytes] = {}
    figures = []
    with _no_cycle_collection():
        if html or pdf:  # matplotlib is imported only when a figure is drawn
            from reports.figures import render_figures

            figures = render_figures(certificate, trajectories=trajectories)
        if json:
            out["json"] = (certificate.to_json(trajectories=trajectories) + "\n").encode()
        if junit:
            out["junit"] = render_junit(certificate, unknown=unknown).encode("utf-8")
        if html:
            from reports.html import render_html

            out["html"] = render_html(certificate, figures).encode("utf-8")
        if pdf:
            from reports.pdf import render_pdf

            out["pdf"] = render_pdf(certificate, figures)
    return out


def write_reports(certificate: Certificate, *, html: PathLike | None = None,
                  pdf: PathLike | None = None, junit: PathLike | None = None,
                  json: PathLike | None = None, unknown: str = "failure",
                  trajectories: bool = False) -> list[Path]:
    """Render, then atomically write each report whose path is given; returns the paths.

    `unknown` is the JUnit policy for UNKNOWN checks ("failure" or "error"); `trajectories`
    adds the figure of each simulated run's states to the HTML and PDF, and the states to
    the JSON.
    """
    targets = {k: Path(v) for k, v in (("html", html), ("pdf", pdf), ("junit", junit),
                                       ("json", json)) if v is not None}
    if not targets:
        return []
    data = render_reports(certificate, unknown=unknown, trajectories=trajectories,
                          **{k: True for k in targets})  # type: ignore[arg-type]
    written = []
    for key, path in targets.items():
        atomic_write_bytes(path, data[key])
        written.append(path)
    return written
