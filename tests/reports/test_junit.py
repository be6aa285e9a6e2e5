"""JUnit reports that CI systems accept: valid against Jenkins' junit-10.xsd, red exactly
when the gate fails, and a check that is not required never shown as a <failure>.

The schema is vendored from pytest's source distribution (tests/data/README.md); it is
checked with lxml's XML Schema validator.
"""

from __future__ import annotations

import dataclasses
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from certify.results import (
    Status,  # noqa: E402
    decide_verdict,  # noqa: E402
)
from reports.junit import render_internal_error, render_junit  # noqa: E402

from .. import fixtures_certificates as F  # noqa: E402

etree = pytest.importorskip("lxml.etree", reason="lxml validates against junit-10.xsd")
SCHEMA = Path(__file__).parents[1] / "data" / "junit-10.xsd"


def _schema():
    return etree.XMLSchema(etree.parse(str(SCHEMA)))


def _assert_valid(xml_text: str) -> None:
    schema = _schema()
    doc = etree.fromstring(xml_text.encode("utf-8"))
    assert schema.validate(doc), "\n".join(str(e) for e in schema.error_log)


def _cases(xml_text: str) -> dict[str, ET.Element]:
    root = ET.fromstring(xml_text.encode("utf-8"))
    return {c.get("name"): c for c in root.iter("testcase")}


def test_the_schema_refuses_what_certify_used_to_write() -> None:
    """The validator is live: a `skipped` attribute on <testsuites> (the old output) fails."""
    bad = ('<?xml version="1.0"?><testsuites name="certify" tests="0" failures="0" '
           'errors="0" skipped="0" time="0.000"/>')
    assert not _schema().validate(etree.fromstring(bad.encode()))


@pytest.mark.parametrize("name", list(F.ALL))
@pytest.mark.parametrize("unknown", ["failure", "error"])
def test_junit_is_valid_and_red_exactly_when_the_gate_fails(name: str, unknown: str) -> None:
    cert = F.ALL[name]()
    xml_text = render_junit(cert, unknown=unknown)
    _assert_valid(xml_text)
    cases = _cases(xml_text)
    red = {n for n, c in cases.items() if c.find("failure") is not None
           or c.find("error") is not None}
    assert (cert.verdict != "CERTIFIED") == bool(red)
    assert red <= set(cert.required)  # never red for a check that is not required
    for c in cases.values():
        assert c.find("system-out") is not None and "status: " in c.find("system-out").text


def test_checks_that_are_not_required_pass_or_skip_with_their_finding() -> None:
    cert = F.violated_vdp_certificate()
    cases = _cases(render_junit(cert))
    for name, result in cert.checks.items():
        case = cases[name]
        if name in cert.required:
            continue
        assert case.find("failure") is None and case.find("error") is None
        if result.status in (Status.PROVED, Status.PASSED):
            assert case.find("skipped") is None
        else:
            skipped = case.find("skipped")
            assert skipped is not None
            assert skipped.get("message").startswith(f"not required: {result.status.value}: ")
            assert result.message in skipped.get("message")


def test_required_unknown_is_failure_or_error_by_policy_and_skipped_when_allowed() -> None:
    cert = F.inconclusive_certificate()
    assert cert.checks["mpdi"].status == Status.UNKNOWN and "mpdi" in cert.required
    assert _cases(render_junit(cert))["mpdi"].find("failure") is not None
    assert _cases(render_junit(cert, unknown="error"))["mpdi"].find("error") is not None
    # allow_unknown waives the other required checks, never the MPDI (the certificate)
    allowed = dataclasses.replace(cert, settings={**cert.settings, "allow_unknown": True},
                                  required=[*cert.required, "lipschitz"])
    allowed.checks["lipschitz"] = dataclasses.replace(cert.checks["lipschitz"],
                                                      status=Status.UNKNOWN)
    allowed.verdict, allowed.summary = decide_verdict(allowed.checks, allowed.required, True)
    assert allowed.verdict == "INCONCLUSIVE"
    xml_text = render_junit(allowed)
    _assert_valid(xml_text)
    assert _cases(xml_text)["mpdi"].find("failure") is not None
    skipped = _cases(xml_text)["lipschitz"].find("skipped")
    assert skipped is not None and "allowed by allow_unknown" in skipped.get("message")


def test_required_check_in_error_and_not_applicable() -> None:
    cert = F.inconclusive_certificate()
    cert.checks["mpdi"] = dataclasses.replace(cert.checks["mpdi"], status=Status.ERROR,
                                              message="solver crashed")
    cert.checks["lipschitz"] = dataclasses.replace(cert.checks["lipschitz"],
                                                   status=Status.NOT_APPLICABLE,
                                                   message="no bound exists")
    xml_text = render_junit(cert)
    _assert_valid(xml_text)
    cases = _cases(xml_text)
    assert cases["mpdi"].find("error").get("type") == "ERROR"
    assert cases["lipschitz"].find("failure").get("type") == "NOT APPLICABLE"
    suite = ET.fromstring(xml_text.encode()).find("testsuite")
    assert (suite.get("failures"), suite.get("errors")) == ("1", "1")


def test_internal_error_report_is_valid() -> None:
    _assert_valid(render_internal_error("figures", "boom", "ValueError"))
