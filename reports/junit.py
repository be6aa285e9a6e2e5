"""JUnit XML: one test case per check, so CI systems show the certificate natively.

Valid against the Jenkins `junit-10.xsd` schema (vendored in tests/data and checked by a
test), and red in CI exactly when the gate fails. A required check: PROVED and PASSED
(evidence only) pass; VIOLATED is a <failure>; ERROR (the check failed internally:
certify's problem, not the network's) is an <error>; UNKNOWN, SKIPPED, NOT APPLICABLE or not
run (nothing established) is a <failure> by default (the policy `unknown="error"` makes it an
<error>, to tell "could not decide" from "proved false" on dashboards), or <skipped> when the
settings allow unknown required checks. A check that is not required never fails the build:
it passes when it passed, and is otherwise <skipped> with its status and finding as the
reason. Every case carries the numbers of both sides in <system-out>; a status with a
qualifier is written with it ("PROVED — vacuous": a vacuous error bound still passes, it is
valid, but never without that word). The error bound, the second headline after the
verdict, opens the bounds case's <system-out> and is in the suite's properties
(`error_bound`, one `error_bound_e<i>_<state>` per component, `error_bound_size` "useful" or
"vacuous", `error_bound_source`, `error_bound_basis` "certificate", "proved" or "unproved"
and `error_bound_title`, which says "Certified" only under a CERTIFIED verdict; without a
bound, `error_bound` says why). When `certify run`
stops on an internal error (exit 4, no certificate), `render_internal_error` gives the one
<error> case CI shows instead.
"""

from __future__ import annotations

import datetime as _dt
import xml.etree.ElementTree as ET

from certify.certificate import Certificate
from certify.presentation import upper_text
from reports import content as C

UNKNOWN_POLICIES = ("failure", "error")


def _numbers_text(row: C.CheckRow, headline: C.HeadlineText | None = None) -> str:
    lines = [headline.line] if headline is not None and row.name == "bounds" else []
    lines += [f"status: {row.badge}" + (" (required)" if row.required else " (not required)"),
             f"message: {row.message}",
             f"sampled side: {row.sampled.label}: {row.sampled.text}",
             f"proved side: {row.proved.label}: {row.proved.text}",
             f"checked with: {row.setting}"]
    lines += [f"{k}: {v}" for k, v in row.numbers]
    return "\n".join(lines)


#: statuses of a check that passed
PASSING = ("PROVED", "PASSED")


def case_outcome(row: C.CheckRow, unknown: str, allow_unknown: bool) -> tuple[str, str]:
    """(element, message) for a check: element is "" (passed), "failure", "error", "skipped".

    Mirrors `certify.results.decide_verdict`, so CI shows red exactly when the gate fails.
    """
    finding = f"{row.badge}: {row.message}"
    if row.status in PASSING:
        return "", finding
    if not row.required:
        return "skipped", f"not required: {finding}"
    if row.status == "VIOLATED":
        return "failure", finding
    if row.status == "ERROR":
        return "error", finding
    # UNKNOWN, SKIPPED, NOT APPLICABLE, not run: nothing established; the MPDI is the
    # certificate, which allow_unknown never waives
    if allow_unknown and row.name != "mpdi":
        return "skipped", f"not established (allowed by allow_unknown): {finding}"
    return ("failure" if unknown == "failure" else "error"), finding


def render_junit(cert: Certificate, *, unknown: str = "failure") -> str:
    """JUnit XML (a <testsuites> document) for the certificate."""
    if unknown not in UNKNOWN_POLICIES:
        raise ValueError(f"unknown must be one of {UNKNOWN_POLICIES}; got {unknown!r}")
    rows = C.check_rows(cert)
    allow_unknown = bool((cert.settings or {}).get("allow_unknown", False))
    name = (cert.system or {}).get("name", "system")
    suite_name = f"certify.{name}"
    counts = {"failure": 0, "error": 0, "skipped": 0}
    cases = []
    headline = C.error_headline_text(cert)
    for row in rows:
        case = ET.Element("testcase", {"classname": suite_name, "name": row.name,
                                       "time": f"{row.seconds or 0.0:.3f}"})
        element, msg = case_outcome(row, unknown, allow_unknown)
        text = _numbers_text(row, headline)
        if element == "skipped":
            ET.SubElement(case, element, {"message": msg})
        elif element:  # a failure or error carries the numbers of both sides itself
            ET.SubElement(case, element, {"message": msg, "type": row.status}).text = text
        if element:
            counts[element] += 1
        ET.SubElement(case, "system-out").text = text
        cases.append(case)
    total_time = sum(r.seconds or 0.0 for r in rows)
    attrs = {"tests": str(len(cases)), "failures": str(counts["failure"]),
             "errors": str(counts["error"]), "time": f"{total_time:.3f}"}
    # junit-10.xsd: <testsuites> has no `skipped` attribute; <testsuite> has one
    root = ET.Element("testsuites", {"name": "certify", **attrs})
    suite = ET.SubElement(root, "testsuite", {"name": suite_name, **attrs,
                                              "skipped": str(counts["skipped"]),
                                              "timestamp": cert.created or ""})
    props = ET.SubElement(suite, "properties")
    ck = cert.checkpoint or {}
    for key, value in (("verdict", cert.verdict), ("summary", cert.summary),
                       ("required", ",".join(cert.required)),
                       ("checkpoint", str(ck.get("path", ""))),
                       ("sha256", str(ck.get("sha256", ""))), ("lam", C.fmt(cert.lam, 6)),
                       ("lam_cert", C.lam_cert_text(cert)),
                       ("unknown_policy", unknown), *_headline_properties(cert)):
        ET.SubElement(props, "property", {"name": key, "value": value})
    suite.extend(cases)
    ET.indent(root)
    return ET.tostring(root, encoding="unicode", xml_declaration=True) + "\n"


def _headline_properties(cert: Certificate) -> list[tuple[str, str]]:
    """The error headline as suite properties: the sentence, its numbers (rounded up, as
    printed), one per component (named by state), the size word and the bound's source."""
    data = cert.error_headline()
    if not data.proved or data.bound is None:
        return [("error_bound", data.reason)]
    text = C.error_headline_text(cert)
    props = [("error_bound", text.sentence), ("error_bound_value", upper_text(data.bound)),
             ("error_bound_noise", f"{data.noise:g}" if data.noise is not None else "")]
    if data.after is not None:
        props.append(("error_bound_after_seconds", upper_text(data.after, 2)))
    props += [(f"error_bound_e{i + 1}" + (f"_{name}" if name else ""), upper_text(v))
              for i, (name, v) in enumerate(data.components)]
    props += [("error_bound_size", text.size_word), ("error_bound_source", data.source),
              ("error_bound_basis", text.basis), ("error_bound_title", text.title)]
    return props


def render_internal_error(where: str, message: str, error_type: str) -> str:
    """JUnit XML for a run that stopped on an internal error (exit 4): one <error> case."""
    suite_attrs = {"name": "certify", "tests": "1", "failures": "0", "errors": "1",
                   "skipped": "0", "time": "0.000"}
    root = ET.Element("testsuites", {k: v for k, v in suite_attrs.items() if k != "skipped"})
    stamp = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
    suite = ET.SubElement(root, "testsuite", {**suite_attrs, "timestamp": stamp})
    case = ET.SubElement(suite, "testcase", {"classname": "certify", "name": where,
                                             "time": "0.000"})
    ET.SubElement(case, "error", {"message": f"internal error in {where}: {message}",
                                  "type": error_type}).text = (
        "certify stopped on an internal error: no certificate was made. This is a problem "
        "in certify, not a verdict on the network; re-run with --debug for the traceback.")
    ET.indent(root)
    return ET.tostring(root, encoding="unicode", xml_declaration=True) + "\n"
