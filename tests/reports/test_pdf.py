"""The PDF report (ReportLab): verdict and error headline first, text that reads back as
written (Unicode included), every font embedded as a subset, every figure embedded at its
own pixel size, a sane page count, and the same bytes for the same certificate.

The byte-level checks need nothing installed; those that read the text back use poppler's
`pdftotext`/`pdffonts`/`pdfimages` (installed in CI by `.ci/run`) and are skipped without it.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import zlib
from functools import cache
from pathlib import Path

import pytest

from certify.certificate import Certificate
from reports.figures import RenderedFigure, render_figures
from reports.pdf import render_pdf

from .. import fixtures_certificates as F
from .builders import proved_rate_certificate


@cache
def _rendered(name: str) -> tuple[Certificate, tuple[RenderedFigure, ...], bytes]:
    cert = F.ALL[name]()
    figures = tuple(render_figures(cert))
    return cert, figures, render_pdf(cert, list(figures))


def _objects(doc: bytes) -> list[bytes]:
    return re.findall(rb"\d+ 0 obj\s*(.*?)\s*endobj", doc, re.S)


def _tool(name: str) -> str:
    path = shutil.which(name)
    if path is None:
        pytest.skip(f"{name} (poppler-utils) is not installed")
    return path


def _run(tool: str, pdf: bytes, tmp_path: Path, *args: str) -> str:
    f = tmp_path / "r.pdf"
    f.write_bytes(pdf)
    return subprocess.run([_tool(tool), *args, str(f), *(["-"] if tool == "pdftotext" else [])],
                          capture_output=True, check=True, text=True).stdout


# ----------------------------------------------------------------------------- bytes

@pytest.mark.parametrize("name", ["certified", "violated"])
def test_every_figure_is_embedded_at_its_pixel_size(name):
    _, figures, pdf = _rendered(name)
    images = [o for o in _objects(pdf) if b"/Subtype /Image" in o]
    sizes = sorted((int(re.search(rb"/Width (\d+)", o).group(1)),
                    int(re.search(rb"/Height (\d+)", o).group(1))) for o in images)
    assert figures and sizes == sorted((f.width_px, f.height_px) for f in figures)
    # binary (Flate) streams, not ASCII85: a quarter smaller
    assert all(b"ASCII85Decode" not in o for o in images)


def test_every_font_is_an_embedded_truetype_subset():
    _, _, pdf = _rendered("certified")
    fonts = [o for o in _objects(pdf) if b"/Type /Font" in o and b"/BaseFont" in o]
    names = {re.search(rb"/BaseFont /([\w+-]+)", o).group(1) for o in fonts}
    assert names and all(re.fullmatch(rb"[A-Z]{6}\+DejaVuSans(-Bold)?", n) for n in names)
    assert all(b"/Subtype /TrueType" in o for o in fonts)  # no Type 1 base font (Helvetica)
    assert pdf.count(b"/FontFile2") == len(fonts)


def test_page_count_is_sane():
    for name in F.ALL:
        _, figures, pdf = _rendered(name)
        pages = len(re.findall(rb"/Type /Page\b", pdf))
        assert 3 <= pages <= 6 + 2 * len(figures), name


def test_same_certificate_same_bytes_dated_by_the_certificate():
    cert, figures, pdf = _rendered("violated")
    assert render_pdf(cert, list(figures)) == pdf
    assert b"/CreationDate (D:20250501080312+00'00')" in pdf  # created 2025-05-01T08:03:12
    assert b"/Title (certify report: vdp \\(NOT CERTIFIED\\))" in pdf


def test_without_figures_and_without_a_date():
    cert = F.inconclusive_certificate()
    cert.created = ""
    pdf = render_pdf(cert, figures=[])
    assert pdf.startswith(b"%PDF-") and pdf.rstrip().endswith(b"%%EOF")
    assert not [o for o in _objects(pdf) if b"/Subtype /Image" in o]


def test_page_streams_are_compressed_text():
    """The pages hold text operators (BT ... Tj ... ET), not outlines of glyphs."""
    _, _, pdf = _rendered("certified")
    streams = re.findall(rb"/Filter \[?\s*/FlateDecode\s*\]?.*?stream\r?\n(.*?)endstream",
                         pdf, re.S)
    text_ops = 0
    for raw in streams:
        try:
            body = zlib.decompress(raw)
        except zlib.error:
            continue
        text_ops += body.count(b" Tj") + body.count(b" TJ")
    assert text_ops > 200


# ----------------------------------------------------------------------------- read back

def _text(pdf: bytes, tmp_path: Path) -> str:
    return re.sub(r"\s+", " ", _run("pdftotext", pdf, tmp_path, "-enc", "UTF-8"))


def test_verdict_then_headline_then_checks_on_the_first_page(tmp_path):
    _, _, pdf = _rendered("certified")
    first = _text(pdf, tmp_path).split("\f")[0]
    order = [first.index(s) for s in ("CERTIFIED", "Certified error bound",
                                      "\u2016e\u2016 \u2264", "Checks", "MPDI")]
    assert order == sorted(order)


def test_unicode_and_markup_characters_read_back_as_written(tmp_path):
    cert = proved_rate_certificate()
    cert.checks["mpdi"].message += " (raise --proof-seconds & <max-boxes>)"
    text = _text(render_pdf(cert, figures=[]), tmp_path)
    for needle in ("NOT CERTIFIED", "Proved error bound (at the proved rate \u03bb_cert "
                   "\u2265 0.4586; the certificate failed at the design rate \u03bb = 2.5)",
                   "\u2016e\u2016 \u2264 1.48 for noise \u2264 0.15 after t \u2265 4.2 s",
                   "D(x\u0302, y) \u2aaf 0", "raise --proof-seconds & <max-boxes>",
                   "He{M} = (M + M\u1d40)/2"):
        assert needle in text, needle
    assert "Certified error bound" not in text


def test_fonts_and_images_as_poppler_sees_them(tmp_path):
    _, figures, pdf = _rendered("certified")
    fonts = _run("pdffonts", pdf, tmp_path).splitlines()[2:]
    assert fonts and all(re.search(r"\byes\s+yes\s+yes\b", ln) for ln in fonts), fonts
    images = [ln for ln in _run("pdfimages", pdf, tmp_path, "-list").splitlines()[2:]
              if ln.split()[2:3] == ["image"]]
    assert len(images) == len(figures)
