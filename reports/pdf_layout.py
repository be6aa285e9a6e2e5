"""The PDF report's page layout: a small flow layout on A4 pages.

Text is measured from the fonts' advance widths (`TextMeasure`), wrapped to the column and
drawn as PDF text (TrueType, so it is searchable); tables wrap inside their cells and repeat
their header after a page break; figures are the report's PNGs embedded as they are, at
their native resolution. Pages are written by `reports.pdf_writer` (text, boxes, lines,
images: all this layout draws). `PdfDocument` knows nothing about certificates:
`reports.pdf` decides what goes on the pages. No system library beyond the Python packages
is needed (the fonts are matplotlib's DejaVu, read with its FreeType binding and fontTools).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

from matplotlib import ft2font
from matplotlib.font_manager import FontProperties, findfont

from reports import content as C
from reports.figures import RenderedFigure
from reports.pdf_writer import PdfWriter, rgb

PAGE_W, PAGE_H = 8.27, 11.69  # A4, inches
MARGIN_X, MARGIN_TOP, MARGIN_BOTTOM = 0.7, 0.7, 0.75
CONTENT_W = PAGE_W - 2 * MARGIN_X
FONT = "DejaVu Sans"
INK, MUTED, LINE, PANEL = "#111827", "#4b5563", "#d1d5db", "#f3f4f6"
PT = 72.0  # points per inch
#: corner radius of rounded boxes, in inches
ROUNDING = 0.05


@dataclass
class Run:
    """A paragraph inside a cell or block, with its style."""

    text: str
    size: float = 9.0
    weight: str = "normal"
    color: str = INK
    family: str = FONT
    style: str = "normal"
    pill: tuple[str, str] | None = None  # (text colour, background) for status badges


@dataclass
class Cell:
    """A table cell: paragraphs stacked top to bottom."""

    runs: list[Run] = field(default_factory=list)


class TextMeasure:
    """Text widths in inches from the fonts' unhinted advance widths (cached per glyph).

    Rendering text to measure it is slow, and hinting at small sizes rounds every glyph up
    and wraps lines early; summed advances match the PDF layout to within about 1%.
    """

    def __init__(self) -> None:
        self._fonts: dict[tuple, ft2font.FT2Font] = {}
        self._paths: dict[tuple, str] = {}
        self._ascent: dict[tuple, float] = {}
        self._adv: dict[tuple, float] = {}

    def _font(self, run: Run) -> tuple[tuple, ft2font.FT2Font]:
        key = (run.family, run.weight, run.style)
        font = self._fonts.get(key)
        if font is None:
            prop = FontProperties(family=run.family, weight=run.weight, style=run.style)
            self._paths[key] = findfont(prop)
            font = ft2font.FT2Font(self._paths[key])
            font.set_size(100, 72)
            glyph = font.load_char(ord("l"), flags=ft2font.LoadFlags.NO_HINTING)
            self._ascent[key] = glyph.horiBearingY / 64 / 100  # in em
            self._fonts[key] = font
        return key, font

    def path(self, run: Run) -> str:
        """The font file `run` is drawn with."""
        key, _ = self._font(run)
        return self._paths[key]

    def ascent(self, run: Run) -> float:
        """From the top of a line of `run` to its baseline, in inches (the height of 'l')."""
        key, _ = self._font(run)
        return self._ascent[key] * run.size / PT

    def advance(self, text: str, run: Run) -> float:
        """The width of `text` as drawn: its glyphs' advances summed, in inches."""
        key, font = self._font(run)
        em = 0.0
        for ch in text:
            a = self._adv.get((key, ch))
            if a is None:
                glyph = font.load_char(ord(ch), flags=ft2font.LoadFlags.NO_HINTING)
                a = glyph.linearHoriAdvance / 65536 / 100
                self._adv[(key, ch)] = a
            em += a
        return em * run.size / PT

    def width(self, text: str, run: Run) -> float:
        """`advance` with 1% to spare (what the layout reserves)."""
        return self.advance(text, run) * 1.01

    def wrap(self, text: str, run: Run, width: float) -> list[str]:
        """Greedy word wrap; words wider than the column (hashes) are cut by characters."""
        lines: list[str] = []
        for para in text.split("\n"):
            cur = ""
            for word in para.split(" "):
                trial = word if not cur else f"{cur} {word}"
                if self.width(trial, run) <= width:
                    cur = trial
                    continue
                if cur:
                    lines.append(cur)
                cur = ""
                while self.width(word, run) > width and len(word) > 1:
                    cut = len(word)
                    while cut > 1 and self.width(word[:cut], run) > width:
                        cut = max(1, int(cut * 0.8)) if cut > 8 else cut - 1
                    lines.append(word[:cut])
                    word = word[cut:]
                cur = word
            lines.append(cur)
        return lines


def line_height(run: Run) -> float:
    """Height of one line of `run`, in inches."""
    return run.size * 1.32 / 72.0


class PdfDocument:
    """Flowing layout on A4 pages; coordinates in inches from the top-left corner."""

    def __init__(self, pdf: PdfWriter, footer: str) -> None:
        self.pdf, self.footer = pdf, footer
        self.m = TextMeasure()
        self.started = False
        self.y = 0.0
        self.page_no = 0

    # -- pages
    def new_page(self) -> None:
        self.pdf.new_page()
        self.started = True
        self.page_no += 1
        self.y = MARGIN_TOP
        self.text(MARGIN_X, PAGE_H - 0.45, self.footer, Run(self.footer, 7.5, color=MUTED))
        self.text(PAGE_W - MARGIN_X, PAGE_H - 0.45, f"page {self.page_no}",
                  Run("", 7.5, color=MUTED), ha="right")

    @property
    def room(self) -> float:
        return PAGE_H - MARGIN_BOTTOM - self.y

    def need(self, h: float) -> None:
        if not self.started or h > self.room:
            self.new_page()

    # -- primitives (inches from the top-left corner of the page)
    def text(self, x: float, y: float, s: str, run: Run, ha: str = "left") -> None:
        """`s` in the style of `run` (its text is ignored), its top at y."""
        assert self.started
        style = Run(s, run.size, run.weight, run.color, run.family, run.style)
        if ha == "right":
            x -= self.m.advance(s, style)
        baseline = y + self.m.ascent(style)
        self.pdf.text(x * PT, (PAGE_H - baseline) * PT, s, self.m.path(style), run.size,
                      rgb(run.color))

    def rect(self, x: float, y: float, w: float, h: float, color: str, *,
             edge: str | None = None, round_: bool = False) -> None:
        assert self.started
        self.pdf.rect(x * PT, (PAGE_H - y - h) * PT, w * PT, h * PT, rgb(color),
                      stroke=rgb(edge) if edge else None, lw=0.6,
                      radius=ROUNDING * PT if round_ else 0.0)

    def hline(self, y: float, x0: float = MARGIN_X, x1: float = PAGE_W - MARGIN_X,
              color: str = LINE, lw: float = 0.6) -> None:
        assert self.started
        yy = (PAGE_H - y) * PT
        self.pdf.line(x0 * PT, yy, x1 * PT, yy, rgb(color), lw)

    # -- layout of runs
    def layout(self, runs: Sequence[Run], width: float) -> list[tuple[str, Run, float]]:
        """(line, run, height) for runs wrapped to width."""
        out = []
        for run in runs:
            for line in self.m.wrap(run.text, run, width - (0.1 if run.pill else 0.0)):
                out.append((line, run, line_height(run) + (0.03 if run.pill else 0.0)))
        return out

    def draw_lines(self, x: float, y: float, lines: list[tuple[str, Run, float]]) -> float:
        for line, run, h in lines:
            if run.pill:
                w = self.m.width(line, run) + 0.12
                self.rect(x, y - 0.005, w, h - 0.02, run.pill[1], round_=True)
                self.text(x + 0.06, y + 0.012, line, Run(line, run.size, "bold", run.pill[0]))
            else:
                self.text(x, y, line, run)
            y += h
        return y

    # -- blocks
    def heading(self, s: str, level: int = 1, badge: str = "", colours: str = "") -> None:
        """A heading; `badge` a status pill after it, coloured as `STATUS_COLOURS[colours]`
        (default: the badge's own text)."""
        size = {0: 17.0, 1: 13.5, 2: 11.0}[level]
        run = Run(s, size, "bold")
        lines = self.layout([run], CONTENT_W - (1.0 if badge else 0))
        h = sum(x[2] for x in lines) + (0.28 if level <= 1 else 0.12)
        self.need(h + 1.2)  # keep a heading with what follows
        self.y += 0.14 if level == 1 else 0.06
        self.y = self.draw_lines(MARGIN_X, self.y, lines)
        if badge:
            last_w = self.m.width(lines[-1][0], run)
            fg, bg = C.STATUS_COLOURS.get(colours or badge, (INK, PANEL))
            pill = Run(badge, 7.5, "bold", fg, pill=(fg, bg))
            self.draw_lines(MARGIN_X + last_w + 0.15, self.y - lines[-1][2] + 0.04,
                            [(badge, pill, line_height(pill))])
        if level == 1:
            self.hline(self.y + 0.04, color="#9ca3af", lw=0.9)
            self.y += 0.12
        self.y += 0.04

    def para(self, s: str, size: float = 9.0, color: str = INK, *, box: str | None = None,
             bar: str | None = None, family: str = FONT, style: str = "normal",
             gap: float = 0.08) -> None:
        pad = 0.1 if (box or bar) else 0.0
        run = Run(s, size, color=color, family=family, style=style)
        lines = self.layout([run], CONTENT_W - 2 * pad - (0.05 if bar else 0))
        while lines:
            # as many lines as fit on this page
            self.need(lines[0][2] + 2 * pad + 0.02)
            take, h = 0, 2 * pad
            while take < len(lines) and h + lines[take][2] <= self.room:
                h += lines[take][2]
                take += 1
            chunk, lines = lines[:take], lines[take:]
            if box:
                self.rect(MARGIN_X, self.y, CONTENT_W, h, box, round_=True)
            if bar:
                self.rect(MARGIN_X, self.y, 0.05, h, bar)
            self.draw_lines(MARGIN_X + pad + (0.05 if bar else 0), self.y + pad, chunk)
            self.y += h
        self.y += gap

    def table(self, header: list[str] | None, rows: list[list[Cell | str]],
              widths: Sequence[float], *, size: float = 8.0, zebra: bool = False,
              header_bg: str = PANEL, key_bold: bool = False,
              spans: dict[int, Cell] | None = None) -> None:
        """Wrapped-cell table; `spans[i]` adds a full-width note row under row i."""
        total = sum(widths)
        ws = [CONTENT_W * w / total for w in widths]
        xs = [MARGIN_X + sum(ws[:i]) for i in range(len(ws))]
        padx, pady = 0.05, 0.035

        def cell(c: Cell | str, bold: bool = False, colour: str = INK) -> Cell:
            if isinstance(c, Cell):
                return c
            return Cell([Run(str(c), size, "bold" if bold else "normal", colour)])

        def lay(cells: list[Cell]) -> tuple[list[list], float]:
            laid = [self.layout(c.runs, w - 2 * padx) for c, w in zip(cells, ws)]
            h = max((sum(x[2] for x in lines) for lines in laid), default=0) + 2 * pady
            return laid, h

        head = None
        if header:
            head = lay([cell(h, True, "#374151") for h in header])

        def draw_header() -> None:
            if head is None:
                return
            laid, h = head
            self.rect(MARGIN_X, self.y, CONTENT_W, h, header_bg)
            for x, lines in zip(xs, laid):
                self.draw_lines(x + padx, self.y + pady, lines)
            self.y += h
            self.hline(self.y, color="#9ca3af")

        first_h = head[1] if head else 0
        self.need(first_h + 0.4)
        draw_header()
        for i, row in enumerate(rows):
            cells = [cell(c, key_bold and j == 0) for j, c in enumerate(row)]
            laid, h = lay(cells)
            span = (spans or {}).get(i)
            span_laid = self.layout(span.runs, CONTENT_W - 2 * padx) if span else []
            span_h = sum(x[2] for x in span_laid) + pady if span else 0.0
            if h + span_h > self.room:
                self.new_page()
                draw_header()
            if zebra and i % 2 == 1:
                self.rect(MARGIN_X, self.y, CONTENT_W, h + span_h, "#fafafa")
            for x, lines in zip(xs, laid):
                self.draw_lines(x + padx, self.y + pady, lines)
            self.y += h
            if span:
                self.draw_lines(MARGIN_X + padx, self.y - pady * 0.5, span_laid)
                self.y += span_h
            self.hline(self.y)
        self.y += 0.12

    def kv(self, facts: list[tuple[str, str]], size: float = 8.5,
           widths: Sequence[float] = (1.0, 2.4)) -> None:
        self.table(None, [[k, v] for k, v in facts], widths, size=size, key_bold=True)

    def image(self, fig: RenderedFigure, caption: str) -> None:
        w = min(CONTENT_W, fig.width_in)
        h = w * fig.height_px / fig.width_px
        cap = Run(caption, 7.8, color=MUTED)
        cap_lines = self.layout([cap], CONTENT_W - 0.4)
        cap_h = sum(x[2] for x in cap_lines)
        fits = self.room - cap_h - 0.15
        if self.started and h > fits >= 0.72 * h:
            w, h = w * fits / h, fits  # shrink a little rather than leave half a page empty
        self.need(h + cap_h + 0.15)
        x0 = MARGIN_X + (CONTENT_W - w) / 2
        self.pdf.image(fig.png, x0 * PT, (PAGE_H - self.y - h) * PT, w * PT, h * PT)
        self.y += h + 0.05
        self.y = self.draw_lines(MARGIN_X + 0.2, self.y, cap_lines) + 0.15
