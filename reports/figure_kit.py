"""The drawing kit shared by the report's figures: style, canvas, recorded marks, primitives.

A figure records what it actually drew (`mark`, read back by `drawn`): a zero contour,
counterexamples, a worst point... and its caption is written from that record
(`reports.captions`), so a caption never mentions what is not there. Point markers (worst
point, witness, counterexamples) are drawn with clip_on=False inside a margin added around
the box (`MARKER_MARGIN`), so a marker on a corner is whole, inside the axes and clear of
the title; legends go below the axes, where they cover nothing. Matplotlib is used through
`Figure` and the Agg canvas only (no pyplot global state).

Layouts are fixed, in inches (`frame`, `grid`, `colorbar_axes`): no layout engine, so a
figure is laid out without measuring its text and drawn in one pass (a layout engine
measures every tick label two or three times before the drawing does it again). The
margins leave room for the tick labels, axis labels, titles and legends these figures have.
Titles are placed at y=1.0 (the automatic placement measures the tick labels again).
"""

from __future__ import annotations

import re
import warnings
from typing import Any

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import Normalize, TwoSlopeNorm
from matplotlib.figure import Figure
from matplotlib.ticker import LogFormatterSciNotation

from reports.content import fmt

WIDTH = 7.0  # inches: a full-width figure in both reports
STYLE = {
    "font.size": 9, "axes.titlesize": 10, "axes.labelsize": 9, "legend.fontsize": 8,
    "xtick.labelsize": 8, "ytick.labelsize": 8, "axes.spines.top": False,
    "axes.spines.right": False, "axes.grid": False, "figure.dpi": 100,
    "font.family": "DejaVu Sans", "image.interpolation": "nearest",
}
BOX_COLOURS = {"proved": "#22c55e", "violated": "#dc2626", "unknown": "#f59e0b"}
STATE_COLOURS = ["#1f77b4", "#ff7f0e", "#2ca02c", "#9467bd", "#8c564b", "#e377c2", "#17becf",
                 "#bcbd22"]


_SUPERSCRIPT = str.maketrans("0123456789-", "\u2070\u00b9\u00b2\u00b3\u2074\u2075\u2076"
                                            "\u2077\u2078\u2079\u207b")


class PlainLogFormatter(LogFormatterSciNotation):
    """matplotlib's log-axis labels (10^-2, 2x10^1) as plain text with superscript digits:
    the same labels without mathtext, whose parser costs more than a small figure."""

    def __call__(self, x: float, pos: int | None = None) -> str:
        label = super().__call__(x, pos)
        m = re.fullmatch(r"\$\\mathdefault\{(.*)\}\$", label)
        if m is None:
            return label
        body = m.group(1).replace("\\times", "\u00d7")
        return re.sub(r"\^\{(-?\d+)\}", lambda e: e.group(1).translate(_SUPERSCRIPT), body)


def log_axis(axis: Any, *, minor: bool = True) -> None:
    """Plain-text labels on a log-scaled axis (`PlainLogFormatter`); without `minor`, no
    minor ticks (decades only, for small panels)."""
    from matplotlib.ticker import NullLocator

    axis.set_major_formatter(PlainLogFormatter())
    if minor:
        axis.set_minor_formatter(PlainLogFormatter(labelOnlyBase=False))
    else:
        axis.set_minor_locator(NullLocator())


def new_figure(height: float, width: float = WIDTH) -> Figure:
    """An empty figure on an Agg canvas (no pyplot state, no layout engine) that records
    what is drawn."""
    fig = Figure(figsize=(width, height))
    FigureCanvasAgg(fig)
    fig.certify_drawn = {}  # type: ignore[attr-defined]
    return fig


def grid(fig: Figure, rows: int, cols: int, *, count: int | None = None, left: float,
         right: float, top: float, bottom: float, wgap: float = 0.0, hgap: float = 0.0,
         width_ratios: list[float] | None = None) -> list[Any]:
    """`count` axes (all rows x cols by default) on a fixed grid, row by row; margins and
    the gaps between cells in inches."""
    W, H = fig.get_size_inches()
    aw = max((W - left - right - (cols - 1) * wgap) / cols, 1e-3)
    ah = max((H - top - bottom - (rows - 1) * hgap) / rows, 1e-3)
    gs = fig.add_gridspec(rows, cols, left=left / W, right=1 - right / W, top=1 - top / H,
                          bottom=bottom / H, wspace=wgap / aw, hspace=hgap / ah,
                          width_ratios=width_ratios)
    n = rows * cols if count is None else count
    return [fig.add_subplot(gs[i // cols, i % cols]) for i in range(n)]


def frame(fig: Figure, *, left: float, right: float, top: float, bottom: float) -> Any:
    """One axes with fixed margins in inches."""
    return grid(fig, 1, 1, left=left, right=right, top=top, bottom=bottom)[0]


#: a heatmap's colour bar, right of its axes: gap and width in inches, and the room its
#: tick labels and label need (what `MAP_RIGHT` leaves beside a map)
COLORBAR_GAP, COLORBAR_WIDTH, COLORBAR_ROOM = 0.15, 0.16, 0.85
MAP_RIGHT = COLORBAR_GAP + COLORBAR_WIDTH + COLORBAR_ROOM


def colorbar_axes(fig: Figure, ax: Any) -> Any:
    """Axes for the colour bar of `ax`: right of it, 95% of its height, centred."""
    W, H = fig.get_size_inches()
    pos = ax.get_position()
    h = 0.95 * pos.height
    return fig.add_axes((pos.x1 + COLORBAR_GAP / W, pos.y0 + (pos.height - h) / 2,
                         COLORBAR_WIDTH / W, h))


def drawn(fig: Figure) -> dict[str, Any]:
    """What a figure of this module drew: element name -> detail (a count, a value)."""
    return getattr(fig, "certify_drawn", {})


def mark(fig: Figure, element: str, detail: Any = True) -> None:
    """Record that `element` is drawn in `fig` (the caption is written from these)."""
    drawn(fig)[element] = detail


#: margin around the box, as a fraction of each side, where markers on its edge are drawn
MARKER_MARGIN = 0.05


def box_limits(ax: Any, x: np.ndarray, y: np.ndarray) -> None:
    """Axes limits: the box plus a margin, so an edge marker fits inside the axes."""
    for values, setter in ((x, ax.set_xlim), (y, ax.set_ylim)):
        lo, hi = float(np.min(values)), float(np.max(values))
        pad = MARKER_MARGIN * (hi - lo if hi > lo else 1.0)
        setter(lo - pad, hi + pad)


def heatmap(fig: Figure, ax: Any, x: np.ndarray, y: np.ndarray, v: np.ndarray, *,
             label: str, diverging: bool, cmap: str = "viridis") -> None:
    """pcolormesh with a colour bar (right of `ax`, in the room `MAP_RIGHT` leaves);
    diverging maps are centred on zero with a zero contour.

    The axes extend past the box by `MARKER_MARGIN` (white); cells where the value is
    undefined (NaN) are drawn grey. What is drawn is recorded with `mark`.
    """
    from matplotlib.colors import ListedColormap

    box_limits(ax, x, y)
    nan = ~np.isfinite(v)
    if nan.any():
        ax.pcolormesh(x, y, np.where(nan, 1.0, np.nan), shading="nearest",
                      cmap=ListedColormap(["#d1d5db"]), vmin=0, vmax=2, rasterized=True)
        mark(fig, "undefined cells")
    finite = v[np.isfinite(v)]
    if finite.size == 0:
        ax.text(0.5, 0.5, "no finite values", ha="center", va="center", transform=ax.transAxes)
        return
    lo, hi = float(finite.min()), float(finite.max())
    mark(fig, "range", (lo, hi))
    if hi - lo <= 1e-12 * max(1.0, abs(hi)):
        ax.pcolormesh(x, y, np.ma.masked_invalid(v), shading="nearest", cmap="Greys",
                      vmin=lo - 1, vmax=lo + 3, rasterized=True)
        ax.text(0.5, 0.5, f"{label} = {fmt(lo)} everywhere on the grid", ha="center",
                va="center", transform=ax.transAxes, fontsize=10,
                bbox={"fc": "white", "ec": "#9ca3af", "boxstyle": "round"})
        mark(fig, "constant", lo)
        return
    if diverging and lo < 0 < hi:
        norm: Normalize = TwoSlopeNorm(vmin=lo, vcenter=0.0, vmax=hi)
        cmap = "RdBu_r"
        mark(fig, "two signs")
    elif diverging:
        # one sign only: keep blue for negative, red for positive
        cmap = "Reds" if lo >= 0 else "Blues_r"
        norm = Normalize(vmin=lo, vmax=hi if hi > lo else lo + 1e-12)
        mark(fig, "one sign", "positive" if lo >= 0 else "negative")
    else:
        norm = Normalize(vmin=lo, vmax=hi if hi > lo else lo + 1e-12)
    masked = np.ma.masked_invalid(v)
    mesh = ax.pcolormesh(x, y, masked, shading="nearest", cmap=cmap, norm=norm,
                         rasterized=True)
    cb = fig.colorbar(mesh, cax=colorbar_axes(fig, ax))
    cb.set_label(label)
    if diverging and lo < 0 < hi:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            cs = ax.contour(x, y, masked, levels=[0.0], colors="black", linewidths=1.4)
        cb.ax.axhline(0.0, color="black", lw=1.2)
        if cs.allsegs and any(len(seg) for seg in cs.allsegs[0]):
            ax.plot([], [], color="black", lw=1.4, label="zero contour")
            mark(fig, "zero contour")


def point_marker(fig: Figure, ax: Any, xy: Any, element: str, **style: Any) -> None:
    """A marker at xy, never clipped (it lies inside the margin), recorded as drawn."""
    ax.scatter([xy[0]], [xy[1]], clip_on=False, **style)
    mark(fig, element, style.get("label", True))


#: inches from the bottom of an axes to the top of the legend below it (clear of the tick
#: labels and the axis label), and the height of one row of that legend
LEGEND_DROP, LEGEND_ROW = 0.5, 0.24


def legend_below(ax: Any, **kw: Any) -> None:
    """The axes' legend below it, outside the map: it never covers a marker or the title."""
    handles, labels = ax.get_legend_handles_labels()
    if handles:
        h_in = ax.get_position().height * ax.figure.get_size_inches()[1]
        ax.legend(**{"loc": "upper center", "bbox_to_anchor": (0.5, -LEGEND_DROP / h_in),
                     "ncol": 3, "frameon": False, "borderaxespad": 0.0, **kw})
