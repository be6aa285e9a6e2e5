"""JUnit XML: one test case per check, so CI systems show the certificate natively.

PROVED and PASSED (evidence only) pass; VIOLATED is a <failure>; ERROR (the check failed
internally: certify's problem, not the network's) is an <error>; SKIPPED is <skipped>;
UNKNOWN is a <failure> by default (the policy `unknown="error"` reports it as an <error>,
to tell "could not decide" from "proved false" on dashboards). Every failure carries the
numbers of both sides. The gate itself is the exit code; JUnit reports every check,
required or not, and says which are required. When `certify run` stops on an internal error
(exit 4, no certificate), `render_internal_error` gives the one <error> case CI shows instead.
"""

from __future__ import annotations

import datetime as _dt
import xml.etree.ElementTree as ET

from certify.certificate import Certificate
from reports import content as C

UNKNOWN_POLICIES = ("failure", "error")


def _numbers_text(row: C.CheckRow) -> str:
    lines = [f"status: {row.status}" + (" (required)" if row.required else " (not required)"),
             f"message: {row.message}",
             f"sampled side: {row.sampled.label}: {row.sampled.text}",
             f"proved side: {row.proved.label}: {row.proved.text}",
             f"checked with: {row.setting}"]
    lines += [f"{k}: {v}" for k, v in row.numbers]
    return "\n".join(lines)


def render_junit(cert: Certificate, *, unknown: str = "failure") -> str:
    """JUnit XML (a <testsuites> document) for the certificate."""
    if unknown not in UNKNOWN_POLICIES:
        raise ValueError(f"unknown must be one of {UNKNOWN_POLICIES}; got {unknown!r}")
    rows = C.check_rows(cert)
    name = (cert.system or {}).get("name", "system")
    suite_name = f"certify.{name}"
    counts = {"failures": 0, "errors": 0, "skipped": 0}
    cases = []
    for row in rows:
        case = ET.Element("testcase", {"classname": suite_name, "name": row.name,
                                       "time": f"{row.seconds or 0.0:.3f}"})
        text = _numbers_text(row)
        tag_prefix = "" if row.required else "[not required] "
        msg = f"{tag_prefix}{row.status}: {row.message}"
        if row.status == "VIOLATED" or (row.status == "UNKNOWN" and unknown == "failure"):
            ET.SubElement(case, "failure", {"message": msg, "type": row.status}).text = text
            counts["failures"] += 1
        elif row.status == "ERROR" or row.status == "UNKNOWN":
            ET.SubElement(case, "error", {"message": msg, "type": row.status}).text = text
            counts["errors"] += 1
        else:
            if row.status == "SKIPPED":
                ET.SubElement(case, "skipped", {"message": msg})
                counts["skipped"] += 1
            ET.SubElement(case, "system-out").text = text
        cases.append(case)
    total_time = sum(r.seconds or 0.0 for r in rows)
    attrs = {"name": suite_name, "tests": str(len(cases)),
             **{k: str(v) for k, v in counts.items()}, "time": f"{total_time:.3f}"}
    root = ET.Element("testsuites", {"name": "certify", **{k: v for k, v in attrs.items()
                                                           if k != "name"}})
    suite = ET.SubElement(root, "testsuite", {**attrs, "timestamp": cert.created or ""})
    props = ET.SubElement(suite, "properties")
    ck = cert.checkpoint or {}
    for key, value in (("verdict", cert.verdict), ("summary", cert.summary),
                       ("required", ",".join(cert.required)),
                       ("checkpoint", str(ck.get("path", ""))),
                       ("sha256", str(ck.get("sha256", ""))), ("lam", C.fmt(cert.lam, 6)),
                       ("lam_cert", C.lam_cert_text(cert)),
                       ("unknown_policy", unknown)):
        ET.SubElement(props, "property", {"name": key, "value": value})
    suite.extend(cases)
    ET.indent(root)
    return ET.tostring(root, encoding="unicode", xml_declaration=True) + "\n"


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
