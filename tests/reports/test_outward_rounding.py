"""Every number a report prints for a sound bound is rounded outward, in every medium: a lower
bound printed is never above the value proved, an upper bound never below it (HTML, PDF,
JUnit, the terminal summary and the JSON's texts).

Property-based: certificates get random values for each bound (lam_cert, the residual and
Lipschitz brackets, the MPDI's, the dissipation rate and gain, the ISS bound's rate, gain and
bias, the headline, its settle time and its components, cond(P)), each medium is rendered
and its numbers are read back out of the text. A printed number that is a value rounded the
wrong way (to 3-8 significant digits; settle times to 2-8) is a failure. Numbers printed for
something else are told apart exactly: an example where a wrong rounding of one value could
also be a number the report prints for another reason (a fixture's own number, or a
rounding of another planted value) is skipped (`assume`).
"""

from __future__ import annotations

import dataclasses
import html as htmlmod
import io
import json
import re
import shutil
import subprocess
import tempfile
import xml.etree.ElementTree as ET
from collections.abc import Callable, Iterator
from decimal import ROUND_CEILING, ROUND_FLOOR, Decimal
from functools import cache
from pathlib import Path

import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from certify.certificate import Certificate
from certify.cli.display import print_summary
from reports import content as C
from reports.html import render_html
from reports.junit import render_junit
from reports.pdf import render_pdf

from .builders import HALF_DIAGONAL, headline_certificate

#: planted value -> the side it bounds ("lower": printed <= value; "upper": printed >= value)
KINDS = {
    "lam_cert": "lower", "lam_sampled": "upper",            # the rate's bracket
    "eps_sampled": "lower", "eps_bar": "upper",             # the residual's
    "L_sampled": "lower", "L": "upper", "L_sdp": "upper", "L_naive": "upper",
    "mpdi_found": "lower", "mpdi_upper": "upper",           # max lam_max(D) (negative)
    "alpha": "lower", "mu": "upper",                        # the dissipation inequality
    "iss_rate": "lower", "iss_gain": "upper", "iss_bias": "upper", "iss_slope": "upper",
    "headline": "upper", "settle": "upper", "ultimate": "upper",
    "pc1": "upper", "pc2": "upper", "kappa": "upper",
}
NEGATIVE = ("mpdi_found", "mpdi_upper")
#: the significant digits a renderer may print (settle times: 2, in "after t >= 1.1 s")
DIGITS = range(3, 9)
SETTLE_DIGITS = range(2, 9)
NUMBER = re.compile(r"[-+]?\d[\d,]*(?:\.\d+)?(?:e[-+]?\d+)?")


@cache
def _base() -> Certificate:
    return headline_certificate()


def planted(values: dict[str, float]) -> Certificate:
    """`headline_certificate` with `values` in every field the renderers print as a bound
    (the ISS bound the best, so the headline rests on the proved rate). The results are
    replaced, never changed: the fixture is built once."""
    cert = dataclasses.replace(_base(), checks=dict(_base().checks))
    c = cert.checks
    v = values
    c["rate"] = dataclasses.replace(c["rate"], proved_lower=v["lam_cert"],
                                    sampled_upper=v["lam_sampled"])
    c["residual"] = dataclasses.replace(c["residual"], sampled=v["eps_sampled"],
                                        upper=v["eps_bar"], structural=False)
    c["lipschitz"] = dataclasses.replace(c["lipschitz"], sampled=v["L_sampled"], value=v["L"],
                                         local_upper=v["L"], lipsdp=v["L_sdp"],
                                         naive=v["L_naive"], lipsdp_P=None)
    c["mpdi"] = dataclasses.replace(c["mpdi"], lower=v["mpdi_found"], upper=v["mpdi_upper"])
    c["dissipation"] = dataclasses.replace(c["dissipation"], alpha=v["alpha"], mu=v["mu"])
    b = c["bounds"]
    iss = dataclasses.replace(b.iss, name="iss", rate=v["iss_rate"], gain=v["iss_gain"],
                              bias=v["iss_bias"], bias_per_unit_noise=v["iss_slope"])
    c["bounds"] = dataclasses.replace(
        b, lam_cert=v["lam_cert"], eps_bar=v["eps_bar"], L=v["L"], iss=iss, iss_metric=None,
        dissipation=None, best="iss", ultimate=v["ultimate"], headline=v["headline"],
        settle_time=v["settle"], per_component=[v["pc1"], v["pc2"]], kappa_P=v["kappa"],
        vacuous=v["headline"] > HALF_DIAGONAL)
    return cert


def bounds_of(cert: Certificate, values: dict[str, float]
              ) -> dict[str, tuple[float, str, range]]:
    """Every bound the reports print: the planted values and the headline's components at
    t >= T (derived from them when the report is made), with their sides and the digits
    they may be printed with."""
    out = {k: (x, KINDS[k], SETTLE_DIGITS if k == "settle" else DIGITS)
           for k, x in values.items()}
    for i, (_, x) in enumerate(cert.error_headline().components):
        out[f"component{i + 1}"] = (x, "upper", DIGITS)
    return out


def directed(x: float, digits: int, rounding: str) -> Decimal:
    d = Decimal(x)
    return d.quantize(Decimal(1).scaleb(d.adjusted() - digits + 1), rounding=rounding)


def prints(x: float, side: str, *, wrong: bool, digits: range = DIGITS) -> set[Decimal]:
    """The texts `x` may be printed as when rounded towards `side`'s safe side (or, with
    `wrong`, the unsafe one), to `digits` significant digits; the exact value is never
    wrong."""
    up = (side == "upper") != wrong
    out = {directed(x, n, ROUND_CEILING if up else ROUND_FLOOR) for n in digits}
    return {d for d in out if not wrong or d != Decimal(x)}


def numbers(text: str) -> set[Decimal]:
    return {Decimal(t.replace(",", "")) for t in NUMBER.findall(text)}


# ----------------------------------------------------------------------------- the media

def html_text(cert: Certificate) -> str:
    page = render_html(cert, figures=[])
    return htmlmod.unescape(re.sub(r"<[^>]+>", " ", page))


def junit_text(cert: Certificate) -> str:
    root = ET.fromstring(render_junit(cert))
    return "\n".join([*(v for e in root.iter() for v in e.attrib.values()),
                      *(e.text or "" for e in root.iter())])


def terminal_text(cert: Certificate) -> str:
    """The summary as a pipe gets it, and as a (wide) terminal gets it from rich."""

    class Tty(io.StringIO):
        def isatty(self) -> bool:
            return True

    plain, tty = io.StringIO(), Tty()
    print_summary(cert, plain)
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("COLUMNS", "2000")
        print_summary(cert, tty)
    return plain.getvalue() + "\n" + tty.getvalue()


def json_text(cert: Certificate) -> str:
    """The texts of the JSON certificate (its numbers are the exact floats)."""

    def strings(node: object) -> Iterator[str]:
        if isinstance(node, str):
            yield node
        elif isinstance(node, dict):
            for v in node.values():
                yield from strings(v)
        elif isinstance(node, list):
            for v in node:
                yield from strings(v)

    return "\n".join(strings(json.loads(cert.to_json())))


def pdf_text(cert: Certificate) -> str:
    tool = shutil.which("pdftotext")
    if tool is None:
        pytest.skip("pdftotext (poppler-utils) is not installed")
    with tempfile.TemporaryDirectory() as tmp:
        f = Path(tmp) / "r.pdf"
        f.write_bytes(render_pdf(cert, figures=[]))
        return subprocess.run([tool, "-enc", "UTF-8", str(f), "-"], capture_output=True,
                              check=True, text=True).stdout


#: fixed values of the same shape, for the numbers a medium prints besides the planted ones
BASELINE = {k: (-1 if k in NEGATIVE else 1) * 1.2345678 * 1.7 ** i
            for i, k in enumerate(KINDS)}


@cache
def baseline_numbers(medium: str) -> frozenset[Decimal]:
    return frozenset(numbers(MEDIA[medium][0](planted(BASELINE))))


#: what the HTML and PDF reports show: every bound but the components' limits (they show
#: the components at t >= T)
SHOWN = tuple(k for k in KINDS if k not in ("pc1", "pc2")) + ("component1", "component2")
#: medium -> (its text, the bounds it must show)
MEDIA: dict[str, tuple[Callable[[Certificate], str], tuple[str, ...]]] = {
    "html": (html_text, SHOWN),
    "pdf": (pdf_text, SHOWN),
    "junit": (junit_text, ("lam_cert", "lam_sampled", "eps_bar", "L", "alpha", "mu",
                           "headline", "settle", "ultimate", "iss_bias", "mpdi_upper")),
    "terminal": (terminal_text, ("lam_cert", "lam_sampled", "L", "headline", "component1")),
    "json": (json_text, ("headline", "settle")),
}


@st.composite
def values(draw: st.DrawFn) -> dict[str, float]:
    out = {}
    for k in KINDS:
        x = 10 ** draw(st.floats(min_value=-2.5, max_value=3.5))
        out[k] = -x if k in NEGATIVE else x
    return out


def check_medium(medium: str, vals: dict[str, float]) -> None:
    cert = planted(vals)
    bounds = bounds_of(cert, vals)
    # a wrong rounding must not also be a number printed for something else
    wrong = {k: prints(x, side, wrong=True, digits=d) for k, (x, side, d) in bounds.items()}
    right = {k: prints(x, side, wrong=False, digits=d) for k, (x, side, d) in bounds.items()}
    for key, (x, side, _) in bounds.items():
        others = set(baseline_numbers(medium))
        for k2, (y, side2, _) in bounds.items():
            if k2 != key and (y, side2) != (x, side):
                others |= wrong[k2] | right[k2]
        assume(not wrong[key] & others)
    text_of, shown = MEDIA[medium]
    printed = numbers(text_of(cert))
    for key, (x, side, _) in bounds.items():
        bad = wrong[key] & printed
        assert not bad, (f"{medium}: {key} = {x!r} is a {side} bound, printed as "
                         f"{sorted(bad)} (rounded the wrong way)")
    missing = [k for k in shown if not right[k] & printed]
    assert not missing, f"{medium} does not show {missing}"


PROPERTY = settings(max_examples=25, deadline=None,
                    suppress_health_check=[HealthCheck.filter_too_much, HealthCheck.too_slow])


@pytest.mark.parametrize("medium", ["html", "junit", "terminal", "json"])
@PROPERTY
@given(vals=values())
def test_bounds_print_rounded_outward(medium, vals):
    check_medium(medium, vals)


@pytest.mark.slow
@settings(max_examples=12, deadline=None,
          suppress_health_check=[HealthCheck.filter_too_much, HealthCheck.too_slow])
@given(vals=values())
def test_pdf_bounds_print_rounded_outward(vals):
    check_medium("pdf", vals)


# ----------------------------------------------------------------------------- known cases

def test_the_reported_cases():
    """A proved lam_cert >= 2.53288 (sampled <= 2.53301) is never printed '[2.533, 2.533]',
    a proved L <= 0.61638 never '0.6163': the numbers a user saw beyond what was proved."""
    vals = dict(BASELINE, lam_cert=2.53288, lam_sampled=2.53301, L=0.61638)
    cert = planted(vals)
    facts = dict(C.system_facts(cert))
    assert facts["Contraction rate \u03bb_cert"] == "\u2208 [+2.532, +2.534]"
    assert "\u2208 [+2.532, +2.534]" in html_text(cert)
    for medium in ("html", "junit", "terminal"):
        printed = numbers(MEDIA[medium][0](cert))
        assert Decimal("2.533") not in printed and Decimal("0.6163") not in printed, medium
        assert Decimal("2.532") in printed and Decimal("0.6164") in printed, medium
