"""The drawing kit shared by the report's figures: style, canvas, recorded marks, primitives.

A figure records what it actually drew (`mark`, read back by `drawn`): a zero contour,
counterexamples, a worst point... and its caption is written from that record
(`reports.captions`), so a caption never mentions what is not there. Point markers (worst
point, witness, counterexamples) are drawn with clip_on=False inside a margin added around
the box (`MARKER_MARGIN`), so a marker on a corner is whole, inside the axes and clear of
the title; legends go below the axes, where they cover nothing. Matplotlib is used through
`Figure` and the Agg canvas only (no pyplot global state).
"""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import Normalize, TwoSlopeNorm
from matplotlib.figure import Figure

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


def new_figure(height: float, width: float = WIDTH) -> Figure:
    """An empty figure on an Agg canvas (no pyplot state) that records what is drawn."""
    fig = Figure(figsize=(width, height), layout="constrained")
    FigureCanvasAgg(fig)
    fig.certify_drawn = {}  # type: ignore[attr-defined]
    return fig


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
    """pcolormesh with a colour bar; diverging maps are centred on zero with a zero contour.

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
    cb = fig.colorbar(mesh, ax=ax, shrink=0.95, pad=0.02)
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


def legend_below(ax: Any, **kw: Any) -> None:
    """The axes' legend below it, outside the map: it never covers a marker or the title."""
    handles, labels = ax.get_legend_handles_labels()
    if handles:
        ax.legend(**{"loc": "upper center", "bbox_to_anchor": (0.5, -0.14), "ncol": 3,
                     "frameon": False, **kw})
