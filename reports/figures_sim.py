"""Figures of the simulation check: the error against the proved bound per run (always),
and the true and estimated states per run (only on request: `--trajectories`).

Panels are small multiples, three to a row; titles are short (the run's name, wrapped) so
none is cut off, and the long story of each run stays in the report's table of runs. What
is drawn is recorded (`reports.figure_kit.mark`) and the captions are written from it.
"""

from __future__ import annotations

import math
import textwrap
import warnings
from typing import Any

import numpy as np
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Patch

from certify.certificate import Certificate
from reports.figure_data import as_array, check_result, state_names
from reports.figure_kit import STATE_COLOURS, grid, log_axis, mark, new_figure

#: at most this many runs are drawn (the table lists all; the default settings simulate 13)
MAX_PANELS = 16
#: panels to a row: NCOLS up to NCOLS^2 panels, one more beyond
NCOLS = 3
PANEL_HEIGHT = 1.75  # inches per row
#: inches: above the panels, the figure's title and two lines of panel title; below, the
#: last row's axis and the legend; between rows, an axis and a panel title; between columns,
#: the tick labels of the next panel
TOP, BOTTOM, ROW_GAP, COL_GAP, LEFT, RIGHT = 0.64, 0.72, 0.74, 0.55, 0.55, 0.15


def _runs(cert: Certificate) -> list[Any]:
    r = check_result(cert, "simulation")
    return [] if r is None else [run for run in r.runs if run.t][:MAX_PANELS]


def short_title(run: Any, width: int = 30) -> str:
    """A run's name for a panel title: before any parenthesis, wrapped to two lines."""
    name = run.label.split(" (")[0]
    if not run.within_conditions:
        name += " (outside the conditions)"
    if run.breach:
        name += " \u2014 BREACH"
    return "\n".join(textwrap.wrap(name, width)[:2])


def _grid(fig: Figure, k: int) -> list[Any]:
    """k panels, `_columns(k)` to a row (only the k axes are made)."""
    ncols = _columns(k)
    return grid(fig, math.ceil(k / ncols), ncols, count=k, left=LEFT, right=RIGHT, top=TOP,
                bottom=BOTTOM, wgap=COL_GAP, hgap=ROW_GAP)


def _columns(k: int) -> int:
    return min(NCOLS if k <= NCOLS * NCOLS else NCOLS + 1, max(k, 1))


def _height(k: int) -> float:
    return PANEL_HEIGHT * math.ceil(k / _columns(k)) + 0.75


def _legend(fig: Figure, handles: list[Any], title: str) -> None:
    """The figure's legend along its bottom edge and its title along the top."""
    fig.legend(handles=handles, loc="lower center", bbox_to_anchor=(0.5, 0.0),
               ncol=len(handles), frameon=False)
    fig.suptitle(title, fontsize=10, y=1.0 - 0.06 / fig.get_size_inches()[1], va="top")


def _half_diagonal(cert: Certificate) -> float | None:
    b = check_result(cert, "bounds")
    return None if b is None else getattr(b, "box_half_diagonal", None)


def fig_bounds(cert: Certificate) -> Figure | None:
    """Observed error against the proved bound, one small panel per run."""
    runs = _runs(cert)
    if not runs:
        return None
    fig = new_figure(_height(len(runs)))
    half = _half_diagonal(cert)
    for ax, run in zip(_grid(fig, len(runs)), runs):
        t, e = as_array(run.t), as_array(run.error)
        ax.semilogy(t, np.maximum(e, 1e-12), color="#1f2937", lw=1.0)
        mark(fig, "error")
        if run.bound:
            b = as_array(run.bound)
            ax.semilogy(t[:len(b)], b, color="#2563eb", lw=1.4, ls="--")
            mark(fig, "bound")
            if half is not None and float(np.nanmax(b)) > half:
                ax.axhline(half, color="#6b7280", lw=0.9, ls=":")
                mark(fig, "half-diagonal", half)
        else:
            ax.text(0.97, 0.95, "no proved bound", transform=ax.transAxes, fontsize=7,
                    color="#4b5563", ha="right", va="top")
            mark(fig, "no bound")
        if run.exit_time is not None:
            ax.axvspan(run.exit_time, t.max(), color="#fecaca", alpha=0.5, lw=0)
            mark(fig, "after exit")
        ax.set_title(short_title(run), fontsize=8, y=1.0)
        ax.set_xlim(t.min(), t.max())
        log_axis(ax.yaxis, minor=False)  # decades only: small panels
        ax.tick_params(labelsize=7)
        ax.set_xlabel("t (s)", fontsize=7.5)
        ax.grid(alpha=0.3, which="major")
    handles = [Line2D([], [], color="#1f2937", lw=1.0,
                      label="observed \u2016x \u2212 x\u0302\u2016")]
    d = fig.certify_drawn  # type: ignore[attr-defined]
    if "bound" in d:
        handles.append(Line2D([], [], color="#2563eb", lw=1.4, ls="--", label="proved bound"))
    if "half-diagonal" in d:
        handles.append(Line2D([], [], color="#6b7280", lw=0.9, ls=":",
                              label="half-diagonal of X"))
    if "after exit" in d:
        handles.append(Patch(color="#fecaca", label="after the first exit (no claim)"))
    _legend(fig, handles, "Simulated error against the proved bound")
    return fig


def caption_bounds(d: dict[str, Any]) -> str:
    parts = ["Observed \u2016x \u2212 x\u0302\u2016 (solid) per run"
             + (" against the proved bound (dashed)" if "bound" in d else "")]
    if "no bound" in d:
        parts.append("runs without a proved bound show the error alone")
    if "half-diagonal" in d:
        parts.append("dotted: half the diagonal of X (a bound above it is vacuous)")
    if "after exit" in d:
        parts.append("shaded: after the first exit from the validity conditions, where no "
                     "bound is claimed")
    return "; ".join(parts) + "."


#: said (as a warning) when the trajectories are asked for but the certificate has none
NO_STATES = ("the certificate holds no simulated states (they are written only on request: "
             "certify run --trajectories), so the trajectories figure is left out")


def fig_simulation(cert: Certificate) -> Figure | None:
    """True (solid) and estimated (dashed) states over time, one panel per run; None (with a
    warning, `NO_STATES`) when the certificate was written without them."""
    runs = _runs(cert)
    if not runs:
        return None
    if not runs[0].x:
        warnings.warn(NO_STATES, stacklevel=2)
        return None
    names = state_names(cert)
    fig = new_figure(_height(len(runs)))
    X = as_array((cert.system or {}).get("X") or [])
    for ax, run in zip(_grid(fig, len(runs)), runs):
        t = as_array(run.t)
        x, xh = as_array(run.x), as_array(run.xhat)
        if x.ndim != 2:
            continue
        for j in range(x.shape[1]):
            c = STATE_COLOURS[j % len(STATE_COLOURS)]
            ax.plot(t, x[:, j], color=c, lw=1.1)
            if xh.ndim == 2 and xh.shape[1] > j:
                ax.plot(t, xh[:, j], color=c, lw=0.9, ls="--")
                mark(fig, "estimates")
            if X.ndim == 2 and X.shape[0] > j:
                for edge in X[j]:
                    ax.axhline(edge, color=c, lw=0.6, ls=":", alpha=0.7)
                mark(fig, "edges")
        if run.exit_time is not None:
            ax.axvline(run.exit_time, color="#b91c1c", lw=1)
            mark(fig, "exit")
        ax.set_title(short_title(run), fontsize=8, y=1.0)
        ax.set_xlim(t.min(), t.max())
        ax.tick_params(labelsize=7)
        ax.set_xlabel("t (s)", fontsize=7.5)
        ax.grid(alpha=0.3)
    d = fig.certify_drawn  # type: ignore[attr-defined]
    handles = [Line2D([], [], color=STATE_COLOURS[j % len(STATE_COLOURS)], lw=1.1, label=nm)
               for j, nm in enumerate(names)]
    handles += [Line2D([], [], color="#374151", lw=1.1, label="true x")]
    if "estimates" in d:
        handles.append(Line2D([], [], color="#374151", lw=0.9, ls="--",
                              label="estimate x\u0302"))
    if "edges" in d:
        handles.append(Line2D([], [], color="#374151", lw=0.6, ls=":", label="edges of X"))
    if "exit" in d:
        handles.append(Line2D([], [], color="#b91c1c", lw=1, label="first exit"))
    _legend(fig, handles, "Simulation: true and estimated states")
    return fig


def caption_simulation(d: dict[str, Any]) -> str:
    parts = ["True states (solid)" + (" and observer estimates (dashed)"
                                      if "estimates" in d else "")]
    if "edges" in d:
        parts.append("dotted: edges of X")
    if "exit" in d:
        parts.append("red line: the first exit from the validity conditions")
    return "; ".join(parts) + "."
