"""What a report shows of a check, as pure data: `Quantity` and `Presentation`.

Each check's presenter (`Check.present` in `certify.checks`) fills these; the certificate
hands them to the renderers (`Certificate.presentation`), so `reports/` formats them without
importing any check.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from certify.arith.text import bound_text, lower_text, special_text, upper_text
from certify.results import BoundsResult, CheckFailure, Status

__all__ = ["Quantity", "Presentation", "NOTHING", "present_failure", "ErrorHeadline",
           "error_headline", "headline_basis", "BASES", "upper_text", "lower_text",
           "bound_text", "special_text", "BOUND_TITLES", "validity_sentence"]


@dataclass(frozen=True)
class Quantity:
    """One thing a report shows: a label, a value, and why the value may be missing.

    `value` is plain data: a number, a bool, a word, a point (list of floats) or a matrix
    (list of lists); `None` means "not established" and `missing` says why. `sig`, `signed`
    and `suffix` are formatting hints for the renderer (which does all formatting).
    `bound`: "upper" or "lower" when the number is a sound bound, so that the renderer rounds
    it outward (`bound_text`: the text never claims more than was proved); "" for a value
    that is rounded to nearest (a sampled value, a count, a setting).
    """

    label: str
    value: Any = None
    missing: str = ""
    sig: int = 4
    signed: bool = False
    suffix: str = ""
    bound: str = ""


@dataclass(frozen=True)
class Presentation:
    """A check in every report: its two sides, what it was checked with, every number.

    `sampled` is the falsification side (a value found at concrete points), `proved` the
    sound side; `setting` names the knobs it ran with; `numbers` lists every number (JUnit
    and the HTML table); `facts` are the key facts of the check's report section.
    `qualifier`: a word that qualifies the status and goes wherever the status goes (e.g.
    "vacuous" for a proved error bound larger than the box): a renderer shows
    "PROVED — vacuous" and never the plain colour of a pass; "" when the status says it all.
    """

    sampled: Quantity
    proved: Quantity
    setting: tuple[Quantity, ...] = ()
    numbers: tuple[Quantity, ...] = ()
    facts: tuple[Quantity, ...] = ()
    qualifier: str = ""


NOTHING = Quantity("", None)


def present_failure(result: CheckFailure) -> Presentation:
    """A check that raised (ERROR) or could not run (not applicable): the reason only."""
    why = ("internal error" if result.status == Status.ERROR else "not applicable")
    side = Quantity("", None, why)
    facts = (Quantity("Status", result.status.value), Quantity("Reason", result.message))
    if result.error_type:
        facts += (Quantity("Exception", result.error_type),)
    return Presentation(side, side, (), facts, facts)


# ----------------------------------------------------------------------------- error headline

#: what each error bound of `BoundsResult.bounds()` is, in words
BOUND_TITLES = {"dissipation": "dissipation certificate",
                "metric": "metric M(x) in stages after the dissipation certificate",
                "iss_metric": "metric-weighted ISS bound", "iss": "ISS bound",
                "theorem3": "Theorem 3 as stated"}

#: relative outward nudge on a bound scaled here (one float multiply and divide)
_NUDGE = 1e-12


@dataclass(frozen=True)
class ErrorHeadline:
    """The error bound as the second headline after the verdict, as data.

    With a bound (`proved`): ||e(t)|| <= `bound` for noise ||v|| <= `noise` for every
    t >= `after` (seconds) from any start with x, xhat in X, under the validity conditions of
    the bounds check; `components` are (state name, bound on |e_i| over the same times);
    `vacuous`: the headline `bound` exceeds `half_diagonal`, the half-diagonal of X
    (true, but it says little); `source` names the bound it comes from (`BOUND_TITLES`).
    `after` is None for a certificate that recorded no settle time: then `bound` is the
    ultimate bound, reached as t -> infinity. Without a bound, `reason` says why, in words
    that start "no error bound".

    Every number is an upper bound as proved (never rounded down); `sentence` and
    `components_text` print them rounded up (`upper_text`). `title` is the heading every
    medium shows: "Certified error bound" only when `basis` is "certificate" (a CERTIFIED
    verdict); otherwise it says what the bound rests on (`note`).
    """

    status: str
    proved: bool
    reason: str = ""
    bound: float | None = None
    noise: float | None = None
    after: float | None = None
    components: tuple[tuple[str, float], ...] = ()
    vacuous: bool = False
    half_diagonal: float | None = None
    source: str = ""
    ultimate: float | None = None
    #: what the bound rests on (`BASES`): "certificate" (the verdict is CERTIFIED), "proved"
    #: (its contraction was proved, but the verdict is not CERTIFIED), "unproved" (the
    #: contraction it rests on was not proved); "" when not assessed (no verdict given)
    basis: str = ""
    #: the proved rate the bound uses (a lower bound) and the design rate, for the note
    lam_cert: float | None = None
    lam_design: float | None = None
    verdict: str = ""
    #: the statuses of the checks it may rest on ("" when not run or not given)
    mpdi_status: str = ""
    rate_status: str = ""
    dissipation_status: str = ""
    #: the validity region (`BoundsResult.region`, "" without one; `validity_sentence`)
    validity: str = ""
    validity_ascii: str = ""

    def _le(self, unicode: bool) -> str:
        return "\u2264" if unicode else "<="

    def sentence(self, unicode: bool = True) -> str:
        """'‖e‖ ≤ 1.25 for noise ≤ 0.15 after t ≥ 3.1 s' (ASCII: '||e|| <= 1.25 ...'); the
        reason when there is no bound."""
        if not self.proved or self.bound is None:
            return self.reason
        le, norm = self._le(unicode), ("\u2016e\u2016" if unicode else "||e||")
        noise = f"{self.noise:g}" if self.noise is not None else "?"
        head = f"{norm} {le} {upper_text(self.bound)} for noise {le} {noise}"
        if self.after is None or not math.isfinite(self.after):
            return head + (" as t \u2192 \u221e" if unicode else " as t -> infinity")
        ge = "\u2265" if unicode else ">="
        return head + f" after t {ge} {upper_text(self.after, 2)} s"

    def components_text(self, unicode: bool = True) -> str:
        """'|e1| ≤ 0.396 (x1), |e2| ≤ 1.38 (x2)'; '' without a bound."""
        le = self._le(unicode)
        return ", ".join(f"|e{i + 1}| {le} {upper_text(v)}" + (f" ({n})" if n else "")
                         for i, (n, v) in enumerate(self.components))

    def size_word(self) -> str:
        """'useful' or 'vacuous' ('' without a bound)."""
        return "" if not self.proved else ("vacuous" if self.vacuous else "useful")

    def size_text(self) -> str:
        """'useful (smaller than the box, half-diagonal 3.61)' or 'vacuous (larger than the
        box, half-diagonal 3.61)'; '' without a bound."""
        if not self.proved:
            return ""
        if self.half_diagonal is None:
            return f"{self.size_word()} (the box's half-diagonal was not recorded)"
        rel = "larger" if self.vacuous else "smaller"
        return f"{self.size_word()} ({rel} than the box, half-diagonal {self.half_diagonal:.3g})"

    def source_text(self, unicode: bool = True) -> str:
        """Which bound it comes from and its limit, for the small print."""
        if not self.proved:
            return ""
        title = BOUND_TITLES.get(self.source, self.source or "bound")
        text = f"from the {title} ({self.source})" if self.source else "from the best bound"
        if self.ultimate is not None and self.after is not None:
            arrow = "t \u2192 \u221e" if unicode else "t -> infinity"
            text += f"; limit {upper_text(self.ultimate)} as {arrow}"
        return text

    def note(self, unicode: bool = True) -> str:
        """What the bound rests on when that is not the certificate, in words ('' for a
        certified bound, one without a bound, or one not assessed): 'at the proved rate
        λ_cert ≥ 0.4586; the certificate failed at the design rate λ = 0.5'."""
        if not self.proved or self.basis in ("", "certificate"):
            return ""
        ge, lam = ("\u2265", "\u03bb") if unicode else (">=", "lam")
        if self.basis == "unproved":
            if self.source == "dissipation":
                return ("NOT PROVED: it rests on the dissipation inequality, whose check is "
                        f"{self.dissipation_status or 'not run'}")
            return (f"NOT PROVED: it rests on the rate {lam}_cert, which neither the rate "
                    f"check ({self.rate_status or 'not run'}) nor the MPDI "
                    f"({self.mpdi_status or 'not run'}) proved")
        if self.source == "dissipation":
            rests = "from the proved dissipation inequality"
        elif self.lam_cert is not None:
            rests = f"at the proved rate {lam}_cert {ge} {lower_text(self.lam_cert, 4)}"
        else:
            rests = "at the proved rate"
        design = "" if self.lam_design is None else f" {lam} = {self.lam_design:g}"
        if self.mpdi_status == Status.VIOLATED.value:
            return f"{rests}; the certificate failed at the design rate{design}"
        if self.mpdi_status != Status.PROVED.value:
            return f"{rests}; the MPDI at the design rate{design} was not proved"
        return f"{rests}, not on the certificate (verdict {self.verdict or 'unknown'})"

    def title(self, unicode: bool = True) -> str:
        """The heading of the headline: 'Certified error bound' only under a CERTIFIED
        verdict; 'Proved error bound (<note>)' when it rests on a proved contraction but
        the verdict is not CERTIFIED; 'Error bound resting on an unproved condition
        (<note>)'; plain 'Error bound' without a bound or when not assessed."""
        if not self.proved or self.basis == "":
            return "Error bound"
        if self.basis == "certificate":
            return "Certified error bound"
        if self.basis == "unproved":
            return f"Error bound resting on an unproved condition ({self.note(unicode)})"
        return f"Proved error bound ({self.note(unicode)})"

    def line(self, unicode: bool = True) -> str:
        """Everything on one line: sentence, per component, size, source (or the reason)."""
        if not self.proved:
            return self.reason
        parts = [self.sentence(unicode)]
        if self.components:
            parts.append(self.components_text(unicode))
        parts.append(self.size_text())
        return "; ".join(parts) + f" [{self.source_text(unicode)}]"

    def validity_text(self, unicode: bool = True) -> str:
        """Where the conditions of the bound are proved, not assumed: 'for every x(0) in R
        and ‖e(0)‖ ≤ 0.37: x̂ stays in X and ‖e(t)‖ ≤ 1.75 for all t ≥ 2.1 s; ...' ('' when
        no region was proved)."""
        return self.validity if unicode else self.validity_ascii

    def to_dict(self) -> dict[str, Any]:
        """The JSON summary (`Certificate.to_dict`'s top-level "error_bound")."""
        return {"status": self.status,
                "statement": self.sentence() if self.proved else None,
                "bound": self.bound, "noise": self.noise, "after": self.after,
                "per_component": {n or f"e{i + 1}": v
                                  for i, (n, v) in enumerate(self.components)},
                "size": self.size_word() or None, "vacuous": self.vacuous if self.proved
                else None, "box_half_diagonal": self.half_diagonal,
                "source": self.source or None, "ultimate": self.ultimate,
                "basis": self.basis or None, "title": self.title(),
                "validity": self.validity or None, "reason": self.reason or None}


def _no_bound(status: str, why: str) -> ErrorHeadline:
    why = why.strip() or "no reason recorded"
    reason = why if why.lower().startswith("no error bound") else f"no error bound: {why}"
    return ErrorHeadline(status=status, proved=False, reason=reason)


#: what an error bound may rest on (`ErrorHeadline.basis`)
BASES = ("certificate", "proved", "unproved")


def _status_word(result: Any) -> str:
    status = getattr(result, "status", None)
    return "" if status is None else (status.value if isinstance(status, Status)
                                      else str(status))


def headline_basis(source: str, checks: Mapping[str, Any], verdict: str) -> str:
    """What a proved bound from `source` rests on (`BASES`), given the certificate's check
    results and verdict.

    The dissipation bound rests on the dissipation check (PROVED: V' <= -alpha V + mu
    ||v||^2 with alpha > 0 is itself a proved contraction); every other bound on lam_cert,
    proved by the rate check (PROVED, a positive proved lower bound) or by a PROVED MPDI
    (contraction at the design rate). Only a CERTIFIED verdict makes it "certificate"."""
    if source == "dissipation":
        proved = _status_word(checks.get("dissipation")) == Status.PROVED.value
    else:
        rate = checks.get("rate")
        lower = getattr(rate, "proved_lower", None)
        proved = ((_status_word(rate) == Status.PROVED.value and lower is not None
                   and lower > 0)
                  or _status_word(checks.get("mpdi")) == Status.PROVED.value)
    if not proved:
        return "unproved"
    return "certificate" if verdict == "CERTIFIED" else "proved"


def error_headline(bounds: Any, states: list[str] | None = None, *,
                   checks: Mapping[str, Any] | None = None, verdict: str | None = None,
                   lam: float | None = None) -> ErrorHeadline:
    """The headline of the bounds check's result (`BoundsResult`, a `CheckFailure` or None
    when it did not run); `states` names the components (the system's state names).

    With the certificate's `checks`, `verdict` and design rate `lam`, the headline also
    says what the bound rests on (`basis`, `headline_basis`): its title says "Certified"
    only under a CERTIFIED verdict. A certificate written before the headline fields
    existed (PROVED, `headline` None) gets the smallest applicable ultimate bound, reached
    as t -> infinity (`after` None)."""
    if bounds is None:
        return _no_bound(Status.SKIPPED.value, "the bounds check was not run")
    status = bounds.status.value if isinstance(bounds.status, Status) else str(bounds.status)
    if isinstance(bounds, CheckFailure):
        if bounds.status == Status.NOT_RUN:  # its message begins "not run: "
            return _no_bound(status, "the bounds check was not run: "
                             + bounds.message.removeprefix("not run: "))
        word = "ended in ERROR" if bounds.status == Status.ERROR else "could not run"
        return _no_bound(status, f"the bounds check {word}: {bounds.message}")
    if not isinstance(bounds, BoundsResult) or bounds.status != Status.PROVED:
        return _no_bound(status, getattr(bounds, "message", ""))
    names = list(states or [])
    applicable = [b for b in bounds.bounds() if b.applicable and b.bias is not None]
    if bounds.headline is not None and bounds.ultimate is not None:
        bound, after, ultimate = float(bounds.headline), bounds.settle_time, float(bounds.ultimate)
        source = bounds.best
    elif applicable:
        best = min(applicable, key=lambda b: float(b.bias))  # type: ignore[arg-type]
        bound, after, ultimate, source = float(best.bias), None, None, best.name  # type: ignore
    else:
        return _no_bound(status, bounds.message or "no applicable bound")
    comps: list[tuple[str, float]] = []
    if bounds.per_component:
        # |e_i| <= per_component[i] at the limit; at t >= after scaled like the norm bound
        scale = 1.0 if ultimate is None or after is None else (
            bound / ultimate if ultimate > 0 else 1.0)
        for i, v in enumerate(bounds.per_component):
            name = names[i] if i < len(names) else ""
            comps.append((name, float(v) * scale * (1.0 + _NUDGE) if scale != 1.0
                          else float(v)))
    basis = "" if checks is None or verdict is None else headline_basis(source, checks,
                                                                           verdict)
    region = bool(getattr(bounds, "region", ""))
    return ErrorHeadline(status=status, proved=True, bound=bound, noise=float(bounds.vbar),
                         after=None if after is None else float(after),
                         components=tuple(comps), vacuous=bool(bounds.vacuous),
                         half_diagonal=bounds.box_half_diagonal, source=source,
                         ultimate=ultimate, basis=basis,
                         lam_cert=None if bounds.lam_cert is None else float(bounds.lam_cert),
                         lam_design=None if lam is None else float(lam),
                         verdict=verdict or "",
                         mpdi_status=_status_word((checks or {}).get("mpdi")),
                         rate_status=_status_word((checks or {}).get("rate")),
                         dissipation_status=_status_word((checks or {}).get("dissipation")),
                         validity=validity_sentence(bounds) if region else "",
                         validity_ascii=validity_sentence(bounds, unicode=False) if region
                         else "")


def validity_sentence(bounds: BoundsResult, unicode: bool = True) -> str:
    """The headline with its conditions proved for a set of starts (`BoundsResult.region`):
    'for every x(0) in R and ‖e(0)‖ ≤ r0: x̂ stays in X and ‖e(t)‖ ≤ B for all t ≥ T (R: ...;
    conditions (a), (b) proved; (c) ‖v‖ ≤ v̄ assumed)', r0 rounded down, B and T up; '' when
    there is no region."""
    if not getattr(bounds, "region", "") or bounds.r0 is None or bounds.headline is None:
        return ""
    le, ge = ("\u2264", "\u2265") if unicode else ("<=", ">=")
    norm = "\u2016e" if unicode else "||e"
    bar = "\u2016" if unicode else "||"
    xhat = "x\u0302" if unicode else "xhat"
    t = bounds.region_settle_time
    when = (("as t \u2192 \u221e" if unicode else "as t -> infinity") if t is None
            else f"for all t {ge} {upper_text(t, 2)} s")
    proved = ", ".join(f"({c})" for c in bounds.proved_conditions)
    assumed = [f"(c) {bar}v{bar} {le} {bounds.vbar:g}"]
    if bounds.L_is_local and "d" not in bounds.proved_conditions:
        assumed.append("(d) y + v in Y")
    return (f"for every x(0) in R and {norm}(0){bar} {le} {lower_text(bounds.r0)}: {xhat} "
            f"stays in X and {norm}(t){bar} {le} {upper_text(bounds.headline)} {when} (R: "
            f"{bounds.region}; conditions {proved} proved, {' and '.join(assumed)} assumed)")
