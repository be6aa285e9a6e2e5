"""Render tests, one per figure: point markers lie whole inside the axes (clear of the
title), titles are not cut off, and each caption names exactly what the figure draws."""

from __future__ import annotations

import dataclasses

import matplotlib
import numpy as np
import pytest

from certify.results import Counterexample  # noqa: E402
from reports import figures as figmod  # noqa: E402
from reports.figures import drawn  # noqa: E402

from .. import fixtures_certificates as F  # noqa: E402

pytestmark = pytest.mark.slow

SPECS = {spec.key: spec for spec in figmod.FIGURES}


def _draw(spec, cert):
    with matplotlib.rc_context(figmod.STYLE):
        fig = spec.build(cert)
        if fig is not None:
            fig.canvas.draw()
    return fig


def _markers(fig):
    """(axes, display x, display y, radius in px, marker zorder) of every scatter point."""
    out = []
    for ax in fig.axes:
        for coll in ax.collections:
            if type(coll).__name__ != "PathCollection" or not len(coll.get_offsets()):
                continue
            pts = coll.get_offset_transform().transform(coll.get_offsets())
            sizes = coll.get_sizes()
            for k, (px, py) in enumerate(pts):
                size = sizes[k % len(sizes)] if len(sizes) else 36.0
                out.append((ax, px, py, np.sqrt(size) / 2 * fig.dpi / 72, coll.get_zorder()))
    return out


def _contour_drawn(fig) -> bool:
    for ax in fig.axes:
        for coll in ax.collections:
            if type(coll).__name__ in ("QuadContourSet", "ContourSet"):
                if any(len(s) for s in coll.allsegs[0]):
                    return True
    return False


def _check_figure(spec, cert) -> None:
    fig = _draw(spec, cert)
    if fig is None:
        return
    renderer = fig.canvas.get_renderer()
    fig_box = fig.bbox
    # every title (and the figure's) lies inside the figure: nothing cut off
    texts = [ax.title for ax in fig.axes if ax.get_visible() and ax.get_title()]
    if fig._suptitle is not None:
        texts.append(fig._suptitle)
    for text in texts:
        bb = text.get_window_extent(renderer)
        assert bb.x0 >= -1 and bb.x1 <= fig_box.x1 + 1, (spec.key, text.get_text())
        assert bb.y1 <= fig_box.y1 + 1, (spec.key, text.get_text())
    # every point marker lies whole inside its axes, and below the title
    for ax, px, py, rad, _ in _markers(fig):
        box = ax.get_window_extent(renderer)
        assert box.x0 - 0.5 <= px - rad and px + rad <= box.x1 + 0.5, (spec.key, px, rad)
        assert box.y0 - 0.5 <= py - rad and py + rad <= box.y1 + 0.5, (spec.key, py, rad)
        if ax.get_title():
            title = ax.title.get_window_extent(renderer)
            assert py + rad <= title.y0 + 0.5, (spec.key, "marker overlaps the title")
    # the caption says exactly what is drawn
    caption = spec.caption(drawn(fig))
    assert ("zero contour" in caption) == _contour_drawn(fig), (spec.key, caption)
    d = drawn(fig)
    assert ("counterexamples" in caption) == ("counterexamples" in d), caption
    assert ("\u2605" in caption) == any(k in d for k in ("worst point", "witness")), caption
    if spec.key in ("mpdi_map", "necessary_map", "residual_map"):
        want = int("worst point" in d or "witness" in d) + int(d.get("counterexamples", 0))
        assert len(_markers(fig)) == want, caption


@pytest.mark.parametrize("key", list(SPECS))
@pytest.mark.parametrize("name", list(F.ALL))
def test_figure_markers_inside_titles_whole_caption_matches(key: str, name: str) -> None:
    _check_figure(SPECS[key], F.ALL[name]())


def test_corner_counterexamples_are_inside_and_drawn_above_the_worst_point() -> None:
    """A worst point and counterexamples on the corners of X: whole inside the axes, and the
    × at the worst point's corner is drawn over the star, not hidden by it."""
    cert = F.violated_vdp_certificate()
    X = cert.system["X"]
    corners = [[X[0][i], X[1][j]] for i in (0, 1) for j in (0, 1)]
    cex = [Counterexample(xhat=c, y=[0.0], value=5.0 - k) for k, c in enumerate(corners)]
    cert.checks["mpdi"] = dataclasses.replace(cert.checks["mpdi"], counterexamples=cex,
                                              worst=cex[3])
    spec = SPECS["mpdi_map"]
    _check_figure(spec, cert)
    fig = _draw(spec, cert)
    marks = _markers(fig)
    star = [m for m in marks if m[4] == 6]
    crosses = [m for m in marks if m[4] == 7]
    assert len(star) == 1 and len(crosses) == 4
    assert "\u00d7 counterexamples (4)" in spec.caption(drawn(fig))


def test_one_signed_map_has_no_zero_contour_in_its_caption() -> None:
    cert = F.certified_certificate()
    fig = _draw(SPECS["mpdi_map"], cert)
    caption = SPECS["mpdi_map"].caption(drawn(fig))
    assert not _contour_drawn(fig)
    assert "zero contour" not in caption and "counterexamples" not in caption
    assert "every grid value is < 0" in caption


def test_trajectories_only_on_request() -> None:
    cert = F.certified_certificate()
    keys = [f.key for f in figmod.render_figures(cert, dpi=40)]
    assert "bounds" in keys and "simulation" not in keys
    keys = [f.key for f in figmod.render_figures(cert, dpi=40, trajectories=True)]
    assert "simulation" in keys


def test_every_run_of_the_default_simulation_gets_a_panel() -> None:
    """The default settings simulate 13 runs (12 with bounded noise, the source protocol):
    each one its own panel, in rows of four beyond nine."""
    cert = F.certified_certificate()
    sim = cert.checks["simulation"]
    runs = [dataclasses.replace(sim.runs[i % len(sim.runs)], label=f"run {i}")
            for i in range(13)]
    cert.checks["simulation"] = dataclasses.replace(sim, runs=runs)
    fig = _draw(SPECS["simulation"], cert)
    panels = [ax for ax in fig.axes if ax.get_title()]
    assert len(panels) == 13
    assert len({round(ax.get_position().x0, 3) for ax in panels}) == 4
