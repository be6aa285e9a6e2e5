"""Self-contained HTML report: inline CSS, figures as base64 PNG, no external resource."""

from __future__ import annotations

import base64
from pathlib import Path
from typing import Any

import jinja2

from certify.certificate import Certificate
from reports import content as C
from reports import sections as S
from reports.figures import RenderedFigure, render_figures

TEMPLATE_DIR = Path(__file__).parent / "templates"
_ENV = jinja2.Environment(
    loader=jinja2.FileSystemLoader(str(TEMPLATE_DIR)),
    autoescape=jinja2.select_autoescape(["html", "j2"], default=True),
    undefined=jinja2.StrictUndefined, trim_blocks=True, lstrip_blocks=True,
)

#: CSS pixels per inch of figure: 7 in figures display at 945 px (the column is ~1120 px)
_CSS_PX_PER_IN = 135


def _figure_ctx(fig: RenderedFigure) -> dict[str, Any]:
    return {"key": fig.key, "caption": fig.caption,
            "b64": base64.b64encode(fig.png).decode("ascii"),
            "css_width": round(fig.width_in * _CSS_PX_PER_IN),
            "css_height": round(fig.height_in * _CSS_PX_PER_IN)}


def _table_ctx(t: S.Table) -> dict[str, Any]:
    widths = t.widths or [1.0] * len(t.header)
    total = sum(widths)
    return {"title": t.title, "header": t.header, "rows": t.rows, "fixed": t.fixed,
            "widths": [f"{100 * w / total:.1f}%" for w in widths]}


def context(cert: Certificate, figures: list[RenderedFigure]) -> dict[str, Any]:
    """Everything the template shows, from the certificate alone."""
    by_section: dict[str, list[dict[str, Any]]] = {}
    for fig in figures:
        by_section.setdefault(fig.section, []).append(_figure_ctx(fig))
    secs = []
    for sec in S.sections(cert):
        secs.append({"anchor": sec.anchor, "title": sec.title, "short": sec.short,
                     "status": sec.status, "badge": sec.badge, "badge_key": sec.badge_key,
                     "message": sec.message, "tone": sec.tone, "paragraphs": sec.paragraphs,
                     "statements": sec.statements, "facts": sec.facts,
                     "tables": [_table_ctx(t) for t in sec.tables],
                     "bullets": sec.bullets, "bullets_title": sec.bullets_title,
                     "empty": sec.empty, "notes": sec.notes,
                     "figures": by_section.get(sec.anchor, [])})
    settings = cert.settings_rows()  # labels and units from certify.settings
    half = (len(settings) + 1) // 2
    ck = cert.checkpoint or {}
    sha = str(ck.get("sha256", ""))
    toc = [("checks", "Checks"), ("system", "System")] + \
        [(s["anchor"], s["short"] or s["title"]) for s in secs] + [("settings", "Settings")]
    sy = cert.system or {}
    return {
        "verdict": cert.verdict, "summary": C.verdict_summary(cert),
        "headline": C.error_headline_text(cert),
        "verdict_colour": C.VERDICT_COLOURS.get(cert.verdict, "#374151"),
        "status_colours": C.STATUS_COLOURS, "system_name": sy.get("name", "system"),
        "system_description": sy.get("description", ""),
        "checkpoint_path": ck.get("path", C.DASH), "sha_short": sha[:16] or C.DASH,
        "created": cert.created or C.DASH, "toc": toc, "rows": C.check_rows(cert),
        "convention": C.CONVENTION, "system_facts": C.system_facts(cert),
        "provenance": C.provenance_facts(cert), "versions": cert.versions or {},
        "versions_list": C.kv_pairs(cert.versions), "timings": C.timing_pairs(cert),
        "sections": secs, "settings_halves": [settings[:half], settings[half:]],
        "required": ", ".join(cert.required) or C.DASH, "schema": cert.schema,
        "schema_version": cert.schema_version, "fmt_seconds": C.fmt_seconds,
    }


def render_html(cert: Certificate, figures: list[RenderedFigure] | None = None) -> str:
    """The HTML report as a string (figures drawn here unless given)."""
    if figures is None:
        figures = render_figures(cert)
    return _ENV.get_template("report.html.j2").render(**context(cert, figures))
