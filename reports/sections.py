"""The report's sections after the checks table: per check, its prose, facts and tables.

Facts come from each check's presenter (`reports.content.check_facts`); what is here is the
part of a section that is layout and explanation (the theorem statements, the tables of
counterexamples, prover statistics, Lipschitz bounds, error bounds and simulation runs).
HTML and PDF lay these `Section`s out the same way.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from certify.certificate import Certificate
from certify.presentation import validity_sentence
from reports.content import (
    DASH,
    badge,
    badge_key,
    check_facts,
    fmt,
    fmt_bound,
    fmt_seconds,
    fmt_vec,
    lam_cert_text,
    result,
    to_float,
)

THEOREM3_TEXT = (
    "Theorem 3 of the source (as stated; He{M} = (M + M\u1d40)/2, P = I): if \u03bb > 2, "
    "\u03b7 = \u03bb \u2212 2 and the noise satisfies \u2016v(t)\u2016 \u2264 v\u0304, then "
    "\u2016x(t) \u2212 x\u0302(t)\u2016 \u2264 \u2016x(0) \u2212 x\u0302(0)\u2016 "
    "e^(\u2212\u03b7t) "
    "+ \u03b5\u0304 / (2\u221a\u03b7) + L v\u0304 / (2\u221a\u03b7). The certificate applies it "
    "with the proved rate \u03bb_cert, never the design \u03bb.")

ISS_TEXT = (
    "ISS bound (METHOD \u00a73.7): if D \u2aaf 0 holds for k itself on X \u00d7 Y with metric P, "
    "and x, x\u0302 stay in X while y and y_e stay in Y, then with W = \u2016P^\u00bd e\u2016: "
    "W\u2032 \u2264 \u22122\u03bbW + \u2016P^\u00bd\u2016\u2082 (\u03b5\u0304 + L v\u0304), so "
    "\u2016e(t)\u2016 \u2264 (e^(\u22122\u03bbt) W(0) + (1 \u2212 e^(\u22122\u03bbt)) "
    "\u2016P^\u00bd\u2016\u2082 (\u03b5\u0304 + L v\u0304) / (2\u03bb)) / \u221a\u03bb_min(P). "
    "It needs no \u03bb > 2; for P = I and \u03bb > 2 it is never larger than Theorem 3's.")

DISSIPATION_TEXT = (
    "Joint dissipation certificate: with V = e\u1d40 P e, the inequality V\u2032 \u2264 "
    "\u2212\u03b1 V + \u03bc \u2016v\u2016\u00b2 (+ \u03bc_r \u03b5\u0304\u00b2 for a "
    "direct gain) is proved over X \u00d7 Y as one matrix inequality in [\u03b4; v]. The path "
    "route joins x to x\u0302 by a segment whose points each flow under their own virtual "
    "system, so J_F and \u2202k/\u2202y meet at the same point; the cover route (one "
    "inequality per vertex of an enclosure of \u2202k/\u2202y) is used where it proves a "
    "smaller bound. The error tends to at most "
    "\u221a((\u03bc v\u0304\u00b2 + \u03bc_r \u03b5\u0304\u00b2) / (\u03b1 "
    "\u03bb_min(P))) without the Cauchy\u2013Schwarz step of the ISS bound.")

METRIC_TEXT = (
    "A metric that follows the state: M(x) is a symmetric matrix polynomial in the state "
    "(never in the measured output), proved \u2ab0 m_min I on the region. After the "
    "constant-metric stage has brought the error inside a tube around the output manifold, "
    "each further stage proves \u1e40 + 2 He{M J_F} + \u03b1 M with the noise block "
    "\u2aaf 0 on the tube the paths can still visit, and the Riemannian distance gives "
    "\u2016e\u2016 \u2264 d_M / \u221am_min. The headline uses the last stage where it "
    "is smaller than the constant-metric bound.")

INVARIANCE_TEXT = (
    "A region R of the plant's states inside X is forward invariant when the flow crosses its "
    "boundary inwards everywhere: a\u1d40 f(x) < 0 on every edge of a polygon (a its outward "
    "normal), f_i < 0 on the upper and f_i > 0 on the lower faces of a box, \u2207V \u00b7 f "
    "< 0 on the level set {V = c} of a sublevel set. Each is proved by branch and bound in "
    "outward-rounded interval arithmetic; then no trajectory that starts in R leaves it, and "
    "the error bounds' conditions (a)-(b) are proved, not assumed, for starts in R with an "
    "initial error small enough that x\u0302 stays in X. The attractor's box comes from "
    "simulating the plant alone: evidence, not proof.")

NECESSARY_TEXT = (
    "For any C\u00b9 gain with exact boundary condition k(x, h(x)) = 0, on the output manifold "
    "the MPDI restricted to the kernel of \u2202h/\u2202x\u0302 does not depend on the network: "
    "q(x\u0302) = \u03bb_max(Z\u1d40 (He{P J_f} + 2\u03bbP) Z), Z an orthonormal basis of "
    "ker \u2202h/\u2202x\u0302. If q > 0 anywhere, no gain at all satisfies MPDI and boundary "
    "condition together with this P and \u03bb.")


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
            ("Budget exhausted", fmt(p.budget_exhausted))] + _estimate_rows(p)


def _estimate_rows(p) -> list[tuple[str, str]]:
    """An unfinished proof's estimate of a complete one (`certify.search.tree_estimate`)."""
    boxes = to_float(getattr(p, "estimated_boxes", None))
    if boxes is None:
        return []
    rel = to_float(getattr(p, "estimate_rel_stderr", None))
    spread = f" (\u00b1{100 * rel:.0f} %)" if rel is not None and rel == rel else ""
    rows = [("Boxes a complete proof needs (estimate)", f"{boxes:.3g}{spread}")]
    more = p.seconds_to_finish()
    if more:
        rows.append(("Time it needs at this speed (estimate)", fmt_seconds(more)))
    return rows


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
        ["LipSDP (verified)", fmt_bound(r.lipsdp, "upper", reason="not verified"),
         "upper, sound", f"raw {fmt(r.lipsdp_raw)}; rebuilt LMI \u03bb_max {lmi}",
         mark("lipsdp")],
        ["Local interval bound", fmt_bound(r.local_upper, "upper", reason="not computed"),
         "upper, sound",
         "sup \u2016\u2202k/\u2202y\u2016\u2082 over X \u00d7 Y (needs y_e \u2208 Y)",
         mark("local")],
        ["Naive (product of norms)", fmt_bound(r.naive, "upper"), "upper, sound", "",
         mark("naive")],
        ["Sampled", fmt_bound(r.sampled, "lower"), "lower",
         "max \u2016\u2202k/\u2202y\u2016\u2082 found", ""],
        ["LipSDP for P^\u00bd k", fmt_bound(r.lipsdp_P, "upper", reason="not computed"),
         "upper, sound", "for the P-weighted ISS bound", ""],
    ]


def bound_rows(cert: Certificate) -> list[list[str]]:
    """[name, applicable, reason, rate, gain, bias, d bias / d vbar] per bound."""
    r = result(cert, "bounds")
    if r is None:
        return []
    rows = []
    for b in r.bounds():
        # rates are lower bounds, gains and biases upper bounds: each rounded outward
        rows.append([b.name, "yes" if b.applicable else "no", b.reason,
                     fmt_bound(b.rate, "lower"), fmt_bound(b.gain, "upper"),
                     fmt_bound(b.bias, "upper"), fmt_bound(b.bias_per_unit_noise, "upper")])
    return rows


def exit_words(run: Any) -> str:
    """What ended a run's valid window, without its time (the window column has it)."""
    if run.exit_time is None:
        return "stayed within the conditions"
    reason = run.exit_reason or DASH
    return reason.split(": ", 1)[1] if reason.startswith("t = ") and ": " in reason else reason


def simulation_rows(cert: Certificate) -> list[list[str]]:
    """One row per run: start, noise, valid window, what ended it, error/bound, breach."""
    r = result(cert, "simulation")
    if r is None:
        return []
    rows = []
    for run in r.runs:
        window = run.window if run.window is not None else run.exit_time
        rows.append([run.label, fmt_vec(run.x0), fmt_vec(run.xhat0),
                     run.noise if run.within_conditions else f"{run.noise} (outside)",
                     fmt(window, 3) + (" (whole run)" if run.exit_time is None else ""),
                     exit_words(run), fmt(run.max_ratio, 3), fmt(run.peak_error, 3),
                     fmt(run.conservatism, 3),
                     "BREACH" if run.breach else "no", fmt(run.mse, 3)])
    return rows


SIM_HEADER = ["Run", "x(0)", "x\u0302(0)", "Noise", "Valid window (s)", "What ended it",
              "Max e/b", "Peak after T", "Bound/peak", "Breach", "MSE"]
SIM_WIDTHS = [1.25, 0.85, 0.85, 0.7, 0.6, 1.85, 0.5, 0.55, 0.55, 0.55, 0.5]


def simulation_starts(cert: Certificate) -> list[str]:
    """How each run was started (certify.simulate.starts), one line per run."""
    r = result(cert, "simulation")
    return [] if r is None else [f"{run.label}: {run.start}" for run in r.runs if run.start]


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
    #: small print after the tables (e.g. how floating-point soundness was kept)
    notes: list[str] = field(default_factory=list)
    #: a word that qualifies the status ("vacuous"): shown beside it, in amber
    qualifier: str = ""

    @property
    def tone(self) -> str:
        if self.qualifier:
            return "warn"
        return {"PROVED": "good", "PASSED": "good", "VIOLATED": "bad", "ERROR": "bad",
                "UNKNOWN": "warn"}.get(self.status, "")

    @property
    def badge(self) -> str:
        """The status as shown beside the title: 'PROVED' or 'PROVED \u2014 vacuous'."""
        return badge(self.status, self.qualifier) if self.status else ""

    @property
    def badge_key(self) -> str:
        return badge_key(self.status, self.qualifier)


def _status(cert: Certificate, name: str) -> str:
    r = cert.checks.get(name)
    return "" if r is None else r.status.value


def _message(cert: Certificate, name: str) -> str:
    r = cert.checks.get(name)
    return "" if r is None else r.message


def _check_section(cert: Certificate, name: str, short: str, text: str) -> Section:
    """The section of check `name`: its title, status, message, `text` and its facts."""
    sec = Section(name, cert.title(name), short, _status(cert, name), _message(cert, name))
    sec.paragraphs.append(text)
    sec.facts = check_facts(cert, name)
    return sec


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
        mp = result(cert, "mpdi")
        if mp.proof is not None and mp.proof.rounding:
            sec.notes.append(f"Floating-point soundness of the proof: {mp.proof.rounding}")
    else:
        _without_result(sec, cert, "mpdi", "The MPDI check was not run.")
    out.append(sec)

    if "rate" in cert.checks:
        r = result(cert, "rate")
        sec = Section("rate", "Contraction rate \u03bb_cert", "Rate",
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
            f"bound measures how tight it is. Used: {r.which or DASH} \u2264 "
            f"{fmt_bound(r.value, 'upper')}.")
        sec.tables.append(Table(["Bound", "Value", "Kind", "Note", "Used"],
                                lipschitz_rows(cert), "", [1.6, 1.1, 0.9, 2.6, 0.5]))
        sec.facts = check_facts(cert, "lipschitz")
    else:
        _without_result(sec, cert, "lipschitz", "The Lipschitz constant was not computed.")
    out.append(sec)

    if "dissipation" in cert.checks:
        out.append(_check_section(cert, "dissipation", "Dissipation", DISSIPATION_TEXT))

    if "metric_bound" in cert.checks:
        sec = _check_section(cert, "metric_bound", "Metric M(x)", METRIC_TEXT)
        mb = result(cert, "metric_bound")
        if mb is not None and mb.stages:
            sec.tables.append(Table(
                ["Stage", "Tube |y\u2032 \u2212 h(z)| \u2264", "\u03b1 \u2265",
                 "\u03bc \u2264", "Boxes"],
                [[str(i + 2), fmt_bound(st.get("tau"), "upper"),
                  fmt_bound(st.get("alpha"), "lower"), fmt_bound(st.get("mu"), "upper"),
                  str(st.get("boxes", DASH))]
                 for i, st in enumerate(mb.stages)], "Stages after the constant metric",
                [0.6, 1.6, 1.0, 1.0, 1.0]))
        out.append(sec)

    if "invariance" in cert.checks:
        sec = _check_section(cert, "invariance", "Invariance", INVARIANCE_TEXT)
        inv = result(cert, "invariance")
        if inv is not None and inv.candidates:
            sec.tables.append(Table(["Region", "How it was made", "Status", "Finding"],
                                    [[c.get("kind", DASH), c.get("how", DASH),
                                      c.get("status", DASH), c.get("message", DASH)]
                                     for c in inv.candidates], "Regions tried",
                                    [0.8, 1.8, 0.8, 4.0]))
        out.append(sec)

    sec = Section("bounds", "Error bounds: the headline bound, Theorem 3 as stated and the "
                  "ISS bounds", "Bounds", _status(cert, "bounds"), _message(cert, "bounds"))
    sec.statements = [THEOREM3_TEXT, ISS_TEXT]
    b = result(cert, "bounds")
    if b is not None:
        pres = cert.presentation("bounds")
        sec.qualifier = getattr(pres, "qualifier", "") if pres is not None else ""
        if b.dissipation is not None:
            sec.statements.append(DISSIPATION_TEXT)
        sec.facts = check_facts(cert, "bounds")
        rows = bound_rows(cert)
        if rows:
            sec.tables.append(Table(["Bound", "Applies", "Why (not)", "Rate", "Gain", "Bias b",
                                     "db/dv\u0304"], rows, "Conditions and numbers",
                                    [1.4, 0.7, 3.0, 0.8, 0.8, 0.8, 0.8]))
        formulas = [(x.name, x.formula) for x in b.bounds() if x.formula]
        if formulas:
            sec.tables.append(Table(["Bound", "Formula"], [list(f) for f in formulas],
                                    "Formulas", [1, 4]))
        validity = validity_sentence(b)
        if validity:
            sec.statements.append(f"Validity, proved: {validity}.")
        sec.bullets = list(b.validity)
        sec.bullets_title = ("Validity conditions (each holds up to its first failure time; "
                             "no bound is claimed after it)")
    else:
        _without_result(sec, cert, "bounds", "No bounds were computed.")
    out.append(sec)

    sec = Section("simulation", "Simulation: plant and observer under noise",
                  "Simulation", _status(cert, "simulation"), _message(cert, "simulation"))
    s = result(cert, "simulation")
    if s is not None and not s.runs:
        sec.paragraphs.append("Nothing was simulated: " + (s.message or "no runs."))
        sec.facts = check_facts(cert, "simulation")
    elif s is not None:
        exits = [run for run in s.runs if run.exit_time is not None]
        tau = (f" One time constant of the bound (1/rate of the bound it is compared with) is "
               f"{fmt(s.time_constant, 3)} s: a window shorter than it compares little."
               if s.time_constant else "")
        sec.paragraphs.append(
            "Plant and observer simulated with bounded noise from starts where the bound's "
            "validity conditions can hold for a while (the plant alone stays in X, small "
            "initial errors in the P-norm). Inside each run's valid window the observed error "
            "must stay under the proved bound (a breach is a bug in the tool, never a pass); "
            "the window ends at the first exit from the conditions (the source's Assumption 1, "
            "forward invariance, is not assumed). Runs with Gaussian noise are outside the "
            "theorem's conditions." + tau + (f" {len(exits)} of {len(s.runs)} runs exit."
                                            if s.runs else ""))
        sec.facts = check_facts(cert, "simulation")
        sec.tables.append(Table(SIM_HEADER, simulation_rows(cert), "Runs", SIM_WIDTHS))
        sec.bullets = simulation_starts(cert)
        sec.bullets_title = "How each run was started"
    else:
        _without_result(sec, cert, "simulation", "No simulation was run.")
    out.append(sec)
    return out
