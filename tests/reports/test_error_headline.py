"""The error bound is the second headline after the verdict, in every medium: "‖e‖ ≤ B for
noise ≤ v̄ after t ≥ T", per component with the state names, "useful" or "vacuous" in words,
and which bound it comes from; without a bound, one line saying why. A vacuous bound is
never shown as a plain (green) PROVED. "Certified error bound" only under a CERTIFIED
verdict: a bound proved at the proved rate under a failed certificate says so, and one
resting on a contraction that was not proved is marked NOT PROVED."""

from __future__ import annotations

import dataclasses
import io
import json
import re
import shutil
import subprocess
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from certify.certificate import Certificate
from certify.cli.display import print_summary, print_verdict
from certify.presentation import ErrorHeadline, error_headline, upper_text
from certify.results import CheckFailure, Status
from reports import content as C
from reports.html import render_html
from reports.junit import render_junit
from reports.pdf import render_pdf

from ..fixtures_certificates import (
    certified_certificate,
    inconclusive_certificate,
    violated_vdp_certificate,
)
from .builders import (
    HALF_DIAGONAL,
    headline_certificate,
    no_bound_certificate,
    proved_rate_certificate,
    unproved_basis_certificate,
)

# ----------------------------------------------------------------------------- the data

def test_upper_text_never_prints_below_the_bound():
    assert upper_text(1.2431) == "1.25"
    assert upper_text(1.25) == "1.25"
    assert upper_text(1240.2) == "1250"
    assert upper_text(0.0123401) == "0.0124"
    assert upper_text(9.9951) == "10"
    assert upper_text(3.0417, 2) == "3.1"
    for x in (1e-7 * 1.2345678, 0.1 + 0.2, 2.0 / 3.0, 123456.789, 7.0000000001):
        assert float(upper_text(x)) >= x


def test_headline_data_from_a_bounds_result():
    cert = headline_certificate()
    h = cert.error_headline()
    assert h.proved and h.source == "dissipation" and not h.vacuous
    assert h.bound == pytest.approx(1.1374 * 1.1) and h.after == pytest.approx(3.0417)
    assert [n for n, _ in h.components] == ["x1", "x2"]
    # per component at t >= T: the ultimate bound scaled like the norm bound, never smaller
    assert h.components[0][1] >= 0.3561 * 1.1 and h.components[1][1] >= 1.1374 * 1.1
    assert h.sentence() == "\u2016e\u2016 \u2264 1.26 for noise \u2264 0.05 after t \u2265 3.1 s"
    assert h.sentence(unicode=False) == "||e|| <= 1.26 for noise <= 0.05 after t >= 3.1 s"
    assert h.components_text() == "|e1| \u2264 0.392 (x1), |e2| \u2264 1.26 (x2)"
    assert h.size_text() == "useful (smaller than the box, half-diagonal 4.3)"
    assert "dissipation certificate (dissipation)" in h.source_text()


def test_no_bound_says_why():
    h = no_bound_certificate().error_headline()
    assert not h.proved and h.reason.startswith("no error bound exists: lam_cert = -0.2")
    h = inconclusive_certificate().error_headline()
    assert h.reason == "no error bound: no bound until the MPDI is proved"
    assert error_headline(None).reason == "no error bound: the bounds check was not run"
    failed = CheckFailure(status=Status.ERROR, message="boom", error_type="RuntimeError")
    assert error_headline(failed).reason == ("no error bound: the bounds check ended in "
                                             "ERROR: boom")


def test_an_older_certificate_without_headline_fields_gets_the_ultimate_bound():
    cert = certified_certificate()  # PROVED, no best/headline/settle_time recorded
    h = cert.error_headline()
    b = cert.checks["bounds"]
    assert h.proved and h.after is None and h.bound == min(b.iss.bias, b.iss_metric.bias)
    assert h.sentence().endswith("as t \u2192 \u221e")


# ----------------------------------------------------------------------------- the media

@pytest.mark.parametrize("vacuous", [False, True])
def test_terminal_headline_on_the_line_after_the_verdict(vacuous):
    cert = headline_certificate(vacuous=vacuous)
    out = io.StringIO()
    print_summary(cert, out)
    lines = out.getvalue().splitlines()
    i = next(k for k, ln in enumerate(lines) if ln.startswith("CERTIFIED: "))
    head = lines[i + 1]
    word = "vacuous" if vacuous else "useful"
    big = "32.3" if vacuous else "1.26"
    assert head.startswith(f"error bound: \u2016e\u2016 \u2264 {big} for noise \u2264 0.05 "
                           "after t \u2265 3.1 s; |e1| \u2264 ")
    assert f"; {word} (" in head and "half-diagonal 4.3" in head and "(x2)" in head
    assert "[from the dissipation certificate (dissipation)" in head
    bounds_row = next(ln for ln in lines if ln.startswith("Error bounds"))
    assert ("PROVED \u2014 vacuous" in bounds_row) == vacuous
    # --quiet prints the same two lines
    quiet = io.StringIO()
    print_verdict(cert, quiet)
    assert quiet.getvalue().splitlines() == [lines[i], head]


def test_terminal_is_ascii_where_the_stream_cannot_print_unicode():
    raw = io.BytesIO()
    out = io.TextIOWrapper(raw, encoding="ascii", errors="strict")
    print_verdict(headline_certificate(), out)
    out.flush()
    text = raw.getvalue().decode("ascii")
    assert "error bound: ||e|| <= 1.26 for noise <= 0.05 after t >= 3.1 s" in text


def test_terminal_no_bound_line():
    out = io.StringIO()
    print_verdict(no_bound_certificate(), out)
    assert out.getvalue().splitlines()[1].startswith("no error bound exists: lam_cert = -0.2")


@pytest.mark.parametrize("vacuous", [False, True])
def test_html_headline_after_the_verdict(vacuous):
    html = render_html(headline_certificate(vacuous=vacuous), figures=[])
    verdict, headline = html.index('id="verdict"'), html.index('<div class="headline')
    assert verdict < headline < html.index('<nav class="toc">')
    block = html[headline:html.index('<nav class="toc">')]
    word = "vacuous" if vacuous else "useful"
    big = "32.3" if vacuous else "1.26"
    assert f"\u2016e\u2016 \u2264 {big} for noise \u2264 0.05 after t \u2265 3.1 s" in block
    assert "|e1| \u2264" in block and "(x1)" in block and "(x2)" in block
    assert f'class="headline {word} basis-certificate"' in block and f">{word}</span>" in block
    assert '<div class="what">Certified error bound</div>' in block
    assert "dissipation certificate (dissipation)" in block
    row = html[html.index('id="row-bounds"'):]
    row = row[:row.index("</tr>")]
    if vacuous:  # never a plain green PROVED for the bounds row or its section
        assert "st-QUALIFIED" in row and "PROVED \u2014 vacuous" in row
        assert "st-PROVED" not in row
        section = html[html.index('<section id="bounds">'):]
        h2 = section[:section.index("</h2>")]
        assert "PROVED \u2014 vacuous" in h2 and "st-PROVED" not in h2
        assert 'class="note warn"' in section[:section.index("</section>")]
    else:
        assert "st-PROVED" in row and "vacuous" not in row


def test_html_no_bound_says_why_in_the_same_place():
    html = render_html(no_bound_certificate(), figures=[])
    block = html[html.index('<div class="headline'):html.index('<nav class="toc">')]
    assert "no error bound exists: lam_cert = -0.2" in block
    assert "\u2016e\u2016 \u2264" not in block


def _pdf_text(pdf: bytes, tmp_path: Path) -> str:
    """The PDF's text as `pdftotext` (poppler-utils) reads it."""
    tool = shutil.which("pdftotext")
    if tool is None:
        pytest.skip("pdftotext (poppler-utils) is not installed")
    f = tmp_path / "r.pdf"
    f.write_bytes(pdf)
    return subprocess.run([tool, "-enc", "UTF-8", str(f), "-"], capture_output=True,
                          check=True, text=True).stdout


@pytest.mark.parametrize("vacuous", [False, True])
def test_pdf_headline_on_the_first_page(vacuous, tmp_path):
    text = _pdf_text(render_pdf(headline_certificate(vacuous=vacuous), figures=[]), tmp_path)
    first = text[:text.index("Checks")]
    big = "32.3" if vacuous else "1.26"
    flat = re.sub(r"\s+", " ", first)
    assert f"\u2016e\u2016 \u2264 {big} for noise \u2264 0.05 after t \u2265 3.1 s" in flat
    assert "Certified error bound" in flat and "(x1)" in flat and "(x2)" in flat
    assert ("vacuous (larger than the box" in flat) == vacuous
    assert ("useful (smaller than the box" in flat) != vacuous
    assert ("PROVED \u2014 vacuous" in re.sub(r"\s+", " ", text)) == vacuous


def test_pdf_no_bound_line(tmp_path):
    text = re.sub(r"\s+", " ", _pdf_text(render_pdf(no_bound_certificate(), figures=[]),
                                         tmp_path))
    assert "no error bound exists: lam_cert = -0.2" in text[:text.index("Checks")]


@pytest.mark.parametrize("vacuous", [False, True])
def test_json_top_level_error_bound(vacuous):
    cert = headline_certificate(vacuous=vacuous)
    data = json.loads(cert.to_json())
    assert list(data)[:3] == ["verdict", "summary", "error_bound"]
    eb = data["error_bound"]
    assert eb["status"] == "PROVED" and eb["source"] == "dissipation"
    assert eb["size"] == ("vacuous" if vacuous else "useful") and eb["vacuous"] is vacuous
    assert eb["bound"] == pytest.approx(cert.checks["bounds"].headline)
    assert eb["noise"] == 0.05 and eb["after"] == pytest.approx(3.0417)
    assert set(eb["per_component"]) == {"x1", "x2"}
    assert eb["statement"].startswith("\u2016e\u2016 \u2264 ")
    assert eb["box_half_diagonal"] == pytest.approx(HALF_DIAGONAL)
    # derived: read back (and ignored) without complaint, written again the same
    again = Certificate.from_dict(data)
    assert json.loads(again.to_json())["error_bound"] == eb


def test_json_no_bound_reason():
    eb = json.loads(no_bound_certificate().to_json())["error_bound"]
    assert eb["status"] == "NOT APPLICABLE" and eb["bound"] is None and eb["size"] is None
    assert eb["reason"].startswith("no error bound exists: lam_cert = -0.2")


def test_json_without_the_key_is_read_as_before():
    data = json.loads(headline_certificate().to_json())
    del data["error_bound"]
    assert Certificate.from_dict(data).error_headline().proved


def _junit(cert: Certificate) -> tuple[ET.Element, dict[str, str], str]:
    root = ET.fromstring(render_junit(cert))
    props = {p.get("name"): p.get("value") for p in root.iter("property")}
    case = next(c for c in root.iter("testcase") if c.get("name") == "bounds")
    return case, props, case.find("system-out").text


@pytest.mark.parametrize("vacuous", [False, True])
def test_junit_headline_in_properties_and_system_out(vacuous):
    case, props, out = _junit(headline_certificate(vacuous=vacuous))
    word = "vacuous" if vacuous else "useful"
    big = "32.3" if vacuous else "1.26"
    assert props["error_bound"] == (f"\u2016e\u2016 \u2264 {big} for noise \u2264 0.05 "
                                    "after t \u2265 3.1 s")
    assert props["error_bound_value"] == big and props["error_bound_noise"] == "0.05"
    assert props["error_bound_after_seconds"] == "3.1"
    assert set(props) >= {"error_bound_e1_x1", "error_bound_e2_x2"}
    assert props["error_bound_size"] == word and props["error_bound_source"] == "dissipation"
    first = out.splitlines()[0]
    assert first.startswith("error bound: \u2016e\u2016 \u2264") and f"; {word} (" in first
    # a vacuous bound is valid: the case passes, and says "vacuous" where its status is
    assert case.find("failure") is None and case.find("error") is None
    assert case.find("skipped") is None
    assert ("status: PROVED \u2014 vacuous (required)" in out) == vacuous


def test_junit_no_bound_reason():
    _, props, _ = _junit(no_bound_certificate())
    assert props["error_bound"].startswith("no error bound exists: lam_cert = -0.2")
    _, props, out = _junit(violated_vdp_certificate())
    assert props["error_bound"] == "no error bound: lam_cert <= -1.35 <= 0"
    assert out.splitlines()[0] == "no error bound: lam_cert <= -1.35 <= 0"


def test_checks_table_badge_for_a_vacuous_bound():
    rows = {r.name: r for r in C.check_rows(headline_certificate(vacuous=True))}
    assert rows["bounds"].status == "PROVED"  # the status word itself stays PROVED
    assert rows["bounds"].badge == "PROVED \u2014 vacuous"
    assert C.STATUS_COLOURS[rows["bounds"].badge_key] != C.STATUS_COLOURS["PROVED"]
    assert rows["bounds"].proved.value == "32.3 (after t \u2265 3.1 s; vacuous)"
    rows = {r.name: r for r in C.check_rows(headline_certificate())}
    assert rows["bounds"].badge == "PROVED" and rows["bounds"].badge_key == "PROVED"


def test_headline_type_is_plain_data():
    h = ErrorHeadline(status="PROVED", proved=True, bound=2.0, noise=0.1, after=1.0,
                      components=(("a", 1.0),), vacuous=False, half_diagonal=3.0,
                      source="iss")
    assert json.loads(json.dumps(h.to_dict()))["per_component"] == {"a": 1.0}


# ----------------------------------------------------------------------------- what it rests on

#: every place a report names its verdict or error bound in a box, badge or heading
_HEADED = re.compile(r'<(h[1-3])[^>]*>(.*?)</\1>|<div class="(?:what|line)">(.*?)</div>'
                     r'|<span class="pill[^"]*">(.*?)</span>', re.S)


def _headings(html: str) -> list[str]:
    return [re.sub(r"<[^>]+>", "", next(g for g in m.groups()[1:] if g is not None))
            for m in _HEADED.finditer(html)]


@pytest.mark.parametrize("build", [violated_vdp_certificate, inconclusive_certificate,
                                   proved_rate_certificate, unproved_basis_certificate])
def test_no_box_badge_or_heading_says_certified_unless_certified(build):
    cert = build()
    assert cert.verdict != "CERTIFIED"
    html = render_html(cert, figures=[])
    said = [h for h in _headings(html) if re.search(r"certified", h, re.I)]
    assert said == [cert.verdict] if "CERTIFIED" in cert.verdict else not said, said
    assert C.error_headline_text(cert).title != "Certified error bound"
    _, props, _ = _junit(cert)
    assert "certified" not in props.get("error_bound_title", "").lower()
    out = io.StringIO()
    print_verdict(cert, out)
    assert "certified" not in out.getvalue().splitlines()[1].lower()


def test_a_bound_at_the_proved_rate_under_a_failed_certificate_says_so(tmp_path):
    """The MPDI failed at the design rate 2.5, but the rate check proved lam_cert >= 0.45861
    and the bounds rest on that: shown, headed by what it rests on, never as certified."""
    cert = proved_rate_certificate()
    assert cert.verdict == "NOT CERTIFIED"
    note = ("at the proved rate \u03bb_cert \u2265 0.4586; the certificate failed at the "
            "design rate \u03bb = 2.5")  # 0.45861 rounded down
    h = cert.error_headline()
    assert h.proved and h.basis == "proved" and h.title() == f"Proved error bound ({note})"
    block = render_html(cert, figures=[])
    block = block[block.index('<div class="headline'):block.index('<nav class="toc">')]
    assert "basis-proved" in block and f"Proved error bound ({note})" in block
    assert "\u2016e\u2016 \u2264 1.48 for noise \u2264 0.15 after t \u2265 4.2 s" in block
    out = io.StringIO()
    print_verdict(cert, out)
    assert out.getvalue().splitlines()[1].startswith(f"error bound ({note}): \u2016e\u2016")
    raw = io.BytesIO()
    ascii_out = io.TextIOWrapper(raw, encoding="ascii")
    print_verdict(cert, ascii_out)
    ascii_out.flush()
    assert "error bound (at the proved rate lam_cert >= 0.4586; the certificate failed at " \
           "the design rate lam = 2.5): ||e|| <= 1.48" in raw.getvalue().decode("ascii")
    _, props, system_out = _junit(cert)
    assert props["error_bound_basis"] == "proved"
    assert props["error_bound_title"] == f"Proved error bound ({note})"
    assert system_out.splitlines()[0].startswith(f"error bound ({note}): ")
    eb = json.loads(cert.to_json())["error_bound"]
    assert eb["basis"] == "proved" and eb["title"] == f"Proved error bound ({note})"
    text = re.sub(r"\s+", " ", _pdf_text(render_pdf(cert, figures=[]), tmp_path))
    first = text[:text.index("Checks")]
    assert f"Proved error bound ({note})" in first and "Certified error bound" not in first


def test_a_bound_resting_on_an_unproved_contraction_is_marked():
    cert = unproved_basis_certificate()
    h = cert.error_headline()
    assert h.proved and h.basis == "unproved"
    assert h.title().startswith("Error bound resting on an unproved condition (NOT PROVED: ")
    assert "rate check (UNKNOWN)" in h.note() and "MPDI (UNKNOWN)" in h.note()
    assert 'class="headline useful basis-unproved"' in render_html(cert, figures=[])
    out = io.StringIO()
    print_verdict(cert, out)
    assert out.getvalue().splitlines()[1].startswith("error bound (NOT PROVED: it rests on ")


def test_a_dissipation_bound_rests_on_the_dissipation_check():
    cert = headline_certificate()
    assert cert.error_headline().basis == "certificate"
    cert.checks["dissipation"] = dataclasses.replace(cert.checks["dissipation"],
                                                     status=Status.UNKNOWN, alpha=None)
    h = cert.error_headline()
    assert h.basis == "unproved" and "dissipation inequality" in h.note()
