"""The PDF writer behind the PDF report, read back without poppler: a well-formed file (every
cross-reference points at its object), text that maps back to its characters through the
fonts' ToUnicode maps (so it can be searched), fonts embedded as TrueType subsets, PNGs
embedded as they are, and the same bytes for the same document."""

from __future__ import annotations

import io
import re
import struct
import zlib

import numpy as np
import pytest
from fontTools.ttLib import TTFont
from matplotlib.font_manager import FontProperties, findfont
from PIL import Image

from reports.pdf_writer import PdfWriter, rgb

SANS = findfont(FontProperties(family="DejaVu Sans"))
BOLD = findfont(FontProperties(family="DejaVu Sans", weight="bold"))
LINES = ["CERTIFIED: max \u03bb_max(D) \u2264 -0.5", "x\u0302 \u2016e\u2016 \u00b7 10\u207b\u00b2",
         "plain ASCII (with parentheses) and \\ backslash"]


def _png(mode: str = "RGB", size: tuple[int, int] = (40, 30)) -> bytes:
    rng = np.random.default_rng(0)
    arr = rng.integers(0, 255, (size[1], size[0], len(mode)), dtype=np.uint8)
    buf = io.BytesIO()
    Image.fromarray(arr, mode).save(buf, format="png")
    return buf.getvalue()


def _document() -> bytes:
    pdf = PdfWriter(595.0, 842.0, {"Title": "t", "Subject": "\u03bb \u2264 0"})
    pdf.new_page()
    for i, line in enumerate(LINES):
        pdf.text(50, 800 - 20 * i, line, BOLD if i == 0 else SANS, 9.0, rgb("#111827"))
    pdf.rect(40, 600, 200, 50, rgb("#f3f4f6"), stroke=rgb("#9ca3af"), radius=4)
    pdf.line(40, 590, 240, 590, rgb("#d1d5db"), 0.6)
    pdf.new_page()
    pdf.image(_png(), 50, 400, 300, 225)
    pdf.image(_png("RGBA"), 50, 100, 300, 225)
    return pdf.close()


def _objects(doc: bytes) -> dict[int, bytes]:
    return {int(m.group(1)): m.group(2)
            for m in re.finditer(rb"(\d+) 0 obj\n(.*?)\nendobj\n", doc, re.S)}


def _raw(body: bytes) -> bytes:
    return body[body.index(b"stream\n") + 7:body.rindex(b"\nendstream")]


def _stream(body: bytes) -> bytes:
    data = _raw(body)
    return zlib.decompress(data) if b"/FlateDecode" in body.split(b"stream\n")[0] else data


def _idat(png: bytes) -> bytes:
    """The concatenated IDAT data of a PNG."""
    pos, out = 8, []
    while pos < len(png):
        (length,) = struct.unpack(">I", png[pos:pos + 4])
        if png[pos + 4:pos + 8] == b"IDAT":
            out.append(png[pos + 8:pos + 8 + length])
        pos += 12 + length
    return b"".join(out)


def test_cross_references_point_at_their_objects() -> None:
    doc = _document()
    assert doc.startswith(b"%PDF-1.4") and doc.rstrip().endswith(b"%%EOF")
    start = int(doc.rsplit(b"startxref\n", 1)[1].split()[0])
    assert doc[start:start + 4] == b"xref"
    table = doc[start:].split(b"trailer")[0].split(b"\n")
    count = int(table[1].split()[1])
    offsets = [int(row.split()[0]) for row in table[3:3 + count - 1]]
    for oid, off in enumerate(offsets, start=1):
        assert doc[off:].startswith(f"{oid} 0 obj".encode())
    assert len(_objects(doc)) == count - 1
    assert doc == _document()  # deterministic


def test_text_reads_back_through_to_unicode() -> None:
    doc = _document()
    objs = _objects(doc)
    fonts = {}  # resource name -> {glyph id: character}
    resources = next(b for b in objs.values() if b.startswith(b"<< /ProcSet"))
    for name, ref in re.findall(rb"/(F\d+) (\d+) 0 R", resources):
        font = objs[int(ref)]
        assert b"/Subtype /Type0" in font and b"/Identity-H" in font
        cmap = _stream(objs[int(re.search(rb"/ToUnicode (\d+) 0 R", font).group(1))])
        fonts[name.decode()] = {int(g, 16): bytes.fromhex(u.decode()).decode("utf-16-be")
                                for g, u in re.findall(rb"<([0-9A-F]{4})> <([0-9A-F]+)>",
                                                       cmap)}
    pages = [b for b in objs.values() if b.startswith(b"<< /Type /Page ")]
    content = _stream(objs[int(re.search(rb"/Contents (\d+) 0 R", pages[0]).group(1))])
    shown = [
        "".join(fonts[f.decode()][int(h[i:i + 4], 16)] for i in range(0, len(h), 4))
        for f, h in re.findall(rb"/(F\d+) [\d.]+ Tf .*? <([0-9A-F]*)> Tj", content)]
    assert shown == LINES


def test_fonts_are_truetype_subsets_with_the_glyphs_drawn() -> None:
    """Each embedded font reads as TrueType, keeps every glyph id of the original, and has
    outlines for the glyphs drawn with it (and the glyphs those are built of) only."""
    objs = _objects(_document())
    descriptors = [b for b in objs.values() if b.startswith(b"<< /Type /FontDescriptor")]
    assert len(descriptors) == 2  # regular and bold, each once
    drawn = {SANS: set("".join(LINES[1:])) - {" "}, BOLD: set(LINES[0]) - {" "}}
    for desc in descriptors:
        assert re.search(rb"/FontName /[A-Z]{6}\+DejaVuSans", desc)
        path = BOLD if b"DejaVuSans-Bold" in desc else SANS
        body = objs[int(re.search(rb"/FontFile2 (\d+) 0 R", desc).group(1))]
        tt = TTFont(io.BytesIO(_stream(body)))
        full = TTFont(path)
        assert tt["maxp"].numGlyphs == full["maxp"].numGlyphs  # ids unchanged
        assert "GSUB" not in tt and "cmap" not in tt
        glyf, names = tt["glyf"], tt.getGlyphOrder()
        cmap = full.getBestCmap()
        for ch in drawn[path]:  # by glyph id: the subset has no glyph names
            assert glyf[names[full.getGlyphID(cmap[ord(ch)])]].numberOfContours != 0, ch
        with_outline = [g for g in names if glyf[g].numberOfContours != 0]
        assert len(with_outline) <= len(drawn[path]) + 6  # .notdef and components


def test_png_data_is_embedded_as_it_is_and_other_pngs_are_decoded() -> None:
    objs = _objects(_document())
    images = [b for b in objs.values() if b"/Subtype /Image" in b]
    assert len(images) == 2
    direct, decoded = images
    assert b"/Predictor 15" in direct and _raw(direct) == _idat(_png())
    assert b"/Predictor" not in decoded
    rgba = np.asarray(Image.open(io.BytesIO(_png("RGBA"))).convert("RGB"))
    raw = _stream(decoded)
    assert raw == rgba.tobytes()


def test_a_character_missing_from_the_font_is_said() -> None:
    pdf = PdfWriter(100.0, 100.0)
    pdf.text(10, 10, "a\u6f22", SANS, 9.0, rgb("black"))  # no CJK in DejaVu Sans
    with pytest.warns(UserWarning, match="missing from font"):
        pdf.close()
