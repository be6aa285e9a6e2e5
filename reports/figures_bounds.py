"""The bound figures of the report: the prover's boxes and progress, the Lipschitz bounds.

`fig_prover` draws the prover's leaf sub-boxes coloured by status and the proved volume over
time; `fig_lipschitz` sets the LipSDP, local and naive Lipschitz bounds against the sampled
lower bound (log scale when they spread). Pure like the map figures: certificate in,
`Figure` (or None when the data is missing) out.
"""

from __future__ import annotations

import math

import numpy as np
from matplotlib.collections import PolyCollection
from matplotlib.figure import Figure
from matplotlib.patches import Patch
from matplotlib.ticker import MaxNLocator

from certify.certificate import Certificate
from reports.content import fmt, fmt_bound
from reports.figure_data import as_array, check_result
from reports.figure_kit import (
    BOX_COLOURS,
    LEGEND_DROP,
    LEGEND_ROW,
    grid,
    log_axis,
    mark,
    new_figure,
)


def fig_prover(cert: Certificate) -> Figure | None:
    """The prover's leaf sub-boxes by status, and proved volume over time."""
    data = cert.figures.proof_boxes
    hist = cert.figures.proof_history
    r = check_result(cert, "mpdi")
    if not hist and r is not None and r.proof is not None:
        hist = r.proof.volume_history
    have_boxes = data is not None and bool(data.lo) and bool(data.hi)
    if not have_boxes and not hist:
        return None
    panels = int(bool(have_boxes)) + int(bool(hist))
    fig = new_figure(3.6)
    axs = grid(fig, 1, panels, width_ratios=[1.25, 1] if panels == 2 else None, left=0.7,
               right=0.2, top=0.35, bottom=LEGEND_DROP + LEGEND_ROW + 0.06, wgap=0.8)
    i = 0
    if have_boxes:
        ax = axs[i]
        i += 1
        lo, hi = as_array(data.lo), as_array(data.hi)
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
        leaves = data.counts()  # leaves per status (coinciding projections are merged)
        counts = {k: int(leaves.get(k, 0)) for k in BOX_COLOURS}
        ax.set_title(f"Prover's leaf boxes ({fmt(sum(leaves.values()))})", y=1.0)
        mark(fig, "boxes", {k: c for k, c in counts.items() if c})
        ax.legend(handles=[Patch(color=c, label=f"{k} ({fmt(counts[k])})")
                           for k, c in BOX_COLOURS.items()],
                  loc="upper center", ncol=3, frameon=False, borderaxespad=0.0,
                  bbox_to_anchor=(0.5, -LEGEND_DROP / (fig.get_size_inches()[1]
                                                       * ax.get_position().height)))
    if hist:
        ax = axs[i]
        h = as_array(hist)
        if h.ndim == 2 and h.shape[1] >= 2:
            ax.plot(h[:, 0], 100 * h[:, 1], color="#15803d", lw=1.8,
                    marker="o" if len(h) <= 40 else None, ms=3)
            ax.fill_between(h[:, 0], 100 * h[:, 1], color="#22c55e", alpha=0.15)
        mark(fig, "volume")
        ax.set_ylim(0, 102)
        ax.set_xlabel("prover time (s)")
        ax.set_ylabel("proved volume (%)")
        ax.set_title("Proved volume over time", y=1.0)
        ax.grid(alpha=0.3)
        if r is not None and r.proof is not None:
            ax.text(0.97, 0.05, f"{fmt(r.proof.boxes_processed)} boxes\n"
                                f"{fmt(r.proof.boxes_per_second)} boxes/s",
                    transform=ax.transAxes, ha="right", va="bottom", fontsize=8,
                    bbox={"boxstyle": "round", "fc": "white", "ec": "#d1d5db"})
    return fig


def fig_lipschitz(cert: Certificate) -> Figure | None:
    """LipSDP / local / naive bounds against the sampled lower bound (log scale)."""
    r = check_result(cert, "lipschitz")
    if r is None:
        return None
    items = [("sampled (lower)", r.sampled, "#6b7280", ""),
             ("local interval", r.local_upper, "#0ea5e9", "local"),
             ("LipSDP", r.lipsdp, "#2563eb", "lipsdp"),
             ("naive", r.naive, "#9333ea", "naive")]
    # each number rounded outward: the sampled one is a lower bound, the others upper
    fig = new_figure(2.3)
    ax = grid(fig, 1, 1, left=1.25, right=0.25, top=0.35, bottom=0.5)[0]
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
        ax.text(v, yy, f"  {fmt_bound(v, 'upper' if key else 'lower')}"
                + ("  \u2190 used" if used else ""), va="center",
                fontsize=8, fontweight="bold" if used else "normal")
    ax.set_yticks(ypos, [n for n, *_ in items])
    if max(vals) / min(vals) > 20:
        ax.set_xscale("log")
        log_axis(ax.xaxis)
        ax.set_xlim(min(vals) / 3, max(vals) * 4)
    else:
        ax.set_xlim(0, max(vals) * 1.35)
    ax.set_xlabel("Lipschitz constant of k in y (L2 \u2192 L2)")
    ax.set_title("Lipschitz bounds side by side", y=1.0)
    return fig
