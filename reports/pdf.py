"""PDF report of a certificate: what goes on the pages, in order.

The verdict banner, the table of checks, the system, provenance, versions and timings, one
section per check (`reports.sections`, shared with the HTML report) with its figures, and
the settings, laid out by the flow layout of `reports.pdf_layout` (real, selectable text;
tables; the same PNG figures as the HTML report).
"""

from __future__ import annotations

from certify.certificate import Certificate
from reports import content as C
from reports import sections as S
from reports.figures import RenderedFigure, render_figures
from reports.pdf_layout import (
    CONTENT_W,
    INK,
    MARGIN_X,
    MUTED,
    PAGE_H,
    PAGE_W,
    PANEL,
    PT,
    Cell,
    PdfDocument,
    Run,
)
from reports.pdf_writer import PdfWriter


def _check_table(doc: PdfDocument, cert: Certificate) -> None:
    rows, spans = [], {}
    for i, r in enumerate(C.check_rows(cert)):
        fg, bg = C.STATUS_COLOURS.get(r.badge_key, (INK, PANEL))
        name = Cell([Run(r.title, 8.2, "bold"),
                     Run(r.name + ("  \u00b7 required" if r.required else ""), 7.2,
                         color="#1e3a8a" if r.required else MUTED)])
        status = Cell([Run(r.badge, 7.2, "bold", fg, pill=(fg, bg))]
                      + ([Run(C.fmt_seconds(r.seconds), 7.2, color=MUTED)]
                         if r.seconds is not None else []))
        sides = []
        for side in (r.sampled, r.proved):
            runs = [Run(side.label, 7.0, color=MUTED), Run(side.value, 9.0, "bold")]
            if side.note:
                runs.append(Run(side.note, 7.0, color=MUTED))
            sides.append(Cell(runs))
        rows.append([name, status, *sides, Cell([Run(r.setting, 7.6)])])
        spans[i] = Cell([Run(r.message, 7.4, color=MUTED)])
    doc.table(["Check", "Status", "Sampled / found side", "Proved side", "Checked with"],
              rows, [1.45, 0.9, 1.45, 1.45, 1.55], spans=spans)


def _verdict(doc: PdfDocument, cert: Certificate) -> None:
    colour = C.VERDICT_COLOURS.get(cert.verdict, "#374151")
    big = Run(cert.verdict, 20, "bold", "white")
    summ = Run(C.verdict_summary(cert), 9.5, color="white")
    ck = cert.checkpoint or {}
    meta = Run(f"checkpoint {ck.get('path', C.DASH)} \u00b7 sha256 "
               f"{str(ck.get('sha256', ''))[:16]}\u2026 \u00b7 created {cert.created or C.DASH}",
               7.8, color="white")
    lines = doc.layout([big, summ, meta], CONTENT_W - 0.3)
    h = sum(x[2] for x in lines) + 0.26
    doc.need(h)
    doc.rect(MARGIN_X, doc.y, CONTENT_W, h, colour, round_=True)
    doc.draw_lines(MARGIN_X + 0.15, doc.y + 0.13, lines)
    doc.y += h + 0.18


def _headline(doc: PdfDocument, cert: Certificate) -> None:
    """The certified error bound under the verdict banner: the sentence and its size word,
    per component, the size against the box, and (small) which bound it comes from; or the
    one line saying why there is none."""
    h = C.error_headline_text(cert)
    what = Run("CERTIFIED ERROR BOUND", 7.2, "bold", MUTED)
    if not h.proved:
        runs = [what, Run(h.sentence, 9.5, color=MUTED)]
        edge, box = "#9ca3af", PANEL
    else:
        fg, bg = C.SIZE_COLOURS[h.size_word]
        runs = [what, Run(h.sentence, 13, "bold"), Run(h.size_word, 8.0, "bold", fg,
                                                      pill=(fg, bg))]
        if h.components:
            runs.append(Run(h.components, 10))
        runs += [Run(h.size, 9), Run(h.source, 7.4, color=MUTED)]
        edge = "#15803d" if h.size_word == "useful" else "#b45309"
        box = PANEL if h.size_word == "useful" else "#fffbeb"
    lines = doc.layout(runs, CONTENT_W - 0.35)
    height = sum(x[2] for x in lines) + 0.22
    doc.need(height)
    doc.rect(MARGIN_X, doc.y, CONTENT_W, height, box, round_=True)
    doc.rect(MARGIN_X, doc.y, 0.06, height, edge)
    doc.draw_lines(MARGIN_X + 0.2, doc.y + 0.11, lines)
    doc.y += height + 0.18


def _section(doc: PdfDocument, sec: S.Section, figures: list[RenderedFigure]) -> None:
    doc.heading(sec.title, 1, sec.badge, sec.badge_key)
    if sec.message:
        tone = {"good": ("#f0fdf4", "#15803d"), "bad": ("#fef2f2", "#b91c1c"),
                "warn": ("#fffbeb", "#b45309")}.get(sec.tone, (PANEL, "#9ca3af"))
        doc.para(sec.message, 8.8, box=tone[0], bar=tone[1])
    for p in sec.paragraphs:
        doc.para(p, 8.8)
    for st in sec.statements:
        doc.para(st, 8.5, box="#f8fafc", bar="#94a3b8")
    if sec.facts:
        doc.kv(sec.facts)
    for t in sec.tables:
        if t.title:
            doc.heading(t.title, 2)
        doc.table(t.header, t.rows, t.widths or [1.0] * len(t.header),
                  size=7.2 if len(t.header) > 6 else 8.0)
    for note in sec.notes:
        doc.para(note, 7.4, MUTED)
    if sec.bullets:
        doc.heading(sec.bullets_title, 2)
        for b in sec.bullets:
            doc.para("\u2022 " + b, 8.5, gap=0.02)
        doc.y += 0.08
    for fig in figures:
        doc.image(fig, fig.caption)
    if sec.empty:
        doc.para(sec.empty, 8.5, MUTED)


def render_pdf(cert: Certificate, figures: list[RenderedFigure] | None = None) -> bytes:
    """The PDF report as bytes (figures drawn here unless given)."""
    if figures is None:
        figures = render_figures(cert)
    by_section: dict[str, list[RenderedFigure]] = {}
    for fig in figures:
        by_section.setdefault(fig.section, []).append(fig)
    sy = cert.system or {}
    name = sy.get("name", "system")
    meta = {"Title": f"certify report: {name} ({cert.verdict})", "Author": "certify",
            "Subject": cert.summary, "Creator": f"certify {cert.versions.get('certify', '')}",
            "Producer": "certify"}
    pdf = PdfWriter(PAGE_W * PT, PAGE_H * PT, meta)
    doc = PdfDocument(pdf, f"certify report \u00b7 {name} \u00b7 {cert.verdict}")
    doc.new_page()
    doc.para(f"certify report \u00b7 {name}", 16, INK, gap=0.0)
    if sy.get("description"):
        doc.para(sy["description"], 9.5, MUTED)
    _verdict(doc, cert)
    _headline(doc, cert)
    doc.heading("Checks", 1)
    _check_table(doc, cert)
    doc.heading("System, metric and rates", 1)
    doc.para(C.CONVENTION, 8.5, box="#f8fafc", bar="#94a3b8")
    doc.kv(C.system_facts(cert))
    doc.heading("Provenance", 2)
    doc.kv(C.provenance_facts(cert))
    doc.heading("Versions and timings", 2)
    vers, tims = C.kv_pairs(cert.versions), C.timing_pairs(cert)
    n = max(len(vers), len(tims))
    vers += [("", "")] * (n - len(vers))
    tims += [("", "")] * (n - len(tims))
    doc.table(["Package", "Version", "Step", "Time"],
              [[a, b, c, d] for (a, b), (c, d) in zip(vers, tims)], [1, 1, 1, 1])
    for sec in S.sections(cert):
        _section(doc, sec, by_section.get(sec.anchor, []))
    doc.heading("Settings", 1)
    doc.para("The settings this certificate was checked with. Required checks: "
             + (", ".join(cert.required) or C.DASH) + ".", 8.8)
    pairs = cert.settings_rows()  # labels and units from certify.settings
    half = (len(pairs) + 1) // 2
    left, right = pairs[:half], pairs[half:] + [("", "")] * (2 * half - len(pairs))
    doc.table(["Setting", "Value", "Setting", "Value"],
              [[a, b, c, d] for (a, b), (c, d) in zip(left, right)], [1.3, 1, 1.3, 1])
    doc.para("Only PROVED counts as a proof (PASSED: a simulation found no breach, evidence "
             "only); UNKNOWN is never a pass. "
             f"Certificate schema {cert.schema} v{cert.schema_version}.", 7.8, MUTED)
    return pdf.close()
