"""What a report says, decided once: number formatting, the checks table, the header facts.

HTML, PDF and JUnit renderers lay this content out; none of them formats a number itself,
so the three always agree. Everything here is a pure function of a `Certificate`. What each
check shows (its two sides, settings, numbers, facts) comes from the presenter beside the
check (`certify.checks.<name>`, as pure data); this module only formats and arranges it.
The per-check sections after the table are in `reports.sections`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from certify.certificate import Certificate
from certify.presentation import ErrorHeadline, Quantity, bound_text, special_text, upper_text
from certify.results import CheckFailure, Status

DASH = "\u2014"

#: the order checks appear in every report
CHECK_ORDER = ("necessary", "metric", "mpdi", "rate", "residual", "lipschitz", "dissipation",
               "metric_bound", "invariance", "bounds", "simulation")

STATUS_COLOURS = {  # text colour, background
    "PROVED": ("#14532d", "#dcfce7"),
    "PASSED": ("#1e3a8a", "#dbeafe"),
    "VIOLATED": ("#7f1d1d", "#fee2e2"),
    "UNKNOWN": ("#78350f", "#fef3c7"),
    "SKIPPED": ("#374151", "#e5e7eb"),
    "NOT APPLICABLE": ("#374151", "#e5e7eb"),
    "NOT RUN": ("#374151", "#e5e7eb"),
    "ERROR": ("#581c87", "#f3e8ff"),
    # a status with a qualifier ("PROVED — vacuous"): amber, never the plain colour of a pass
    "QUALIFIED": ("#78350f", "#fef3c7"),
}
#: the colours of the error headline's size word
SIZE_COLOURS = {"useful": STATUS_COLOURS["PROVED"], "vacuous": STATUS_COLOURS["QUALIFIED"]}
VERDICT_COLOURS = {"CERTIFIED": "#15803d", "NOT CERTIFIED": "#b91c1c", "INCONCLUSIVE": "#b45309"}

CONVENTION = ("Convention: He{M} = (M + M\u1d40)/2 and D = He{P (J_f + \u2202k/\u2202x\u0302)} "
              "+ 2\u03bbP. D \u2aaf 0 on X \u00d7 Y means the error contracts at rate 2\u03bb "
              "in the P-norm: \u2016P^\u00bd e(t)\u2016 \u2264 e^(\u22122\u03bbt) "
              "\u2016P^\u00bd e(0)\u2016 without noise or residual (rate 2\u03bb, not \u03bb).")

# ----------------------------------------------------------------------------- numbers

def to_float(x: Any) -> float | None:
    """A number to float; None, bools and anything else to None (no strings decoded here:
    a certificate read from JSON already holds floats, see `certify.results`)."""
    if x is None or isinstance(x, bool) or not isinstance(x, (int, float)):
        return None
    return float(x)


def fmt(x: Any, sig: int = 4, *, signed: bool = False, none: str = DASH) -> str:
    """A number with `sig` significant digits; None -> dash; NaN/Inf spelled out."""
    if x is None:
        return none
    if isinstance(x, bool):
        return "yes" if x else "no"
    if isinstance(x, int):
        return f"{x:+,d}" if signed else f"{x:,d}"
    v = to_float(x)
    if v is None:
        return str(x)
    special = special_text(v, signed)
    if special is not None:
        return special
    a = abs(v)
    if a >= 1e6 or a < 1e-3:
        s = f"{v:.{max(sig - 1, 0)}e}"
        mant, exp = s.split("e")
        s = f"{mant}e{int(exp)}"
    else:
        s = f"{v:.{sig}g}"
        if "e" in s:  # e.g. 1.235e+05 for sig=4
            s = f"{v:,.0f}"
    if signed and v > 0:
        s = "+" + s
    return s  # ASCII minus: searchable in the PDF and greppable in CI logs


def fmt_none(x: Any, reason: str, sig: int = 4, *, signed: bool = False) -> str:
    """Like `fmt`, but a None says why: '— (no proof attempted)'."""
    if x is None:
        return f"{DASH} ({reason})" if reason else DASH
    return fmt(x, sig, signed=signed)


def fmt_bound(x: Any, side: str, sig: int = 4, reason: str = "", *,
              signed: bool = False) -> str:
    """A sound bound on `side` ("upper" or "lower") rounded outward (`bound_text`), so the
    text never claims more than was proved; None (or a non-number) says why, as `fmt_none`."""
    v = to_float(x)
    if v is None:
        return fmt_none(None, reason) if x is None else fmt(x)
    return bound_text(v, side, sig, signed=signed)


def fmt_vec(v: Any, sig: int = 3) -> str:
    """A point as (a, b, c)."""
    if v is None:
        return DASH
    return "(" + ", ".join(fmt(a, sig) for a in v) + ")"


def fmt_seconds(s: Any) -> str:
    v = to_float(s)
    if v is None:
        return DASH
    if v < 1:
        return f"{v * 1000:.0f} ms"
    if v < 120:
        return f"{v:.3g} s"
    return f"{v / 60:.3g} min"


def fmt_matrix(M: Any, sig: int = 4) -> str:
    """A matrix as [[a, b], [c, d]] on one line."""
    if M is None:
        return DASH
    return "[" + ", ".join("[" + ", ".join(fmt(a, sig) for a in row) + "]" for row in M) + "]"


def fmt_box(B: Any, names: list[str] | None = None) -> str:
    """A box as 'x1 ∈ [-2, 2], x2 ∈ [-3, 3]'."""
    if not B:
        return DASH
    names = names or [f"z{i + 1}" for i in range(len(B))]
    return ", ".join(f"{n} \u2208 [{fmt(lo)}, {fmt(hi)}]" for n, (lo, hi) in zip(names, B))


# ----------------------------------------------------------------------------- checks table

@dataclass(frozen=True)
class Side:
    """One side of a check: what the number bounds, the number, and why it is missing."""

    label: str
    value: str
    note: str = ""

    @property
    def text(self) -> str:
        return f"{self.value} ({self.note})" if self.note else self.value


@dataclass(frozen=True)
class CheckRow:
    """One line of the checks table (and one JUnit test case)."""

    name: str
    title: str
    status: str
    required: bool
    sampled: Side
    proved: Side
    setting: str
    message: str
    seconds: float | None
    numbers: list[tuple[str, str]] = field(default_factory=list)  # every number, for JUnit
    #: a word that qualifies the status (the presenter's `qualifier`, e.g. "vacuous")
    qualifier: str = ""

    @property
    def badge(self) -> str:
        """The status as every report shows it: 'PROVED' or 'PROVED — vacuous'."""
        return badge(self.status, self.qualifier)

    @property
    def badge_key(self) -> str:
        """The key of the badge's colours in `STATUS_COLOURS` (and its HTML class)."""
        return badge_key(self.status, self.qualifier)


def badge(status: str, qualifier: str = "") -> str:
    """A status with its qualifier: 'PROVED — vacuous'."""
    return f"{status} {DASH} {qualifier}" if qualifier else status


def badge_key(status: str, qualifier: str = "") -> str:
    """'QUALIFIED' for a qualified status (amber), else the status itself."""
    return "QUALIFIED" if qualifier else status


def fmt_value(v: Any, sig: int = 4, *, signed: bool = False) -> str:
    """Any value a presenter gives: word, number, point (list) or matrix (list of lists)."""
    if isinstance(v, str):
        return v
    if isinstance(v, (list, tuple)):
        if v and isinstance(v[0], (list, tuple)):
            return fmt_matrix(v, sig)
        return fmt_vec(v, sig)
    return fmt(v, sig, signed=signed)


def side(q: Quantity) -> Side:
    """A presenter's Quantity as a formatted Side (the dash and the reason when missing)."""
    if q.value is None:
        return Side(q.label, DASH, q.missing)
    if q.bound and to_float(q.value) is not None and not isinstance(q.value, bool):
        return Side(q.label, bound_text(to_float(q.value), q.bound, q.sig, signed=q.signed)
                    + q.suffix)
    return Side(q.label, fmt_value(q.value, q.sig, signed=q.signed) + q.suffix)


def pairs(quantities: Any) -> list[tuple[str, str]]:
    """Quantities as formatted (label, text) pairs."""
    return [(q.label, side(q).text) for q in quantities]


def setting_text(quantities: Any) -> str:
    """What a check ran with, on one line: 'grid points ≥ 1,000,000; proof budget 60 s'."""
    return "; ".join(f"{q.label} {side(q).text}" for q in quantities)


def check_names(cert: Certificate) -> list[str]:
    """Checks to report: every check present, plus required ones that were not run."""
    names = [n for n in CHECK_ORDER if n in cert.checks or n in cert.required]
    names += [n for n in cert.checks if n not in names]
    return names




def check_rows(cert: Certificate) -> list[CheckRow]:
    """One `CheckRow` per reported check, in report order, from each check's presenter."""
    rows = []
    for name in check_names(cert):
        r = cert.checks.get(name)
        title = cert.title(name)
        required = name in cert.required
        if r is None:
            rows.append(CheckRow(name, title, Status.SKIPPED.value, required,
                                 Side("", DASH), Side("", DASH), "", "not run", None))
            continue
        pres = cert.presentation(name)
        qualifier = ""
        if pres is None:
            sampled, proved, setting, nums = Side("", DASH), Side("", DASH), "", []
        else:
            sampled, proved = side(pres.sampled), side(pres.proved)
            setting, nums = setting_text(pres.setting), pairs(pres.numbers)
            qualifier = getattr(pres, "qualifier", "")
        seconds = to_float((cert.timings or {}).get(name))
        if seconds is None:
            seconds = to_float(getattr(r, "seconds", None))
        rows.append(CheckRow(name, title, r.status.value, required, sampled, proved, setting,
                             r.message, seconds, nums, qualifier))
    return rows


def check_facts(cert: Certificate, name: str) -> list[tuple[str, str]]:
    """The key facts of a check's section, from its presenter (empty if it did not run)."""
    pres = cert.presentation(name)
    return [] if pres is None else pairs(pres.facts)


def result(cert: Certificate, name: str) -> Any:
    """The check's own result, or None when it did not run or failed (`CheckFailure`)."""
    r = cert.checks.get(name)
    return None if r is None or isinstance(r, CheckFailure) else r


# ----------------------------------------------------------------------------- facts

def lam_cert_text(cert: Certificate) -> str:
    """lam_cert as the bracket the rate check established, rounded outward: the proved
    lower end down, the sampled upper end up ('∈ [2.532, 2.534]')."""
    rate = result(cert, "rate")
    if rate is None:
        b = result(cert, "bounds")
        return (f"\u2265 {bound_text(b.lam_cert, 'lower', 4, signed=True)}"
                if b is not None and to_float(b.lam_cert) is not None
                else f"{DASH} (rate not checked)")
    upper = (DASH if to_float(rate.sampled_upper) is None
             else bound_text(rate.sampled_upper, "upper", 4, signed=True))
    if to_float(rate.proved_lower) is None:
        return f"\u2264 {upper} (sampled); no proved lower bound"
    return f"\u2208 [{bound_text(rate.proved_lower, 'lower', 4, signed=True)}, {upper}]"


def system_facts(cert: Certificate) -> list[tuple[str, str]]:
    """(label, value) pairs for the system section."""
    sy = cert.system or {}
    states = sy.get("states") or []
    outputs = sy.get("outputs") or []
    f = sy.get("f") or []
    h = sy.get("h") or []
    facts = [("System", f"{sy.get('name', DASH)}: {sy.get('description', '')}".strip(": "))]
    facts += [(f"f{i + 1} = d{states[i] if i < len(states) else i + 1}/dt", e)
              for i, e in enumerate(f)]
    facts += [(f"h{i + 1} = {outputs[i] if i < len(outputs) else ''}", e)
              for i, e in enumerate(h)]
    facts += [("X (state box)", fmt_box(sy.get("X"), states)),
              ("Y (output box)", fmt_box(sy.get("Y"), outputs)),
              ("Metric P", fmt_matrix(cert.P))]
    metric = result(cert, "metric")
    bounds = result(cert, "bounds")
    if metric is not None and metric.condition_number is not None:
        facts.append(("cond(P)", fmt(metric.condition_number)))
    elif bounds is not None and to_float(bounds.kappa_P) is not None:  # a sound upper bound
        facts.append(("cond(P)", f"\u2264 {bound_text(bounds.kappa_P, 'upper', 4)}"))
    facts += [("Design rate \u03bb", fmt(cert.lam)),
              ("Contraction rate \u03bb_cert", lam_cert_text(cert))]
    net = cert.network or {}
    if net:
        hidden = net.get("hidden")
        arch = (f"tanh MLP on (x\u0302, y), hidden {hidden}, structure "
                f"{net.get('structure', DASH)}")
        if net.get("parameters"):
            arch += f", {fmt(net['parameters'])} parameters"
        facts.append(("Gain network", arch))
    return facts


def provenance_facts(cert: Certificate) -> list[tuple[str, str]]:
    """Checkpoint, creation time, training summary."""
    ck = cert.checkpoint or {}
    facts = [("Checkpoint", str(ck.get("path", DASH))),
             ("Checkpoint sha256", str(ck.get("sha256", DASH))),
             ("Checkpoint created", str(ck.get("created", DASH) or DASH)),
             ("Certificate created", cert.created or DASH),
             ("Schema", f"{cert.schema} v{cert.schema_version}")]
    training = ck.get("training") or {}
    if training:
        facts.append(("Training", ", ".join(f"{k} = {fmt(v) if not isinstance(v, str) else v}"
                                            for k, v in training.items()
                                            if not isinstance(v, (list, dict)))))
    return facts


def kv_pairs(d: dict[str, Any] | None) -> list[tuple[str, str]]:
    """A flat mapping as formatted (key, value) pairs (lists joined)."""
    out = []
    for k, v in (d or {}).items():
        if isinstance(v, (list, tuple)):
            v = ", ".join(str(a) for a in v) or DASH
        elif isinstance(v, dict):
            v = ", ".join(f"{a}={b}" for a, b in v.items()) or DASH
        elif not isinstance(v, str):
            v = fmt(v, 6)
        out.append((str(k), v))
    return out


def timing_pairs(cert: Certificate) -> list[tuple[str, str]]:
    return [(k, fmt_seconds(v)) for k, v in (cert.timings or {}).items()]


def box_words(box: Any, names: Any = None) -> str:
    """'x1 in [-2.5, 2.5], x2 in [-3.3, 3.3]' (4 digits: words, not bounds)."""
    names = list(names or [])
    return ", ".join(f"{names[i] if i < len(names) else f'x{i + 1}'} in [{fmt(lo)}, {fmt(hi)}]"
                     for i, (lo, hi) in enumerate(box or []))


def verdict_notes(cert: Certificate) -> list[str]:
    """What the verdict alone does not say: a true certificate whose bound says little, and
    a plant whose attractor leaves X (the bound cannot hold for a plant on it)."""
    notes = []
    inv = result(cert, "invariance")
    if inv is not None and getattr(inv, "attractor_leaves_box", False):
        names = (cert.system or {}).get("states")
        where = box_words(inv.attractor_box, names)
        notes.append(f"the plant's simulated attractor leaves X ({where}): the error bound "
                     "holds only while the plant is in X, not for a plant that has settled "
                     f"on its attractor; a box that holds it: "
                     f"{box_words(inv.suggested_box, names)} (leave room for the estimation "
                     "error too)")
    b = result(cert, "bounds")
    if b is not None and getattr(b, "vacuous", False):
        # the number judged vacuous: the headline (an older certificate: the best limit)
        shown = getattr(b, "headline", None)
        limit = b.ultimate if b.ultimate is not None else min(
            (x.bias for x in b.bounds() if x.applicable and x.bias is not None), default=None)
        if shown is None:
            shown, limit = limit, None
        text = DASH if shown is None else upper_text(float(shown))
        if limit is not None and upper_text(float(limit)) != text:
            text += f" (limit {upper_text(float(limit))})"
        notes.append(f"the proved error bound {text} is valid but vacuous: larger than "
                     f"the box (half-diagonal of X {fmt(b.box_half_diagonal)})")
    return notes


# ----------------------------------------------------------------------------- error headline

@dataclass(frozen=True)
class HeadlineText:
    """The error bound, the second headline after the verdict, as the lines every medium
    shows (`error_headline_text`): `title` (the heading: 'Certified error bound' only under
    a CERTIFIED verdict, else what the bound rests on: `ErrorHeadline.title`), `note` (that
    qualification alone, '' for a certified bound), `sentence` ('‖e‖ ≤ 1.25 for noise ≤
    0.15 after t ≥ 3.1 s', or the reason there is none), `components` ('|e1| ≤ 0.396 (x1),
    ...'), `size_word` ('useful' / 'vacuous', '' without a bound), `size` (the word with
    the box's half-diagonal), `source` (which bound it comes from: small print), `basis`
    (`certify.presentation.BASES`, '' without a bound), `validity` (the bound with its
    conditions proved for a set of starts: `ErrorHeadline.validity_text`, '' without)."""

    proved: bool
    sentence: str
    components: str = ""
    size_word: str = ""
    size: str = ""
    source: str = ""
    title: str = "Error bound"
    note: str = ""
    basis: str = ""
    #: the bound with its conditions proved for a set of starts ('' without a region)
    validity: str = ""

    @property
    def label(self) -> str:
        """'error bound' and, when it does not rest on the certificate, what it rests on in
        parentheses: what the terminal and JUnit put before the sentence."""
        return "error bound" + (f" ({self.note})" if self.note else "")

    @property
    def line(self) -> str:
        """One line: 'error bound: <sentence>; <components>; <size> [<source>]' (with the
        note after 'error bound' when there is one), or the reason there is none."""
        if not self.proved:
            return self.sentence
        parts = [self.sentence] + ([self.components] if self.components else []) + [self.size]
        return (f"{self.label}: " + "; ".join(parts)
                + (f" [{self.source}]" if self.source else ""))


def error_headline(cert: Certificate) -> ErrorHeadline:
    """The error headline's data (`Certificate.error_headline`)."""
    return cert.error_headline()


def error_headline_text(cert: Certificate, *, unicode: bool = True) -> HeadlineText:
    """The error headline as text: Unicode (‖e‖ ≤) where the medium allows, else ASCII."""
    h = error_headline(cert)
    if not h.proved:
        return HeadlineText(False, h.reason)
    return HeadlineText(True, h.sentence(unicode), h.components_text(unicode), h.size_word(),
                        h.size_text(), h.source_text(unicode), h.title(unicode),
                        h.note(unicode), h.basis, h.validity_text(unicode))


def verdict_summary(cert: Certificate) -> str:
    """The summary with its notes: what the verdict line, the HTML and the PDF show."""
    return "; ".join([cert.summary, *(f"note: {n}" for n in verdict_notes(cert))])


def verdict_line(cert: Certificate) -> str:
    """The one line a terminal, a log or a banner shows: verdict, summary, notes."""
    return f"{cert.verdict}: {verdict_summary(cert)}"
