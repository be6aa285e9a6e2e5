"""The map figures of the report: a check's quantity as a heatmap over the state box.

`fig_mpdi_map` (max over y of lam_max(D), zero contour, worst point, counterexamples),
`fig_necessary_map` (q(xhat) on the output manifold, witness) and `fig_residual_map`
(||k(x, h(x))||, worst point). Each is pure: it reads the certificate's typed map
(`reports.figure_data`) and the check's result, draws with `reports.figure_kit`, and returns
a `Figure`, or None when its data is missing (every figure is optional).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure

from certify.certificate import Certificate
from reports.content import fmt
from reports.figure_data import check_result, grid_map, state_names
from reports.figure_kit import (
    LEGEND_DROP,
    LEGEND_ROW,
    MAP_RIGHT,
    frame,
    heatmap,
    legend_below,
    mark,
    new_figure,
    point_marker,
)

#: a map's margins in inches: the y tick labels and name; the title; the x axis and one
#: row of legend below it
MAP_LEFT, MAP_TOP, MAP_BOTTOM = 0.7, 0.4, LEGEND_DROP + LEGEND_ROW + 0.06


def _open_map(fig_height: float, x: np.ndarray, y: np.ndarray, v: np.ndarray, label: str,
              **style: Any) -> tuple[Figure, Axes]:
    """A new figure with one axes holding the heatmap of v over the (x, y) grid."""
    fig = new_figure(fig_height)
    ax = frame(fig, left=MAP_LEFT, right=MAP_RIGHT, top=MAP_TOP, bottom=MAP_BOTTOM)
    heatmap(fig, ax, x, y, v, label=label, **style)
    return fig, ax


def _star(fig: Figure, ax: Axes, xy: Any, element: str, color: str, label: str) -> None:
    """The map's one distinguished point (worst point, witness): a large outlined star."""
    point_marker(fig, ax, xy, element, marker="*", s=150, c=color, edgecolors="black",
                 linewidths=0.8, zorder=6, label=label)


def _finish(ax: Axes, axes: list[str], title: str) -> None:
    """Axis names, title and the legend below the map."""
    ax.set_xlabel(axes[0])
    ax.set_ylabel(axes[1] if len(axes) > 1 else "")
    ax.set_title(title, y=1.0)
    legend_below(ax)


def fig_mpdi_map(cert: Certificate) -> Figure | None:
    """Heatmap of max over y of lam_max(D) over the xhat box, zero contour, counterexamples."""
    g = grid_map(cert, "mpdi_map")
    if g is None:
        return None
    x, y, v, axes = g
    fig, ax = _open_map(4.3, x, y, v, "max over y of \u03bb_max(D)", diverging=True)
    r = check_result(cert, "mpdi")
    if r is not None:
        if r.worst is not None and len(r.worst.xhat) >= 2:
            _star(fig, ax, r.worst.xhat, "worst point", "#fde047",
                  f"worst point ({fmt(r.worst.value, 4, signed=True)})")
        pts = np.array([c.xhat[:2] for c in r.counterexamples if len(c.xhat) >= 2])
        if len(pts):  # above the star: a counterexample on the worst point stays visible
            ax.scatter(pts[:, 0], pts[:, 1], marker="x", s=40, c="#111827", linewidths=1.5,
                       label=f"counterexamples ({len(pts)})", zorder=7, clip_on=False)
            mark(fig, "counterexamples", len(pts))
    n = len(state_names(cert))
    extra = " (other states at their box centre)" if n > 2 else ""
    if n > 2:
        mark(fig, "slice")
    _finish(ax, axes, "MPDI map: max over y of \u03bb_max(D(x\u0302, y))" + extra)
    return fig


def fig_necessary_map(cert: Certificate) -> Figure | None:
    """q(xhat) over X with its zero contour and witness; blank where h(xhat) is not in Y."""
    g = grid_map(cert, "necessary_map")
    if g is None:
        return None
    x, y, v, axes = g
    fig, ax = _open_map(3.9, x, y, v, "q(x\u0302)", diverging=True)
    r = check_result(cert, "necessary")
    if r is not None and r.witness is not None and len(r.witness) >= 2:
        _star(fig, ax, r.witness, "witness", "#fde047",
              f"witness (q = {fmt(r.q_max, 4, signed=True)})")
    if np.isnan(v).any():
        ax.scatter([], [], marker="s", s=40, c="#d1d5db", label="h(x\u0302) \u2209 Y")
    _finish(ax, axes, "Necessary condition: q(x\u0302) on the output manifold (> 0: impossible)")
    return fig


def fig_residual_map(cert: Certificate) -> Figure | None:
    """||k(x, h(x))|| over X."""
    g = grid_map(cert, "residual_map")
    if g is None:
        return None
    x, y, v, axes = g
    r = check_result(cert, "residual")
    if r is not None and r.structural and np.all(v[np.isfinite(v)] == 0):
        return None  # zero by construction: the section says so, a blank map adds nothing
    fig, ax = _open_map(3.9, x, y, v, "\u2016k(x, h(x))\u2016", diverging=False,
                        cmap="viridis")
    if r is not None and r.worst is not None and len(r.worst) >= 2:
        _star(fig, ax, r.worst, "worst point", "#f472b6", f"worst ({fmt(r.sampled)})")
    title = "Boundary residual \u2016k(x, h(x))\u2016 over X"
    if r is not None and r.structural:
        title += " (zero by construction)"
    _finish(ax, axes, title)
    return fig


#: points per axis of the metric map (the polynomial is evaluated here, at figure size)
METRIC_MAP_POINTS = 61


def metric_eigenvalues(metric: dict[str, Any], x: np.ndarray, y: np.ndarray,
                       centre: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Smallest and largest eigenvalue [len(y), len(x)] of M at the grid's points (states 1
    and 2 on the axes, the others at `centre`), from the metric's plain data
    (`exponents` [K, n], `coefficients` [K, n, n]); None when the data is unusable."""
    try:
        e = np.asarray(metric["exponents"], dtype=np.int64)
        c = np.asarray(metric["coefficients"], dtype=np.float64)
    except (KeyError, TypeError, ValueError):
        return None
    n = len(centre)
    if e.ndim != 2 or c.ndim != 3 or e.shape[1] != n or c.shape != (len(e), n, n) or n < 2:
        return None
    X1, X2 = np.meshgrid(x, y)
    pts = np.broadcast_to(centre, X1.shape + (n,)).copy()
    pts[..., 0], pts[..., 1] = X1, X2
    mono = np.prod(pts[..., None, :] ** e, axis=-1)  # [ny, nx, K]
    M = np.einsum("abk,kij->abij", mono, c)
    w = np.linalg.eigvalsh(0.5 * (M + np.swapaxes(M, -1, -2)))
    return w[..., 0], w[..., -1]


def fig_metric_map(cert: Certificate) -> Figure | None:
    """The smallest eigenvalue of the metric M(x) over X, with the plant box the stages were
    proved on; the largest eigenvalue's range in the title."""
    r = check_result(cert, "metric_bound")
    box = (cert.system or {}).get("X")
    if r is None or not r.metric or not box or len(box) < 2:
        return None
    B = np.asarray(box, dtype=np.float64)
    x = np.linspace(B[0, 0], B[0, 1], METRIC_MAP_POINTS)
    y = np.linspace(B[1, 0], B[1, 1], METRIC_MAP_POINTS)
    eig = metric_eigenvalues(r.metric, x, y, B.mean(1))
    if eig is None:
        return None
    lo, hi = eig
    axes = state_names(cert)[:2]
    fig, ax = _open_map(3.9, x, y, lo, "\u03bb_min(M(x))", diverging=False, cmap="viridis")
    if r.plant_box and len(r.plant_box) >= 2:
        (a, b), (c, d) = r.plant_box[0], r.plant_box[1]
        ax.plot([a, b, b, a, a], [c, c, d, d, c], color="#f472b6", linewidth=1.6,
                label="plant box of the stages")
        mark(fig, "plant box")
    n = len(state_names(cert))
    if n > 2:
        mark(fig, "slice")
    finite = hi[np.isfinite(hi)]
    top = f"; \u03bb_max from {fmt(float(finite.min()))} to {fmt(float(finite.max()))}" \
        if finite.size else ""
    mark(fig, "largest", top)
    _finish(ax, axes, "Metric M(x): smallest eigenvalue over X" + top
            + (" (other states at their box centre)" if n > 2 else ""))
    return fig
