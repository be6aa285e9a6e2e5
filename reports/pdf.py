"""PDF report of a certificate, laid out with ReportLab's platypus: what goes on the pages.

In order: the verdict banner, the error headline, the table of checks, the system,
provenance, versions and timings, one section per check (`reports.sections`, shared with
the HTML report) with its figures, and the settings. Text is real text in embedded, subset
TrueType fonts (matplotlib's own DejaVu Sans files, so no system font is needed and every
machine draws the same glyphs): selectable and searchable, Unicode included (‖e‖ ≤ λ).
Figures are the HTML report's PNGs. The same certificate gives the same bytes: the
document is written invariant, dated with the certificate's creation time.
"""

from __future__ import annotations

import datetime as _dt
import io
from collections.abc import Iterator
from contextlib import contextmanager
from functools import cache, lru_cache
from pathlib import Path
from typing import Any
from xml.sax.saxutils import escape

from reportlab.lib.pagesizes import A4
from reportlab.lib.styles import ParagraphStyle
from reportlab.lib.utils import ImageReader
from reportlab.pdfbase import pdfmetrics
from reportlab.pdfbase.ttfonts import TTFont
from reportlab.platypus import (
    CondPageBreak,
    Flowable,
    Paragraph,
    SimpleDocTemplate,
    Spacer,
    Table,
)
from reportlab.platypus.flowables import HRFlowable

from certify.certificate import Certificate
from reports import content as C
from reports import sections as S
from reports.figures import RenderedFigure, render_figures

#: lengths in points (1/72 in) on A4
PAGE_W, PAGE_H = A4
MARGIN, MARGIN_BOTTOM = 50.4, 54.0
CONTENT_W = PAGE_W - 2 * MARGIN
FONT, BOLD = "CertifySans", "CertifySans-Bold"
INK, MUTED, LINE, PANEL = "#111827", "#4b5563", "#d1d5db", "#f3f4f6"
WHITE = "#ffffff"
#: line height per point of font size
LEADING = 1.3
#: the tones of a section's message box: (background, bar)
TONES = {"good": ("#f0fdf4", "#15803d"), "bad": ("#fef2f2", "#b91c1c"),
         "warn": ("#fffbeb", "#b45309"), "": (PANEL, "#9ca3af")}
#: the edge of the headline box: by the bound's size when it rests on the certificate,
#: else by what it rests on (`certify.presentation.BASES`)
HEADLINE_EDGES = {"useful": "#15803d", "vacuous": "#b45309", "proved": "#6b7280",
                  "unproved": "#b91c1c", "none": "#9ca3af"}


@lru_cache(maxsize=1)
def _register_fonts() -> None:
    """matplotlib's DejaVu Sans, regular and bold, as the family `FONT` (shipped with
    matplotlib: the same on every machine, whatever fonts the system has); once a process."""
    import matplotlib
    from reportlab.lib.fonts import addMapping

    ttf = Path(matplotlib.get_data_path()) / "fonts" / "ttf"
    pdfmetrics.registerFont(TTFont(FONT, str(ttf / "DejaVuSans.ttf")))
    pdfmetrics.registerFont(TTFont(BOLD, str(ttf / "DejaVuSans-Bold.ttf")))
    for italic in (0, 1):  # no italic face: <i> falls back to the upright one
        addMapping(FONT, 0, italic, FONT)
        addMapping(FONT, 1, italic, BOLD)


@cache
def _style(size: float, bold: bool = False, colour: str = INK, after: float = 0.0,
           indent: float = 0.0) -> ParagraphStyle:
    return ParagraphStyle(f"s{size}{bold}{colour}{after}{indent}", fontName=BOLD if bold
                          else FONT, fontSize=size, leading=size * LEADING, textColor=colour,
                          spaceAfter=after, leftIndent=indent, rightIndent=indent,
                          autoLeading="max")


def text(s: str) -> str:
    """Plain text as paragraph markup: escaped, line breaks kept."""
    return escape(s).replace("\n", "<br/>")


def para(s: str, size: float = 8.8, colour: str = INK, *, bold: bool = False,
         after: float = 5.8, indent: float = 0.0, markup: bool = False) -> Paragraph:
    """A paragraph of plain text (`markup`: `s` is already paragraph markup)."""
    return Paragraph(s if markup else text(s), _style(size, bold, colour, after, indent))


def badge(word: str, fg: str, bg: str, size: float = 7.5) -> str:
    """A status badge inside a paragraph: bold, coloured, on its own background."""
    return (f'<font name="{BOLD}" size="{size}" color="{fg}" backColor="{bg}">'
            f"\u00a0{text(word)}\u00a0</font>")


def box(content: list[Any], fill: str, *, bar: str | None = None, pad: float = 7.2,
        after: float = 9.0) -> Table:
    """Flowables in a filled box across the column, a coloured bar on its left."""
    style = [("FONTNAME", (0, 0), (-1, -1), FONT), ("BACKGROUND", (0, 0), (-1, -1), fill),
             ("LEFTPADDING", (0, 0), (-1, -1), pad + (5 if bar else 0)),
             ("RIGHTPADDING", (0, 0), (-1, -1), pad),
             ("TOPPADDING", (0, 0), (-1, -1), pad),
             ("BOTTOMPADDING", (0, 0), (-1, -1), pad)]
    if bar:
        style.append(("LINEBEFORE", (0, 0), (0, -1), 4.3, bar))
    else:
        style.append(("ROUNDEDCORNERS", [3.6] * 4))
    t = Table([[content]], colWidths=[CONTENT_W], style=style, splitInRow=1)
    t.spaceAfter = after
    return t


def heading(title: str, level: int = 1, word: str = "", key: str = "") -> list[Any]:
    """A heading (with a status badge after it, coloured as `STATUS_COLOURS[key]`), on a
    new page when less than about an inch and a half is left."""
    size = 13.5 if level == 1 else 11.0
    markup = text(title)
    if word:
        fg, bg = C.STATUS_COLOURS.get(key or word, (INK, PANEL))
        markup += "\u2002" + badge(word, fg, bg)
    out: list[Any] = [CondPageBreak(size * LEADING * 2 + 86),
                      Spacer(1, 10 if level == 1 else 4),
                      para(markup, size, bold=True, after=2.9, markup=True)]
    if level == 1:
        out.append(HRFlowable(width="100%", thickness=0.9, color="#9ca3af", spaceBefore=0,
                              spaceAfter=8.6))
    return out


def grid(header: list[str] | None, rows: list[list[Any]], widths: list[float], *,
         size: float = 8.0, key_bold: bool = False, style: list | None = None) -> Table:
    """A table of wrapping cells (plain strings or flowables) across the column; its header
    repeats after a page break."""
    total = sum(widths)
    cols = [CONTENT_W * w / total for w in widths]

    def cell(c: Any, bold: bool = False, colour: str = INK) -> Any:
        return para(c, size, colour, bold=bold, after=0) if isinstance(c, str) else c

    data = [[cell(h, True, "#374151") for h in header]] if header else []
    data += [[cell(c, key_bold and j == 0) for j, c in enumerate(r)] for r in rows]
    look = [("FONTNAME", (0, 0), (-1, -1), FONT), ("VALIGN", (0, 0), (-1, -1), "TOP"),
            ("LEFTPADDING", (0, 0), (-1, -1), 3.6), ("RIGHTPADDING", (0, 0), (-1, -1), 3.6),
            ("TOPPADDING", (0, 0), (-1, -1), 2.5), ("BOTTOMPADDING", (0, 0), (-1, -1), 3.0),
            ("LINEBELOW", (0, 0), (-1, -1), 0.6, LINE)]
    if header:
        look += [("BACKGROUND", (0, 0), (-1, 0), PANEL),
                 ("LINEBELOW", (0, 0), (-1, 0), 0.8, "#9ca3af")]
    t = Table(data, colWidths=cols, style=look + (style or []), repeatRows=1 if header else 0,
              hAlign="LEFT")
    t.spaceAfter = 8.6
    return t


def kv(facts: list[tuple[str, str]], size: float = 8.5) -> Table:
    return grid(None, [[k, v] for k, v in facts], [1.0, 2.4], size=size, key_bold=True)


class FigureBlock(Flowable):
    """A figure centred at its own width (at most the column's) with its caption below;
    shrunk by up to a quarter where that keeps it on the page, rather than leave most of
    the page empty."""

    def __init__(self, fig: RenderedFigure) -> None:
        super().__init__()
        self.fig = fig
        self.caption = para(fig.caption, 7.8, MUTED, after=0, indent=14.4)
        self.spaceAfter = 10.8
        self.size = (0.0, 0.0, 0.0)

    def wrap(self, avail_w: float, avail_h: float) -> tuple[float, float]:
        w = min(avail_w, self.fig.width_in * 72)
        h = w * self.fig.height_px / self.fig.width_px
        _, cap_h = self.caption.wrap(avail_w, avail_h)
        room = avail_h - cap_h - 3.6
        if h > room >= 0.72 * h:
            w, h = w * room / h, room
        self.size = (w, h, cap_h)
        self.width = avail_w
        return avail_w, h + 3.6 + cap_h

    def draw(self) -> None:
        w, h, cap_h = self.size
        self.canv.drawImage(ImageReader(io.BytesIO(self.fig.png)), (self.width - w) / 2,
                            cap_h + 3.6, w, h)
        self.caption.drawOn(self.canv, 0, 0)


# ----------------------------------------------------------------------------- the pages

def _verdict(cert: Certificate) -> Table:
    ck = cert.checkpoint or {}
    meta = (f"checkpoint {ck.get('path', C.DASH)} \u00b7 sha256 "
            f"{str(ck.get('sha256', ''))[:16]}\u2026 \u00b7 created {cert.created or C.DASH}")
    return box([para(cert.verdict, 20, WHITE, bold=True, after=3),
                para(C.verdict_summary(cert), 9.5, WHITE, after=3),
                para(meta, 7.8, WHITE, after=0)],
               C.VERDICT_COLOURS.get(cert.verdict, "#374151"), pad=10.8)


def _headline(cert: Certificate) -> Table:
    """The error bound under the verdict banner, headed by what it rests on ('Certified
    error bound' only under a CERTIFIED verdict): the sentence and its size word, per
    component, the size against the box, and (small) which bound it comes from; or the
    one line saying why there is none."""
    h = C.error_headline_text(cert)
    head = para(h.title, 8.0, MUTED, bold=True, after=2)
    if not h.proved:
        return box([head, para(h.sentence, 9.5, MUTED, after=0)], PANEL,
                   bar=HEADLINE_EDGES["none"])
    fg, bg = C.SIZE_COLOURS[h.size_word]
    lines = [head, para(text(h.sentence) + "\u2002" + badge(h.size_word, fg, bg, 8.0), 13,
                        bold=True, after=2, markup=True)]
    if h.components:
        lines.append(para(h.components, 10, after=1))
    lines += [para(h.size, 9, after=1), para(h.source, 7.4, MUTED, after=0)]
    certified = h.basis == "certificate"
    edge = HEADLINE_EDGES[h.size_word if certified else h.basis or "none"]
    fill = ("#fffbeb" if certified and h.size_word == "vacuous"
            else "#fef2f2" if h.basis == "unproved" else PANEL)
    return box(lines, fill, bar=edge)


def _check_table(cert: Certificate) -> Table:
    """One row per check (name, status badge, both sides, settings), its message under it
    across the table."""
    rows, style = [], []
    for r in C.check_rows(cert):
        fg, bg = C.STATUS_COLOURS.get(r.badge_key, (INK, PANEL))
        colour = "#1e3a8a" if r.required else MUTED
        required = " \u00b7 required" if r.required else ""
        name = para(f"<b>{text(r.title)}</b><br/><font size=\"7.2\" color=\"{colour}\">"
                    f"{text(r.name)}{required}</font>", 8.2, after=0, markup=True)
        seconds = (f'<br/><font name="{FONT}" size="7.2" color="{MUTED}">'
                   f"{text(C.fmt_seconds(r.seconds))}</font>" if r.seconds is not None else "")
        status = para(text(r.badge) + seconds, 7.2, fg, bold=True, after=0, markup=True)
        sides = []
        for side in (r.sampled, r.proved):
            markup = (f'<font size="7" color="{MUTED}">{text(side.label)}</font><br/>'
                      f'<font name="{BOLD}" size="9">{text(side.value)}</font>')
            if side.note:
                markup += f'<br/><font size="7" color="{MUTED}">{text(side.note)}</font>'
            sides.append(para(markup, 7.6, after=0, markup=True))
        i = 1 + len(rows)
        rows.append([name, status, *sides, para(r.setting, 7.6, after=0)])
        rows.append([para(r.message, 7.4, MUTED, after=0), "", "", "", ""])
        style += [("BACKGROUND", (1, i), (1, i), bg), ("SPAN", (0, i + 1), (-1, i + 1)),
                  ("NOSPLIT", (0, i), (-1, i + 1)),
                  ("LINEBELOW", (0, i), (-1, i), 0, WHITE),
                  ("TOPPADDING", (0, i + 1), (-1, i + 1), 0)]
    return grid(["Check", "Status", "Sampled / found side", "Proved side", "Checked with"],
                rows, [1.45, 0.95, 1.45, 1.45, 1.5], size=7.6, style=style)


def _section(sec: S.Section, figures: list[RenderedFigure]) -> list[Any]:
    out = heading(sec.title, 1, sec.badge, sec.badge_key)
    if sec.message:
        fill, bar = TONES.get(sec.tone, TONES[""])
        out.append(box([para(sec.message, after=0)], fill, bar=bar))
    out += [para(p) for p in sec.paragraphs]
    out += [box([para(st, 8.5, after=0)], "#f8fafc", bar="#94a3b8") for st in sec.statements]
    if sec.facts:
        out.append(kv(sec.facts))
    for t in sec.tables:
        if t.title:
            out += heading(t.title, 2)
        out.append(grid(t.header, t.rows, t.widths or [1.0] * len(t.header),
                        size=7.2 if len(t.header) > 6 else 8.0))
    out += [para(note, 7.4, MUTED) for note in sec.notes]
    if sec.bullets:
        out += heading(sec.bullets_title, 2)
        out += [para("\u2022 " + b, 8.5, after=1.5) for b in sec.bullets]
        out.append(Spacer(1, 5.8))
    out += [FigureBlock(fig) for fig in figures]
    if sec.empty:
        out.append(para(sec.empty, 8.5, MUTED))
    return out


def _side_by_side(left: list[tuple[str, str]], right: list[tuple[str, str]]
                  ) -> list[list[str]]:
    n = max(len(left), len(right))
    left = left + [("", "")] * (n - len(left))
    right = right + [("", "")] * (n - len(right))
    return [[a, b, c, d] for (a, b), (c, d) in zip(left, right)]


def _story(cert: Certificate, figures: list[RenderedFigure]) -> list[Any]:
    by_section: dict[str, list[RenderedFigure]] = {}
    for fig in figures:
        by_section.setdefault(fig.section, []).append(fig)
    sy = cert.system or {}
    story: list[Any] = [para(f"certify report \u00b7 {sy.get('name', 'system')}", 16,
                             after=2)]
    if sy.get("description"):
        story.append(para(sy["description"], 9.5, MUTED))
    story += [_verdict(cert), _headline(cert), *heading("Checks"), _check_table(cert),
              *heading("System, metric and rates"),
              box([para(C.CONVENTION, 8.5, after=0)], "#f8fafc", bar="#94a3b8"),
              kv(C.system_facts(cert)), *heading("Provenance", 2),
              kv(C.provenance_facts(cert)), *heading("Versions and timings", 2),
              grid(["Package", "Version", "Step", "Time"],
                   _side_by_side(C.kv_pairs(cert.versions), C.timing_pairs(cert)),
                   [1, 1, 1, 1])]
    for sec in S.sections(cert):
        story += _section(sec, by_section.get(sec.anchor, []))
    pairs = cert.settings_rows()  # labels and units from certify.settings
    half = (len(pairs) + 1) // 2
    story += [*heading("Settings"),
              para("The settings this certificate was checked with. Required checks: "
                   + (", ".join(cert.required) or C.DASH) + "."),
              grid(["Setting", "Value", "Setting", "Value"],
                   _side_by_side(pairs[:half], pairs[half:]), [1.3, 1, 1.3, 1]),
              para("Only PROVED counts as a proof (PASSED: a simulation found no breach, "
                   "evidence only); UNKNOWN is never a pass. "
                   f"Certificate schema {cert.schema} v{cert.schema_version}.", 7.8, MUTED)]
    return story


def _pdf_date(created: str) -> str | None:
    """The certificate's creation time as a PDF date, None when it has none."""
    try:
        when = _dt.datetime.fromisoformat(created)
    except (TypeError, ValueError):
        return None
    if when.tzinfo is not None:
        when = when.astimezone(_dt.timezone.utc)
    return when.strftime("D:%Y%m%d%H%M%S+00'00'")


@contextmanager
def _binary_streams() -> Iterator[None]:
    """ReportLab's streams without its ASCII85 text encoding (`rl_config.useA85`, a
    process-wide setting, restored afterwards): images stay binary, a quarter smaller and
    not run through the pure-Python encoder."""
    from reportlab import rl_config

    was = rl_config.useA85
    rl_config.useA85 = 0
    try:
        yield
    finally:
        rl_config.useA85 = was


def render_pdf(cert: Certificate, figures: list[RenderedFigure] | None = None) -> bytes:
    """The PDF report as bytes (figures drawn here unless given)."""
    if figures is None:
        figures = render_figures(cert)
    _register_fonts()
    name = (cert.system or {}).get("name", "system")
    footer = f"certify report \u00b7 {name} \u00b7 {cert.verdict}"
    date = _pdf_date(cert.created)

    def on_page(canvas: Any, doc: Any) -> None:
        if date is not None:
            canvas.setDateFormatter(lambda *_: date)
        canvas.saveState()
        canvas.setFont(FONT, 7.5)
        canvas.setFillColor(MUTED)
        canvas.drawString(MARGIN, 27, footer)
        canvas.drawRightString(PAGE_W - MARGIN, 27, f"page {doc.page}")
        canvas.restoreState()

    out = io.BytesIO()
    doc = SimpleDocTemplate(
        out, pagesize=A4, leftMargin=MARGIN, rightMargin=MARGIN, topMargin=MARGIN,
        bottomMargin=MARGIN_BOTTOM, title=f"certify report: {name} ({cert.verdict})",
        author="certify", subject=cert.summary, lang="en", invariant=1,
        creator=f"certify {(cert.versions or {}).get('certify', '')}".strip(),
        initialFontName=FONT)
    with _binary_streams():
        doc.build(_story(cert, figures), onFirstPage=on_page, onLaterPages=on_page)
    return out.getvalue()
