"""What a report says, decided once: number formatting, the checks table, section facts.

HTML, PDF and JUnit renderers lay this content out; none of them formats a number itself,
so the three always agree. Everything here is a pure function of a `Certificate`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from certify.certificate import Certificate
from certify.results import Status

DASH = "\u2014"

#: the order checks appear in every report
CHECK_ORDER = ("necessary", "metric", "mpdi", "rate", "residual", "lipschitz", "bounds",
               "simulation")

CHECK_TITLES = {
    "necessary": "Pre-flight necessary condition",
    "metric": "Metric P (SDP)",
    "mpdi": "MPDI: D(x\u0302, y) \u2aaf 0",
    "rate": "Certified rate \u03bb_cert",
    "residual": "Boundary residual \u03b5\u0304",
    "lipschitz": "Lipschitz constant L",
    "bounds": "Error bounds (Theorem 3, ISS)",
    "simulation": "Simulation vs bound",
}

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
    """A JSON-ish number ("NaN"/"Infinity" strings included) to float; None stays None."""
    if x is None or isinstance(x, bool):
        return None
    if isinstance(x, str):
        return {"NaN": math.nan, "Infinity": math.inf, "-Infinity": -math.inf}.get(x)
    try:
        return float(x)
    except (TypeError, ValueError):
        return None


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


def _side(label: str, x: Any, reason: str, sig: int = 4, *, signed: bool = False,
          suffix: str = "") -> Side:
    """A Side for a number that may be None (then the dash and the reason)."""
    if x is None:
        return Side(label, DASH, reason)
    return Side(label, fmt(x, sig, signed=signed) + suffix)


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


def _settings(cert: Certificate) -> dict[str, Any]:
    return cert.settings or {}


def _row_mpdi(r: Any, s: dict) -> tuple[Side, Side, str, list]:
    upper_reason = ("not needed: counterexample found" if r.status == Status.VIOLATED
                    else "no proof attempted")
    sampled = Side("max \u03bb_max(D) found (grid + ascent)", fmt(r.lower, signed=True))
    proved = _side("sound upper bound on max \u03bb_max(D)", r.upper, upper_reason,
                   signed=True)
    setting = (f"grid \u2265 {fmt(r.grid_points or s.get('grid_points'))} points, "
               f"{fmt(r.adversarial_starts)} ascent starts; proof budget "
               f"{fmt(s.get('proof_seconds'))} s / {fmt(s.get('max_boxes'))} boxes")
    nums = [("lower (sampled max lambda_max(D))", fmt(r.lower, 6, signed=True)),
            ("upper (proved bound)", fmt_none(r.upper, upper_reason, 6, signed=True)),
            ("violating fraction of grid", fmt(r.violating_fraction)),
            ("counterexamples", str(len(r.counterexamples)))]
    if r.worst is not None:
        nums.append(("worst xhat, y", f"{fmt_vec(r.worst.xhat)}, {fmt_vec(r.worst.y)}"))
    if r.proof is not None:
        nums += [("boxes processed", fmt(r.proof.boxes_processed)),
                 ("proved volume fraction", fmt(r.proof.proved_volume_fraction)),
                 ("budget exhausted", fmt(r.proof.budget_exhausted))]
    return sampled, proved, setting, nums


def _row_rate(r: Any, s: dict) -> tuple[Side, Side, str, list]:
    sampled = Side("\u03bb_cert \u2264 (sampled)", fmt(r.sampled_upper, signed=True))
    proved = _side("\u03bb_cert \u2265 (proved)", r.proved_lower,
                   "MPDI not proved at any \u03bb > 0", signed=True)
    setting = (f"design \u03bb = {fmt(r.lam_design)}; "
               f"B&B budget {fmt(s.get('rate_seconds'))} s")
    nums = [("lam_design", fmt(r.lam_design, 6)), ("sampled upper", fmt(r.sampled_upper, 6)),
            ("proved lower", fmt(r.proved_lower, 6))]
    return sampled, proved, setting, nums


def _row_residual(r: Any, s: dict) -> tuple[Side, Side, str, list]:
    sampled = Side("\u03b5\u0304 \u2265 (sampled + ascent)", fmt(r.sampled))
    proved = (Side("\u03b5\u0304 \u2264 (interval B&B)", "0", "by construction")
              if r.structural and r.upper in (0, 0.0, None)
              else _side("\u03b5\u0304 \u2264 (interval B&B)", r.upper, "bound not established"))
    setting = f"budget {fmt(s.get('residual_seconds'))} s over X"
    nums = [("sampled", fmt(r.sampled, 6)), ("upper", fmt(r.upper, 6)),
            ("structural", fmt(r.structural))]
    return sampled, proved, setting, nums


def _row_lipschitz(r: Any, s: dict) -> tuple[Side, Side, str, list]:
    sampled = Side("L \u2265 (sampled max \u2016\u2202k/\u2202y\u2016)", fmt(r.sampled))
    which = f" ({r.which})" if r.which else ""
    proved = _side("L \u2264 (bound used)", r.value, "no sound bound", suffix=which)
    solver = (r.solver or {}).get("name", "")
    setting = (f"budget {fmt(s.get('lipschitz_seconds'))} s"
               + (f"; LipSDP with {solver}" if solver else ""))
    nums = [("LipSDP (verified)", fmt_none(r.lipsdp, "not verified", 6)),
            ("LipSDP raw", fmt(r.lipsdp_raw, 6)),
            ("LMI max eigenvalue", fmt(r.lipsdp_lmi_max_eig, 3, signed=True)),
            ("local interval bound", fmt(r.local_upper, 6)), ("naive", fmt(r.naive, 6)),
            ("sampled", fmt(r.sampled, 6)), ("used", f"{fmt(r.value, 6)}{which}")]
    return sampled, proved, setting, nums


def _row_necessary(r: Any, s: dict, cert: Certificate) -> tuple[Side, Side, str, list]:
    sampled = Side("max q found" + (f" at x\u0302 = {fmt_vec(r.witness)}" if r.witness else ""),
                   fmt(r.q_max, signed=True))
    proved = _side("q \u2264 (sound bound)", r.q_upper, "not bounded", signed=True)
    setting = f"\u03bb = {fmt(cert.lam)}, P = {fmt_matrix(cert.P, 3)}"
    nums = [("q_max", fmt(r.q_max, 6, signed=True)), ("q_upper", fmt(r.q_upper, 6, signed=True)),
            ("witness", fmt_vec(r.witness, 4)), ("rate cap", fmt(r.rate_cap, 6)),
            ("residual price", fmt(r.residual_price, 6))]
    return sampled, proved, setting, nums


def _row_metric(r: Any, s: dict) -> tuple[Side, Side, str, list]:
    sampled = Side("condition number of P", fmt(r.condition_number))
    proved = Side("SDP margin", fmt(r.margin, signed=True))
    setting = f"\u03bb = {fmt(r.lam)}; {(r.solver or {}).get('name', 'SDP')}"
    nums = [("P", fmt_matrix(r.P, 6)), ("cond P", fmt(r.condition_number, 6)),
            ("margin", fmt(r.margin, 6))]
    return sampled, proved, setting, nums


def _bias_text(b: Any) -> str:
    if b is None:
        return "not computed"
    if not b.applicable:
        return "not applicable"
    return f"b = {fmt(b.bias)} (rate {fmt(b.rate)})"


def _row_bounds(r: Any, s: dict) -> tuple[Side, Side, str, list]:
    sampled = Side("Theorem 3 (as stated)", _bias_text(r.theorem3))
    proved = Side("ISS bound: ultimate bias", _bias_text(r.iss))
    setting = (f"v\u0304 = {fmt(r.vbar)}; \u03bb_cert used: "
               f"{fmt_none(r.lam_cert, 'none', signed=False)}")
    nums = [("vbar", fmt(r.vbar, 6)), ("lam_cert", fmt(r.lam_cert, 6)),
            ("eps_bar", fmt(r.eps_bar, 6)), ("L", fmt(r.L, 6))]
    for b in (r.theorem3, r.iss, r.iss_metric):
        if b is not None:
            nums.append((b.name, (f"bias {fmt(b.bias, 6)}, rate {fmt(b.rate, 6)}, "
                                  f"gain {fmt(b.gain, 6)}") if b.applicable
                         else f"not applicable: {b.reason}"))
    return sampled, proved, setting, nums


def _row_simulation(r: Any, s: dict) -> tuple[Side, Side, str, list]:
    ratios = [run.max_ratio for run in r.runs if run.max_ratio is not None]
    exits = sum(run.exit_time is not None for run in r.runs)
    breaches = sum(bool(run.breach) for run in r.runs)
    sampled = _side("max error / bound (valid times)", max(ratios) if ratios else None,
                    "no bound to compare")
    proved = Side("breaches / exits from X, Y",
                  f"{breaches} breach{'es' if breaches != 1 else ''}, "
                  f"{exits} of {len(r.runs)} runs exit")
    setting = (f"{len(r.runs)} runs, T = {fmt(s.get('sim_time'))} s, "
               f"dt = {fmt(s.get('sim_dt'))}, v\u0304 = {fmt(s.get('noise'))}")
    nums = [("runs", str(len(r.runs))), ("breaches", str(breaches)), ("exits", str(exits)),
            ("max error/bound", fmt(max(ratios), 6) if ratios else DASH)]
    for run in r.runs:
        nums.append((f"run {run.label}",
                     f"max ratio {fmt(run.max_ratio)}, exit {fmt(run.exit_time)} "
                     f"{run.exit_reason}".strip()))
    return sampled, proved, setting, nums


_ROWS = {"mpdi": _row_mpdi, "rate": _row_rate, "residual": _row_residual,
         "lipschitz": _row_lipschitz, "metric": _row_metric, "bounds": _row_bounds,
         "simulation": _row_simulation}


def check_names(cert: Certificate) -> list[str]:
    """Checks to report: every check present, plus required ones that were not run."""
    names = [n for n in CHECK_ORDER if n in cert.checks or n in cert.required]
    names += [n for n in cert.checks if n not in names]
    return names


def check_rows(cert: Certificate) -> list[CheckRow]:
    """One `CheckRow` per reported check, in report order."""
    s = _settings(cert)
    rows = []
    for name in check_names(cert):
        r = cert.checks.get(name)
        title = CHECK_TITLES.get(name, name)
        required = name in cert.required
        if r is None:
            rows.append(CheckRow(name, title, Status.SKIPPED.value, required,
                                 Side("", DASH), Side("", DASH), "", "not run", None))
            continue
        if name == "necessary":
            sampled, proved, setting, nums = _row_necessary(r, s, cert)
        elif name in _ROWS:
            sampled, proved, setting, nums = _ROWS[name](r, s)
        else:
            sampled, proved, setting, nums = Side("", DASH), Side("", DASH), "", []
        seconds = to_float(getattr(r, "seconds", None))
        if seconds is None:
            seconds = to_float((cert.timings or {}).get(name))
        rows.append(CheckRow(name, title, r.status.value, required, sampled, proved, setting,
                             r.message, seconds, nums))
    return rows


# ----------------------------------------------------------------------------- facts

def lam_cert_text(cert: Certificate) -> str:
    """lam_cert as the bracket the rate check established."""
    rate = cert.checks.get("rate")
    if rate is None:
        b = cert.checks.get("bounds")
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
    metric = cert.checks.get("metric")
    bounds = cert.checks.get("bounds")
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
    r = cert.checks.get("mpdi")
    if r is None:
        return []
    return [[str(i + 1), fmt_vec(c.xhat, 4), fmt_vec(c.y, 4), fmt(c.value, 5, signed=True)]
            for i, c in enumerate(r.counterexamples[:limit])]


def proof_facts(cert: Certificate) -> list[tuple[str, str]]:
    r = cert.checks.get("mpdi")
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


def mpdi_facts(cert: Certificate) -> list[tuple[str, str]]:
    r = cert.checks.get("mpdi")
    if r is None:
        return []
    out = [("Status", r.status.value),
           ("Sampled max \u03bb_max(D)", fmt(r.lower, 6, signed=True)),
           ("Proved upper bound", fmt_none(r.upper, "not needed: counterexample found"
                                           if r.status == Status.VIOLATED else
                                           "no proof attempted", 6, signed=True)),
           ("Violating fraction of the grid",
            f"{100 * (to_float(r.violating_fraction) or 0):.2f} %"),
           ("Grid points / ascent starts",
            f"{fmt(r.grid_points)} / {fmt(r.adversarial_starts)}")]
    if r.worst is not None:
        out.append(("Worst point (x\u0302, y)",
                    f"{fmt_vec(r.worst.xhat, 4)}, {fmt_vec(r.worst.y, 4)}: "
                    f"{fmt(r.worst.value, 5, signed=True)}"))
    return out


def necessary_facts(cert: Certificate) -> list[tuple[str, str]]:
    r = cert.checks.get("necessary")
    if r is None:
        return []
    return [("Status", r.status.value),
            ("max q found", fmt(r.q_max, 6, signed=True)),
            ("Sound bound q \u2264", fmt_none(r.q_upper, "not bounded", 6, signed=True)),
            ("Witness x\u0302", fmt_vec(r.witness, 4)),
            ("Witness y = h(x\u0302)", fmt_vec(r.witness_y, 4)),
            ("Rate cap (any gain with exact BC)",
             fmt_none(r.rate_cap, "not computed", 5, signed=True)),
            ("Price in residual (\u03b5\u0304 \u2265)",
             fmt_none(r.residual_price, "not applicable", 5))]


def residual_facts(cert: Certificate) -> list[tuple[str, str]]:
    r = cert.checks.get("residual")
    if r is None:
        return []
    return [("Status", r.status.value), ("Sampled \u03b5\u0304 \u2265", fmt(r.sampled, 6)),
            ("Sound bound \u03b5\u0304 \u2264", fmt_none(r.upper, "not established", 6)),
            ("Zero by construction", fmt(r.structural)),
            ("Worst x", fmt_vec(r.worst, 4))]


def lipschitz_rows(cert: Certificate) -> list[list[str]]:
    """[bound, value, sound?, note] rows, LipSDP / local / naive / sampled side by side."""
    r = cert.checks.get("lipschitz")
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
    r = cert.checks.get("bounds")
    if r is None:
        return []
    rows = []
    for b in (r.theorem3, r.iss, r.iss_metric):
        if b is None:
            continue
        rows.append([b.name, "yes" if b.applicable else "no", b.reason,
                     fmt(b.rate), fmt(b.gain), fmt(b.bias), fmt(b.bias_per_unit_noise)])
    return rows


def bounds_facts(cert: Certificate) -> list[tuple[str, str]]:
    r = cert.checks.get("bounds")
    if r is None:
        return []
    return [("Status", r.status.value), ("Noise level v\u0304", fmt(r.vbar)),
            ("\u03bb_cert used", fmt_none(r.lam_cert, "none: no bound")),
            ("\u03b5\u0304 used", fmt(r.eps_bar)), ("L used", fmt(r.L)),
            ("cond(P)", fmt(r.kappa_P))]


def simulation_rows(cert: Certificate) -> list[list[str]]:
    r = cert.checks.get("simulation")
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
    if "mpdi" in cert.checks:
        sec.facts = mpdi_facts(cert)
        cex = counterexample_rows(cert)
        if cex:
            sec.tables.append(Table(["#", "x\u0302", "y", "\u03bb_max(D)"], cex,
                                    "Counterexamples (largest first)", [0.6, 3, 2, 1.6]))
        proof = proof_facts(cert)
        if proof:
            sec.tables.append(Table(["Prover statistic", "Value"], [list(p) for p in proof],
                                    "Proof statistics", [1, 2]))
    else:
        sec.empty = "The MPDI check was not run."
    out.append(sec)

    if "rate" in cert.checks:
        r = cert.checks["rate"]
        sec = Section("rate", "Certified contraction rate \u03bb_cert", "Rate", r.status.value,
                      r.message)
        sec.paragraphs.append(
            "\u03bb_cert = \u2212max \u03bb_max(He{P (J_f + \u2202k/\u2202x\u0302)}, P) / 2 is the "
            "largest rate for which the MPDI holds. Every error bound below uses \u03bb_cert "
            "(it may be below the design \u03bb); if \u03bb_cert \u2264 0 there is no bound "
            "at all.")
        sec.facts = [("Design \u03bb", fmt(r.lam_design)),
                     ("\u03bb_cert \u2264 (sampled)", fmt(r.sampled_upper, 6, signed=True)),
                     ("\u03bb_cert \u2265 (proved, branch and bound)",
                      fmt_none(r.proved_lower, "not proved", 6, signed=True)),
                     ("Bracket", lam_cert_text(cert))]
        if r.worst is not None:
            sec.facts.append(("Where the sampled side is attained",
                              f"x\u0302 = {fmt_vec(r.worst.xhat, 4)}, y = {fmt_vec(r.worst.y, 4)}"))
        out.append(sec)

    sec = Section("necessary", "Pre-flight necessary condition (independent of the network)",
                  "Necessary condition", _status(cert, "necessary"), _message(cert, "necessary"))
    sec.paragraphs.append(NECESSARY_TEXT)
    r = cert.checks.get("necessary")
    if r is not None:
        if r.explanation:
            sec.statements.append(r.explanation)
        sec.facts = necessary_facts(cert)
    else:
        sec.empty = "The necessary condition was not checked."
    out.append(sec)

    if "metric" in cert.checks:
        m = cert.checks["metric"]
        sec = Section("metric", "Metric P found by SDP", "Metric", m.status.value, m.message)
        sec.facts = [("P", fmt_matrix(m.P)), ("cond(P)", fmt(m.condition_number)),
                     ("SDP margin", fmt(m.margin, signed=True)), ("\u03bb", fmt(m.lam)),
                     ("Output-injection gain K", fmt_matrix(m.K)),
                     ("Solver", ", ".join(f"{k} {v}" for k, v in (m.solver or {}).items())
                      or DASH)]
        if m.witness is not None:
            wy = getattr(m, "witness_y", None)
            sec.facts.append(("Witness (no constant P works here)",
                              fmt_vec(m.witness, 4) + (f", y = {fmt_vec(wy, 4)}" if wy else "")))
        out.append(sec)

    sec = Section("residual", "Boundary residual \u03b5\u0304 = sup over X of "
                              "\u2016k(x, h(x))\u2016", "Residual", _status(cert, "residual"),
                  _message(cert, "residual"))
    sec.paragraphs.append(
        "The boundary condition k(x, h(x)) = 0 says the correction vanishes when the estimate "
        "is exact; its residual \u03b5\u0304 enters every error bound as a bias.")
    if "residual" in cert.checks:
        sec.facts = residual_facts(cert)
    else:
        sec.empty = "The residual was not checked."
    out.append(sec)

    sec = Section("lipschitz", "Lipschitz constant L of k in y", "Lipschitz",
                  _status(cert, "lipschitz"),
                  _message(cert, "lipschitz"))
    r = cert.checks.get("lipschitz")
    if r is not None:
        sec.paragraphs.append(
            "L bounds how much measurement noise moves the correction, uniformly in "
            "x\u0302 (an L2 \u2192 L2 constant, so v\u0304 bounds the Euclidean norm of the "
            "noise). LipSDP is re-verified by rebuilding its LMI at the solver's multipliers; "
            "the smallest sound upper bound is used downstream. The gap to the sampled lower "
            f"bound measures how tight it is. Used: {r.which or DASH} = {fmt(r.value)}.")
        sec.tables.append(Table(["Bound", "Value", "Kind", "Note", "Used"],
                                lipschitz_rows(cert), "", [1.6, 1.1, 0.9, 2.6, 0.5]))
        if r.solver:
            sec.facts = [("LipSDP solver", ", ".join(
                f"{k} {v if isinstance(v, str) else fmt(v)}" for k, v in r.solver.items()))]
    else:
        sec.empty = "The Lipschitz constant was not computed."
    out.append(sec)

    sec = Section("bounds", "Error bounds: Theorem 3 as stated and the ISS bound",
                  "Bounds", _status(cert, "bounds"), _message(cert, "bounds"))
    sec.statements = [THEOREM3_TEXT, ISS_TEXT]
    b = cert.checks.get("bounds")
    if b is not None:
        sec.facts = bounds_facts(cert)
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
        sec.empty = "No bounds were computed."
    out.append(sec)

    sec = Section("simulation", "Simulation: plant and observer under noise",
                  "Simulation", _status(cert, "simulation"), _message(cert, "simulation"))
    s = cert.checks.get("simulation")
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
        sec.empty = "No simulation was run."
    out.append(sec)
    return out
