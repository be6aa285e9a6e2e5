"""Figures of a certificate (matplotlib, Agg canvas, no pyplot global state).

Each `fig_*` function is pure: it takes a `Certificate`, reads `certificate.figures` and the
check results, and returns a `matplotlib.figure.Figure`, or None when its data is missing
(every figure is optional). A figure records what it actually drew (`drawn(fig)`: a zero
contour, counterexamples, a worst point...), and its caption is written from that record,
so a caption never mentions what is not there. Point markers (worst point, witness,
counterexamples) are drawn with clip_on=False inside a margin added around the box, so a
marker on a corner is whole, inside the axes, clear of the title, and counterexamples are
drawn above the worst-point star. `render_figures` draws them all once to PNG so the HTML
and PDF reports embed identical images; the simulation figures are in
`reports.figures_sim` (the trajectories only on request).
"""

from __future__ import annotations

import io
import math
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import matplotlib
import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import PolyCollection
from matplotlib.colors import Normalize, TwoSlopeNorm
from matplotlib.figure import Figure
from matplotlib.patches import Patch
from matplotlib.ticker import MaxNLocator

from certify.certificate import Certificate
from certify.figuredata import GridMap
from certify.results import CheckFailure
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


# ----------------------------------------------------------------------------- helpers

def _array(values: Any) -> np.ndarray:
    """Typed figure data (float lists, NaN where undefined) to a float array."""
    return np.asarray(values, dtype=float)


def _check(cert: Certificate, name: str) -> Any:
    """A check's own result, or None (not run, or a `CheckFailure`: nothing to draw)."""
    r = cert.checks.get(name)
    return None if r is None or isinstance(r, CheckFailure) else r


def _grid(cert: Certificate, key: str) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                 list[str]] | None:
    """(x [nx], y [ny], values [ny, nx], axis names) of a figure map, or None if unusable."""
    data: GridMap | None = getattr(cert.figures, key, None)
    if data is None:
        return None
    try:
        x, y, v = _array(data.x), _array(data.y), _array(data.values)
    except (ValueError, TypeError):
        return None
    if v.ndim != 2 or v.shape != (len(y), len(x)) or v.size == 0:
        return None
    return x, y, v, list(data.axes or ["x1", "x2"])


def _new(height: float, width: float = WIDTH) -> Figure:
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


def _box_limits(ax: Any, x: np.ndarray, y: np.ndarray) -> None:
    """Axes limits: the box plus a margin, so an edge marker fits inside the axes."""
    for values, setter in ((x, ax.set_xlim), (y, ax.set_ylim)):
        lo, hi = float(np.min(values)), float(np.max(values))
        pad = MARKER_MARGIN * (hi - lo if hi > lo else 1.0)
        setter(lo - pad, hi + pad)


def _names(cert: Certificate) -> list[str]:
    return list((cert.system or {}).get("states") or ["x1", "x2"])


def _heatmap(fig: Figure, ax: Any, x: np.ndarray, y: np.ndarray, v: np.ndarray, *,
             label: str, diverging: bool, cmap: str = "viridis") -> None:
    """pcolormesh with a colour bar; diverging maps are centred on zero with a zero contour.

    The axes extend past the box by `MARKER_MARGIN` (white); cells where the value is
    undefined (NaN) are drawn grey. What is drawn is recorded with `mark`.
    """
    from matplotlib.colors import ListedColormap

    _box_limits(ax, x, y)
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


def _point(fig: Figure, ax: Any, xy: Any, element: str, **style: Any) -> None:
    """A marker at xy, never clipped (it lies inside the margin), recorded as drawn."""
    ax.scatter([xy[0]], [xy[1]], clip_on=False, **style)
    mark(fig, element, style.get("label", True))


def _legend(ax: Any, **kw: Any) -> None:
    """The axes' legend below it, outside the map: it never covers a marker or the title."""
    handles, labels = ax.get_legend_handles_labels()
    if handles:
        ax.legend(**{"loc": "upper center", "bbox_to_anchor": (0.5, -0.14), "ncol": 3,
                     "frameon": False, **kw})


# ----------------------------------------------------------------------------- figures

def fig_mpdi_map(cert: Certificate) -> Figure | None:
    """Heatmap of max over y of lam_max(D) over the xhat box, zero contour, counterexamples."""
    g = _grid(cert, "mpdi_map")
    if g is None:
        return None
    x, y, v, axes = g
    fig = _new(4.3)
    ax = fig.add_subplot()
    _heatmap(fig, ax, x, y, v, label="max over y of \u03bb_max(D)", diverging=True)
    r = _check(cert, "mpdi")
    if r is not None:
        if r.worst is not None and len(r.worst.xhat) >= 2:
            _point(fig, ax, r.worst.xhat, "worst point", marker="*", s=150, c="#fde047",
                   edgecolors="black", linewidths=0.8, zorder=6,
                   label=f"worst point ({fmt(r.worst.value, 4, signed=True)})")
        pts = np.array([c.xhat[:2] for c in r.counterexamples if len(c.xhat) >= 2])
        if len(pts):  # above the star: a counterexample on the worst point stays visible
            ax.scatter(pts[:, 0], pts[:, 1], marker="x", s=40, c="#111827", linewidths=1.5,
                       label=f"counterexamples ({len(pts)})", zorder=7, clip_on=False)
            mark(fig, "counterexamples", len(pts))
    ax.set_xlabel(axes[0])
    ax.set_ylabel(axes[1] if len(axes) > 1 else "")
    n = len(_names(cert))
    extra = " (other states at their box centre)" if n > 2 else ""
    if n > 2:
        mark(fig, "slice")
    ax.set_title("MPDI map: max over y of \u03bb_max(D(x\u0302, y))" + extra)
    _legend(ax)
    return fig


def fig_prover(cert: Certificate) -> Figure | None:
    """The prover's leaf sub-boxes by status, and proved volume over time."""
    data = cert.figures.proof_boxes
    hist = cert.figures.proof_history
    r = _check(cert, "mpdi")
    if not hist and r is not None and r.proof is not None:
        hist = r.proof.volume_history
    have_boxes = data is not None and bool(data.lo) and bool(data.hi)
    if not have_boxes and not hist:
        return None
    panels = int(bool(have_boxes)) + int(bool(hist))
    fig = _new(3.6)
    axs = fig.subplots(1, panels, width_ratios=[1.25, 1] if panels == 2 else None,
                       squeeze=False)[0]
    i = 0
    if have_boxes:
        ax = axs[i]
        i += 1
        lo, hi = _array(data.lo), _array(data.hi)
        status = np.asarray(data.status or ["unknown"] * len(lo))
        verts = np.stack([np.stack([lo[:, 0], lo[:, 1]], 1), np.stack([hi[:, 0], lo[:, 1]], 1),
                          np.stack([hi[:, 0], hi[:, 1]], 1), np.stack([lo[:, 0], hi[:, 1]], 1)],
                         axis=1)
        colours = [BOX_COLOURS.get(str(s), "#9ca3af") for s in status]
        edge = 0.3 if len(lo) <= 5000 else 0.0
        ax.add_collection(PolyCollection(verts, facecolors=colours, edgecolors="white",
                                         linewidths=edge, rasterized=True))
        ax.set_xlim(lo[:, 0].min(), hi[:, 0].max())
        ax.set_ylim(lo[:, 1].min(), hi[:, 1].max())
        axes = list(data.axes or ["x1", "x2"])
        ax.set_xlabel(axes[0])
        ax.set_ylabel(axes[1] if len(axes) > 1 else "")
        ax.xaxis.set_major_locator(MaxNLocator(5))
        ax.set_title(f"Prover's leaf boxes ({fmt(len(lo))})")
        counts = {k: int(np.sum(status == k)) for k in BOX_COLOURS}
        mark(fig, "boxes", {k: c for k, c in counts.items() if c})
        ax.legend(handles=[Patch(color=c, label=f"{k} ({fmt(counts[k])})")
                           for k, c in BOX_COLOURS.items()],
                  loc="upper center", bbox_to_anchor=(0.5, -0.18), ncol=3, frameon=False)
    if hist:
        ax = axs[i]
        h = _array(hist)
        if h.ndim == 2 and h.shape[1] >= 2:
            ax.plot(h[:, 0], 100 * h[:, 1], color="#15803d", lw=1.8,
                    marker="o" if len(h) <= 40 else None, ms=3)
            ax.fill_between(h[:, 0], 100 * h[:, 1], color="#22c55e", alpha=0.15)
        mark(fig, "volume")
        ax.set_ylim(0, 102)
        ax.set_xlabel("prover time (s)")
        ax.set_ylabel("proved volume (%)")
        ax.set_title("Proved volume over time")
        ax.grid(alpha=0.3)
        if r is not None and r.proof is not None:
            ax.text(0.97, 0.05, f"{fmt(r.proof.boxes_processed)} boxes\n"
                                f"{fmt(r.proof.boxes_per_second)} boxes/s",
                    transform=ax.transAxes, ha="right", va="bottom", fontsize=8,
                    bbox={"boxstyle": "round", "fc": "white", "ec": "#d1d5db"})
    return fig


def fig_necessary_map(cert: Certificate) -> Figure | None:
    """q(xhat) over X with its zero contour and witness; blank where h(xhat) is not in Y."""
    g = _grid(cert, "necessary_map")
    if g is None:
        return None
    x, y, v, axes = g
    fig = _new(3.9)
    ax = fig.add_subplot()
    _heatmap(fig, ax, x, y, v, label="q(x\u0302)", diverging=True)
    r = _check(cert, "necessary")
    if r is not None and r.witness is not None and len(r.witness) >= 2:
        _point(fig, ax, r.witness, "witness", marker="*", s=150, c="#fde047",
               edgecolors="black", linewidths=0.8, zorder=6,
               label=f"witness (q = {fmt(r.q_max, 4, signed=True)})")
    if np.isnan(v).any():
        ax.scatter([], [], marker="s", s=40, c="#d1d5db", label="h(x\u0302) \u2209 Y")
    ax.set_xlabel(axes[0])
    ax.set_ylabel(axes[1] if len(axes) > 1 else "")
    ax.set_title("Necessary condition: q(x\u0302) on the output manifold (> 0: impossible)")
    _legend(ax)
    return fig


def fig_residual_map(cert: Certificate) -> Figure | None:
    """||k(x, h(x))|| over X."""
    g = _grid(cert, "residual_map")
    if g is None:
        return None
    x, y, v, axes = g
    r = _check(cert, "residual")
    if r is not None and r.structural and np.all(v[np.isfinite(v)] == 0):
        return None  # zero by construction: the section says so, a blank map adds nothing
    fig = _new(3.9)
    ax = fig.add_subplot()
    _heatmap(fig, ax, x, y, v, label="\u2016k(x, h(x))\u2016", diverging=False,
             cmap="viridis")
    if r is not None and r.worst is not None and len(r.worst) >= 2:
        _point(fig, ax, r.worst, "worst point", marker="*", s=150, c="#f472b6",
               edgecolors="black", linewidths=0.8, zorder=6, label=f"worst ({fmt(r.sampled)})")
    ax.set_xlabel(axes[0])
    ax.set_ylabel(axes[1] if len(axes) > 1 else "")
    title = "Boundary residual \u2016k(x, h(x))\u2016 over X"
    if r is not None and r.structural:
        title += " (zero by construction)"
    ax.set_title(title)
    _legend(ax)
    return fig


def fig_lipschitz(cert: Certificate) -> Figure | None:
    """LipSDP / local / naive bounds against the sampled lower bound (log scale)."""
    r = _check(cert, "lipschitz")
    if r is None:
        return None
    items = [("sampled (lower)", r.sampled, "#6b7280", ""),
             ("local interval", r.local_upper, "#0ea5e9", "local"),
             ("LipSDP", r.lipsdp, "#2563eb", "lipsdp"),
             ("naive", r.naive, "#9333ea", "naive")]
    fig = _new(2.3)
    ax = fig.add_subplot()
    vals = [v for _, v, _, _ in items if v is not None and math.isfinite(v) and v > 0]
    if not vals:
        return None
    ypos = np.arange(len(items))[::-1]
    for yy, (_, v, colour, key) in zip(ypos, items):
        if v is None or not math.isfinite(v) or v <= 0:
            ax.text(min(vals), yy, "  \u2014 not available", va="center", fontsize=8,
                    color="#6b7280")
            continue
        used = key and key == r.which
        if used:
            mark(fig, "used", key)
        ax.barh(yy, v, color=colour, alpha=1.0 if used else 0.55,
                edgecolor="black" if used else "none", linewidth=1.2, height=0.6)
        ax.text(v, yy, f"  {fmt(v)}" + ("  \u2190 used" if used else ""), va="center",
                fontsize=8, fontweight="bold" if used else "normal")
    ax.set_yticks(ypos, [n for n, *_ in items])
    if max(vals) / min(vals) > 20:
        ax.set_xscale("log")
        ax.set_xlim(min(vals) / 3, max(vals) * 4)
    else:
        ax.set_xlim(0, max(vals) * 1.35)
    ax.set_xlabel("Lipschitz constant of k in y (L2 \u2192 L2)")
    ax.set_title("Lipschitz bounds side by side")
    return fig


# ----------------------------------------------------------------------------- rendering

@dataclass(frozen=True)
class FigureSpec:
    """A figure of the report: where it goes, how it is drawn, and its caption, written from
    what `build` recorded as drawn (`drawn(fig)`). `on_request`: drawn only when asked."""

    key: str
    section: str
    caption: Callable[[dict[str, Any]], str]
    build: Callable[[Certificate], Figure | None]
    on_request: bool = False


def _specs() -> tuple[FigureSpec, ...]:
    from reports import figures_sim as sim
    from reports.captions import (
        caption_lipschitz,
        caption_mpdi_map,
        caption_necessary_map,
        caption_prover,
        caption_residual_map,
    )

    return (
        FigureSpec("mpdi_map", "mpdi", caption_mpdi_map, fig_mpdi_map),
        FigureSpec("prover", "mpdi", caption_prover, fig_prover),
        FigureSpec("necessary_map", "necessary", caption_necessary_map, fig_necessary_map),
        FigureSpec("residual_map", "residual", caption_residual_map, fig_residual_map),
        FigureSpec("lipschitz", "lipschitz", caption_lipschitz, fig_lipschitz),
        FigureSpec("bounds", "simulation", sim.caption_bounds, sim.fig_bounds),
        FigureSpec("simulation", "simulation", sim.caption_simulation, sim.fig_simulation,
                   on_request=True),
    )


@dataclass(frozen=True)
class RenderedFigure:
    """One figure drawn to PNG (shared by the HTML and the PDF report)."""

    key: str
    section: str
    caption: str
    png: bytes
    width_in: float
    height_in: float
    width_px: int
    height_px: int


def figure_png(fig: Figure, dpi: int) -> bytes:
    """PNG bytes of a figure (fixed metadata, so identical inputs give identical bytes)."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, facecolor="white",
                metadata={"Software": None})
    return buf.getvalue()


def render_figures(cert: Certificate, dpi: int = 150, *,
                   trajectories: bool = False) -> list[RenderedFigure]:
    """Draw every figure whose data is present, in report order; the ones drawn only on
    request (the simulated trajectories) when `trajectories`."""
    out = []
    with matplotlib.rc_context(STYLE):
        for spec in FIGURES:
            if spec.on_request and not trajectories:
                continue
            fig = spec.build(cert)
            if fig is None:
                continue
            png = figure_png(fig, dpi)
            w, h = fig.get_size_inches()
            wpx, hpx = _png_size(png)
            out.append(RenderedFigure(spec.key, spec.section, spec.caption(drawn(fig)), png,
                                      float(w), float(h), wpx, hpx))
    return out


def _png_size(png: bytes) -> tuple[int, int]:
    """Width and height from a PNG's IHDR chunk."""
    return int.from_bytes(png[16:20], "big"), int.from_bytes(png[20:24], "big")


FIGURES: tuple[FigureSpec, ...] = _specs()
