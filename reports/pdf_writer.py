"""A small PDF writer: pages of text, filled boxes, lines and PNG images, nothing else.

Text is real text in embedded TrueType fonts: each font is subset to the glyphs used
(`subset_truetype`: their outlines and metrics, glyph ids unchanged; no cmap, names or
layout tables, which a PDF viewer does not use), CID-keyed (Identity-H) with a ToUnicode
map, so the text can be searched and copied. A line
of text is as wide as the sum of its glyphs' advances (no kerning), which is how
`reports.pdf_layout.TextMeasure` measures it. PNG images that are 8-bit RGB and not
interlaced (what `reports.figures.figure_png` writes) are embedded with their compressed
data as it is (Flate with PNG predictors); other PNGs are decoded and compressed again.

Coordinates are PDF points (1/72 inch) from the bottom-left corner of the page. The output
depends on its input only (no dates, subset names derived from the glyphs used), so the
same document gives the same bytes.
"""

from __future__ import annotations

import hashlib
import io
import struct
import warnings
import zlib
from dataclasses import dataclass, field

RGB = tuple[float, float, float]

_NAMED = {"white": (1.0, 1.0, 1.0), "black": (0.0, 0.0, 0.0)}


def rgb(colour: str) -> RGB:
    """'#rrggbb' (or 'white' / 'black') as three floats in [0, 1]."""
    named = _NAMED.get(colour)
    if named is not None:
        return named
    c = colour.lstrip("#")
    if len(c) != 6:
        raise ValueError(f"colour {colour!r} is not #rrggbb")
    return tuple(int(c[i:i + 2], 16) / 255 for i in (0, 2, 4))  # type: ignore[return-value]


def _num(v: float) -> str:
    """A PDF number: at most 3 decimals, no exponent, no trailing zeros."""
    s = f"{v:.3f}".rstrip("0").rstrip(".")
    return "0" if s in ("-0", "") else s


def _colour(c: RGB, stroke: bool = False) -> str:
    return " ".join(_num(v) for v in c) + (" RG" if stroke else " rg")


def _text_string(s: str) -> bytes:
    """A PDF text string (document information): literal if ASCII, else UTF-16BE."""
    if all(32 <= ord(ch) < 127 for ch in s):
        esc = s.replace("\\", "\\\\").replace("(", "\\(").replace(")", "\\)")
        return f"({esc})".encode("ascii")
    return b"<FEFF" + s.encode("utf-16-be").hex().upper().encode("ascii") + b">"


@dataclass
class _Font:
    """A font in use: its file, the characters drawn with it, its resource name."""

    path: str
    name: str  # resource name, /F1 ...
    chars: set[str] = field(default_factory=set)
    gid: dict[str, int] = field(default_factory=dict)  # char -> glyph id in the subset


@dataclass
class _Image:
    name: str  # resource name, /Im1 ...
    width: int
    height: int
    data: bytes
    predictor: bool  # data is PNG IDAT (Flate with PNG predictors)


def _png_rgb(png: bytes) -> tuple[int, int, bytes, bool]:
    """(width, height, Flate data, whether it carries PNG predictors) of a PNG."""
    if png[:8] != b"\x89PNG\r\n\x1a\n":
        raise ValueError("not a PNG")
    pos, idat, head = 8, [], None
    while pos + 8 <= len(png):
        (length,) = struct.unpack(">I", png[pos:pos + 4])
        kind = png[pos + 4:pos + 8]
        data = png[pos + 8:pos + 8 + length]
        if kind == b"IHDR":
            head = struct.unpack(">IIBBBBB", data)
        elif kind == b"IDAT":
            idat.append(data)
        elif kind == b"IEND":
            break
        pos += 12 + length
    if head is None:
        raise ValueError("PNG without IHDR")
    w, h, depth, colour_type, _, _, interlace = head
    if depth == 8 and colour_type == 2 and interlace == 0:
        return w, h, b"".join(idat), True
    from PIL import Image  # any other PNG: decode to RGB, compress again

    img = Image.open(io.BytesIO(png)).convert("RGB")
    return img.width, img.height, zlib.compress(img.tobytes(), 6), False


class PdfWriter:
    """Pages of drawing operations, written out as one PDF by `close`."""

    def __init__(self, width: float, height: float, info: dict[str, str] | None = None):
        self.width, self.height = width, height
        self.info = dict(info or {})
        self.pages: list[list[tuple]] = []
        self.fonts: dict[str, _Font] = {}
        self.images: list[_Image] = []

    # -- drawing
    def new_page(self) -> None:
        self.pages.append([])

    def _ops(self) -> list[tuple]:
        if not self.pages:
            self.new_page()
        return self.pages[-1]

    def text(self, x: float, y: float, s: str, font_path: str, size: float,
             colour: RGB) -> None:
        """`s` with its baseline starting at (x, y), in the TrueType font at `font_path`."""
        font = self.fonts.get(font_path)
        if font is None:
            font = self.fonts[font_path] = _Font(font_path, f"F{len(self.fonts) + 1}")
        font.chars.update(s)
        self._ops().append(("text", font, size, x, y, s, colour))

    def rect(self, x: float, y: float, w: float, h: float, fill: RGB | None, *,
             stroke: RGB | None = None, lw: float = 0.6, radius: float = 0.0) -> None:
        """A box with its lower-left corner at (x, y), filled and/or outlined; corners
        rounded by `radius` points."""
        r = max(0.0, min(radius, w / 2, h / 2))
        if r > 0:
            k = 0.5523 * r  # cubic Bezier approximation of a quarter circle
            x1, y1 = x + w, y + h
            path = (f"{_num(x + r)} {_num(y)} m {_num(x1 - r)} {_num(y)} l "
                    f"{_num(x1 - r + k)} {_num(y)} {_num(x1)} {_num(y + r - k)} {_num(x1)} "
                    f"{_num(y + r)} c {_num(x1)} {_num(y1 - r)} l "
                    f"{_num(x1)} {_num(y1 - r + k)} {_num(x1 - r + k)} {_num(y1)} "
                    f"{_num(x1 - r)} {_num(y1)} c {_num(x + r)} {_num(y1)} l "
                    f"{_num(x + r - k)} {_num(y1)} {_num(x)} {_num(y1 - r + k)} {_num(x)} "
                    f"{_num(y1 - r)} c {_num(x)} {_num(y + r)} l "
                    f"{_num(x)} {_num(y + r - k)} {_num(x + r - k)} {_num(y)} {_num(x + r)} "
                    f"{_num(y)} c h")
        else:
            path = f"{_num(x)} {_num(y)} {_num(w)} {_num(h)} re"
        paint = {(True, True): "B", (True, False): "f", (False, True): "S"}.get(
            (fill is not None, stroke is not None))
        if paint is None:
            return
        parts = ["q"]
        if fill is not None:
            parts.append(_colour(fill))
        if stroke is not None:
            parts += [_colour(stroke, stroke=True), f"{_num(lw)} w"]
        parts += [path, paint, "Q"]
        self._ops().append(("raw", " ".join(parts)))

    def line(self, x0: float, y0: float, x1: float, y1: float, colour: RGB,
             lw: float) -> None:
        self._ops().append(("raw", f"q {_colour(colour, stroke=True)} {_num(lw)} w "
                                   f"{_num(x0)} {_num(y0)} m {_num(x1)} {_num(y1)} l S Q"))

    def image(self, png: bytes, x: float, y: float, w: float, h: float) -> None:
        """A PNG image filling the box with lower-left corner (x, y), w x h points."""
        pw, ph, data, predictor = _png_rgb(png)
        img = _Image(f"Im{len(self.images) + 1}", pw, ph, data, predictor)
        self.images.append(img)
        self._ops().append(("raw", f"q {_num(w)} 0 0 {_num(h)} {_num(x)} {_num(y)} cm "
                                   f"/{img.name} Do Q"))

    # -- output
    def close(self) -> bytes:
        """The whole document as PDF bytes."""
        out = _Objects()
        catalog, pages_id = out.reserve(), out.reserve()
        font_refs = {f.name: self._write_font(out, f) for f in self.fonts.values()}
        image_refs = {}
        for img in self.images:
            parms = (f" /DecodeParms << /Predictor 15 /Colors 3 /BitsPerComponent 8 "
                     f"/Columns {img.width} >>" if img.predictor else "")
            image_refs[img.name] = out.stream(
                f"/Type /XObject /Subtype /Image /Width {img.width} /Height {img.height} "
                f"/ColorSpace /DeviceRGB /BitsPerComponent 8 /Filter /FlateDecode{parms}",
                img.data)
        resources = out.add(
            "<< /ProcSet [/PDF /Text /ImageC] /Font << "
            + " ".join(f"/{k} {v} 0 R" for k, v in font_refs.items()) + " >> /XObject << "
            + " ".join(f"/{k} {v} 0 R" for k, v in image_refs.items()) + " >> >>")
        kids = []
        for ops in self.pages or [[]]:
            content = out.stream("/Filter /FlateDecode",
                                 zlib.compress(self._content(ops).encode("latin-1"), 6))
            kids.append(out.add(
                f"<< /Type /Page /Parent {pages_id} 0 R /MediaBox [0 0 {_num(self.width)} "
                f"{_num(self.height)}] /Resources {resources} 0 R /Contents {content} 0 R >>"))
        out.put(pages_id, f"<< /Type /Pages /Kids [{' '.join(f'{k} 0 R' for k in kids)}] "
                          f"/Count {len(kids)} >>")
        out.put(catalog, f"<< /Type /Catalog /Pages {pages_id} 0 R >>")
        info = out.add(b"<< " + b" ".join(b"/" + k.encode("ascii") + b" " + _text_string(v)
                                          for k, v in self.info.items() if v) + b" >>")
        return out.finish(catalog, info)

    def _content(self, ops: list[tuple]) -> str:
        parts = []
        for op in ops:
            if op[0] == "raw":
                parts.append(op[1])
                continue
            _, font, size, x, y, s, colour = op
            glyphs = "".join(f"{font.gid.get(ch, 0):04X}" for ch in s)
            parts.append(f"BT /{font.name} {_num(size)} Tf {_colour(colour)} {_num(x)} "
                         f"{_num(y)} Td <{glyphs}> Tj ET")
        return "\n".join(parts)

    def _write_font(self, out: _Objects, font: _Font) -> int:
        """Subset, embed and describe a font; fills `font.gid`; returns its object id."""
        from matplotlib import ft2font

        face = ft2font.FT2Font(font.path)
        ps_name = face.postscript_name or "Font"
        for ch in sorted(font.chars):
            gid = face.get_char_index(ord(ch))
            font.gid[ch] = gid
            if gid == 0 and ch not in "\n\r":
                warnings.warn(f"Glyph {ord(ch)} ({ch!r}) missing from font {ps_name}",
                              stacklevel=3)
        with open(font.path, "rb") as fh:
            data, advances = subset_truetype(fh.read(), set(font.gid.values()))
        scale = 1000 / face.units_per_EM
        post = face.get_sfnt_table("post") or {}
        angle = post.get("italicAngle", (0, 0))
        italic = angle[0] + angle[1] / 65536 if isinstance(angle, tuple) else float(angle)
        tag = "".join(chr(65 + b % 26) for b in hashlib.sha256(
            (ps_name + "".join(sorted(font.chars))).encode("utf-8")).digest()[:6])
        base = f"{tag}+{ps_name}"
        file_id = out.stream(f"/Length1 {len(data)} /Filter /FlateDecode",
                             zlib.compress(data, 6))
        desc = out.add(
            f"<< /Type /FontDescriptor /FontName /{base} /Flags {32 | (64 if italic else 0)} "
            f"/FontBBox [{' '.join(_num(v * scale) for v in face.bbox)}] "
            f"/ItalicAngle {_num(italic)} /Ascent {_num(face.ascender * scale)} "
            f"/Descent {_num(face.descender * scale)} /CapHeight "
            f"{_num(face.ascender * scale)} /StemV 80 /FontFile2 {file_id} 0 R >>")
        w_array = " ".join(f"{g} [{_num(advances[g] * scale)}]"
                           for g in sorted(set(font.gid.values())))
        cid = out.add(
            f"<< /Type /Font /Subtype /CIDFontType2 /BaseFont /{base} /CIDSystemInfo "
            f"<< /Registry (Adobe) /Ordering (Identity) /Supplement 0 >> /FontDescriptor "
            f"{desc} 0 R /DW 1000 /W [{w_array}] /CIDToGIDMap /Identity >>")
        to_unicode = out.stream("/Filter /FlateDecode", zlib.compress(
            _to_unicode(font.gid).encode("ascii"), 6))
        return out.add(
            f"<< /Type /Font /Subtype /Type0 /BaseFont /{base} /Encoding /Identity-H "
            f"/DescendantFonts [{cid} 0 R] /ToUnicode {to_unicode} 0 R >>")


#: the tables of an embedded TrueType font: outlines, metrics and the hinting programs the
#: outlines' instructions call (a PDF viewer needs no cmap, names or layout tables: text is
#: drawn by glyph id)
_KEEP = (b"cvt ", b"fpgm", b"glyf", b"head", b"hhea", b"hmtx", b"loca", b"maxp", b"prep")


def _checksum(table: bytes) -> int:
    table += b"\0" * (-len(table) % 4)
    return sum(struct.unpack(f">{len(table) // 4}I", table)) & 0xFFFFFFFF


def subset_truetype(data: bytes, gids: set[int]) -> tuple[bytes, dict[int, int]]:
    """(a TrueType font, advance width in font units per glyph id of `gids`).

    The font keeps the outlines of `gids`, of the glyphs their composite outlines are built
    of and of .notdef, every other glyph empty: glyph ids are those of `data`, so a PDF draws
    by them unchanged (CIDToGIDMap /Identity). Only the `_KEEP` tables are kept.
    """
    (count,) = struct.unpack(">H", data[4:6])
    tables = {}
    for i in range(count):
        tag, _, off, length = struct.unpack(">4sIII", data[12 + 16 * i:28 + 16 * i])
        tables[tag] = data[off:off + length]
    head, glyf = tables[b"head"], tables[b"glyf"]
    (n,) = struct.unpack(">H", tables[b"maxp"][4:6])
    long_loca = struct.unpack(">h", head[50:52])[0] == 1
    offs = struct.unpack(f">{n + 1}{'I' if long_loca else 'H'}",
                         tables[b"loca"][:(n + 1) * (4 if long_loca else 2)])
    offs = offs if long_loca else tuple(2 * o for o in offs)
    need = {0} | {g for g in gids if 0 <= g < n}
    todo = list(need)
    while todo:  # composite glyphs: add their components
        g = todo.pop()
        body = glyf[offs[g]:offs[g + 1]]
        if len(body) < 10 or struct.unpack(">h", body[:2])[0] >= 0:
            continue
        pos, more = 10, True
        while more:
            flags, comp = struct.unpack(">HH", body[pos:pos + 4])
            pos += 4 + (4 if flags & 0x0001 else 2)
            pos += 2 if flags & 0x0008 else 4 if flags & 0x0040 else 8 if flags & 0x0080 else 0
            if comp < n and comp not in need:
                need.add(comp)
                todo.append(comp)
            more = bool(flags & 0x0020)
    new_glyf, new_offs = bytearray(), []
    for g in range(n):
        new_offs.append(len(new_glyf))
        if g in need:
            body = glyf[offs[g]:offs[g + 1]]
            new_glyf += body + b"\0" * (-len(body) % 4)
    new_offs.append(len(new_glyf))
    keep = {tag: tables[tag] for tag in _KEEP if tag in tables}
    keep[b"glyf"] = bytes(new_glyf)
    keep[b"loca"] = struct.pack(f">{n + 1}I", *new_offs)
    # long offsets; checkSumAdjustment 0 while the checksums are summed
    keep[b"head"] = head[:8] + bytes(4) + head[12:50] + struct.pack(">h", 1) + head[52:]
    tags = sorted(keep)
    sel = len(tags).bit_length() - 1
    out = bytearray(struct.pack(">IHHHH", 0x00010000, len(tags), 16 << sel, sel,
                                16 * len(tags) - (16 << sel)))
    offset, where = 12 + 16 * len(tags), {}
    for tag in tags:
        out += struct.pack(">4sIII", tag, _checksum(keep[tag]), offset, len(keep[tag]))
        where[tag] = offset
        offset += len(keep[tag]) + (-len(keep[tag]) % 4)
    for tag in tags:
        out += keep[tag] + b"\0" * (-len(keep[tag]) % 4)
    adjust = (0xB1B0AFBA - _checksum(bytes(out))) & 0xFFFFFFFF
    out[where[b"head"] + 8:where[b"head"] + 12] = struct.pack(">I", adjust)
    (metrics,) = struct.unpack(">H", tables[b"hhea"][34:36])
    hmtx = tables[b"hmtx"]
    advances = {g: struct.unpack(">H", hmtx[4 * min(g, metrics - 1):][:2])[0] for g in gids}
    return bytes(out), advances


def _to_unicode(gid: dict[str, int]) -> str:
    """The ToUnicode CMap: glyph id -> the character it draws."""
    pairs = sorted({g: ch for ch, g in gid.items()}.items())
    chunks = []
    for i in range(0, len(pairs), 100):  # at most 100 entries per bfchar block
        block = pairs[i:i + 100]
        chunks.append(f"{len(block)} beginbfchar\n" + "\n".join(
            f"<{g:04X}> <{ch.encode('utf-16-be').hex().upper()}>" for g, ch in block)
            + "\nendbfchar")
    return ("/CIDInit /ProcSet findresource begin\n12 dict begin\nbegincmap\n"
            "/CIDSystemInfo << /Registry (Adobe) /Ordering (UCS) /Supplement 0 >> def\n"
            "/CMapName /Adobe-Identity-UCS def\n/CMapType 2 def\n"
            "1 begincodespacerange\n<0000> <FFFF>\nendcodespacerange\n"
            + "\n".join(chunks)
            + "\nendcmap\nCMapName currentdict /CMap defineresource pop\nend\nend")


class _Objects:
    """Numbered PDF objects and the file around them (header, xref table, trailer)."""

    def __init__(self) -> None:
        self.bodies: dict[int, bytes] = {}
        self.count = 0

    def reserve(self) -> int:
        self.count += 1
        return self.count

    def put(self, oid: int, body: str | bytes) -> None:
        self.bodies[oid] = body.encode("latin-1") if isinstance(body, str) else body

    def add(self, body: str | bytes) -> int:
        oid = self.reserve()
        self.put(oid, body)
        return oid

    def stream(self, dictionary: str, data: bytes) -> int:
        return self.add(f"<< {dictionary} /Length {len(data)} >>\nstream\n".encode("latin-1")
                        + data + b"\nendstream")

    def finish(self, root: int, info: int) -> bytes:
        buf = io.BytesIO()
        buf.write(b"%PDF-1.4\n%\xe2\xe3\xcf\xd3\n")
        offsets = [0] * (self.count + 1)
        for oid in range(1, self.count + 1):
            offsets[oid] = buf.tell()
            buf.write(f"{oid} 0 obj\n".encode("ascii") + self.bodies[oid] + b"\nendobj\n")
        xref = buf.tell()
        buf.write(f"xref\n0 {self.count + 1}\n0000000000 65535 f \n".encode("ascii"))
        for oid in range(1, self.count + 1):
            buf.write(f"{offsets[oid]:010d} 00000 n \n".encode("ascii"))
        buf.write(f"trailer\n<< /Size {self.count + 1} /Root {root} 0 R /Info {info} 0 R >>\n"
                  f"startxref\n{xref}\n%%EOF\n".encode("ascii"))
        return buf.getvalue()
