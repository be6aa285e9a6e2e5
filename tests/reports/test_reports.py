"""Reports: HTML, PDF, JUnit and JSON rendered from hand-built certificates.

The certificates come from `tests/fixtures_certificates.py` (certified, the paper-preset VdP
that is NOT CERTIFIED, and an INCONCLUSIVE Duffing); rendering is done once per certificate
and shared by the tests of this module.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import re
import shutil
import subprocess
import warnings
import xml.etree.ElementTree as ET
from html.parser import HTMLParser
from pathlib import Path

import pytest

from certify.certificate import Certificate  # noqa: E402
from certify.figuredata import FigureData, GridMap  # noqa: E402
from certify.results import Status  # noqa: E402
from reports import content as C  # noqa: E402
from reports import figures as figmod  # noqa: E402
from reports import render_html, render_junit, render_reports, write_reports  # noqa: E402

from .. import fixtures_certificates as F  # noqa: E402

NAMES = list(F.ALL)
_CACHE: dict[str, tuple[Certificate, dict[str, bytes], list[str]]] = {}


def rendered(name: str) -> tuple[Certificate, dict[str, bytes], list[str]]:
    """(certificate, {html, pdf, junit, json} bytes, warnings) rendered once per module."""
    if name not in _CACHE:
        cert = F.ALL[name]()
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            data = render_reports(cert, html=True, pdf=True, junit=True, json=True)
        _CACHE[name] = (cert, data, [str(w.message) for w in caught])
    return _CACHE[name]


class _Collector(HTMLParser):
    """Text, attributes and a tag-balance check of an HTML document."""

    VOID = {"meta", "img", "br", "hr", "col", "link", "input", "source", "wbr"}

    def __init__(self) -> None:
        super().__init__(convert_charrefs=True)
        self.text: list[str] = []
        self.attrs: list[tuple[str, str, str]] = []
        self.stack: list[str] = []
        self.errors: list[str] = []
        self.tags: list[str] = []

    def handle_starttag(self, tag, attrs):
        self.tags.append(tag)
        for k, v in attrs:
            self.attrs.append((tag, k, v or ""))
        if tag not in self.VOID:
            self.stack.append(tag)

    def handle_endtag(self, tag):
        if not self.stack or self.stack[-1] != tag:
            self.errors.append(f"unbalanced </{tag}> (open: {self.stack[-3:]})")
        else:
            self.stack.pop()

    def handle_data(self, data):
        self.text.append(data)


def parse_html(doc: str) -> _Collector:
    p = _Collector()
    p.feed(doc)
    p.close()
    return p


def _norm(s: str) -> str:
    return re.sub(r"\s+", " ", s)


# ----------------------------------------------------------------------------- content

def test_number_formatting() -> None:
    assert C.fmt(None) == "\u2014"
    assert C.fmt(7.7, signed=True) == "+7.7"
    assert C.fmt(-1.35) == "-1.35"
    assert C.fmt(6.0, signed=True) == "+6"
    assert C.fmt(0.0) == "0"
    assert C.fmt(1e-5) == "1.000e-5"
    assert C.fmt(-2.1e-9, 3, signed=True) == "-2.10e-9"
    assert C.fmt(1234567.0) == "1.235e6"
    assert C.fmt(2_000_000) == "2,000,000"
    assert C.fmt(float("nan")) == "NaN" and C.fmt("NaN") == "NaN"
    assert C.fmt(float("inf"), signed=True) == "+\u221e"
    assert C.fmt(0.123456789) == "0.1235"
    assert C.fmt(True) == "yes"
    assert C.fmt_none(None, "not proved") == "\u2014 (not proved)"


def test_check_rows_cover_every_check_and_missing_required() -> None:
    cert = F.violated_vdp_certificate()
    names = [r.name for r in C.check_rows(cert)]
    assert names == ["necessary", "mpdi", "rate", "residual", "lipschitz", "bounds",
                     "simulation"]
    cert.required = ["mpdi", "metric"]  # required but never run: reported as SKIPPED
    rows = {r.name: r for r in C.check_rows(cert)}
    assert rows["metric"].status == "SKIPPED" and rows["metric"].required
    vdp = rows["mpdi"]
    assert vdp.sampled.value == "+7.7"
    assert vdp.proved.value == "\u2014" and "counterexample" in vdp.proved.note


# ----------------------------------------------------------------------------- HTML

@pytest.mark.parametrize("name", NAMES)
@pytest.mark.slow
def test_html_parses_and_shows_verdict_and_every_number(name: str) -> None:
    cert, data, _ = rendered(name)
    doc = data["html"].decode("utf-8")
    p = parse_html(doc)
    assert not p.errors, p.errors[:5]
    assert not p.stack, f"unclosed tags {p.stack}"
    text = _norm(" ".join(p.text))
    assert cert.verdict in text and cert.summary in text
    # the verdict line is the first thing in the body after the title
    assert text.index(cert.verdict) < text.index("Checks")
    for row in C.check_rows(cert):
        assert row.status in text
        for side in (row.sampled, row.proved):
            assert _norm(side.value) in text, (row.name, side.value)
            if side.note:
                assert side.note in text
        assert _norm(row.setting) in text, row.setting
        assert _norm(row.message) in text
    assert cert.checkpoint["sha256"] in text
    assert "rate 2\u03bb" in text  # the contraction-rate convention, stated
    for version in cert.versions.values():
        assert version in text


def test_html_known_numbers_of_the_paper_preset() -> None:
    _, data, _ = rendered("violated")
    text = _norm(" ".join(parse_html(data["html"].decode()).text))
    for needle in ("NOT CERTIFIED", "+7.7", "-1.35", "+6", "-0.5", "18", "(0, -3)",
                   "not needed: counterexample found", "0.4187", "12.34 (lipsdp)", "1874",
                   "9.821", "no error bound", "Theorem 3", "4 of 4 runs exit",
                   "x leaves X: |x2| = 3.03 at t = 0.25"):
        assert needle in text, needle
    # the necessary condition's own explanation paragraph is shown
    assert "no gain, however trained" in text


@pytest.mark.parametrize("name", NAMES)
def test_html_is_self_contained(name: str) -> None:
    cert, data, _ = rendered(name)
    doc = data["html"].decode("utf-8")
    p = parse_html(doc)
    for tag, key, value in p.attrs:
        if key in ("src", "href", "srcset", "data", "action", "poster"):
            assert value.startswith(("data:", "#")), (tag, key, value[:80])
        assert "http://" not in value and "https://" not in value, (tag, key, value[:80])
    assert "@import" not in doc
    assert not re.search(r"url\(\s*['\"]?(https?:)?//", doc)
    assert "<link" not in doc and "<script" not in doc
    # one embedded PNG per figure with data
    imgs = [v for t, k, v in p.attrs if t == "img" and k == "src"]
    assert all(v.startswith("data:image/png;base64,") for v in imgs)
    # violated: no prover picture (a counterexample was found, no proof attempted)
    # certified: no residual map either (zero by construction); the trajectories are drawn
    # only on request (--trajectories)
    assert len(imgs) == {"certified": 5, "violated": 5, "inconclusive": 6}[name]


def test_html_sections_present() -> None:
    _, data, _ = rendered("certified")
    p = parse_html(data["html"].decode())
    ids = {v for t, k, v in p.attrs if k == "id"}
    for anchor in ("verdict", "checks", "system", "mpdi", "rate", "necessary", "metric",
                   "residual", "lipschitz", "bounds", "simulation", "settings",
                   "fig-mpdi_map", "fig-prover", "fig-necessary_map",
                   "fig-lipschitz", "fig-bounds"):
        assert anchor in ids, anchor
    assert "fig-simulation" not in ids  # trajectories: on request
    text = _norm(" ".join(p.text))
    assert "Validity conditions" in text and "(c) the measurement noise" in text
    assert "Boxes per second" in text and "184,733" in text


@pytest.mark.slow
def test_missing_figure_data_is_skipped() -> None:
    cert = F.violated_vdp_certificate()
    # malformed: 1 value for a 2 x 1 grid
    cert.figures = FigureData(mpdi_map=GridMap(x=[0.0, 1.0], y=[0.0], values=[[1.0]]))
    cert.checks["simulation"].runs = []
    doc = render_html(cert)
    p = parse_html(doc)
    imgs = [v for t, k, v in p.attrs if t == "img" and k == "src"]
    # only the Lipschitz bar chart has data (it comes from the check itself)
    assert len(imgs) == 1
    assert 'id="fig-lipschitz"' in doc and 'id="fig-mpdi_map"' not in doc


@pytest.mark.slow
def test_round_trip_through_json_gives_the_same_html() -> None:
    cert, data, _ = rendered("inconclusive")  # has NaN in a figure map
    again = Certificate.from_dict(json.loads(cert.to_json()))
    assert render_html(again).encode("utf-8") == data["html"]


def test_figure_data_is_typed_and_nan_survives_json() -> None:
    """Figure arrays are floats (NaN where undefined), in memory and after a JSON round trip:
    the JSON spelling "NaN" is decoded once, by the certificate reader."""
    cert = F.inconclusive_certificate()  # built from a dict with "NaN" strings
    values = cert.figures.necessary_map.values
    assert all(isinstance(v, float) for row in values for v in row)
    assert any(math.isnan(v) for row in values for v in row)
    text = cert.to_json()
    assert '"NaN"' in text  # JSON has no NaN literal
    again = Certificate.from_dict(json.loads(text))
    back = again.figures.necessary_map.values
    assert all(isinstance(v, float) for row in back for v in row)
    assert [[math.isnan(v) for v in row] for row in back] == \
        [[math.isnan(v) for v in row] for row in values]
    assert figmod.fig_necessary_map(again) is not None


# ----------------------------------------------------------------------------- PDF

def _tool(name: str) -> str:
    path = shutil.which(name)
    if path is None:
        pytest.skip(f"{name} (poppler-utils) is not installed; "
                    "apt-get install -y poppler-utils")
    return path


def _pdf_text(pdf: bytes, tmp_path: Path) -> str:
    f = tmp_path / "r.pdf"
    f.write_bytes(pdf)
    out = subprocess.run([_tool("pdftotext"), "-enc", "UTF-8", str(f), "-"],
                         capture_output=True, check=True, text=True).stdout
    return _norm(out)


@pytest.mark.parametrize("name", NAMES)
def test_pdf_text_is_searchable_with_verdict_and_numbers(name: str, tmp_path: Path) -> None:
    cert, data, caught = rendered(name)
    assert data["pdf"].startswith(b"%PDF")
    text = _pdf_text(data["pdf"], tmp_path)
    assert cert.verdict in text
    for row in C.check_rows(cert):
        assert row.status in text
        for side in (row.sampled, row.proved):
            assert side.value in text, (row.name, side.value)
    assert cert.checkpoint["sha256"][:16] in text
    assert not [w for w in caught if "missing from font" in w], caught


def test_pdf_known_numbers_of_the_paper_preset(tmp_path: Path) -> None:
    _, data, _ = rendered("violated")
    text = _pdf_text(data["pdf"], tmp_path)
    for needle in ("NOT CERTIFIED", "+7.7", "-1.35", "+6", "18", "Theorem 3",
                   "Validity conditions", "no gain, however trained", "rate 2\u03bb"):
        assert needle in text, needle


@pytest.mark.parametrize("name", ["certified", "violated"])
def test_pdf_embeds_every_figure(name: str, tmp_path: Path) -> None:
    cert, data, _ = rendered(name)
    f = tmp_path / "r.pdf"
    f.write_bytes(data["pdf"])
    listing = subprocess.run([_tool("pdfimages"), "-list", str(f)], capture_output=True,
                             check=True, text=True).stdout.splitlines()
    images = [ln for ln in listing[2:] if ln.split()[2:3] == ["image"]]
    want = {"certified": 5, "violated": 5}[name]
    assert len(images) == want
    info = subprocess.run([_tool("pdfinfo"), str(f)], capture_output=True, check=True,
                          text=True).stdout
    pages = int(re.search(r"Pages:\s+(\d+)", info).group(1))
    assert pages >= 5
    fonts = subprocess.run([_tool("pdffonts"), str(f)], capture_output=True, check=True,
                           text=True).stdout
    assert "DejaVuSans" in fonts and "TrueType" in fonts  # real text, not outlines


# ----------------------------------------------------------------------------- JUnit

def _cases(xml_text: str) -> tuple[ET.Element, list[ET.Element]]:
    root = ET.fromstring(xml_text.encode("utf-8"))
    assert root.tag == "testsuites"
    suite = root.find("testsuite")
    return suite, suite.findall("testcase")


@pytest.mark.parametrize("name", NAMES)
def test_junit_one_case_per_check_and_one_failure_per_failed_check(name: str) -> None:
    cert, data, _ = rendered(name)
    suite, cases = _cases(data["junit"].decode("utf-8"))
    rows = C.check_rows(cert)
    assert [c.get("name") for c in cases] == [r.name for r in rows]
    failed = {r.name for r in rows if r.required and r.status not in ("PROVED", "PASSED", "ERROR")}
    got = {c.get("name") for c in cases if c.find("failure") is not None}
    assert got == failed
    assert int(suite.get("failures")) == len(failed)
    assert int(suite.get("tests")) == len(rows)
    props = {p.get("name"): p.get("value") for p in suite.find("properties")}
    assert props["verdict"] == cert.verdict
    for c in cases:
        fail = c.find("failure")
        if fail is not None:
            row = next(r for r in rows if r.name == c.get("name"))
            assert row.sampled.value in fail.text and row.proved.value in fail.text
            assert fail.get("type") == row.status


def test_junit_violated_case_carries_the_numbers() -> None:
    _, data, _ = rendered("violated")
    _, cases = _cases(data["junit"].decode())
    mpdi = next(c for c in cases if c.get("name") == "mpdi")
    fail = mpdi.find("failure")
    assert "+7.7" in fail.get("message") and "+7.7" in fail.text
    assert "counterexamples: 5" in fail.text


def test_junit_unknown_policy_error_and_skipped_and_error_statuses() -> None:
    cert = F.inconclusive_certificate()
    cert.checks["residual"] = dataclasses.replace(cert.checks["residual"],
                                                  status=Status.ERROR, message="solver crashed")
    _, cases = _cases(render_junit(cert, unknown="error"))
    by = {c.get("name"): c for c in cases}
    assert by["mpdi"].find("error") is not None and by["mpdi"].find("failure") is None
    # not required: an ERROR there is shown, but never turns CI red
    assert by["residual"].find("skipped").get("message").startswith("not required: ERROR")
    assert by["residual"].find("error") is None
    assert by["simulation"].find("skipped") is not None
    assert by["necessary"].find("failure") is None and by["necessary"].find("error") is None
    with pytest.raises(ValueError, match="unknown must be one of"):
        render_junit(cert, unknown="pass")


# ----------------------------------------------------------------------------- files

@pytest.mark.slow
def test_write_reports_writes_all_four(tmp_path: Path) -> None:
    cert = F.inconclusive_certificate()
    cert.figures, cert.checks["simulation"].runs = FigureData(), []  # fewer figures: quicker
    paths = write_reports(cert, html=tmp_path / "r.html", pdf=tmp_path / "r.pdf",
                          junit=tmp_path / "r.xml", json=tmp_path / "out" / "r.json")
    assert [p.name for p in paths] == ["r.html", "r.pdf", "r.xml", "r.json"]
    html_text = (tmp_path / "r.html").read_text(encoding="utf-8")
    assert "INCONCLUSIVE" in html_text and not parse_html(html_text).errors
    assert html_text == render_html(cert)  # deterministic: same certificate, same bytes
    _cases((tmp_path / "r.xml").read_text(encoding="utf-8"))
    again = Certificate.load(tmp_path / "out" / "r.json")
    assert again.verdict == "INCONCLUSIVE" and again.to_json() == cert.to_json()
    assert (tmp_path / "r.pdf").read_bytes()[:5] == b"%PDF-"
    leftovers = [p for p in tmp_path.rglob("*") if p.name.startswith(".") or
                 p.suffix == ".tmp"]
    assert not leftovers
    assert write_reports(cert) == []


def _broken_figures(exc: BaseException) -> tuple:
    def boom(cert):
        raise exc

    specs = list(figmod.FIGURES)
    specs[2] = dataclasses.replace(specs[2], build=boom)
    return tuple(specs)


@pytest.mark.parametrize("exc", [RuntimeError("figure failed"), KeyboardInterrupt()])
@pytest.mark.slow
def test_failing_render_leaves_no_file(exc: BaseException, tmp_path: Path,
                                       monkeypatch: pytest.MonkeyPatch) -> None:
    cert = F.violated_vdp_certificate()
    old = tmp_path / "old.html"
    old.write_text("previous report")
    monkeypatch.setattr(figmod, "FIGURES", _broken_figures(exc))
    with pytest.raises(type(exc)):
        write_reports(cert, html=old, pdf=tmp_path / "r.pdf", junit=tmp_path / "r.xml",
                      json=tmp_path / "r.json")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["old.html"]
    assert old.read_text() == "previous report"  # untouched, not half-replaced


def test_interrupt_while_writing_leaves_no_partial_file(tmp_path: Path,
                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    import certify.files as ck

    cert = F.violated_vdp_certificate()
    calls = {"n": 0}
    real_fsync = os.fsync

    def fsync(fd):
        calls["n"] += 1
        if calls["n"] == 2:  # the second file: interrupted after its bytes were written
            raise KeyboardInterrupt
        return real_fsync(fd)

    monkeypatch.setattr(ck.os, "fsync", fsync)
    with pytest.raises(KeyboardInterrupt):
        write_reports(cert, junit=tmp_path / "r.xml", json=tmp_path / "r.json")
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == ["r.xml"]  # the first is complete, the second absent, no temp file
    ET.fromstring((tmp_path / "r.xml").read_bytes())


def test_minimal_certificate_renders_everywhere(tmp_path: Path) -> None:
    """No checks run, no figures, sparse metadata: every renderer still works."""
    cert = Certificate(verdict="INCONCLUSIVE", summary="not established: mpdi", checks={},
                       required=["mpdi"], settings={}, system={}, lam=1.0,
                       P=[[1.0, 0.0], [0.0, 1.0]], network={}, checkpoint={}, versions={},
                       timings={})
    doc = render_html(cert)
    p = parse_html(doc)
    assert not p.errors and "INCONCLUSIVE" in doc and "The MPDI check was not run." in doc
    assert not [a for a in p.attrs if a[0] == "img"]
    _, cases = _cases(render_junit(cert))
    assert [c.get("name") for c in cases] == ["mpdi"]
    # required and not run: nothing established, the gate fails, so CI shows it red
    assert cases[0].find("failure").get("message") == "SKIPPED: not run"
    write_reports(cert, pdf=tmp_path / "r.pdf")
    text = _pdf_text((tmp_path / "r.pdf").read_bytes(), tmp_path)
    assert "INCONCLUSIVE" in text
