"""What a report says, decided once: number formatting, the checks table, section facts.

HTML, PDF and JUnit renderers lay this content out; none of them formats a number itself,
so the three always agree. Everything here is a pure function of a `Certificate`. What each
check shows (its two sides, settings, numbers, facts) comes from the presenter beside the
check (`certify.checks.<name>`, as pure data); this module only formats and arranges it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from certify.certificate import Certificate
from certify.checks.base import Quantity
from certify.checks.registry import get_check, presentation
from certify.results import CheckFailure, Status

DASH = "\u2014"

#: the order checks appear in every report
CHECK_ORDER = ("necessary", "metric", "mpdi", "rate", "residual", "lipschitz", "bounds",
               "simulation")

STATUS_COLOURS = {  # text colour, background
    "PROVED": ("#14532d", "#dcfce7"),
    "PASSED": ("#1e3a8a", "#dbeafe"),
    "VIOLATED": ("#7f1d1d", "#fee2e2"),
    "UNKNOWN": ("#78350f", "#fef3c7"),
    "SKIPPED": ("#374151", "#e5e7eb"),
    "ERROR": ("#581c87", "#f3e8ff"),
}
VERDICT_COLOURS = {"CERTIFIED": "#15803d", "NOT CERTIFIED": "#b91c1c", "INCONCLUSIVE": "#b45309"}

CONVENTION = ("Convention: He{M} = (M + M\u1d40)/2 and D = He{P (J_f + \u2202k/\u2202x\u0302)} "
              "+ 2\u03bbP. D \u2aaf 0 on X \u00d7 Y means the error contracts at rate 2\u03bb "
              "in the P-norm: \u2016P^\u00bd e(t)\u2016 \u2264 e^(\u22122\u03bbt) "
              "\u2016P^\u00bd e(0)\u2016 without noise or residual (rate 2\u03bb, not \u03bb).")

THEOREM3_TEXT = (
    "Theorem 3 of the source (as stated; He{M} = (M + M\u1d40)/2, P = I): if \u03bb > 2, "
    "\u03b7 = \u03bb \u2212 2 and the noise satisfies \u2016v(t)\u2016 \u2264 v\u0304, then "
    "\u2016x(t) \u2212 x\u0302(t)\u2016 \u2264 \u2016x(0) \u2212 x\u0302(0)\u2016 "
    "e^(\u2212\u03b7t) "
    "+ \u03b5\u0304 / (2\u221a\u03b7) + L v\u0304 / (2\u221a\u03b7). The certificate applies it "
    "with the certified rate \u03bb_cert, never the design \u03bb.")

ISS_TEXT = (
    "ISS bound (METHOD \u00a73.7): if D \u2aaf 0 holds for k itself on X \u00d7 Y with metric P, "
    "and x, x\u0302 stay in X while y and y_e stay in Y, then with W = \u2016P^\u00bd e\u2016: "
    "W\u2032 \u2264 \u22122\u03bbW + \u2016P^\u00bd\u2016\u2082 (\u03b5\u0304 + L v\u0304), so "
    "\u2016e(t)\u2016 \u2264 (e^(\u22122\u03bbt) W(0) + (1 \u2212 e^(\u22122\u03bbt)) "
    "\u2016P^\u00bd\u2016\u2082 (\u03b5\u0304 + L v\u0304) / (2\u03bb)) / \u221a\u03bb_min(P). "
    "It needs no \u03bb > 2; for P = I and \u03bb > 2 it is never larger than Theorem 3's.")

NECESSARY_TEXT = (
    "For any C\u00b9 gain with exact boundary condition k(x, h(x)) = 0, on the output manifold "
    "the MPDI restricted to the kernel of \u2202h/\u2202x\u0302 does not depend on the network: "
    "q(x\u0302) = \u03bb_max(Z\u1d40 (He{P J_f} + 2\u03bbP) Z), Z an orthonormal basis of "
    "ker \u2202h/\u2202x\u0302. If q > 0 anywhere, no gain at all satisfies MPDI and boundary "
    "condition together with this P and \u03bb.")


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
    if math.isnan(v):
        return "NaN"
    if math.isinf(v):
        return ("+\u221e" if signed else "\u221e") if v > 0 else "-\u221e"
    if v == 0:
        return "0"
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


def check_title(name: str) -> str:
    try:
        return get_check(name).title or name
    except KeyError:
        return name


def check_rows(cert: Certificate) -> list[CheckRow]:
    """One `CheckRow` per reported check, in report order, from each check's presenter."""
    rows = []
    for name in check_names(cert):
        r = cert.checks.get(name)
        title = check_title(name)
        required = name in cert.required
        if r is None:
            rows.append(CheckRow(name, title, Status.SKIPPED.value, required,
                                 Side("", DASH), Side("", DASH), "", "not run", None))
            continue
        pres = presentation(name, r, cert)
        if pres is None:
            sampled, proved, setting, nums = Side("", DASH), Side("", DASH), "", []
        else:
            sampled, proved = side(pres.sampled), side(pres.proved)
            setting, nums = setting_text(pres.setting), pairs(pres.numbers)
        seconds = to_float((cert.timings or {}).get(name))
        if seconds is None:
            seconds = to_float(getattr(r, "seconds", None))
        rows.append(CheckRow(name, title, r.status.value, required, sampled, proved, setting,
                             r.message, seconds, nums))
    return rows


def check_facts(cert: Certificate, name: str) -> list[tuple[str, str]]:
    """The key facts of a check's section, from its presenter (empty if it did not run)."""
    r = cert.checks.get(name)
    pres = None if r is None else presentation(name, r, cert)
    return [] if pres is None else pairs(pres.facts)


def result(cert: Certificate, name: str) -> Any:
    """The check's own result, or None when it did not run or failed (`CheckFailure`)."""
    r = cert.checks.get(name)
    return None if r is None or isinstance(r, CheckFailure) else r


# ----------------------------------------------------------------------------- facts

def lam_cert_text(cert: Certificate) -> str:
    """lam_cert as the bracket the rate check established."""
    rate = result(cert, "rate")
    if rate is None:
        b = result(cert, "bounds")
        return fmt(b.lam_cert) if b is not None and b.lam_cert is not None else \
            f"{DASH} (rate not checked)"
    if rate.proved_lower is None:
        return f"\u2264 {fmt(rate.sampled_upper)} (sampled); no proved lower bound"
    return f"\u2208 [{fmt(rate.proved_lower)}, {fmt(rate.sampled_upper)}]"


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
    cond = (metric.condition_number if metric is not None else
            bounds.kappa_P if bounds is not None else None)
    if cond is not None:
        facts.append(("cond(P)", fmt(cond)))
    facts += [("Design rate \u03bb", fmt(cert.lam)),
              ("Certified rate \u03bb_cert", lam_cert_text(cert))]
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


def verdict_line(cert: Certificate) -> str:
    return f"{cert.verdict}: {cert.summary}"


def counterexample_rows(cert: Certificate, limit: int = 10) -> list[list[str]]:
    r = result(cert, "mpdi")
    if r is None:
        return []
    return [[str(i + 1), fmt_vec(c.xhat, 4), fmt_vec(c.y, 4), fmt(c.value, 5, signed=True)]
            for i, c in enumerate(r.counterexamples[:limit])]


def proof_facts(cert: Certificate) -> list[tuple[str, str]]:
    r = result(cert, "mpdi")
    if r is None or r.proof is None:
        return []
    p = r.proof
    return [("Boxes processed", fmt(p.boxes_processed)),
            ("Boxes per second", fmt(p.boxes_per_second)),
            ("Prover time", fmt_seconds(p.seconds)),
            ("Proved volume", f"{100 * (to_float(p.proved_volume_fraction) or 0):.2f} %"),
            ("Maximum depth", fmt(p.max_depth)),
            ("Budget exhausted", fmt(p.budget_exhausted)),
            ("Floating-point soundness", p.rounding or DASH)]


def lipschitz_rows(cert: Certificate) -> list[list[str]]:
    """[bound, value, sound?, note] rows, LipSDP / local / naive / sampled side by side."""
    r = result(cert, "lipschitz")
    if r is None:
        return []
    used = r.which

    def mark(key: str) -> str:
        return "used" if key == used else ""

    lmi = fmt(r.lipsdp_lmi_max_eig, 3, signed=True)
    return [
        ["LipSDP (verified)", fmt_none(r.lipsdp, "not verified"), "upper, sound",
         f"raw {fmt(r.lipsdp_raw)}; rebuilt LMI \u03bb_max {lmi}", mark("lipsdp")],
        ["Local interval bound", fmt_none(r.local_upper, "not computed"), "upper, sound",
         "sup \u2016\u2202k/\u2202y\u2016\u2082 over X \u00d7 Y (needs y_e \u2208 Y)",
         mark("local")],
        ["Naive (product of norms)", fmt(r.naive), "upper, sound", "", mark("naive")],
        ["Sampled", fmt(r.sampled), "lower", "max \u2016\u2202k/\u2202y\u2016\u2082 found",
         ""],
        ["LipSDP for P^\u00bd k", fmt_none(r.lipsdp_P, "not computed"), "upper, sound",
         "for the P-weighted ISS bound", ""],
    ]


def bound_rows(cert: Certificate) -> list[list[str]]:
    """[name, applicable, reason, rate, gain, bias, d bias / d vbar] per bound."""
    r = result(cert, "bounds")
    if r is None:
        return []
    rows = []
    for b in (r.theorem3, r.iss, r.iss_metric):
        if b is None:
            continue
        rows.append([b.name, "yes" if b.applicable else "no", b.reason,
                     fmt(b.rate), fmt(b.gain), fmt(b.bias), fmt(b.bias_per_unit_noise)])
    return rows


def simulation_rows(cert: Certificate) -> list[list[str]]:
    r = result(cert, "simulation")
    if r is None:
        return []
    rows = []
    for run in r.runs:
        rows.append([run.label, fmt_vec(run.x0), fmt_vec(run.xhat0), run.noise,
                     "yes" if run.within_conditions else "no",
                     fmt_none(run.exit_time, "never") if run.exit_time is not None
                     else "never",
                     run.exit_reason or DASH, fmt(run.max_ratio),
                     "BREACH" if run.breach else "no", fmt(run.mse, 3),
                     fmt(run.final_error, 3)])
    return rows


SIM_HEADER = ["Run", "x(0)", "x\u0302(0)", "Noise", "Valid", "Exit at", "Exit reason",
              "Max e/b", "Breach", "MSE", "Final \u2016e\u2016"]


# ----------------------------------------------------------------------------- sections

@dataclass
class Table:
    """A plain table: header, rows of strings, relative column widths (for the PDF)."""

    header: list[str]
    rows: list[list[str]]
    title: str = ""
    widths: list[float] | None = None
    fixed: bool = True


@dataclass
class Section:
    """One report section after the checks table, in the same form for HTML and PDF."""

    anchor: str
    title: str
    short: str = ""
    status: str = ""
    message: str = ""
    paragraphs: list[str] = field(default_factory=list)
    statements: list[str] = field(default_factory=list)
    facts: list[tuple[str, str]] = field(default_factory=list)
    tables: list[Table] = field(default_factory=list)
    bullets: list[str] = field(default_factory=list)
    bullets_title: str = ""
    empty: str = ""

    @property
    def tone(self) -> str:
        return {"PROVED": "good", "PASSED": "good", "VIOLATED": "bad", "ERROR": "bad",
                "UNKNOWN": "warn"}.get(self.status, "")


def _status(cert: Certificate, name: str) -> str:
    r = cert.checks.get(name)
    return "" if r is None else r.status.value


def _message(cert: Certificate, name: str) -> str:
    r = cert.checks.get(name)
    return "" if r is None else r.message


def _without_result(sec: Section, cert: Certificate, name: str, empty: str) -> None:
    """A section whose check has no result: why (ERROR, not applicable) or `empty`."""
    if name in cert.checks:
        sec.facts = check_facts(cert, name)
    else:
        sec.empty = empty


def sections(cert: Certificate) -> list[Section]:
    """The report's sections after the checks table (system facts are separate)."""
    out: list[Section] = []

    sec = Section("mpdi", "MPDI: D(x\u0302, y) \u2aaf 0 on X \u00d7 Y", "MPDI",
                  _status(cert, "mpdi"),
                  _message(cert, "mpdi"))
    sec.paragraphs.append(
        "D(x\u0302, y) = He{P (J_f(x\u0302) + \u2202k/\u2202x\u0302(x\u0302, y))} + 2\u03bbP must "
        "be negative semidefinite everywhere on the box. The sampled side (dense grid and "
        "multi-start gradient ascent) can only find violations: any point with "
        "\u03bb_max(D) > 0 is a counterexample. The proved side is a sound upper bound from "
        "interval branch and bound; only it can prove the MPDI.")
    if result(cert, "mpdi") is not None:
        sec.facts = check_facts(cert, "mpdi")
        cex = counterexample_rows(cert)
        if cex:
            sec.tables.append(Table(["#", "x\u0302", "y", "\u03bb_max(D)"], cex,
                                    "Counterexamples (largest first)", [0.6, 3, 2, 1.6]))
        proof = proof_facts(cert)
        if proof:
            sec.tables.append(Table(["Prover statistic", "Value"], [list(p) for p in proof],
                                    "Proof statistics", [1, 2]))
    else:
        _without_result(sec, cert, "mpdi", "The MPDI check was not run.")
    out.append(sec)

    if "rate" in cert.checks:
        r = result(cert, "rate")
        sec = Section("rate", "Certified contraction rate \u03bb_cert", "Rate",
                      _status(cert, "rate"), _message(cert, "rate"))
        sec.paragraphs.append(
            "\u03bb_cert = \u2212max \u03bb_max(He{P (J_f + \u2202k/\u2202x\u0302)}, P) / 2 is the "
            "largest rate for which the MPDI holds. Every error bound below uses \u03bb_cert "
            "(it may be below the design \u03bb); if \u03bb_cert \u2264 0 there is no bound "
            "at all.")
        sec.facts = check_facts(cert, "rate")
        if r is not None:
            sec.facts.append(("Bracket", lam_cert_text(cert)))
        out.append(sec)

    sec = Section("necessary", "Pre-flight necessary condition (independent of the network)",
                  "Necessary condition", _status(cert, "necessary"), _message(cert, "necessary"))
    sec.paragraphs.append(NECESSARY_TEXT)
    r = result(cert, "necessary")
    if r is not None:
        if r.explanation:
            sec.statements.append(r.explanation)
        sec.facts = check_facts(cert, "necessary")
    else:
        _without_result(sec, cert, "necessary", "The necessary condition was not checked.")
    out.append(sec)

    if "metric" in cert.checks:
        sec = Section("metric", "Metric P found by SDP", "Metric", _status(cert, "metric"),
                      _message(cert, "metric"))
        sec.facts = check_facts(cert, "metric")
        out.append(sec)

    sec = Section("residual", "Boundary residual \u03b5\u0304 = sup over X of "
                              "\u2016k(x, h(x))\u2016", "Residual", _status(cert, "residual"),
                  _message(cert, "residual"))
    sec.paragraphs.append(
        "The boundary condition k(x, h(x)) = 0 says the correction vanishes when the estimate "
        "is exact; its residual \u03b5\u0304 enters every error bound as a bias.")
    if result(cert, "residual") is not None:
        sec.facts = check_facts(cert, "residual")
    else:
        _without_result(sec, cert, "residual", "The residual was not checked.")
    out.append(sec)

    sec = Section("lipschitz", "Lipschitz constant L of k in y", "Lipschitz",
                  _status(cert, "lipschitz"),
                  _message(cert, "lipschitz"))
    r = result(cert, "lipschitz")
    if r is not None:
        sec.paragraphs.append(
            "L bounds how much measurement noise moves the correction, uniformly in "
            "x\u0302 (an L2 \u2192 L2 constant, so v\u0304 bounds the Euclidean norm of the "
            "noise). LipSDP is re-verified by rebuilding its LMI at the solver's multipliers; "
            "the smallest sound upper bound is used downstream. The gap to the sampled lower "
            f"bound measures how tight it is. Used: {r.which or DASH} = {fmt(r.value)}.")
        sec.tables.append(Table(["Bound", "Value", "Kind", "Note", "Used"],
                                lipschitz_rows(cert), "", [1.6, 1.1, 0.9, 2.6, 0.5]))
        sec.facts = check_facts(cert, "lipschitz")
    else:
        _without_result(sec, cert, "lipschitz", "The Lipschitz constant was not computed.")
    out.append(sec)

    sec = Section("bounds", "Error bounds: Theorem 3 as stated and the ISS bound",
                  "Bounds", _status(cert, "bounds"), _message(cert, "bounds"))
    sec.statements = [THEOREM3_TEXT, ISS_TEXT]
    b = result(cert, "bounds")
    if b is not None:
        sec.facts = check_facts(cert, "bounds")
        rows = bound_rows(cert)
        if rows:
            sec.tables.append(Table(["Bound", "Applies", "Why (not)", "Rate", "Gain", "Bias b",
                                     "db/dv\u0304"], rows, "Conditions and numbers",
                                    [1.4, 0.7, 3.0, 0.8, 0.8, 0.8, 0.8]))
        formulas = [(x.name, x.formula) for x in (b.theorem3, b.iss, b.iss_metric)
                    if x is not None and x.formula]
        if formulas:
            sec.tables.append(Table(["Bound", "Formula"], [list(f) for f in formulas],
                                    "Formulas", [1, 4]))
        sec.bullets = list(b.validity)
        sec.bullets_title = ("Validity conditions (each holds up to its first failure time; "
                             "no bound is claimed after it)")
    else:
        _without_result(sec, cert, "bounds", "No bounds were computed.")
    out.append(sec)

    sec = Section("simulation", "Simulation: plant and observer under noise",
                  "Simulation", _status(cert, "simulation"), _message(cert, "simulation"))
    s = result(cert, "simulation")
    if s is not None:
        exits = [run for run in s.runs if run.exit_time is not None]
        sec.paragraphs.append(
            "Plant and observer simulated from several initial conditions. While the validity "
            "conditions hold the observed error must stay under the proved bound (a breach is "
            "a bug in the tool, never a pass). Exits from X or Y (the source's Assumption 1, "
            "forward invariance) are reported, and runs with Gaussian noise are outside the "
            "theorem's conditions." + (f" {len(exits)} of {len(s.runs)} runs exit."
                                       if s.runs else ""))
        sec.tables.append(Table(SIM_HEADER, simulation_rows(cert), "Runs",
                                [1.3, 0.95, 0.8, 0.85, 0.65, 0.6, 2.1, 0.7, 0.75, 0.8, 0.8]))
    else:
        _without_result(sec, cert, "simulation", "No simulation was run.")
    out.append(sec)
    return out
