"""Figures of a certificate: the list of the report's figures and their rendering to PNG.

`FIGURES` says, for each figure, where it goes (the report section), how it is drawn and its
caption, written from what the drawing recorded (`drawn(fig)`). `render_figures` draws them
all once to PNG so the HTML and PDF reports embed identical images. The figures themselves
live by kind: the heatmaps over the box in `reports.figures_maps`, the prover's boxes and the
Lipschitz bounds in `reports.figures_bounds`, the simulation in `reports.figures_sim` (the
trajectories only on request); what they read is `reports.figure_data` and how they draw is
`reports.figure_kit` (matplotlib, Agg canvas, no pyplot global state).
"""

from __future__ import annotations

import io
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import matplotlib
import numpy as np
from matplotlib.figure import Figure

from certify.certificate import Certificate
from reports import figures_sim as sim
from reports.captions import (
    caption_lipschitz,
    caption_metric_map,
    caption_mpdi_map,
    caption_necessary_map,
    caption_prover,
    caption_residual_map,
)
from reports.figure_kit import STYLE, drawn
from reports.figures_bounds import fig_lipschitz, fig_prover
from reports.figures_maps import (
    fig_metric_map,
    fig_mpdi_map,
    fig_necessary_map,
    fig_residual_map,
)

__all__ = ["FIGURES", "STYLE", "FigureSpec", "RenderedFigure", "drawn", "fig_lipschitz",
           "fig_mpdi_map", "fig_necessary_map", "fig_prover", "fig_residual_map",
           "figure_png", "render_figures"]


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
    return (
        FigureSpec("mpdi_map", "mpdi", caption_mpdi_map, fig_mpdi_map),
        FigureSpec("prover", "mpdi", caption_prover, fig_prover),
        FigureSpec("necessary_map", "necessary", caption_necessary_map, fig_necessary_map),
        FigureSpec("residual_map", "residual", caption_residual_map, fig_residual_map),
        FigureSpec("lipschitz", "lipschitz", caption_lipschitz, fig_lipschitz),
        FigureSpec("metric_map", "metric_bound", caption_metric_map, fig_metric_map),
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
    """An 8-bit RGB PNG of a figure on white (no alpha channel: the PDF embeds the PNG's
    data as it is) with no metadata, so identical inputs give identical bytes."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from PIL import Image

    canvas = fig.canvas if isinstance(fig.canvas, FigureCanvasAgg) else FigureCanvasAgg(fig)
    fig.set_dpi(dpi)
    fig.patch.set_facecolor("white")
    canvas.draw()
    rgb = np.asarray(canvas.buffer_rgba())[..., :3]
    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(rgb)).save(buf, format="png")
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
