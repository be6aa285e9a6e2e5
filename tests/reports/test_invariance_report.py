"""The invariance check and the validity region in every medium: the terminal's "validity:"
line, the bounds section's proved statement, the invariance section, JUnit, the JSON (a
round trip), and the verdict's note when the plant's attractor leaves X."""

from __future__ import annotations

import dataclasses
import io
import json
import re
import xml.etree.ElementTree as ET

from certify.certificate import Certificate
from certify.cli.display import print_summary, print_verdict
from certify.results import InvarianceResult, Status
from reports import content as C
from reports.html import render_html
from reports.junit import render_junit
from reports.sections import sections

from .builders import headline_certificate

POLYGON = [[2.3, 0.0], [1.2, 2.9], [-1.5, 2.6], [-2.3, 0.0], [-1.2, -2.9], [1.5, -2.6]]


def region_certificate(*, leaves: bool = False) -> Certificate:
    """`headline_certificate` with an invariance result (a polygon proved inside X, or the
    attractor leaving X and nothing proved) and the bounds' validity region."""
    cert = headline_certificate()
    if leaves:
        inv = InvarianceResult(
            Status.UNKNOWN, "a polygon of 128 vertices is forward invariant but not inside X",
            attractor="cycle", attractor_box=[[-2.009, 2.009], [-3.678, 3.678]],
            attractor_leaves_box=True, suggested_box=[[-2.5, 2.5], [-4.5, 4.5]],
            candidates=[{"kind": "polygon", "how": "polygon of 128 edges around the cycle",
                         "status": "PROVED", "message": "forward invariant"}])
        cert.checks["invariance"] = inv
        cert.checks["bounds"] = dataclasses.replace(
            cert.checks["bounds"], region_reason="no plant region inside X was proved "
            "forward invariant (invariance UNKNOWN)")
        return cert
    cert.checks["invariance"] = InvarianceResult(
        Status.PROVED, "a polygon of 6 vertices (given by the spec) is forward invariant",
        region={"kind": "polygon", "origin": "spec", "text": "a polygon of 6 vertices",
                "vertices": POLYGON},
        hull=[[-2.3, 2.3], [-2.9, 2.9]], output_range=[[-2.3, 2.3]], margin=-0.0123,
        attractor="cycle", attractor_box=[[-2.009, 2.009], [-2.678, 2.678]],
        candidates=[{"kind": "polygon", "how": "given by the spec", "status": "PROVED",
                     "message": "forward invariant"}])
    cert.checks["bounds"] = dataclasses.replace(
        cert.checks["bounds"], region="a polygon of 6 vertices, proved forward invariant, "
        "in [-2.3, 2.3] x [-2.9, 2.9]", r0=0.123456, r0_W=0.2, region_settle_time=1.234,
        proved_conditions=["a", "b", "d"])
    return cert


def test_the_terminal_prints_the_validity_line_after_the_error_bound():
    out = io.StringIO()
    print_verdict(region_certificate(), out)
    lines = out.getvalue().splitlines()
    assert lines[0].startswith("CERTIFIED: ") and lines[1].startswith("error bound: ")
    assert lines[2] == ("validity: for every x(0) in R and \u2016e(0)\u2016 \u2264 0.123: "
                        "x\u0302 stays in X and \u2016e(t)\u2016 \u2264 1.26 for all t \u2265 "
                        "1.3 s (R: a polygon of 6 vertices, proved forward invariant, in "
                        "[-2.3, 2.3] x [-2.9, 2.9]; conditions (a), (b), (d) proved, (c) "
                        "\u2016v\u2016 \u2264 0.05 assumed)")
    full = io.StringIO()
    print_summary(region_certificate(), full)
    assert full.getvalue().splitlines()[-3:] == lines
    # no region: no validity line
    plain = io.StringIO()
    print_verdict(headline_certificate(), plain)
    assert len(plain.getvalue().splitlines()) == 2


def test_the_terminal_falls_back_to_ascii():
    raw = io.BytesIO()
    out = io.TextIOWrapper(raw, encoding="ascii", errors="strict")
    print_verdict(region_certificate(), out)
    out.flush()
    assert "validity: for every x(0) in R and ||e(0)|| <= 0.123: xhat stays in X" in \
        raw.getvalue().decode("ascii")


def test_the_report_has_an_invariance_section_and_the_proved_statement():
    cert = region_certificate()
    secs = {s.anchor: s for s in sections(cert)}
    inv = secs["invariance"]
    assert inv.status == "PROVED" and inv.tables[0].rows[0][1] == "given by the spec"
    facts = dict(inv.facts)
    assert facts["Region R"] == "polygon of 6 vertices (given by the spec)"
    assert "x1 in [-2.3, 2.3]" in facts["R lies in"]
    assert any(st.startswith("Validity, proved: for every x(0) in R")
               for st in secs["bounds"].statements)
    assert [s.anchor for s in sections(cert)].index("invariance") < \
        [s.anchor for s in sections(cert)].index("bounds")
    html = render_html(cert, figures=[])
    flat = re.sub(r"\s+", " ", html)
    assert "Forward invariance of a plant region" in flat
    assert "Validity, proved: for every x(0) in R and" in flat
    names = [r.name for r in C.check_rows(cert)]
    assert names.index("invariance") == names.index("bounds") - 1


def test_junit_and_json_carry_the_region():
    cert = region_certificate()
    root = ET.fromstring(render_junit(cert))
    case = next(c for c in root.iter("testcase") if c.get("name") == "invariance")
    assert case.find("failure") is None
    bounds_out = next(c for c in root.iter("testcase")
                      if c.get("name") == "bounds").find("system-out").text
    assert "initial error r0" in bounds_out
    data = json.loads(cert.to_json())
    assert data["error_bound"]["validity"].startswith("for every x(0) in R")
    assert data["checks"]["invariance"]["region"]["vertices"] == POLYGON
    again = Certificate.from_dict(data)
    assert again.checks["invariance"] == cert.checks["invariance"]
    assert again.checks["bounds"].r0 == 0.123456
    assert again.checks["bounds"].proved_conditions == ["a", "b", "d"]


def test_the_verdict_notes_an_attractor_that_leaves_x():
    cert = region_certificate(leaves=True)
    line = C.verdict_line(cert)
    assert "note: the plant's simulated attractor leaves X (x1 in [-2.009, 2.009], x2 in " \
        "[-3.678, 3.678])" in line
    assert "a box that holds it: x1 in [-2.5, 2.5], x2 in [-4.5, 4.5]" in line
    out = io.StringIO()
    print_verdict(cert, out)
    assert "attractor leaves X" in out.getvalue().splitlines()[0]
    assert len(out.getvalue().splitlines()) == 2  # no validity line
    html = re.sub(r"\s+", " ", render_html(cert, figures=[])).replace("&#39;", "'")
    assert "note: the plant's simulated attractor leaves X" in html
    assert "invariance UNKNOWN" in json.loads(cert.to_json())["checks"]["bounds"][
        "region_reason"]
